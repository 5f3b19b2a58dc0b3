//! SmolVLA's VLM side: images, instruction and state in, the expert's [`PrefixKv`] out, as
//! LeRobot 0.6.1's `VLAFlowMatching.embed_prefix` and prefix prefill compute it.
//!
//! Prefix layout per observation (LeRobot's `embed_prefix`, `add_image_special_tokens=false`):
//! for every camera slot, its connector tokens `x sqrt(text hidden)` (padding for an empty
//! camera); the language tokens `embed_tokens(t) x sqrt(text hidden)` (padding where the
//! tokenizer's attention mask is 0); the state token `state_proj(state)`; then padding up to
//! `prefix_length` if that is set. See `text` for the layers and masks.
//!
//! It runs on the engine's CPU kernels only (the vision tower is 212 GFLOP per 512x512 camera;
//! see docs/ENGINE.md for why not Candle's `siglip`): the vision tower and connector in
//! [`vision`], the text layers in `text`, the weights in [`weights`].

mod text;
pub mod vision;
pub mod weights;

use std::path::Path;

use super::config::{self, ExpertDims, SmolVlaConfig, VlmConfig, kept_vlm_layers};
use super::prefix::PrefixKv;
use crate::EngineError;
use crate::kernels::Pool;
use crate::options::{EngineOptions, Target};
use crate::weights::{Checkpoint, StoredTensor};
use text::{CpuText, ValidPrefix};
use vision::{CpuVision, VisionImage, VisionOutput};
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

/// The loaded VLM: vision tower, connector, token embeddings and the kept text layers.
pub struct SmolVlaVlm {
    config: VlmConfig,
    prefix_length: usize,
    vision: CpuVision,
    text: CpuText,
    /// As the checkpoint stores it (bf16 for SmolVLM2: 95 MB instead of 189 MB in `f32`); rows
    /// are widened, exactly, when looked up.
    embed_tokens: StoredTensor,
    pool: Pool,
}

impl std::fmt::Debug for SmolVlaVlm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaVlm")
            .field("config", &self.config)
            .field("pool", &self.pool)
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

    /// Build from weights in memory (a copy of them is packed). The VLM runs on the fast CPU
    /// kernels; `options` gives the threads and instruction set (CUDA is not supported).
    pub fn from_weights(
        weights: &VlmWeights,
        cfg: &SmolVlaConfig,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        Self::build(weights.clone(), cfg, options)
    }

    /// [`Self::from_weights`], consuming the weights: each tensor is dropped once packed.
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
        let pool = match options.target()? {
            Target::Fast(pool) => pool,
            Target::Candle(candle_core::Device::Cpu) => Pool::new(options.threads)?,
            Target::Candle(d) => {
                return Err(EngineError::InvalidInput(format!(
                    "the SmolVLA VLM runs on the CPU kernels only, not on {d:?}"
                )));
            }
        };
        let precision = options.precision.resolve(pool.isa());
        let config = weights.config.clone();
        let embed_tokens = std::mem::take(&mut weights.embed_tokens);
        let text = CpuText::new(
            &config.text_config,
            std::mem::take(&mut weights.layers),
            precision,
        );
        Ok(SmolVlaVlm {
            config,
            prefix_length: usize::try_from(cfg.prefix_length).unwrap_or(0),
            vision: CpuVision::new(weights, precision),
            text,
            embed_tokens,
            pool,
        })
    }

    /// The VLM's config.
    pub fn config(&self) -> &VlmConfig {
        &self.config
    }

    /// Tokens one `side x side` image becomes.
    pub fn tokens_per_image(&self, side: usize) -> usize {
        self.vision.tokens_per_image(side)
    }

    /// LeRobot's `embed_image` for each image: the vision tower and the connector, batched.
    pub fn embed_images(&self, images: &[VisionImage<'_>]) -> Result<VisionOutput, EngineError> {
        self.vision.forward(&self.pool, images)
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
            || dims.layers.len() != self.text.layers()
            || dims.vlm_hidden != t.hidden_size
        {
            return Err(EngineError::InvalidInput(format!(
                "the expert ({} layers, kv width {}) does not fit this VLM ({} layers, kv width {kvw})",
                dims.layers.len(),
                dims.kv_width(),
                self.text.layers()
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
        let kv = self.text.forward(&self.pool, &inputs);
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
