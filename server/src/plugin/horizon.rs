//! [`WasmHorizonPolicy`]: a `horizon-policy` component behind the native [`HorizonPolicy`]
//! trait, with containment and a fallback policy.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use wasmtime::Store;
use wasmtime::component::{Component, Linker};

use super::bindings::{WitVersion, since_v0_1_0, since_v0_2_0, since_v0_3_0};
use super::health::{FailureKind, Health, PluginStats};
use super::reload::Reloader;
use super::runtime::{CallCost, CallFailure, Compiled, Exec, LoadError, PluginMeta, World, load};
use super::sandbox::HostState;
use super::{PluginKind, PluginOptions, PluginSource};
use kairos_core::horizon::{
    HorizonError, HorizonInput, HorizonPolicy, PolicyParams, validate_horizon,
};
use kairos_core::scheduler::{RobotId, ServerLoad};

use since_v0_1_0::horizon as v0_1;
use since_v0_2_0::horizon as v0_2;
use since_v0_3_0::horizon as v0_3;

pub(crate) struct HorizonWorld;

pub(crate) enum HorizonPre {
    V0_1(v0_1::HorizonPolicyPre<HostState>),
    V0_2(v0_2::HorizonPolicyPre<HostState>),
    V0_3(v0_3::HorizonPolicyPre<HostState>),
}

pub(crate) enum HorizonInstance {
    V0_1(v0_1::HorizonPolicy),
    V0_2(v0_2::HorizonPolicy),
    V0_3(v0_3::HorizonPolicy),
}

impl World for HorizonWorld {
    const KIND: PluginKind = PluginKind::Horizon;
    type Pre = HorizonPre;
    type Instance = HorizonInstance;

    fn pre(
        version: WitVersion,
        linker: &Linker<HostState>,
        component: &Component,
    ) -> wasmtime::Result<HorizonPre> {
        // `inspect` admitted only supported versions; each maps to its bindings here.
        match (version.major, version.minor) {
            (0, 1) => Ok(HorizonPre::V0_1(v0_1::HorizonPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            (0, 2) => Ok(HorizonPre::V0_2(v0_2::HorizonPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            (0, 3) => Ok(HorizonPre::V0_3(v0_3::HorizonPolicyPre::new(
                linker.instantiate_pre(component)?,
            )?)),
            _ => Err(wasmtime::Error::msg(format!(
                "no bindings for version {version}"
            ))),
        }
    }

    fn instantiate(
        pre: &HorizonPre,
        store: &mut Store<HostState>,
    ) -> wasmtime::Result<HorizonInstance> {
        match pre {
            HorizonPre::V0_1(pre) => pre.instantiate(store).map(HorizonInstance::V0_1),
            HorizonPre::V0_2(pre) => pre.instantiate(store).map(HorizonInstance::V0_2),
            HorizonPre::V0_3(pre) => pre.instantiate(store).map(HorizonInstance::V0_3),
        }
    }
}

/// Calls `choose` through one version's bindings. The `horizon` interface is the same in
/// 0.1.0 and 0.2.0 (only the generated types' paths differ, hence a macro); 0.3.0 adds the
/// context's `load`, passed with `load`.
macro_rules! call_choose_in {
    ($version:ident, $bindings:expr, $store:expr, $input:expr, $params:expr) => {
        call_choose_in!($version, $bindings, $store, $input, $params, {})
    };
    ($version:ident, $bindings:expr, $store:expr, $input:expr, $params:expr, load) => {
        call_choose_in!($version, $bindings, $store, $input, $params, {
            load: $input.load.map(|l| wit::ServerLoad {
                queued: l.queued,
                running: l.running,
                open_tasks: l.open_tasks,
                backlog_ns: kairos_core::time::duration_nanos(l.backlog),
            }),
        })
    };
    ($version:ident, $bindings:expr, $store:expr, $input:expr, $params:expr, { $($load:tt)* }) => {{
        use $version::exports::kairos::policy::horizon as wit;
        let chunk = &$input.chunk;
        let wit_chunk = wit::Chunk {
            samples: to_u32(chunk.samples),
            steps: to_u32(chunk.steps),
            chunk_len: to_u32(chunk.chunk_len),
            action_dim: to_u32(chunk.action_dim),
            updates: chunk.updates,
            actions: chunk.actions,
        };
        let context = wit::HorizonContext {
            h_min: to_u32($input.h_min),
            h_max: to_u32($input.h_max),
            control_hz: $input.control_hz,
            round_index: $input.round_index,
            recent_horizons: $input.recent_horizons,
            $($load)*
        };
        let wit_params: Vec<$version::kairos::policy::types::Param<'_>> = $params
            .iter()
            .map(|(name, value)| $version::kairos::policy::types::Param {
                name,
                value: *value,
            })
            .collect();
        let answer = $bindings.kairos_policy_horizon().call_choose(
            $store,
            wit_chunk,
            context,
            &wit_params,
        )?;
        Ok(answer.map_err(|e| match e {
            wit::HorizonError::InvalidParam(p) => HorizonError::InvalidParam {
                name: p.name,
                reason: p.reason,
            },
            wit::HorizonError::Unsupported(m) => HorizonError::Unsupported(m),
            wit::HorizonError::Failed(m) => HorizonError::Failed(m),
        }))
    }};
}

/// Calls `choose` on `instance` with `input`, converted to the instance's WIT version.
fn call_choose(
    store: &mut Store<HostState>,
    instance: &HorizonInstance,
    input: &HorizonInput<'_>,
    params: &[(String, f64)],
) -> wasmtime::Result<Result<u32, HorizonError>> {
    match instance {
        HorizonInstance::V0_1(bindings) => call_choose_in!(v0_1, bindings, store, input, params),
        HorizonInstance::V0_2(bindings) => call_choose_in!(v0_2, bindings, store, input, params),
        HorizonInstance::V0_3(bindings) => {
            call_choose_in!(v0_3, bindings, store, input, params, load)
        }
    }
}

/// Sizes beyond `u32` cannot occur (the protocol caps chunks far below); saturate rather
/// than wrap so a plugin never sees a small bogus value.
fn to_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

/// A [`HorizonInput`] with owned buffers, to send to a worker thread.
#[derive(Clone, Debug, PartialEq)]
pub struct OwnedHorizonInput {
    /// `S`.
    pub samples: usize,
    /// `K`.
    pub steps: usize,
    /// `N`.
    pub chunk_len: usize,
    /// `D`.
    pub action_dim: usize,
    /// `[S][K][N][D]`.
    pub updates: Vec<f32>,
    /// `[S][N][D]`.
    pub actions: Vec<f32>,
    /// `H_min`.
    pub h_min: usize,
    /// `H_max`.
    pub h_max: usize,
    /// Control frequency.
    pub control_hz: f32,
    /// Round index.
    pub round_index: u64,
    /// Recent horizons.
    pub recent_horizons: Vec<u32>,
    /// Parameters.
    pub params: PolicyParams,
    /// The server's load.
    pub load: Option<ServerLoad>,
}

impl OwnedHorizonInput {
    /// Copies `input`.
    pub fn copy_of(input: &HorizonInput<'_>) -> Self {
        OwnedHorizonInput {
            samples: input.chunk.samples,
            steps: input.chunk.steps,
            chunk_len: input.chunk.chunk_len,
            action_dim: input.chunk.action_dim,
            updates: input.chunk.updates.to_vec(),
            actions: input.chunk.actions.to_vec(),
            h_min: input.h_min,
            h_max: input.h_max,
            control_hz: input.control_hz,
            round_index: input.round_index,
            recent_horizons: input.recent_horizons.to_vec(),
            params: input.params.clone(),
            load: input.load,
        }
    }

    /// Borrows it as a [`HorizonInput`].
    pub fn view(&self) -> HorizonInput<'_> {
        HorizonInput {
            chunk: kairos_core::horizon::ChunkView {
                samples: self.samples,
                steps: self.steps,
                chunk_len: self.chunk_len,
                action_dim: self.action_dim,
                updates: &self.updates,
                actions: &self.actions,
            },
            h_min: self.h_min,
            h_max: self.h_max,
            control_hz: self.control_hz,
            round_index: self.round_index,
            recent_horizons: &self.recent_horizons,
            params: &self.params,
            load: self.load,
        }
    }
}

/// An executor with the plugin version its instance runs.
type VersionedExec = (Arc<Compiled<HorizonWorld>>, Exec<HorizonWorld>);

/// What every handle of one loaded horizon plugin shares.
struct Shared {
    /// The running version.
    current: Mutex<Arc<Compiled<HorizonWorld>>>,
    options: Arc<PluginOptions>,
    health: Mutex<Health>,
    /// Idle executors (each with its instance, kept warm), tagged with their version.
    idle: Mutex<Vec<VersionedExec>>,
    reloader: Option<Mutex<Reloader<HorizonWorld>>>,
    peak_memory: AtomicUsize,
}

/// A loaded horizon-policy component, shared by every request that uses it.
///
/// The server builds a horizon policy per request; [`HorizonPlugin::policy`] makes that cheap
/// (no compilation, no instantiation): handles share one compiled plugin, one health record
/// (so quarantine is per plugin and robot, not per request) and a pool of warm instances, one
/// per concurrent call.
#[derive(Clone)]
pub struct HorizonPlugin(Arc<Shared>);

impl std::fmt::Debug for HorizonPlugin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("HorizonPlugin")
            .field(&self.meta().name)
            .finish()
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding one of these locks leaves consistent data (counters, a pool):
    // keep serving rather than poisoning every later decision.
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl HorizonPlugin {
    /// Loads (compiles, links) the plugin in `source` and starts watching its file.
    pub fn load(source: &PluginSource, options: PluginOptions) -> Result<Self, LoadError> {
        let plugin = load::<HorizonWorld>(source, &options)?;
        let options = Arc::new(options);
        let reloader = match (source, options.reload_poll) {
            (PluginSource::File(path), Some(poll)) => Some(Mutex::new(
                Reloader::spawn(path.clone(), plugin.meta.sha256, options.clone(), poll).map_err(
                    |e| LoadError::Compile {
                        name: plugin.meta.name.clone(),
                        message: format!("cannot start its reload watcher: {e}"),
                    },
                )?,
            )),
            _ => None,
        };
        // One executor up front: a worker thread that cannot start fails the load, not a call.
        let first = Exec::new(plugin.clone(), options.clone())?;
        Ok(HorizonPlugin(Arc::new(Shared {
            health: Mutex::new(Health::new(plugin.meta.name.clone(), &options)),
            idle: Mutex::new(vec![(plugin.clone(), first)]),
            current: Mutex::new(plugin),
            options,
            reloader,
            peak_memory: AtomicUsize::new(0),
        })))
    }

    /// A policy object for one request (or one owner), answering with `fallback` when the
    /// plugin fails.
    pub fn policy(&self, fallback: Box<dyn HorizonPolicy>) -> WasmHorizonPolicy {
        WasmHorizonPolicy {
            name: self.meta().name,
            plugin: self.clone(),
            fallback,
            robot: None,
            params: Default::default(),
            fell_back: false,
        }
    }

    /// What is loaded now.
    pub fn meta(&self) -> PluginMeta {
        lock(&self.0.current).meta.clone()
    }

    /// Counters since load, over every handle.
    pub fn stats(&self) -> PluginStats {
        lock(&self.0.health).stats()
    }

    /// Largest linear memory any instance had after a successful call, in bytes.
    pub fn peak_memory(&self) -> usize {
        self.0.peak_memory.load(Ordering::Relaxed)
    }

    /// Swaps in a newly compiled version, if the watcher has one.
    fn check_reload(&self) {
        let Some(reloader) = &self.0.reloader else {
            return;
        };
        let Some(plugin) = lock(reloader).poll() else {
            return;
        };
        *lock(&self.0.current) = plugin;
        // Old instances are dropped as they come back; idle ones right now.
        lock(&self.0.idle).clear();
        lock(&self.0.health).reloaded();
    }

    /// An executor of the running version: a warm idle one, or a new one.
    fn checkout(&self) -> Result<VersionedExec, CallFailure> {
        self.check_reload();
        let current = lock(&self.0.current).clone();
        let mut idle = lock(&self.0.idle);
        while let Some((plugin, exec)) = idle.pop() {
            if Arc::ptr_eq(&plugin, &current) {
                return Ok((plugin, exec));
            }
        }
        drop(idle);
        let exec = Exec::new(current.clone(), self.0.options.clone())
            .map_err(|e| CallFailure::new(FailureKind::Instantiate, e.to_string()))?;
        Ok((current, exec))
    }

    /// Returns an executor to the pool, unless a newer version has been loaded meanwhile.
    fn checkin(&self, plugin: Arc<Compiled<HorizonWorld>>, exec: Exec<HorizonWorld>) {
        if Arc::ptr_eq(&plugin, &lock(&self.0.current)) {
            lock(&self.0.idle).push((plugin, exec));
        }
    }
}

/// A horizon-policy component as a [`HorizonPolicy`]: one handle of a [`HorizonPlugin`].
///
/// A valid answer of the plugin is returned as is; a plugin's own refusal
/// (`horizon-error`) is returned as the matching [`HorizonError`], as a native policy would.
/// A trap, a timeout, an exceeded limit or an answer outside `[h_min, h_max]` discards the
/// instance and answers with the fallback policy (or `h_min` should the fallback fail too).
pub struct WasmHorizonPolicy {
    name: String,
    plugin: HorizonPlugin,
    fallback: Box<dyn HorizonPolicy>,
    /// The robot whose rounds this handle decides (its quarantine is that robot's first).
    robot: Option<RobotId>,
    /// The last parameters, converted once and reused while they stay the same.
    params: (PolicyParams, Vec<(String, f64)>),
    /// Whether the last decision was the fallback's (see [`HorizonPolicy::answered_by`]).
    fell_back: bool,
}

impl WasmHorizonPolicy {
    /// Loads the plugin in `source` and returns one handle, with `fallback` for decisions it
    /// fails. Use [`HorizonPlugin`] to share one plugin between many handles.
    pub fn load(
        source: &PluginSource,
        options: PluginOptions,
        fallback: Box<dyn HorizonPolicy>,
    ) -> Result<Self, LoadError> {
        Ok(HorizonPlugin::load(source, options)?.policy(fallback))
    }

    /// The plugin this handle calls.
    pub fn plugin(&self) -> &HorizonPlugin {
        &self.plugin
    }

    /// What is loaded now.
    pub fn meta(&self) -> PluginMeta {
        self.plugin.meta()
    }

    /// The plugin's counters since load (over every handle).
    pub fn stats(&self) -> PluginStats {
        self.plugin.stats()
    }

    /// Largest linear memory any instance had after a successful call, in bytes.
    pub fn peak_memory(&self) -> usize {
        self.plugin.peak_memory()
    }

    /// One call into the plugin with no fallback and no health accounting: the answer
    /// (validated) and what the call cost. For `kairos plugin check`, benches and tests.
    pub fn call_plugin(
        &mut self,
        input: &HorizonInput<'_>,
    ) -> Result<(Result<usize, HorizonError>, CallCost), CallFailure> {
        if self.params.0 != *input.params {
            self.params = (
                input.params.clone(),
                input.params.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            );
        }
        let (plugin, mut exec) = self.plugin.checkout()?;
        let params = &self.params.1;
        let outcome = exec.call(
            |store, instance| call_choose(store, instance, input, params),
            || {
                let owned = OwnedHorizonInput::copy_of(input);
                let params = params.clone();
                Box::new(move |store, instance| {
                    call_choose(store, instance, &owned.view(), &params)
                })
            },
            |answer| match answer {
                Ok(h) => validate_horizon(h as usize, input)
                    .map(Ok)
                    .map_err(|e| CallFailure::new(FailureKind::InvalidAnswer, e.to_string())),
                // The plugin's own refusal is an answer, passed on like a native policy's error.
                Err(refusal) => Ok(Err(refusal)),
            },
        );
        if let Ok((_, cost)) = &outcome {
            self.plugin
                .0
                .peak_memory
                .fetch_max(cost.peak_memory, Ordering::Relaxed);
        }
        // Whatever happened, the executor is usable again: a failed instance was discarded, a
        // stuck worker thread replaced.
        self.plugin.checkin(plugin, exec);
        outcome
    }

    fn fall_back(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        self.fell_back = true;
        match self
            .fallback
            .choose(input)
            .and_then(|h| validate_horizon(h, input))
        {
            Ok(h) => Ok(h),
            // The fallback could not decide either: the most conservative executable answer.
            Err(_) => validate_horizon(input.h_min, input),
        }
    }
}

impl HorizonPolicy for WasmHorizonPolicy {
    fn name(&self) -> &str {
        &self.name
    }

    fn answered_by(&self) -> Option<&str> {
        self.fell_back.then(|| self.fallback.name())
    }

    fn serve_robot(&mut self, robot: RobotId) {
        self.robot = Some(robot);
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        self.fell_back = false;
        if !input.chunk.is_consistent() {
            // Not the plugin's fault, and the WIT promises consistent buffers: no call.
            return self.fall_back(input);
        }
        if !lock(&self.plugin.0.health).admit(self.robot) {
            self.plugin.check_reload();
            return self.fall_back(input);
        }
        let result = self.call_plugin(input);
        let mut health = lock(&self.plugin.0.health);
        match result {
            Ok((answer, cost)) => {
                health.succeeded(self.robot, cost.elapsed, cost.peak_memory);
                if let Err(refusal) = &answer {
                    health.refused(&refusal.to_string());
                }
                answer
            }
            Err(failure) => {
                health.failed(self.robot, failure.kind, &failure.message);
                drop(health);
                self.fall_back(input)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plugin::runtime::testing::{shipped, short_patience};
    use kairos_core::horizon::ChunkView;

    #[test]
    fn a_stuck_worker_thread_is_abandoned_and_replaced() {
        // As `priority`'s test of the same name, for `choose`: one wrapper, one behaviour.
        let options = short_patience(PluginOptions::horizon());
        let plugin = HorizonPlugin::load(&shipped("threshold"), options).unwrap();
        // The C plugin runs inline; give its one pooled executor a worker thread, as a WASI
        // component gets.
        let release = {
            let current = lock(&plugin.0.current).clone();
            let mut exec = Exec::worker(current.clone(), plugin.0.options.clone()).unwrap();
            let release = exec.block_worker();
            let mut idle = lock(&plugin.0.idle);
            idle.clear();
            idle.push((current, exec));
            release
        };
        let fallback =
            kairos_core::horizon::builtin("static", &PolicyParams::from([("h".to_string(), 3.0)]))
                .unwrap();
        let mut policy = plugin.policy(fallback);
        let updates = [0.1, 0.1, 0.1, 0.1, 0.2, 0.2, 0.2, 0.2];
        let (actions, params) = ([0.0; 4], PolicyParams::new());
        let input = HorizonInput {
            chunk: ChunkView {
                samples: 1,
                steps: 2,
                chunk_len: 4,
                action_dim: 1,
                updates: &updates,
                actions: &actions,
            },
            h_min: 1,
            h_max: 4,
            control_hz: 10.0,
            round_index: 0,
            recent_horizons: &[],
            params: &params,
            load: None,
        };
        assert_eq!(policy.choose(&input), Ok(3), "the fallback answers");
        assert_eq!(policy.answered_by(), Some("static"), "and is named as such");
        let stats = policy.stats();
        assert_eq!(
            (stats.failures_of(FailureKind::Stuck), stats.fallbacks),
            (1, 1)
        );
        let answer = policy.choose(&input);
        assert_eq!(policy.stats().answered, 1, "the replacement thread answers");
        assert_eq!(policy.answered_by(), None, "the plugin answered itself");
        let mut native = kairos_core::horizon::builtin("threshold", &params).unwrap();
        assert_eq!(
            answer,
            native.choose(&input),
            "the plugin is the native policy's twin"
        );
        drop(release);
    }
}
