//! The whole SmolVLA policy for one checkpoint directory, LeRobot's `predict_action_chunk`:
//!
//! ```text
//! Observation --preprocessor--> PreparedObservation --VLM (SmolVlaVlm)--> PrefixKv
//!     --expert + Euler (SmolVlaExpert)--> normalised [chunk][max_action_dim]
//!     --cut to action dim, postprocessor--> actions [chunk][action_dim]
//! ```
//!
//! Each stage is its own component: [`SmolVlaCheckpoint`] (processors), [`SmolVlaVlm`] (vision
//! tower, connector, SmolLM2 prefix layers) and [`SmolVlaExpert`] (action expert and Euler loop).
//! `model.safetensors` is read once and shared by the VLM and the expert.

use std::path::Path;
use std::time::Instant;

use super::checkpoint::ACTION_KEY;
use super::checkpoint::{Observation, PreparedObservation, SmolVlaCheckpoint};
use super::config::{ExpertDims, VlmConfig};
use super::vlm::vision::VisionImage;
use super::vlm::{SmolVlaVlm, VlmObservation};
use super::{ExpertWeights, SmolVlaExpert};
pub use crate::model::StagePaths;
use crate::sampler::gaussian_noise;
use crate::weights::Checkpoint;
use crate::{ActionChunk, ActionModel, ActionRequest, EngineError, EngineOptions, ModelSpec};

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

/// A SmolVLA checkpoint ready to predict: processors, VLM and expert.
pub struct SmolVlaPipeline {
    checkpoint: SmolVlaCheckpoint,
    vlm: SmolVlaVlm,
    expert: SmolVlaExpert,
    spec: ModelSpec,
}

impl std::fmt::Debug for SmolVlaPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaPipeline")
            .field("checkpoint", &self.checkpoint.dir())
            .field("expert", &self.expert)
            .field("vlm", &self.vlm)
            .finish()
    }
}

impl SmolVlaPipeline {
    /// Load the processors, the VLM and the expert from `dir` (`tokenizer`: see
    /// [`SmolVlaCheckpoint::open`]).
    pub fn load(
        dir: &Path,
        tokenizer: Option<&Path>,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let checkpoint = SmolVlaCheckpoint::open(dir, tokenizer)?;
        let cfg = checkpoint.config();
        let vlm_config = VlmConfig::for_checkpoint(dir, cfg)?;
        let dims = ExpertDims::resolve(cfg, &vlm_config.text_config)?;
        let weights_path = dir.join("model.safetensors");
        if !weights_path.exists() {
            return Err(EngineError::MissingFile {
                path: weights_path.display().to_string(),
            });
        }
        let ckpt = Checkpoint::open(&weights_path)?;
        let expert = SmolVlaExpert::from_weights(&ExpertWeights::load(&ckpt, &dims)?, options)?;
        let vlm = SmolVlaVlm::load_from(&ckpt, cfg, &vlm_config, options)?;
        let spec = ModelSpec {
            cameras: checkpoint.camera_keys(),
            camera_aliases: checkpoint.camera_aliases(),
            name: "smolvla".into(),
            chunk_len: dims.chunk,
            action_dim: checkpoint.action_dim(),
            state_dim: checkpoint.state_dim(),
            steps: dims.steps,
            max_images: checkpoint.camera_keys().len(),
        };
        Ok(SmolVlaPipeline {
            checkpoint,
            vlm,
            expert,
            spec,
        })
    }

    /// The path each stage runs on.
    pub fn paths(&self) -> StagePaths {
        StagePaths {
            vision: self.vlm.path().to_owned(),
            prefix: self.vlm.path().to_owned(),
            expert: self.expert.path().to_owned(),
        }
    }

    /// The VLM.
    pub fn vlm(&self) -> &SmolVlaVlm {
        &self.vlm
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
        let d = self.expert.dims();
        let noises: Vec<Vec<f32>> = seeds
            .iter()
            .map(|&s| gaussian_noise(s, 0, d.chunk * d.action_pad))
            .collect();
        self.predict_with_noise(observations, &noises)
    }

    /// [`SmolVlaPipeline::predict`] from given initial noise, `[chunk][max_action_dim]` per
    /// observation (LeRobot's `noise` argument).
    pub fn predict_with_noise(
        &self,
        observations: &[Observation],
        noises: &[Vec<f32>],
    ) -> Result<(Vec<Prediction>, StageTimes), EngineError> {
        if observations.len() != noises.len() {
            return Err(EngineError::InvalidInput(format!(
                "{} observations but {} noises",
                observations.len(),
                noises.len()
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

        let t = Instant::now();
        let prefixes = self.prefixes(&prepared)?;
        times.prefix = ms(t);

        let t = Instant::now();
        let d = self.expert.dims();
        let noises: Vec<Vec<Vec<f32>>> = noises.iter().map(|n| vec![n.clone()]).collect();
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

    /// The VLM prefix of each prepared observation, in one batch.
    pub fn prefixes(
        &self,
        prepared: &[PreparedObservation],
    ) -> Result<Vec<super::PrefixKv>, EngineError> {
        let states: Vec<Vec<f32>> = prepared.iter().map(|p| p.state.clone()).collect();
        let state_tokens = self.expert.embed_state(&states)?;
        let observations = prepared
            .iter()
            .zip(&state_tokens)
            .map(|(p, state_token)| {
                let images = p
                    .images
                    .iter()
                    .map(|img| {
                        if img.height != img.width {
                            return Err(EngineError::InvalidInput(format!(
                                "prepared image is {}x{}; the vision tower takes square images \
                                 (resize_imgs_with_padding)",
                                img.height, img.width
                            )));
                        }
                        Ok(img.present.then_some(VisionImage {
                            side: img.height,
                            pixels: &img.pixels,
                        }))
                    })
                    .collect::<Result<Vec<_>, EngineError>>()?;
                Ok(VlmObservation {
                    images,
                    tokens: &p.tokens.ids,
                    token_mask: &p.tokens.mask,
                    state_token,
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        self.vlm.prefix(self.expert.dims(), &observations)
    }
}

/// The whole policy behind the server's model interface: a request's images are matched to the
/// model's cameras by their names ([`ActionRequest::cameras`], resolved as
/// [`SmolVlaCheckpoint::resolve_camera`] does: the key, its rename-map source, or the part after
/// `observation.images.`), or, for a request without names, are the model's cameras in order
/// ([`SmolVlaCheckpoint::camera_keys`]); cameras not given are missing and follow
/// `empty_cameras`. Its instruction is the task, its state the raw state. Samples of one request share
/// the prefix. The chunk is in the robot's units: actions exactly as LeRobot's postprocessor
/// gives them, and the noise and per-step updates mapped by the same affine unnormalisation
/// (updates by its scale only), so `noise + sum(updates)` is the actions up to rounding.
impl ActionModel for SmolVlaPipeline {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    /// `rtc` and `inpaint` in the expert's sampler; the action space is not declared (SmolVLA's
    /// config does not say whether its actions are absolute positions).
    fn chunking(&self) -> crate::ModelChunking {
        crate::ModelChunking {
            guidance: self.expert.guidance_support(),
            action_space: crate::ActionSpace::Unspecified,
        }
    }

    fn paths(&self) -> Option<StagePaths> {
        Some(SmolVlaPipeline::paths(self))
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        self.spec.validate(batch)?;
        let keys = self.checkpoint.camera_keys();
        let prepared = batch
            .iter()
            .map(|r| {
                let names = if r.cameras.is_empty() {
                    &keys
                } else {
                    &r.cameras
                };
                let obs = Observation {
                    images: names
                        .iter()
                        .cloned()
                        .zip(r.images.iter().cloned())
                        .collect(),
                    state: r.state.clone(),
                    task: r.instruction.clone(),
                };
                self.checkpoint.prepare(&obs)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let prefixes = self.prefixes(&prepared)?;
        let requests: Vec<(&super::PrefixKv, usize, u64)> = prefixes
            .iter()
            .zip(batch)
            .map(|(p, r)| (p, r.samples, r.seed))
            .collect();
        let guidance: Vec<Option<&crate::Guidance>> =
            batch.iter().map(|r| r.guidance.as_ref()).collect();
        // A guidance prefix is in the robot's units; the expert samples normalised actions, so
        // the committed actions are normalised with the postprocessor's own action stats (the
        // inverse of what `unnormalize_chunk` applies). Stats that do not fit the action are
        // refused there, for the whole chunk.
        let unnormalizer = self.checkpoint.postprocessor().unnormalizer.as_ref();
        let to_model = |action: &mut [f32]| {
            if let Some(n) = unnormalizer {
                let _ = n.normalize(ACTION_KEY, action);
            }
        };
        self.expert
            .generate_guided(&requests, &guidance, &to_model)?
            .into_iter()
            .map(|chunk| self.unnormalize_chunk(chunk))
            .collect()
    }
}

impl SmolVlaPipeline {
    fn unnormalize_chunk(&self, mut chunk: ActionChunk) -> Result<ActionChunk, EngineError> {
        let dim = chunk.action_dim;
        chunk.actions = self
            .checkpoint
            .finish_actions(&chunk.actions, dim)?
            .concat();
        let affine = self
            .checkpoint
            .postprocessor()
            .unnormalizer
            .as_ref()
            .and_then(|n| n.inverse_affine(ACTION_KEY));
        if let Some((scale, shift)) = affine {
            if scale.len() != dim {
                return Err(EngineError::InvalidInput(format!(
                    "action stats have {} values, the action dim is {dim}",
                    scale.len()
                )));
            }
            for (i, x) in chunk.noise.iter_mut().enumerate() {
                *x = scale[i % dim] * *x + shift[i % dim];
            }
            for (i, u) in chunk.updates.iter_mut().enumerate() {
                *u *= scale[i % dim];
            }
        }
        Ok(chunk)
    }
}
