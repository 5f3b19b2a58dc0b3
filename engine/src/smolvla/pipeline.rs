//! The whole SmolVLA policy for one checkpoint directory, LeRobot's `predict_action_chunk`:
//!
//! ```text
//! Observation --preprocessor--> PreparedObservation --VLM (PrefixModel)--> PrefixKv
//!     --expert + Euler (SmolVlaExpert)--> normalised [chunk][max_action_dim]
//!     --cut to action dim, postprocessor--> actions [chunk][action_dim]
//! ```
//!
//! The processors ([`SmolVlaCheckpoint`]) and the expert exist; the VLM that turns a prepared
//! observation into the prefix is a [`PrefixModel`]. Without one, [`SmolVlaPipeline::predict`]
//! fails with [`EngineError::Unsupported`]: it never invents a prefix.

use std::path::Path;
use std::time::Instant;

use super::checkpoint::{Observation, PreparedObservation, SmolVlaCheckpoint};
use super::{PrefixKv, SmolVlaExpert};
use crate::sampler::gaussian_noise;
use crate::{EngineError, EngineOptions};

/// The VLM half of SmolVLA: images, task tokens and state of each observation to the prefix
/// key/value cache the expert attends to (LeRobot's `embed_prefix` and the prefix forward with
/// `fill_kv_cache=True`). Called with a batch; each result must equal the one it gets alone.
pub trait PrefixModel: Send + Sync {
    /// One [`PrefixKv`] per observation, in order. `state_tokens[i]` is `state_proj` of
    /// observation `i`'s padded state (the expert owns `state_proj`).
    fn prefix(
        &self,
        batch: &[PreparedObservation],
        state_tokens: &[Vec<f32>],
    ) -> Result<Vec<PrefixKv>, EngineError>;
}

/// Milliseconds spent in each stage of one [`SmolVlaPipeline::predict`] call.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Decoding, resizing, tokenizing, normalising.
    pub preprocess: f64,
    /// The VLM prefix (vision tower, connector, text layers).
    pub prefix: f64,
    /// The expert's Euler loop.
    pub expert: f64,
    /// Cutting and unnormalising the actions.
    pub postprocess: f64,
    /// All of it.
    pub total: f64,
}

/// One observation's result: the robot's actions.
#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    /// `[chunk][action_dim]`, unnormalised.
    pub actions: Vec<Vec<f32>>,
    /// The model's normalised output, `[chunk][max_action_dim]` (before the cut).
    pub normalized: Vec<f32>,
}

/// A SmolVLA checkpoint ready to predict: processors, expert, and (when available) the VLM.
pub struct SmolVlaPipeline {
    checkpoint: SmolVlaCheckpoint,
    expert: SmolVlaExpert,
    vlm: Option<Box<dyn PrefixModel>>,
}

impl std::fmt::Debug for SmolVlaPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaPipeline")
            .field("checkpoint", &self.checkpoint.dir())
            .field("expert", &self.expert)
            .field("vlm", &self.vlm.is_some())
            .finish()
    }
}

impl SmolVlaPipeline {
    /// Load the processors and the expert from `dir`; the VLM is attached with
    /// [`SmolVlaPipeline::with_vlm`].
    pub fn load(
        dir: &Path,
        tokenizer: Option<&Path>,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let checkpoint = SmolVlaCheckpoint::open(dir, tokenizer)?;
        let expert = SmolVlaExpert::load(dir, options)?;
        Ok(SmolVlaPipeline {
            checkpoint,
            expert,
            vlm: None,
        })
    }

    /// Attach the VLM.
    pub fn with_vlm(mut self, vlm: Box<dyn PrefixModel>) -> Self {
        self.vlm = Some(vlm);
        self
    }

    /// The processors.
    pub fn checkpoint(&self) -> &SmolVlaCheckpoint {
        &self.checkpoint
    }

    /// The expert.
    pub fn expert(&self) -> &SmolVlaExpert {
        &self.expert
    }

    /// Actions per chunk.
    pub fn chunk(&self) -> usize {
        self.expert.dims().chunk
    }

    /// The robot's action width.
    pub fn action_dim(&self) -> usize {
        self.checkpoint.action_dim()
    }

    /// Predict one chunk per observation; noise of observation `i` is
    /// [`gaussian_noise`]`(seeds[i], 0, chunk * max_action_dim)`.
    pub fn predict(
        &self,
        observations: &[Observation],
        seeds: &[u64],
    ) -> Result<(Vec<Prediction>, StageTimes), EngineError> {
        if observations.len() != seeds.len() {
            return Err(EngineError::InvalidInput(format!(
                "{} observations but {} seeds",
                observations.len(),
                seeds.len()
            )));
        }
        let start = Instant::now();
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        let mut times = StageTimes::default();

        let t = Instant::now();
        let prepared = observations
            .iter()
            .map(|o| self.checkpoint.prepare(o))
            .collect::<Result<Vec<_>, _>>()?;
        times.preprocess = ms(t);

        let vlm = self.vlm.as_ref().ok_or_else(|| {
            EngineError::Unsupported(
                "the SmolVLA VLM (SigLIP vision tower, connector, SmolLM2 prefix layers) is not \
                 in this build, so no prefix can be computed; refusing to predict from a \
                 stand-in"
                    .into(),
            )
        })?;
        let t = Instant::now();
        let states: Vec<Vec<f32>> = prepared.iter().map(|p| p.state.clone()).collect();
        let state_tokens = self.expert.embed_state(&states)?;
        let prefixes = vlm.prefix(&prepared, &state_tokens)?;
        if prefixes.len() != prepared.len() {
            return Err(EngineError::InvalidInput(format!(
                "the VLM returned {} prefixes for {} observations",
                prefixes.len(),
                prepared.len()
            )));
        }
        times.prefix = ms(t);

        let t = Instant::now();
        let d = self.expert.dims();
        let len = d.chunk * d.action_pad;
        let noises: Vec<Vec<Vec<f32>>> = seeds
            .iter()
            .map(|&s| vec![gaussian_noise(s, 0, len)])
            .collect();
        let inputs: Vec<super::ExpertInput<'_>> = prefixes
            .iter()
            .zip(&noises)
            .map(|(prefix, noise)| super::ExpertInput { prefix, noise })
            .collect();
        let samples = self.expert.sample(&inputs)?;
        times.expert = ms(t);

        let t = Instant::now();
        let predictions = samples
            .into_iter()
            .map(|s| {
                Ok(Prediction {
                    actions: self.checkpoint.finish_actions(&s.actions, d.action_pad)?,
                    normalized: s.actions,
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        times.postprocess = ms(t);
        times.total = ms(start);
        Ok((predictions, times))
    }
}
