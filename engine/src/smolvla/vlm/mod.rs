//! SmolVLA's VLM side: images, instruction and state in, the expert's [`PrefixKv`] out, as
//! LeRobot 0.6.1's `VLAFlowMatching.embed_prefix` and prefix prefill compute it.
//!
//! Prefix layout per observation (LeRobot's `embed_prefix`, `add_image_special_tokens=false`):
//! for every camera slot, its connector tokens `x sqrt(text hidden)` (padding for an empty
//! camera); the language tokens `embed_tokens(t) x sqrt(text hidden)` (padding where the
//! tokenizer's attention mask is 0); the state token `state_proj(state)`; then padding up to
//! `prefix_length` if that is set. See `text` for the layers and masks.
//!
//! Two backends run it, as for the expert: the engine's CPU kernels (the vision tower and
//! connector in [`vision`], the text layers in `text`), and Candle ops on any Candle device
//! (`vision`'s Candle tower, `candle_text`), the reference on the CPU and the path on CUDA. The
//! prefix embeddings are assembled on the host for both. The weights are in [`weights`].

mod candle_text;
mod text;
pub mod vision;
pub mod weights;

use std::path::Path;

use super::config::{self, ExpertDims, SmolVlaConfig, VlmConfig, kept_vlm_layers};
use super::prefix::PrefixKv;
use crate::EngineError;
use crate::kernels::Pool;
use crate::options::{EngineOptions, Target};
use crate::smolvla::candle_weights::matmul_dtype;
use crate::weights::{Checkpoint, StoredTensor};
use candle_text::CandleText;
use text::{CpuText, ValidKv, ValidPrefix};
use vision::{CandleVision, CpuVision, VisionImage, VisionOutput};
use weights::VlmWeights;

/// One observation as the VLM takes it (after LeRobot's processors and `prepare_images`).
#[derive(Clone, Debug)]
pub struct VlmObservation<'a> {
    /// Camera slots in LeRobot's order (present cameras in config order, then up to
    /// `empty_cameras` empty ones): a prepared image, or `None` for an empty camera, whose
    /// tokens are padding (as large as the last present image's).
    pub images: Vec<Option<VisionImage<'a>>>,
    /// Language token ids (`observation.language.tokens`).
    pub tokens: &'a [u32],
    /// The tokenizer's attention mask (`observation.language.attention_mask`).
    pub token_mask: &'a [bool],
    /// `state_proj` of the padded, normalised state ([`super::SmolVlaExpert::embed_state`]).
    pub state_token: &'a [f32],
}

/// The prefix embeddings of one observation (LeRobot's `embed_prefix` output).
#[derive(Clone, Debug, PartialEq)]
pub struct PrefixEmbeddings {
    /// `[len][text hidden]`; zeros at padding positions.
    pub embeddings: Vec<f32>,
    /// The pad mask.
    pub valid: Vec<bool>,
}

/// Where the vision tower and the text layers run.
enum Backend {
    /// The engine's CPU kernels on a pool of threads.
    Fast {
        vision: Box<CpuVision>,
        text: CpuText,
        pool: Pool,
    },
    /// Candle ops on one device.
    Candle {
        vision: Box<CandleVision>,
        text: CandleText,
    },
}

/// The loaded VLM: vision tower, connector, token embeddings and the kept text layers.
pub struct SmolVlaVlm {
    config: VlmConfig,
    prefix_length: usize,
    backend: Backend,
    /// As the checkpoint stores it (bf16 for SmolVLM2: 95 MB instead of 189 MB in `f32`); rows
    /// are widened, exactly, when looked up.
    embed_tokens: StoredTensor,
    /// The path it runs on, e.g. `fast:avx2-fma` or `candle:cuda:0` (see [`Target::path`]).
    path: String,
}

impl std::fmt::Debug for SmolVlaVlm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaVlm")
            .field("config", &self.config)
            .field("path", &self.path)
            .finish()
    }
}

impl SmolVlaVlm {
    /// Load from a LeRobot SmolVLA checkpoint directory (`config.json`, `model.safetensors`,
    /// and `vlm_config.json` for a VLM other than SmolVLM2-500M).
    pub fn load(dir: &Path, options: &EngineOptions) -> Result<Self, EngineError> {
        let cfg: SmolVlaConfig = config::read_json(&dir.join("config.json"))?;
        let vlm = VlmConfig::for_checkpoint(dir, &cfg)?;
        let ckpt = Checkpoint::open(&dir.join("model.safetensors"))?;
        Self::load_from(&ckpt, &cfg, &vlm, options)
    }

    /// Load from an open checkpoint (shared with the expert's loader). The weight matrices are
    /// read as stored (bf16 stays bf16: half their f32 size, and at most the packed model's
    /// size), then packed one layer at a time, each layer's stored tensors dropped once packed,
    /// so loading needs about the packed model's memory and no more.
    pub fn load_from(
        ckpt: &Checkpoint,
        cfg: &SmolVlaConfig,
        vlm: &VlmConfig,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let weights = VlmWeights::load(ckpt, vlm, kept_vlm_layers(cfg, &vlm.text_config))?;
        Self::build(weights, cfg, options)
    }

    /// Build from weights in memory (a copy of them is packed, or put on the device). The VLM
    /// runs where `options` say: the fast CPU kernels, or Candle on the CPU or a GPU.
    pub fn from_weights(
        weights: &VlmWeights,
        cfg: &SmolVlaConfig,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        Self::build(weights.clone(), cfg, options)
    }

    /// [`Self::from_weights`], consuming the weights: each tensor is dropped once packed (or
    /// once on the device).
    fn build(
        mut weights: VlmWeights,
        cfg: &SmolVlaConfig,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        if cfg.add_image_special_tokens {
            return Err(EngineError::Load {
                path: "config.json".into(),
                reason: "add_image_special_tokens = true is not supported".into(),
            });
        }
        let target = options.target()?;
        let path = target.path(options.precision);
        let config = weights.config.clone();
        let embed_tokens = std::mem::take(&mut weights.embed_tokens);
        let backend = match target {
            Target::Fast(pool) => {
                let precision = options.precision.resolve(pool.isa());
                let text = CpuText::new(
                    &config.text_config,
                    std::mem::take(&mut weights.layers),
                    precision,
                );
                Backend::Fast {
                    vision: Box::new(CpuVision::new(weights, precision)),
                    text,
                    pool,
                }
            }
            Target::Candle(device) => {
                let dtype = matmul_dtype(options.precision);
                let text = CandleText::new(&config.text_config, &weights.layers, dtype, &device)?;
                weights.layers = Vec::new();
                Backend::Candle {
                    vision: Box::new(CandleVision::new(&weights, dtype, &device)?),
                    text,
                }
            }
        };
        Ok(SmolVlaVlm {
            config,
            prefix_length: usize::try_from(cfg.prefix_length).unwrap_or(0),
            backend,
            embed_tokens,
            path,
        })
    }

    /// The path the vision tower, connector and text layers run on, e.g. `fast:avx2-fma`,
    /// `fast:avx512-bf16`, `candle:cpu` or `candle:cuda:0`.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// The VLM's config.
    pub fn config(&self) -> &VlmConfig {
        &self.config
    }

    /// Tokens one `side x side` image becomes.
    pub fn tokens_per_image(&self, side: usize) -> usize {
        vision::tokens_per_image(&self.config, side)
    }

    /// LeRobot's `embed_image` for each image: the vision tower and the connector, batched.
    pub fn embed_images(&self, images: &[VisionImage<'_>]) -> Result<VisionOutput, EngineError> {
        match &self.backend {
            Backend::Fast { vision, pool, .. } => vision.forward(pool, images),
            Backend::Candle { vision: tower, .. } => {
                let grids = vision::validate(&self.config, images)?;
                tower.forward(images, &grids)
            }
        }
    }

    /// Number of kept text layers.
    fn text_layers(&self) -> usize {
        match &self.backend {
            Backend::Fast { text, .. } => text.layers(),
            Backend::Candle { text, .. } => text.layers(),
        }
    }

    /// The text layers over the valid tokens of each observation.
    fn text_forward(&self, inputs: &[ValidPrefix<'_>]) -> Result<Vec<ValidKv>, EngineError> {
        match &self.backend {
            Backend::Fast { text, pool, .. } => Ok(text.forward(pool, inputs)),
            Backend::Candle { text, .. } => text.forward(inputs),
        }
    }

    /// LeRobot's `embed_prefix` for each observation (all images of the batch in one pass).
    pub fn embed_prefix(
        &self,
        observations: &[VlmObservation<'_>],
    ) -> Result<Vec<PrefixEmbeddings>, EngineError> {
        let h = self.config.text_config.hidden_size;
        let vocab = self.config.text_config.vocab_size;
        let mut present = Vec::new();
        for (o, obs) in observations.iter().enumerate() {
            if obs.tokens.len() != obs.token_mask.len() {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: {} tokens but {} attention-mask values",
                    obs.tokens.len(),
                    obs.token_mask.len()
                )));
            }
            if let Some(&t) = obs.tokens.iter().find(|&&t| t as usize >= vocab) {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: token id {t} is outside the vocabulary of {vocab}"
                )));
            }
            if obs.state_token.len() != h {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: state token has {} values, expected {h}",
                    obs.state_token.len()
                )));
            }
            if obs.images.iter().all(Option::is_none) {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: every camera is missing; at least one image is needed"
                )));
            }
            present.extend(obs.images.iter().flatten().copied());
        }
        let vision = self.embed_images(&present)?;
        let scale = (h as f64).sqrt() as f32;
        let mut images = vision.embeddings.into_iter();
        observations
            .iter()
            .map(|obs| {
                let mut embeddings = Vec::new();
                let mut valid = Vec::new();
                let mut last_tokens = 0;
                for slot in &obs.images {
                    match slot {
                        Some(_) => {
                            let e = images.next().unwrap_or_default();
                            last_tokens = e.len() / h;
                            embeddings.extend(e.iter().map(|v| v * scale));
                            valid.extend(std::iter::repeat_n(true, last_tokens));
                        }
                        None => {
                            let n = obs
                                .images
                                .iter()
                                .flatten()
                                .last()
                                .map_or(last_tokens, |im| self.tokens_per_image(im.side));
                            embeddings.extend(std::iter::repeat_n(0.0, n * h));
                            valid.extend(std::iter::repeat_n(false, n));
                        }
                    }
                }
                for (&t, &m) in obs.tokens.iter().zip(obs.token_mask) {
                    if m {
                        let at = t as usize * h;
                        let row = self.embed_tokens.widened(at..at + h);
                        embeddings.extend(row.iter().map(|v| v * scale));
                    } else {
                        embeddings.extend(std::iter::repeat_n(0.0, h));
                    }
                    valid.push(m);
                }
                embeddings.extend_from_slice(obs.state_token);
                valid.push(true);
                while valid.len() < self.prefix_length {
                    embeddings.extend(std::iter::repeat_n(0.0, h));
                    valid.push(false);
                }
                Ok(PrefixEmbeddings { embeddings, valid })
            })
            .collect()
    }

    /// The expert's prefix cache for each observation: [`Self::embed_prefix`], then the text
    /// layers over all observations at once. Keys and values at padding positions are zero.
    pub fn prefix(
        &self,
        dims: &ExpertDims,
        observations: &[VlmObservation<'_>],
    ) -> Result<Vec<PrefixKv>, EngineError> {
        let t = &self.config.text_config;
        let kvw = t.num_key_value_heads * t.head_dim;
        if dims.kv_width() != kvw
            || dims.layers.len() != self.text_layers()
            || dims.vlm_hidden != t.hidden_size
        {
            return Err(EngineError::InvalidInput(format!(
                "the expert ({} layers, kv width {}) does not fit this VLM ({} layers, kv width {kvw})",
                dims.layers.len(),
                dims.kv_width(),
                self.text_layers()
            )));
        }
        let h = t.hidden_size;
        let embedded = self.embed_prefix(observations)?;
        let compact: Vec<Vec<f32>> = embedded
            .iter()
            .map(|p| {
                p.embeddings
                    .chunks_exact(h)
                    .zip(&p.valid)
                    .filter(|(_, v)| **v)
                    .flat_map(|(row, _)| row.iter().copied())
                    .collect()
            })
            .collect();
        let inputs: Vec<ValidPrefix<'_>> = compact
            .iter()
            .map(|e| ValidPrefix { embeddings: e })
            .collect();
        let kv = self.text_forward(&inputs)?;
        embedded
            .into_iter()
            .zip(kv)
            .map(|(p, kv)| {
                let scatter = |layers: Vec<Vec<f32>>| -> Vec<Vec<f32>> {
                    layers
                        .into_iter()
                        .map(|compact| {
                            let mut full = vec![0.0f32; p.valid.len() * kvw];
                            let mut rows = compact.chunks_exact(kvw);
                            for (dst, _) in full
                                .chunks_exact_mut(kvw)
                                .zip(&p.valid)
                                .filter(|(_, v)| **v)
                            {
                                if let Some(src) = rows.next() {
                                    dst.copy_from_slice(src);
                                }
                            }
                            full
                        })
                        .collect()
                };
                let (keys, values) = (scatter(kv.keys), scatter(kv.values));
                PrefixKv::new(dims, p.valid, keys, values)
            })
            .collect()
    }
}

/// Where each of several blocks of `counts[i]` rows starts when they are stacked.
fn starts(counts: &[usize]) -> Vec<usize> {
    counts
        .iter()
        .scan(0, |acc, &n| {
            let s = *acc;
            *acc += n;
            Some(s)
        })
        .collect()
}
