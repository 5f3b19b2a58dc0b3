//! The whole π0 / π0.5 policy for one checkpoint directory, LeRobot's `predict_action_chunk`
//! with its pre- and postprocessor:
//!
//! ```text
//! Observation --PiCheckpoint::prepare--> PiPrepared --PiModel::prefix--> PrefixCache
//!     --PiModel::sample (Euler)--> normalised [chunk][max_action_dim]
//!     --PiCheckpoint::finish_actions (cut, unnormalise, absolute)--> [chunk][action_dim]
//! ```
//!
//! The model runs where the options put it, as SmolVLA does: on the CPU, by default on the
//! engine's fast kernels ([`FastPiModel`], f32 or bf16 weight GEMMs); with `kernels = candle`,
//! or on CUDA (the `cuda` feature), on Candle ops ([`PiModel`], f32).

use std::path::Path;
use std::time::Instant;

use super::checkpoint::{PiCheckpoint, PiPrepared};
use super::config::PiDims;
use super::fast::{FastPiModel, FastPrefix, FastSampleInput};
use super::gemma::PrefixCache;
use super::model::{PiModel, PiObservation, SampleInput};
use crate::guidance::RowGuide;
use crate::model::StagePaths;
use crate::options::Target;
use crate::sampler::{RowLayout, gaussian_noise};
use crate::smolvla::ExpertSample;
use crate::smolvla::checkpoint::{ACTION_KEY, Observation};
use crate::smolvla::pipeline::{Prediction, StageTimes};
use crate::weights::Checkpoint;
use crate::{
    ActionChunk, ActionModel, ActionRequest, EngineError, EngineOptions, ModelSpec, Precision,
};

/// Where the network runs.
enum Backend {
    /// The engine's fast CPU kernels.
    Fast(Box<FastPiModel>),
    /// Candle ops on a Candle device.
    Candle(Box<PiModel>),
}

/// One observation's prefix on either backend.
enum Prefix {
    Fast(FastPrefix),
    Candle(PrefixCache),
}

/// A π checkpoint ready to predict: processors and model.
pub struct PiPipeline {
    checkpoint: PiCheckpoint,
    backend: Backend,
    /// The path every stage runs on (`fast:<isa>[-bf16]` or `candle:<device>`).
    path: String,
    spec: ModelSpec,
}

impl std::fmt::Debug for PiPipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PiPipeline")
            .field("checkpoint", &self.checkpoint.dir())
            .field("path", &self.path)
            .finish()
    }
}

impl PiPipeline {
    /// Load the processors and the model from `dir` (`tokenizer`: the PaliGemma tokenizer
    /// file, else `tokenizer.json` beside the checkpoint).
    pub fn load(
        dir: &Path,
        tokenizer: Option<&Path>,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let checkpoint = PiCheckpoint::open(dir, tokenizer)?;
        let weights_path = dir.join("model.safetensors");
        if !weights_path.exists() {
            return Err(EngineError::MissingFile {
                path: weights_path.display().to_string(),
            });
        }
        let ckpt = Checkpoint::open(&weights_path)?;
        let dims = PiDims::from_checkpoint(checkpoint.config(), checkpoint.family(), &ckpt)?;
        let target = options.target()?;
        // The Candle path computes π in f32 whatever the precision asked.
        let path = match &target {
            Target::Fast(_) => target.path(options.precision),
            Target::Candle(_) => target.path(Precision::F32),
        };
        let backend = match target {
            Target::Fast(pool) => {
                let model = FastPiModel::load(&ckpt, &dims, pool, options.precision)?;
                Backend::Fast(Box::new(model))
            }
            Target::Candle(device) => {
                if options.precision == Precision::Bf16 {
                    tracing::warn!(
                        "π0 / π0.5 on Candle ops compute in f32; --precision bf16 applies to \
                         the fast CPU kernels"
                    );
                }
                Backend::Candle(Box::new(PiModel::load(&ckpt, &dims, &device)?))
            }
        };
        let spec = ModelSpec {
            name: checkpoint.family().policy_type().into(),
            chunk_len: dims.chunk,
            action_dim: checkpoint.action_dim(),
            state_dim: checkpoint.state_dim(),
            steps: dims.steps,
            max_images: checkpoint.camera_keys().len(),
            cameras: checkpoint.camera_keys(),
            camera_aliases: checkpoint.camera_aliases(),
        };
        Ok(PiPipeline {
            checkpoint,
            backend,
            path,
            spec,
        })
    }

    /// The path each stage runs on: all on the fast kernels (`fast:<isa>`, `-bf16` when the
    /// weight GEMMs run in bf16) or all on Candle ops (`candle:<device>`).
    pub fn paths(&self) -> StagePaths {
        StagePaths::all(&self.path)
    }

    /// Shapes.
    pub fn dims(&self) -> &PiDims {
        match &self.backend {
            Backend::Fast(m) => m.dims(),
            Backend::Candle(m) => m.dims(),
        }
    }

    /// The network on Candle ops, when it runs there.
    pub fn candle_model(&self) -> Option<&PiModel> {
        match &self.backend {
            Backend::Candle(m) => Some(m),
            Backend::Fast(_) => None,
        }
    }

    /// The network on the fast CPU kernels, when it runs there.
    pub fn fast_model(&self) -> Option<&FastPiModel> {
        match &self.backend {
            Backend::Fast(m) => Some(m),
            Backend::Candle(_) => None,
        }
    }

    /// The processors.
    pub fn checkpoint(&self) -> &PiCheckpoint {
        &self.checkpoint
    }

    /// Actions per chunk.
    pub fn chunk(&self) -> usize {
        self.dims().chunk
    }

    /// The robot's action width.
    pub fn action_dim(&self) -> usize {
        self.checkpoint.action_dim()
    }

    /// Predict one chunk per observation; the noise of observation `i` is
    /// [`gaussian_noise`]`(seeds[i], 0, chunk * max_action_dim)`.
    pub fn predict(
        &self,
        observations: &[Observation],
        seeds: &[u64],
    ) -> Result<(Vec<Prediction>, StageTimes), EngineError> {
        let d = self.dims();
        let noises: Vec<Vec<f32>> = seeds
            .iter()
            .map(|&s| gaussian_noise(s, 0, d.chunk * d.action_pad))
            .collect();
        self.predict_with_noise(observations, &noises)
    }

    /// [`PiPipeline::predict`] from given initial noise, `[chunk][max_action_dim]` per
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
        let noises: Vec<Vec<Vec<f32>>> = noises.iter().map(|n| vec![n.clone()]).collect();
        let samples = self.sample(&prepared, &prefixes, &noises, &[])?;
        times.expert = ms(t);

        let t = Instant::now();
        let pad = self.dims().action_pad;
        let predictions = samples
            .into_iter()
            .zip(&prepared)
            .map(|(s, p)| {
                Ok(Prediction {
                    actions: self
                        .checkpoint
                        .finish_actions(&s.actions, pad, &p.raw_state)?,
                    normalized: s.actions,
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        times.postprocess = ms(t);
        times.total = ms(start);
        Ok((predictions, times))
    }

    /// The prefix of each prepared observation, the cameras of the batch through the vision
    /// tower together.
    fn prefixes(&self, prepared: &[PiPrepared]) -> Result<Vec<Prefix>, EngineError> {
        let observations: Vec<PiObservation<'_>> = prepared
            .iter()
            .map(|p| PiObservation {
                images: p
                    .images
                    .iter()
                    .map(|img| img.present.then_some(img.pixels.as_slice()))
                    .collect(),
                tokens: &p.tokens.ids,
                token_mask: &p.tokens.mask,
            })
            .collect();
        Ok(match &self.backend {
            Backend::Fast(m) => m
                .prefix(&observations)?
                .into_iter()
                .map(Prefix::Fast)
                .collect(),
            Backend::Candle(m) => m
                .prefix(&observations)?
                .into_iter()
                .map(Prefix::Candle)
                .collect(),
        })
    }

    /// The Euler loop for every prepared observation (`noises[i]`: its samples' noise) on
    /// its prefix.
    fn sample(
        &self,
        prepared: &[PiPrepared],
        prefixes: &[Prefix],
        noises: &[Vec<Vec<f32>>],
        guides: &[Option<RowGuide>],
    ) -> Result<Vec<ExpertSample>, EngineError> {
        let mismatch = || EngineError::InvalidInput("a prefix of the other backend".into());
        let requests = prepared.iter().zip(prefixes).zip(noises);
        match &self.backend {
            Backend::Fast(m) => {
                let inputs = requests
                    .map(|((p, prefix), noise)| match prefix {
                        Prefix::Fast(prefix) => Ok(FastSampleInput {
                            prefix,
                            state: Some(&p.state),
                            noise,
                        }),
                        Prefix::Candle(_) => Err(mismatch()),
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                m.sample_guided(&inputs, guides)
            }
            Backend::Candle(m) => {
                let inputs = requests
                    .map(|((p, prefix), noise)| match prefix {
                        Prefix::Candle(prefix) => Ok(SampleInput {
                            prefix,
                            state: Some(&p.state),
                            noise,
                        }),
                        Prefix::Fast(_) => Err(mismatch()),
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                m.sample_guided(&inputs, guides)
            }
        }
    }

    /// One guide per sample row (`[request][sample]`) for the requests' guidance, or none when
    /// no request has any. A guidance prefix is in the robot's units; the expert samples
    /// normalised actions, so each committed action is mapped back as the postprocessor maps
    /// forward, inverted: minus the state offset (relative actions), then normalised with the
    /// action stats.
    fn guides(
        &self,
        batch: &[ActionRequest],
        prepared: &[PiPrepared],
        noises: &[Vec<Vec<f32>>],
    ) -> Result<Vec<Option<RowGuide>>, EngineError> {
        if batch.iter().all(|r| r.guidance.is_none()) {
            return Ok(Vec::new());
        }
        let support = self.chunking().guidance;
        if let Some(mode) = batch
            .iter()
            .filter_map(|r| r.guidance.as_ref())
            .map(|g| g.mode)
            .find(|&mode| !support.supports(mode))
        {
            return Err(EngineError::InvalidInput(format!(
                "guidance `{}`: π0 / π0.5 have no backward pass on {} (rtc and inpaint \
                 work); {}",
                mode.as_str(),
                self.path,
                crate::candle_vjp::VJP_PATH
            )));
        }
        let d = self.dims();
        let dim = self.checkpoint.action_dim();
        let unnormalizer = self.checkpoint.postprocessor().unnormalizer.as_ref();
        let mut guides = Vec::new();
        for ((r, p), noise) in batch.iter().zip(prepared).zip(noises) {
            let offset = self.checkpoint.absolute_offset(&p.raw_state)?;
            let to_model = |action: &mut [f32]| {
                if let Some(offset) = &offset {
                    for (a, o) in action.iter_mut().zip(offset) {
                        *a -= o;
                    }
                }
                if let Some(n) = unnormalizer {
                    let _ = n.normalize(ACTION_KEY, action);
                }
            };
            for sample_noise in noise {
                guides.push(
                    r.guidance
                        .as_ref()
                        .map(|g| {
                            RowGuide::prepare(
                                g,
                                d.chunk,
                                dim,
                                d.action_pad,
                                sample_noise,
                                &to_model,
                            )
                        })
                        .transpose()?,
                );
            }
        }
        Ok(guides)
    }

    /// A chunk in the robot's units: the actions as the postprocessor gives them, the noise
    /// and the updates mapped by the same affine map (updates by its scale only), so
    /// `noise + sum(updates)` is the actions up to rounding.
    fn to_robot_units(
        &self,
        mut chunk: ActionChunk,
        raw_state: &[f32],
    ) -> Result<ActionChunk, EngineError> {
        let dim = chunk.action_dim;
        chunk.actions = self
            .checkpoint
            .finish_actions(&chunk.actions, dim, raw_state)?
            .concat();
        let affine = self
            .checkpoint
            .postprocessor()
            .unnormalizer
            .as_ref()
            .and_then(|n| n.inverse_affine(ACTION_KEY));
        let offset = self.checkpoint.absolute_offset(raw_state)?;
        let (scale, mut shift) = match affine {
            Some((scale, shift)) if scale.len() == dim => (scale, shift),
            Some((scale, _)) => {
                return Err(EngineError::InvalidInput(format!(
                    "action stats have {} values, the action dim is {dim}",
                    scale.len()
                )));
            }
            None => (vec![1.0; dim], vec![0.0; dim]),
        };
        if let Some(offset) = offset {
            for (s, o) in shift.iter_mut().zip(offset) {
                *s += o;
            }
        }
        for (i, x) in chunk.noise.iter_mut().enumerate() {
            *x = scale[i % dim] * *x + shift[i % dim];
        }
        for (i, u) in chunk.updates.iter_mut().enumerate() {
            *u *= scale[i % dim];
        }
        Ok(chunk)
    }
}

/// The whole policy behind the server's model interface: a request's images are matched to the
/// model's cameras by name (or, without names, are the cameras in order), its instruction is
/// the task, its state the raw state; samples of one request share the prefix. Chunks are in
/// the robot's units (see `to_robot_units`). A request's guidance (`rtc`, `inpaint`) steers its
/// rows in the shared sampler, in the normalised action space (see `guides`).
impl ActionModel for PiPipeline {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn paths(&self) -> Option<StagePaths> {
        Some(PiPipeline::paths(self))
    }

    /// `rtc` and `inpaint` in the shared sampler, on both paths; `rtc_vjp` on the Candle path
    /// only, which takes the vector–Jacobian product with Candle's autograd (the fast kernels
    /// have no backward pass). The action space is not declared, as for SmolVLA.
    fn chunking(&self) -> crate::ModelChunking {
        crate::ModelChunking {
            guidance: match self.backend {
                Backend::Fast(_) => crate::GuidanceSupport::PREFIX,
                Backend::Candle(_) => crate::GuidanceSupport::ALL,
            },
            action_space: crate::ActionSpace::Unspecified,
        }
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
        let d = self.dims();
        let len = d.chunk * d.action_pad;
        let noises: Vec<Vec<Vec<f32>>> = batch
            .iter()
            .map(|r| {
                (0..r.samples)
                    .map(|s| gaussian_noise(r.seed, s, len))
                    .collect()
            })
            .collect();
        let guides = self.guides(batch, &prepared, &noises)?;
        let out = self.sample(&prepared, &prefixes, &noises, &guides)?;
        let layout = RowLayout {
            samples: batch.iter().map(|r| r.samples).collect(),
            steps: d.steps,
            chunk_len: d.chunk,
            full_dim: d.action_pad,
            action_dim: self.checkpoint.action_dim(),
        };
        let cat = |f: fn(&crate::smolvla::ExpertSample) -> &Vec<f32>| -> Vec<f32> {
            out.iter().flat_map(|o| f(o).iter().copied()).collect()
        };
        layout
            .chunks(
                &cat(|o| &o.noise),
                &cat(|o| &o.actions),
                &cat(|o| &o.updates),
            )
            .into_iter()
            .zip(&prepared)
            .map(|(chunk, p)| self.to_robot_units(chunk, &p.raw_state))
            .collect()
    }
}
