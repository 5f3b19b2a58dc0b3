//! [`WasmPriorityPolicy`]: a `priority-policy` component behind the native
//! [`PriorityPolicy`] trait, with containment and a fallback policy.

use std::sync::Arc;

use wasmtime::Store;
use wasmtime::component::{Component, Linker};

use super::bindings::{WitVersion, since_v0_1_0};
use super::health::{FailureKind, Health, PluginStats};
use super::reload::Reloader;
use super::runtime::{CallCost, CallFailure, Compiled, Exec, LoadError, PluginMeta, World, load};
use super::sandbox::HostState;
use super::{PluginKind, PluginOptions, PluginSource};
use crate::horizon::PolicyParams;
use crate::scheduler::{FinishedTask, PendingView, PolicyError, PriorityPolicy, validate_order};
use crate::time::Timestamp;

use since_v0_1_0::priority as v0_1;

pub(crate) struct PriorityWorld;

pub(crate) enum PriorityPre {
    V0_1(v0_1::PriorityPolicyPre<HostState>),
}

pub(crate) enum PriorityInstance {
    V0_1(v0_1::PriorityPolicy),
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
        }
    }
}

fn nanos(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

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

/// Calls `order` on `instance`. `Ok(Err(_))` is the plugin's own refusal.
fn call_order(
    store: &mut Store<HostState>,
    instance: &PriorityInstance,
    now: Timestamp,
    pending: &[PendingView],
    params: &[(String, f64)],
) -> wasmtime::Result<Result<Vec<u32>, String>> {
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
            bindings.kairos_policy_priority().call_order(
                store,
                now.as_micros(),
                &wit_pending,
                &wit_params,
            )
        }
    }
}

fn call_task_finished(
    store: &mut Store<HostState>,
    instance: &PriorityInstance,
    summary: &FinishedTask,
) -> wasmtime::Result<()> {
    match instance {
        PriorityInstance::V0_1(bindings) => {
            use v0_1::exports::kairos::policy::priority as wit;
            bindings.kairos_policy_priority().call_task_finished(
                store,
                wit::FinishedTask {
                    task: summary.task.0,
                    rounds: summary.rounds,
                    latency_ns: nanos(summary.latency),
                    attained_service_ns: nanos(summary.attained_service),
                    wait_ns: nanos(summary.wait),
                },
            )
        }
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
    options: Arc<PluginOptions>,
    exec: Exec<PriorityWorld>,
    health: Health,
    fallback: Box<dyn PriorityPolicy>,
    reloader: Option<Reloader<PriorityWorld>>,
    params: Vec<(String, f64)>,
    peak_memory: usize,
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
            options,
            fallback,
            reloader,
            params: params.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            peak_memory: 0,
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

    /// Tells the plugin (only) that a task finished, reporting any failure.
    pub fn call_task_finished(&mut self, summary: &FinishedTask) -> Result<(), CallFailure> {
        let summary = *summary;
        match &mut self.exec {
            Exec::Inline(live) => live
                .call(|store, instance| call_task_finished(store, instance, &summary))
                .map(drop),
            Exec::Worker(worker) => worker
                .run(move |live| {
                    live.call(|store, instance| call_task_finished(store, instance, &summary))
                        .map(drop)
                })
                .unwrap_or_else(|| {
                    Err(CallFailure::new(
                        FailureKind::Timeout,
                        "worker did not answer",
                    ))
                }),
        }
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
        let result = match &mut self.exec {
            Exec::Inline(live) => {
                let params = &self.params;
                live.call(|store, instance| call_order(store, instance, now, pending, params))
            }
            Exec::Worker(worker) => {
                let owned = pending.to_vec();
                let params = self.params.clone();
                let answer = worker.run(move |live| {
                    live.call(|store, instance| call_order(store, instance, now, &owned, &params))
                });
                match answer {
                    Some(answer) => answer,
                    None => {
                        self.exec =
                            Exec::new(self.plugin.clone(), self.options.clone()).map_err(|e| {
                                CallFailure::new(FailureKind::Instantiate, e.to_string())
                            })?;
                        return Err(CallFailure::new(
                            FailureKind::Timeout,
                            "the plugin's worker thread did not answer; replaced it",
                        ));
                    }
                }
            }
        };
        let (answer, cost) = result?;
        self.peak_memory = self.peak_memory.max(cost.peak_memory);
        let failure = match answer {
            Ok(indices) => {
                order.extend(indices.iter().map(|&i| i as usize));
                match validate_order(pending.len(), order) {
                    Ok(()) => return Ok(cost),
                    Err(e) => CallFailure::new(FailureKind::InvalidAnswer, e.to_string()),
                }
            }
            Err(reason) => CallFailure::new(FailureKind::Refused, reason),
        };
        order.clear();
        self.exec.discard();
        Err(failure)
    }

    fn check_reload(&mut self) {
        let Some(plugin) = self.reloader.as_ref().and_then(Reloader::poll) else {
            return;
        };
        let swapped = match &mut self.exec {
            Exec::Inline(live) => {
                live.replace(plugin.clone());
                Ok(())
            }
            Exec::Worker(_) => {
                Exec::new(plugin.clone(), self.options.clone()).map(|exec| self.exec = exec)
            }
        };
        match swapped {
            Ok(()) => {
                self.plugin = plugin;
                self.health.reloaded();
            }
            Err(error) => {
                tracing::error!(plugin = %self.plugin.meta.name, %error, "cannot swap in the reloaded plugin; keeping the running version");
            }
        }
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
        if !self.health.admit() {
            self.fall_back(now, pending, order);
            return Ok(());
        }
        match self.call_plugin(now, pending, order) {
            Ok(cost) => self.health.succeeded(cost.elapsed, cost.peak_memory),
            Err(failure) => {
                self.health.failed(failure.kind, &failure.message);
                self.fall_back(now, pending, order);
            }
        }
        Ok(())
    }

    fn task_finished(&mut self, summary: &FinishedTask) {
        // The fallback learns too, so it is ready whenever it has to step in.
        self.fallback.task_finished(summary);
        if let Err(failure) = self.call_task_finished(summary) {
            tracing::debug!(plugin = %self.plugin.meta.name, %failure, "task-finished failed");
        }
    }
}
