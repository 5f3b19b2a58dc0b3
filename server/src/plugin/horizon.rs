//! [`WasmHorizonPolicy`]: a `horizon-policy` component behind the native [`HorizonPolicy`]
//! trait, with containment and a fallback policy.

use std::sync::Arc;

use wasmtime::Store;
use wasmtime::component::{Component, Linker};

use super::bindings::{WitVersion, since_v0_1_0};
use super::health::{FailureKind, Health, PluginStats};
use super::reload::Reloader;
use super::runtime::{CallCost, CallFailure, Compiled, Exec, LoadError, PluginMeta, World, load};
use super::sandbox::HostState;
use super::{PluginKind, PluginOptions, PluginSource};
use crate::horizon::{HorizonError, HorizonInput, HorizonPolicy, PolicyParams, validate_horizon};

use since_v0_1_0::horizon as v0_1;

pub(crate) struct HorizonWorld;

pub(crate) enum HorizonPre {
    V0_1(v0_1::HorizonPolicyPre<HostState>),
}

pub(crate) enum HorizonInstance {
    V0_1(v0_1::HorizonPolicy),
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
        }
    }
}

/// Calls `choose` on `instance` with `input`, converted to the instance's WIT version.
fn call_choose(
    store: &mut Store<HostState>,
    instance: &HorizonInstance,
    input: &HorizonInput<'_>,
    params: &[(String, f64)],
) -> wasmtime::Result<Result<u32, HorizonError>> {
    match instance {
        HorizonInstance::V0_1(bindings) => {
            use v0_1::exports::kairos::policy::horizon as wit;
            let chunk = &input.chunk;
            let wit_chunk = wit::Chunk {
                samples: to_u32(chunk.samples),
                steps: to_u32(chunk.steps),
                chunk_len: to_u32(chunk.chunk_len),
                action_dim: to_u32(chunk.action_dim),
                updates: chunk.updates,
                actions: chunk.actions,
            };
            let context = wit::HorizonContext {
                h_min: to_u32(input.h_min),
                h_max: to_u32(input.h_max),
                control_hz: input.control_hz,
                round_index: input.round_index,
                recent_horizons: input.recent_horizons,
            };
            let wit_params: Vec<v0_1::kairos::policy::types::Param<'_>> = params
                .iter()
                .map(|(name, value)| v0_1::kairos::policy::types::Param {
                    name,
                    value: *value,
                })
                .collect();
            let answer = bindings.kairos_policy_horizon().call_choose(
                store,
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
        }
    }

    /// Borrows it as a [`HorizonInput`].
    pub fn view(&self) -> HorizonInput<'_> {
        HorizonInput {
            chunk: crate::horizon::ChunkView {
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
        }
    }
}

/// A horizon-policy component as a [`HorizonPolicy`].
///
/// A valid answer of the plugin is returned as is; a plugin's own refusal
/// (`horizon-error`) is returned as the matching [`HorizonError`], as a native policy would.
/// A trap, a timeout, an exceeded limit or an answer outside `[h_min, h_max]` discards the
/// instance and answers with the fallback policy (or `h_min` should the fallback fail too).
pub struct WasmHorizonPolicy {
    plugin: Arc<Compiled<HorizonWorld>>,
    options: Arc<PluginOptions>,
    exec: Exec<HorizonWorld>,
    health: Health,
    fallback: Box<dyn HorizonPolicy>,
    reloader: Option<Reloader<HorizonWorld>>,
    /// The last parameters, converted once and reused while they stay the same.
    params: (PolicyParams, Vec<(String, f64)>),
    peak_memory: usize,
}

impl WasmHorizonPolicy {
    /// Loads the plugin in `source`, with `fallback` for decisions it fails.
    pub fn load(
        source: &PluginSource,
        options: PluginOptions,
        fallback: Box<dyn HorizonPolicy>,
    ) -> Result<Self, LoadError> {
        let plugin = load::<HorizonWorld>(source, &options)?;
        let options = Arc::new(options);
        let reloader = match (source, options.reload_poll) {
            (PluginSource::File(path), Some(poll)) => Some(
                Reloader::spawn(path.clone(), plugin.meta.sha256, options.clone(), poll).map_err(
                    |e| LoadError::Compile {
                        name: plugin.meta.name.clone(),
                        message: format!("cannot start its reload watcher: {e}"),
                    },
                )?,
            ),
            _ => None,
        };
        Ok(WasmHorizonPolicy {
            exec: Exec::new(plugin.clone(), options.clone())?,
            health: Health::new(plugin.meta.name.clone(), &options),
            plugin,
            options,
            fallback,
            reloader,
            params: Default::default(),
            peak_memory: 0,
        })
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
        let result = match &mut self.exec {
            Exec::Inline(live) => {
                let params = &self.params.1;
                live.call(|store, instance| call_choose(store, instance, input, params))
            }
            Exec::Worker(worker) => {
                let owned = OwnedHorizonInput::copy_of(input);
                let params = self.params.1.clone();
                let answer = worker.run(move |live| {
                    let input = owned.view();
                    live.call(|store, instance| call_choose(store, instance, &input, &params))
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
        match answer {
            Ok(h) => match validate_horizon(h as usize, input) {
                Ok(h) => Ok((Ok(h), cost)),
                Err(e) => {
                    self.discard_instance();
                    Err(CallFailure::new(FailureKind::InvalidAnswer, e.to_string()))
                }
            },
            Err(e) => Ok((Err(e), cost)),
        }
    }

    fn discard_instance(&mut self) {
        match &mut self.exec {
            Exec::Inline(live) => live.discard(),
            Exec::Worker(worker) => {
                let _ = worker.run(|live| live.discard());
            }
        }
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

    fn fall_back(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
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
        &self.plugin.meta.name
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        self.check_reload();
        if !input.chunk.is_consistent() {
            // Not the plugin's fault, and the WIT promises consistent buffers: no call.
            return self.fall_back(input);
        }
        if !self.health.admit() {
            return self.fall_back(input);
        }
        match self.call_plugin(input) {
            Ok((answer, cost)) => {
                self.health.succeeded(cost.elapsed, cost.peak_memory);
                if let Err(refusal) = &answer {
                    self.health.refused(&refusal.to_string());
                }
                answer
            }
            Err(failure) => {
                self.health.failed(failure.kind, &failure.message);
                self.fall_back(input)
            }
        }
    }
}
