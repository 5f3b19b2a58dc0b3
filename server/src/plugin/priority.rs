//! [`WasmPriorityPolicy`]: a `priority-policy` component behind the native
//! [`PriorityPolicy`] trait, with containment and a fallback policy.

use std::sync::Arc;

use wasmtime::Store;
use wasmtime::component::{Component, Linker};

use super::bindings::{WitVersion, since_v0_1_0, since_v0_2_0, since_v0_3_0};
use super::health::{FailureKind, Health, PluginStats};
use super::reload::Reloader;
use super::runtime::{CallCost, CallFailure, Compiled, Exec, LoadError, PluginMeta, World, load};
use super::sandbox::HostState;
use super::{PluginKind, PluginOptions, PluginSource};
use kairos_core::horizon::PolicyParams;
use kairos_core::scheduler::{
    FinishedTask, PendingView, PolicyError, PriorityPolicy, order_by_indexed_key, validate_order,
};
use kairos_core::time::Timestamp;

use since_v0_1_0::priority as v0_1;
use since_v0_2_0::priority as v0_2;
use since_v0_3_0::priority as v0_3;

pub(crate) struct PriorityWorld;

pub(crate) enum PriorityPre {
    V0_1(v0_1::PriorityPolicyPre<HostState>),
    V0_2(v0_2::PriorityPolicyPre<HostState>),
    V0_3(v0_3::PriorityPolicyPre<HostState>),
}

pub(crate) enum PriorityInstance {
    V0_1(v0_1::PriorityPolicy),
    V0_2(v0_2::PriorityPolicy),
    V0_3(v0_3::PriorityPolicy),
}

impl World for PriorityWorld {
    const KIND: PluginKind = PluginKind::Priority;
    type Pre = PriorityPre;
    type Instance = PriorityInstance;

    fn pre(
        version: WitVersion,
        linker: &Linker<HostState>,
        component: &Component,
    ) -> wasmtime::Result<PriorityPre> {
        match (version.major, version.minor) {
            (0, 1) => Ok(PriorityPre::V0_1(v0_1::PriorityPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            (0, 2) => Ok(PriorityPre::V0_2(v0_2::PriorityPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            (0, 3) => Ok(PriorityPre::V0_3(v0_3::PriorityPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            _ => Err(wasmtime::Error::msg(format!(
                "no bindings for version {version}"
            ))),
        }
    }

    fn instantiate(
        pre: &PriorityPre,
        store: &mut Store<HostState>,
    ) -> wasmtime::Result<PriorityInstance> {
        match pre {
            PriorityPre::V0_1(pre) => pre.instantiate(store).map(PriorityInstance::V0_1),
            PriorityPre::V0_2(pre) => pre.instantiate(store).map(PriorityInstance::V0_2),
            PriorityPre::V0_3(pre) => pre.instantiate(store).map(PriorityInstance::V0_3),
        }
    }
}

use kairos_core::time::duration_nanos as nanos;

/// The pending list in v0.1.0's types.
fn pending_v0_1(pending: &[PendingView]) -> Vec<v0_1::exports::kairos::policy::priority::Pending> {
    use v0_1::exports::kairos::policy::priority as wit;
    pending
        .iter()
        .map(|p| wit::Pending {
            request: p.request.0,
            task: p.task.0,
            round_index: p.round_index,
            arrived_at_us: p.arrived_at.as_micros(),
            task_started_at_us: p.task_started_at.as_micros(),
            skipped: p.skipped,
            wait_ns: nanos(p.wait),
            attained_service_ns: nanos(p.attained_service),
            queued_ns: nanos(p.queued),
            last_exec_ns: p.last_exec.map(nanos),
            exec_ends_at_us: p.exec_ends_at.map(Timestamp::as_micros),
            last_gen_ns: p.last_gen.map(nanos),
            rounds_completed: p.rounds_completed,
            remaining: p.remaining.map(|r| wit::RemainingWork {
                rounds: r.rounds,
                seconds: r.seconds,
            }),
        })
        .collect()
}

/// The pending list as `kairos:policy@0.2.0` columns: one vector per field, reused between
/// calls, each lowered into the sandbox as one block copy.
#[derive(Clone, Debug)]
pub(crate) struct PendingColumns(v0_2::exports::kairos::policy::priority::PendingColumns);

impl Default for PendingColumns {
    fn default() -> Self {
        PendingColumns(v0_2::exports::kairos::policy::priority::PendingColumns {
            request: Vec::new(),
            task: Vec::new(),
            round_index: Vec::new(),
            arrived_at_us: Vec::new(),
            task_started_at_us: Vec::new(),
            skipped: Vec::new(),
            wait_ns: Vec::new(),
            attained_service_ns: Vec::new(),
            queued_ns: Vec::new(),
            last_exec_ns: Vec::new(),
            exec_ends_at_us: Vec::new(),
            last_gen_ns: Vec::new(),
            rounds_completed: Vec::new(),
            remaining_rounds: Vec::new(),
            remaining_seconds: Vec::new(),
            present: Vec::new(),
        })
    }
}

/// Builds a `$to` from every column of `$from`, leaving `$from`'s columns empty (no copy): 0.2.0's
/// and 0.3.0's `pending-columns` have the same fields.
macro_rules! take_columns {
    ($from:expr => $to:ident) => {
        take_columns!($from => $to; request, task, round_index, arrived_at_us, task_started_at_us,
            skipped, wait_ns, attained_service_ns, queued_ns, last_exec_ns, exec_ends_at_us,
            last_gen_ns, rounds_completed, remaining_rounds, remaining_seconds, present)
    };
    ($from:expr => $to:ident; $($field:ident),*) => {
        $to { $( $field: std::mem::take(&mut $from.$field), )* }
    };
}

impl PendingColumns {
    /// The columns as 0.3.0's type, leaving these empty (no copy).
    fn move_to_v0_3(&mut self) -> v0_3::exports::kairos::policy::priority::PendingColumns {
        use v0_3::exports::kairos::policy::priority::PendingColumns as V0_3Columns;
        take_columns!(self.0 => V0_3Columns)
    }

    /// Takes the vectors back (keeping their capacity for the next call).
    fn move_back_from_v0_3(
        &mut self,
        from: &mut v0_3::exports::kairos::policy::priority::PendingColumns,
    ) {
        use v0_2::exports::kairos::policy::priority::PendingColumns as V0_2Columns;
        self.0 = take_columns!(from => V0_2Columns);
    }
}

/// Bits of `pending-columns.present` (WIT 0.2.0 `present-bits`).
mod present {
    /// `last-exec-ns` is known.
    pub(super) const LAST_EXEC: u8 = 1;
    /// `exec-ends-at-us` is known.
    pub(super) const EXEC_ENDS_AT: u8 = 2;
    /// `last-gen-ns` is known.
    pub(super) const LAST_GEN: u8 = 4;
    /// The client sent `remaining-rounds`.
    pub(super) const REMAINING_ROUNDS: u8 = 8;
    /// The client sent `remaining-seconds`.
    pub(super) const REMAINING_SECONDS: u8 = 16;
}

impl PendingColumns {
    /// Refills every column from `pending`: one pass over the rows, each read once, writing
    /// into columns pre-sized to `n` (so the loop has no capacity checks).
    pub(crate) fn fill(&mut self, pending: &[PendingView]) {
        fn sized<T: Copy + Default>(column: &mut Vec<T>, n: usize) -> &mut [T] {
            column.clear();
            column.resize(n, T::default());
            column
        }
        let n = pending.len();
        let c = &mut self.0;
        let request = sized(&mut c.request, n);
        let task = sized(&mut c.task, n);
        let round_index = sized(&mut c.round_index, n);
        let arrived_at_us = sized(&mut c.arrived_at_us, n);
        let task_started_at_us = sized(&mut c.task_started_at_us, n);
        let skipped = sized(&mut c.skipped, n);
        let wait_ns = sized(&mut c.wait_ns, n);
        let attained_service_ns = sized(&mut c.attained_service_ns, n);
        let queued_ns = sized(&mut c.queued_ns, n);
        let last_exec_ns = sized(&mut c.last_exec_ns, n);
        let exec_ends_at_us = sized(&mut c.exec_ends_at_us, n);
        let last_gen_ns = sized(&mut c.last_gen_ns, n);
        let rounds_completed = sized(&mut c.rounds_completed, n);
        let remaining_rounds = sized(&mut c.remaining_rounds, n);
        let remaining_seconds = sized(&mut c.remaining_seconds, n);
        let present_bits = sized(&mut c.present, n);
        for (i, p) in pending.iter().enumerate() {
            request[i] = p.request.0;
            task[i] = p.task.0;
            round_index[i] = p.round_index;
            arrived_at_us[i] = p.arrived_at.as_micros();
            task_started_at_us[i] = p.task_started_at.as_micros();
            skipped[i] = p.skipped;
            wait_ns[i] = nanos(p.wait);
            attained_service_ns[i] = nanos(p.attained_service);
            queued_ns[i] = nanos(p.queued);
            let mut bits = 0;
            if let Some(d) = p.last_exec {
                last_exec_ns[i] = nanos(d);
                bits |= present::LAST_EXEC;
            }
            if let Some(t) = p.exec_ends_at {
                exec_ends_at_us[i] = t.as_micros();
                bits |= present::EXEC_ENDS_AT;
            }
            if let Some(d) = p.last_gen {
                last_gen_ns[i] = nanos(d);
                bits |= present::LAST_GEN;
            }
            rounds_completed[i] = p.rounds_completed;
            if let Some(remaining) = p.remaining {
                if let Some(rounds) = remaining.rounds {
                    remaining_rounds[i] = rounds;
                    bits |= present::REMAINING_ROUNDS;
                }
                if let Some(seconds) = remaining.seconds {
                    remaining_seconds[i] = seconds;
                    bits |= present::REMAINING_SECONDS;
                }
            }
            present_bits[i] = bits;
        }
    }
}

/// A plugin's answer, whatever its version.
enum Ranking {
    /// Indices, most urgent first (0.1.0's only answer; 0.2.0 `order`).
    Order(Vec<u32>),
    /// 0.2.0 `keys`: the host sorts by `(major, minor, arrived, request)`.
    Keys { major: Vec<u64>, minor: Vec<u64> },
}

/// Calls the policy on `instance`. `Ok(Err(_))` is the plugin's own refusal. `columns` is
/// scratch for 0.2.0 instances.
fn call_rank(
    store: &mut Store<HostState>,
    instance: &PriorityInstance,
    now: Timestamp,
    pending: &[PendingView],
    params: &[(String, f64)],
    columns: &mut PendingColumns,
) -> wasmtime::Result<Result<Ranking, String>> {
    match instance {
        PriorityInstance::V0_1(bindings) => {
            let wit_pending = pending_v0_1(pending);
            let wit_params: Vec<v0_1::kairos::policy::types::Param> = params
                .iter()
                .map(|(name, value)| v0_1::kairos::policy::types::Param {
                    name: name.clone(),
                    value: *value,
                })
                .collect();
            let answer = bindings.kairos_policy_priority().call_order(
                store,
                now.as_micros(),
                &wit_pending,
                &wit_params,
            )?;
            Ok(answer.map(Ranking::Order))
        }
        PriorityInstance::V0_2(bindings) => {
            use v0_2::exports::kairos::policy::priority as wit;
            columns.fill(pending);
            let wit_params: Vec<v0_2::kairos::policy::types::Param> = params
                .iter()
                .map(|(name, value)| v0_2::kairos::policy::types::Param {
                    name: name.clone(),
                    value: *value,
                })
                .collect();
            let answer = bindings.kairos_policy_priority().call_rank(
                store,
                now.as_micros(),
                &columns.0,
                &wit_params,
            )?;
            Ok(answer.map(|ranking| match ranking {
                wit::Ranking::Order(order) => Ranking::Order(order),
                wit::Ranking::Keys(keys) => Ranking::Keys {
                    major: keys.major,
                    minor: keys.minor,
                },
            }))
        }
        PriorityInstance::V0_3(bindings) => {
            // The `priority` interface of 0.3.0 is 0.2.0's: the same columns under another
            // package version. They are moved into 0.3.0's type and back, never copied.
            use v0_3::exports::kairos::policy::priority as wit;
            columns.fill(pending);
            let wit_params: Vec<v0_3::kairos::policy::types::Param> = params
                .iter()
                .map(|(name, value)| v0_3::kairos::policy::types::Param {
                    name: name.clone(),
                    value: *value,
                })
                .collect();
            let mut moved = columns.move_to_v0_3();
            let answer = bindings.kairos_policy_priority().call_rank(
                store,
                now.as_micros(),
                &moved,
                &wit_params,
            );
            columns.move_back_from_v0_3(&mut moved);
            Ok(answer?.map(|ranking| match ranking {
                wit::Ranking::Order(order) => Ranking::Order(order),
                wit::Ranking::Keys(keys) => Ranking::Keys {
                    major: keys.major,
                    minor: keys.minor,
                },
            }))
        }
    }
}

/// Sorts `pending` by the plugin's keys: `(major, minor, arrived, request)` ascending, an
/// empty key list standing for all zeros. `request` is unique, so the order is total and
/// independent of the sort algorithm. Replaces what `order` held. Errors name a key list of
/// the wrong length.
pub(crate) fn order_by_sort_keys(
    pending: &[PendingView],
    major: &[u64],
    minor: &[u64],
    scratch: &mut Vec<SortRow>,
    order: &mut Vec<usize>,
) -> Result<(), String> {
    let n = pending.len();
    for (name, keys) in [("major", major), ("minor", minor)] {
        if !keys.is_empty() && keys.len() != n {
            return Err(format!(
                "{} {name} keys for {n} pending requests",
                keys.len()
            ));
        }
    }
    let key = |keys: &[u64], i: usize| keys.get(i).copied().unwrap_or(0);
    order.clear();
    order_by_indexed_key(pending, order, scratch, |i, p| {
        (
            key(major, i),
            key(minor, i),
            p.arrived_at.as_micros(),
            p.request.0,
        )
    });
    Ok(())
}

/// One row of [`order_by_sort_keys`]'s scratch: the full key, then the pending index.
pub(crate) type SortRow = ((u64, u64, u64, u64), usize);

fn call_task_finished(
    store: &mut Store<HostState>,
    instance: &PriorityInstance,
    summary: &FinishedTask,
) -> wasmtime::Result<()> {
    // `finished-task` is the same record in every version so far.
    macro_rules! finished {
        ($version:ident, $bindings:expr) => {{
            use $version::exports::kairos::policy::priority as wit;
            $bindings.kairos_policy_priority().call_task_finished(
                store,
                wit::FinishedTask {
                    task: summary.task.0,
                    rounds: summary.rounds,
                    latency_ns: nanos(summary.latency),
                    attained_service_ns: nanos(summary.attained_service),
                    wait_ns: nanos(summary.wait),
                },
            )
        }};
    }
    match instance {
        PriorityInstance::V0_1(bindings) => finished!(v0_1, bindings),
        PriorityInstance::V0_2(bindings) => finished!(v0_2, bindings),
        PriorityInstance::V0_3(bindings) => finished!(v0_3, bindings),
    }
}

/// A priority-policy component as a [`PriorityPolicy`].
///
/// The plugin's order is validated (a permutation of the pending indices). A trap, a
/// timeout, an exceeded limit, a refusal or an invalid order discards the instance and
/// orders this decision with the fallback policy (or in arrival-list order should the
/// fallback fail too), so the scheduler always gets a complete order.
pub struct WasmPriorityPolicy {
    plugin: Arc<Compiled<PriorityWorld>>,
    exec: Exec<PriorityWorld>,
    health: Health,
    fallback: Box<dyn PriorityPolicy>,
    reloader: Option<Reloader<PriorityWorld>>,
    params: Vec<(String, f64)>,
    peak_memory: usize,
    /// Scratch reused between calls: the 0.2.0 columns and the key sort.
    columns: PendingColumns,
    sort_rows: Vec<SortRow>,
}

impl WasmPriorityPolicy {
    /// Loads the plugin in `source` with its configuration `params`, with `fallback` for
    /// decisions it fails. The parameters are checked at load with a call on an empty
    /// pending list; a refusal is a load error.
    pub fn load(
        source: &PluginSource,
        params: &PolicyParams,
        options: PluginOptions,
        fallback: Box<dyn PriorityPolicy>,
    ) -> Result<Self, LoadError> {
        let plugin = load::<PriorityWorld>(source, &options)?;
        let options = Arc::new(options);
        let name = plugin.meta.name.clone();
        let reloader = match (source, options.reload_poll) {
            (PluginSource::File(path), Some(poll)) => Some(
                Reloader::spawn(path.clone(), plugin.meta.sha256, options.clone(), poll).map_err(
                    |e| LoadError::Compile {
                        name: name.clone(),
                        message: format!("cannot start its reload watcher: {e}"),
                    },
                )?,
            ),
            _ => None,
        };
        let mut policy = WasmPriorityPolicy {
            exec: Exec::new(plugin.clone(), options.clone())?,
            health: Health::new(name.clone(), &options),
            plugin,
            fallback,
            reloader,
            params: params.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            peak_memory: 0,
            columns: PendingColumns::default(),
            sort_rows: Vec::new(),
        };
        let mut order = Vec::new();
        match policy.call_plugin(Timestamp::ZERO, &[], &mut order) {
            Ok(_) => Ok(policy),
            Err(failure) => Err(LoadError::Compile {
                name,
                message: format!("rejected its parameters or failed a trial call: {failure}"),
            }),
        }
    }

    /// What was loaded.
    pub fn meta(&self) -> &PluginMeta {
        &self.plugin.meta
    }

    /// Counters since load.
    pub fn stats(&self) -> PluginStats {
        self.health.stats()
    }

    /// Largest linear memory any instance had after a successful call, in bytes.
    pub fn peak_memory(&self) -> usize {
        self.peak_memory
    }

    /// Tells the plugin (only) that a task finished, reporting any failure; no health
    /// accounting. For `kairos plugin check`, benches and tests.
    pub fn call_task_finished(&mut self, summary: &FinishedTask) -> Result<(), CallFailure> {
        let summary = *summary;
        let (answer, cost) = self.exec.call(
            |store, instance| call_task_finished(store, instance, &summary),
            || Box::new(move |store, instance| call_task_finished(store, instance, &summary)),
            Ok,
        )?;
        self.peak_memory = self.peak_memory.max(cost.peak_memory);
        Ok(answer)
    }

    /// One call into the plugin with no fallback and no health accounting: fills `order`
    /// (validated) and returns what the call cost. For `kairos plugin check`, benches and
    /// tests.
    pub fn call_plugin(
        &mut self,
        now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<CallCost, CallFailure> {
        order.clear();
        let (params, columns, sort_rows) = (&self.params, &mut self.columns, &mut self.sort_rows);
        let result = self.exec.call(
            |store, instance| call_rank(store, instance, now, pending, params, columns),
            || {
                let owned = pending.to_vec();
                let params = params.clone();
                Box::new(move |store, instance| {
                    let mut columns = PendingColumns::default();
                    call_rank(store, instance, now, &owned, &params, &mut columns)
                })
            },
            |answer| match answer {
                Ok(Ranking::Order(indices)) => {
                    order.extend(indices.iter().map(|&i| i as usize));
                    validate_order(pending.len(), order)
                        .map_err(|e| CallFailure::new(FailureKind::InvalidAnswer, e.to_string()))
                }
                Ok(Ranking::Keys { major, minor }) => {
                    order_by_sort_keys(pending, &major, &minor, sort_rows, order)
                        .map_err(|e| CallFailure::new(FailureKind::InvalidAnswer, e))
                }
                Err(reason) => Err(CallFailure::new(FailureKind::Refused, reason)),
            },
        );
        match result {
            Ok(((), cost)) => {
                self.peak_memory = self.peak_memory.max(cost.peak_memory);
                Ok(cost)
            }
            Err(failure) => {
                order.clear();
                Err(failure)
            }
        }
    }

    fn check_reload(&mut self) {
        let Some(plugin) = self.reloader.as_ref().and_then(Reloader::poll) else {
            return;
        };
        self.exec.replace(plugin.clone());
        self.plugin = plugin;
        self.health.reloaded();
    }

    fn fall_back(&mut self, now: Timestamp, pending: &[PendingView], order: &mut Vec<usize>) {
        order.clear();
        let fallback_ok = self.fallback.order(now, pending, order).is_ok()
            && validate_order(pending.len(), order).is_ok();
        if !fallback_ok {
            // The fallback failed too: the pending list's own order is always complete.
            order.clear();
            order.extend(0..pending.len());
        }
    }
}

impl PriorityPolicy for WasmPriorityPolicy {
    fn name(&self) -> &str {
        &self.plugin.meta.name
    }

    fn order(
        &mut self,
        now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        self.check_reload();
        if !self.health.admit(None) {
            self.fall_back(now, pending, order);
            return Ok(());
        }
        match self.call_plugin(now, pending, order) {
            Ok(cost) => self.health.succeeded(None, cost.elapsed, cost.peak_memory),
            Err(failure) => {
                self.health.failed(None, failure.kind, &failure.message);
                self.fall_back(now, pending, order);
            }
        }
        Ok(())
    }

    fn task_finished(&mut self, summary: &FinishedTask) {
        // The fallback learns too, so it is ready whenever it has to step in.
        self.fallback.task_finished(summary);
        self.check_reload();
        // A quarantined plugin is not called; its probe is a decision.
        if self.health.quarantined() {
            return;
        }
        // Failures count like a decision's (kind, log once, quarantine); there is no answer
        // to fall back for.
        if let Err(failure) = self.call_task_finished(summary) {
            self.health.notice_failed(failure.kind, &failure.message);
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::plugin::runtime::testing::{shipped, short_patience};
    use kairos_core::scheduler::{PolicySpec, RemainingWork, RequestId, TaskId, build_policy};

    fn view(request: u64, arrived_us: u64) -> PendingView {
        PendingView {
            request: RequestId(request),
            task: TaskId(request),
            round_index: 0,
            arrived_at: Timestamp::from_micros(arrived_us),
            task_started_at: Timestamp::ZERO,
            skipped: 0,
            wait: Duration::ZERO,
            attained_service: Duration::ZERO,
            queued: Duration::ZERO,
            last_exec: None,
            exec_ends_at: None,
            last_gen: None,
            rounds_completed: 0,
            remaining: None,
        }
    }

    #[test]
    fn sort_keys_order_by_major_minor_then_arrival_then_request() {
        let pending = [view(7, 30), view(3, 10), view(5, 10), view(1, 20)];
        let (mut rows, mut order) = (Vec::new(), Vec::new());
        // Empty keys: arrival, then request.
        order_by_sort_keys(&pending, &[], &[], &mut rows, &mut order).unwrap();
        assert_eq!(order, [1, 2, 3, 0]);
        // Major first; minor breaks its ties; empty minor is all zeros.
        order_by_sort_keys(&pending, &[1, 0, 1, 0], &[], &mut rows, &mut order).unwrap();
        assert_eq!(order, [1, 3, 2, 0]);
        order_by_sort_keys(
            &pending,
            &[1, 0, 1, 0],
            &[0, 9, 5, 2],
            &mut rows,
            &mut order,
        )
        .unwrap();
        assert_eq!(order, [3, 1, 0, 2]);
    }

    #[test]
    fn key_lists_of_the_wrong_length_are_refused_by_name() {
        let pending = [view(1, 1), view(2, 2)];
        let (mut rows, mut order) = (Vec::new(), Vec::new());
        let err = order_by_sort_keys(&pending, &[1], &[], &mut rows, &mut order).unwrap_err();
        assert!(err.contains("1 major keys for 2"), "{err}");
        let err = order_by_sort_keys(&pending, &[], &[1, 2, 3], &mut rows, &mut order).unwrap_err();
        assert!(err.contains("3 minor keys for 2"), "{err}");
    }

    #[test]
    fn columns_carry_every_field_and_mark_what_is_known() {
        let mut full = view(4, 40);
        full.last_exec = Some(Duration::from_nanos(1_500));
        full.exec_ends_at = Some(Timestamp::from_micros(99));
        full.last_gen = Some(Duration::from_nanos(2_500));
        full.remaining = Some(RemainingWork {
            rounds: Some(3),
            seconds: Some(0.5),
        });
        let mut hint_rounds_only = view(6, 60);
        hint_rounds_only.remaining = Some(RemainingWork {
            rounds: Some(0),
            seconds: None,
        });
        let mut columns = PendingColumns::default();
        columns.fill(&[view(2, 20), full, hint_rounds_only]);
        let c = &columns.0;
        assert_eq!(c.request, [2, 4, 6]);
        assert_eq!(c.arrived_at_us, [20, 40, 60]);
        assert_eq!(c.last_exec_ns, [0, 1_500, 0]);
        assert_eq!(c.exec_ends_at_us, [0, 99, 0]);
        assert_eq!(c.last_gen_ns, [0, 2_500, 0]);
        assert_eq!(c.remaining_rounds, [0, 3, 0]);
        assert_eq!(c.remaining_seconds, [0.0, 0.5, 0.0]);
        assert_eq!(c.present, [0, 31, present::REMAINING_ROUNDS]);
        // Refilling reuses the vectors and drops the old rows.
        columns.fill(&[view(9, 1)]);
        assert_eq!(columns.0.request, [9]);
        assert_eq!(columns.0.present, [0]);
    }

    #[test]
    fn a_stuck_worker_thread_is_abandoned_and_replaced_in_every_export() {
        let options = short_patience(PluginOptions::priority());
        let fallback = build_policy(&PolicySpec::named("fifo")).unwrap();
        let mut policy = WasmPriorityPolicy::load(
            &shipped("fifo"),
            &PolicyParams::new(),
            options.clone(),
            fallback,
        )
        .unwrap();
        // The C plugin runs inline; give it a worker thread as a WASI component gets.
        policy.exec = Exec::worker(policy.plugin.clone(), Arc::new(options)).unwrap();
        let pending = [view(1, 10), view(2, 5)];
        let now = Timestamp::from_micros(100);
        let summary = FinishedTask {
            task: TaskId(1),
            rounds: 2,
            latency: Duration::from_secs(1),
            attained_service: Duration::from_millis(100),
            wait: Duration::from_millis(10),
        };
        let mut order = Vec::new();

        // `order`: the stuck thread is given up, the fallback orders, a new thread answers next.
        let stuck = policy.exec.block_worker();
        policy.order(now, &pending, &mut order).unwrap();
        assert_eq!(order, [1, 0]);
        let stats = policy.stats();
        assert_eq!(
            (stats.failures_of(FailureKind::Stuck), stats.fallbacks),
            (1, 1)
        );
        order.clear();
        policy.order(now, &pending, &mut order).unwrap();
        assert_eq!(policy.stats().answered, 1, "the replacement thread answers");
        // Released now, the abandoned thread's late answer goes nowhere.
        drop(stuck);

        // `task-finished`: the same, through the same wrapper.
        let stuck = policy.exec.block_worker();
        policy.task_finished(&summary);
        assert_eq!(policy.stats().failures_of(FailureKind::Stuck), 2);
        assert_eq!(policy.call_task_finished(&summary), Ok(()));
        order.clear();
        policy.order(now, &pending, &mut order).unwrap();
        assert_eq!(order, [1, 0]);
        let stats = policy.stats();
        assert_eq!((stats.answered, stats.fallbacks), (2, 1));
        drop(stuck);
    }
}
