//! The horizon bench's flow-matching policy ([`FlowPolicy`]) as an engine model, so that
//! `kairos serve --model horizon-flow:DIR` (and `kairos bench horizon --live`) serves it like any
//! other model: on a [`kairos_server::pool::LocalEngine`]'s own thread, batched by the real scheduler.
//!
//! Each request of a batch is sampled on its own, with its own seed and sample count, exactly as
//! the in-process bench samples it ([`FlowPolicy::sample`]): a request's chunk is then the same
//! bit for bit whatever it was batched with (the `ActionModel` contract), which is what lets
//! `--live` reproduce the in-process episodes. The network is a few thousand weights; batching
//! the requests' rows into one matmul would gain little and would tie each chunk's rounding to
//! its batch-mates.

use std::path::Path;

use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineError, GuidanceSupport, ModelChunking, ModelSpec,
};
use kairos_server::pool::ModelSchemes;

use super::env::{ACTION_DIM, OBS_DIM};
use super::model::{FlowPolicy, ModelError};

/// The model scheme that selects this model: `horizon-flow:DIR`, `DIR` holding `config.json`
/// and `model.safetensors` (e.g. `workloads/horizon/model`).
pub const HORIZON_FLOW_SCHEME: &str = "horizon-flow";

/// [`HORIZON_FLOW_SCHEME`] with its colon: the start of a model spec.
pub const HORIZON_FLOW_PREFIX: &str = "horizon-flow:";

/// Registers `horizon-flow:DIR` with `schemes`, so servers, workers and profiles built with them
/// load this model. A tokenizer is refused before the policy is loaded: the model reads no text.
pub fn register(schemes: &mut ModelSchemes) -> &mut ModelSchemes {
    schemes.register(HORIZON_FLOW_SCHEME, |dir, tokenizer, _options| {
        if tokenizer.is_some() {
            return Err(EngineError::InvalidInput(format!(
                "a tokenizer was given, but `{HORIZON_FLOW_PREFIX}{dir}` reads no text"
            )));
        }
        let model = HorizonFlowModel::load(Path::new(dir)).map_err(|e| EngineError::Load {
            path: dir.into(),
            reason: e.to_string(),
        })?;
        Ok(Box::new(model))
    })
}

/// The model schemes of the bench's tools: the engine crate's models plus `horizon-flow:DIR`.
pub fn schemes() -> ModelSchemes {
    let mut schemes = ModelSchemes::new();
    register(&mut schemes);
    schemes
}

/// The model's name in `Welcome` and the engine profile.
pub const HORIZON_FLOW_MODEL: &str = "horizon-flow";

/// [`FlowPolicy`] behind the engine's [`ActionModel`] trait.
pub struct HorizonFlowModel {
    policy: FlowPolicy,
    spec: ModelSpec,
}

impl std::fmt::Debug for HorizonFlowModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HorizonFlowModel")
            .field("spec", &self.spec)
            .finish()
    }
}

impl HorizonFlowModel {
    /// Serves `policy`: the state is the task's observation, no images, no instruction.
    pub fn new(policy: FlowPolicy) -> HorizonFlowModel {
        let cfg = policy.config();
        let spec = ModelSpec {
            name: HORIZON_FLOW_MODEL.to_string(),
            chunk_len: cfg.chunk_len,
            action_dim: ACTION_DIM,
            state_dim: OBS_DIM,
            steps: cfg.steps,
            max_images: 0,
            cameras: Vec::new(),
            camera_aliases: Default::default(),
        };
        HorizonFlowModel { policy, spec }
    }

    /// Loads the policy saved in `dir`.
    pub fn load(dir: &Path) -> Result<HorizonFlowModel, ModelError> {
        let (policy, _) = FlowPolicy::load(dir)?;
        Ok(HorizonFlowModel::new(policy))
    }
}

/// `Some(model)` when `name` is `horizon-flow:DIR` (loaded from `DIR`), `None` for any other
/// model spec.
pub fn resolve(name: &str) -> Option<Result<HorizonFlowModel, EngineError>> {
    let dir = name.strip_prefix(HORIZON_FLOW_PREFIX)?;
    Some(
        HorizonFlowModel::load(Path::new(dir)).map_err(|e| EngineError::Load {
            path: dir.into(),
            reason: e.to_string(),
        }),
    )
}

impl ActionModel for HorizonFlowModel {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        batch
            .iter()
            .map(|request| {
                let obs: [f32; OBS_DIM] = request.state.as_slice().try_into().map_err(|_| {
                    EngineError::InvalidInput(format!(
                        "state has {} values, the horizon task observes {OBS_DIM}",
                        request.state.len()
                    ))
                })?;
                self.policy
                    .sample_guided(
                        &obs,
                        request.samples.max(1),
                        request.seed,
                        request.guidance.as_ref(),
                    )
                    .map_err(|e| EngineError::InvalidInput(format!("sampling: {e}")))
            })
            .collect()
    }

    /// Every guidance mode (the sampler's, with Candle's autograd for `rtc_vjp`); the task's
    /// actions are velocity commands, from which the server cannot roll a state forward.
    fn chunking(&self) -> ModelChunking {
        ModelChunking {
            guidance: GuidanceSupport::ALL,
            action_space: kairos_engine::ActionSpace::Unspecified,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::horizon_bench::env::{Env, EnvConfig};
    use crate::horizon_bench::model::ModelConfig;

    fn request(obs: &[f32; OBS_DIM], samples: usize, seed: u64) -> ActionRequest {
        ActionRequest {
            state: obs.to_vec(),
            images: Vec::new(),
            cameras: Vec::new(),
            instruction: String::new(),
            samples,
            seed,
            guidance: None,
        }
    }

    #[test]
    fn a_batch_gives_each_request_the_chunk_the_bench_samples_alone() {
        let cfg = ModelConfig {
            hidden: 16,
            steps: 3,
            ..ModelConfig::default()
        };
        let model = HorizonFlowModel::new(FlowPolicy::new(cfg).unwrap());
        let (a, b) = (
            Env::new(EnvConfig::default(), 1).observe(),
            Env::new(EnvConfig::default(), 2).observe(),
        );
        let chunks = model
            .generate(&[request(&a, 1, 11), request(&b, 4, 12)])
            .unwrap();
        assert_eq!(chunks.len(), 2);
        assert_eq!((chunks[0].samples, chunks[1].samples), (1, 4));
        assert_eq!(
            (chunks[1].chunk_len, chunks[1].steps, chunks[1].action_dim),
            (16, 3, ACTION_DIM)
        );
        // Bit for bit what the in-process bench draws for the same observation and seed.
        assert_eq!(chunks[0], model.policy.sample(&a, 1, 11).unwrap());
        assert_eq!(chunks[1], model.policy.sample(&b, 4, 12).unwrap());
        assert_ne!(chunks[1], model.policy.sample(&b, 4, 13).unwrap());
        let short = ActionRequest {
            state: vec![0.0; OBS_DIM - 1],
            ..request(&a, 1, 0)
        };
        assert!(model.generate(&[short]).is_err());
    }

    #[test]
    fn the_registered_scheme_refuses_a_tokenizer_before_loading() {
        use kairos_engine::EngineOptions;
        // The directory does not exist: the tokenizer is refused without trying to load it.
        let error = schemes()
            .resolve(
                "horizon-flow:/nonexistent/horizon-model",
                Some(Path::new("tokenizer.json")),
                &EngineOptions::default(),
            )
            .err()
            .expect("a tokenizer for a model that reads no text is refused");
        assert!(error.to_string().contains("reads no text"), "{error}");
        let error = schemes()
            .resolve(
                "horizon-flow:/nonexistent/horizon-model",
                None,
                &EngineOptions::default(),
            )
            .err()
            .expect("a missing directory fails to load");
        assert!(
            error.to_string().contains("/nonexistent/horizon-model"),
            "{error}"
        );
    }

    #[test]
    fn only_the_horizon_flow_prefix_resolves_here() {
        assert!(resolve("builtin").is_none());
        assert!(resolve("ckpt/model.safetensors").is_none());
        let Some(Err(error)) = resolve("horizon-flow:/nonexistent/model") else {
            panic!("a missing directory must fail to load");
        };
        assert!(error.to_string().contains("/nonexistent/model"), "{error}");
    }
}
