//! The built-in flow head: a small observation-conditioned flow-matching action model for robots
//! and tests without a VLM.
//!
//! Architecture: the SmolVLA expert's design at small width (a DiT over the `N` action tokens
//! with alternating self- and cross-attention layers, RMSNorm, SwiGLU, the same time embedding
//! and Euler sampler), conditioned on observation tokens instead of a VLM prefix:
//! - one state token, `state_proj(state)`;
//! - one token per camera, `image_proj(pooled_features(image))` (an `image_grid^2 x 3` vector,
//!   see [`crate::image_features`]); missing cameras are masked out;
//! - per layer, the tokens' keys and values come from a [`PrefixEncoder`].
//!
//! The observation is encoded once per request; `S` samples share it and run along the batch
//! dimension. The default size (hidden 256, 4 layers, chunk 50 x 7, 10 steps) takes tens of
//! milliseconds per batch-1 generation on a 2-core CPU; `kairos serve` runs it with seeded
//! random weights unless given a checkpoint (`config.json` with `"type": "kairos_flow_head"`
//! and `model.safetensors`, see `docs/ENGINE.md`).

use std::path::Path;

use crate::image_features::pooled_features;
use crate::kernels::gemm::gemm;
use crate::kernels::{Init, Isa, MatMut, MatRef, PackedMatrix};
use crate::prefix_encoder::PrefixEncoder;
use crate::smolvla::ExpertWeights;
use crate::smolvla::config::{ExpertDims, LayerKind, intermediate_size, read_json};
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::{PrefixKv, SmolVlaExpert};
use crate::weights::{Checkpoint, serialize_f32};
use crate::{ActionChunk, ActionModel, ActionRequest, EngineError, EngineOptions, ModelSpec};

/// The `type` of a flow-head `config.json`.
pub const FLOW_HEAD_TYPE: &str = "kairos_flow_head";

/// Flow-head configuration (`config.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct FlowHeadConfig {
    /// Always `kairos_flow_head`.
    #[serde(rename = "type")]
    pub model_type: String,
    /// Model name reported in [`ModelSpec::name`].
    pub name: String,
    /// Robot state length.
    pub state_dim: usize,
    /// Action dimension.
    pub action_dim: usize,
    /// Actions per chunk.
    pub chunk_size: usize,
    /// Euler steps.
    pub num_steps: usize,
    /// Most cameras per observation.
    pub max_images: usize,
    /// Pooling grid per image side.
    pub image_grid: usize,
    /// Observation token width.
    pub token_dim: usize,
    /// Transformer width.
    pub hidden: usize,
    /// Transformer layers.
    pub layers: usize,
    /// Query heads.
    pub heads: usize,
    /// Key/value heads.
    pub kv_heads: usize,
    /// Head width.
    pub head_dim: usize,
    /// Every n-th layer self-attends (over observation and action tokens), the others
    /// cross-attend to the observation.
    pub self_attn_every_n_layers: usize,
    /// RMSNorm epsilon.
    pub rms_norm_eps: f64,
    /// Time-embedding periods.
    pub min_period: f64,
    /// Time-embedding periods.
    pub max_period: f64,
}

impl Default for FlowHeadConfig {
    fn default() -> Self {
        FlowHeadConfig {
            model_type: FLOW_HEAD_TYPE.into(),
            name: "flow-head-small".into(),
            state_dim: 8,
            action_dim: 7,
            chunk_size: 50,
            num_steps: 10,
            max_images: 2,
            image_grid: 8,
            token_dim: 128,
            hidden: 256,
            layers: 4,
            heads: 4,
            kv_heads: 2,
            head_dim: 64,
            self_attn_every_n_layers: 2,
            rms_norm_eps: 1e-5,
            min_period: 4e-3,
            max_period: 4.0,
        }
    }
}

impl FlowHeadConfig {
    /// The expert shapes this config describes.
    pub fn dims(&self) -> Result<ExpertDims, EngineError> {
        let bad = |m: &str| EngineError::InvalidInput(format!("flow head config: {m}"));
        if self.model_type != FLOW_HEAD_TYPE {
            return Err(bad(&format!(
                "type is `{}`, expected `{FLOW_HEAD_TYPE}`",
                self.model_type
            )));
        }
        if self.heads == 0 || self.kv_heads == 0 || !self.heads.is_multiple_of(self.kv_heads) {
            return Err(bad("heads must be a positive multiple of kv_heads"));
        }
        if !self.head_dim.is_multiple_of(2)
            || !self.hidden.is_multiple_of(2)
            || self.layers == 0
            || self.num_steps == 0
        {
            return Err(bad(
                "head_dim and hidden must be even; layers and num_steps positive",
            ));
        }
        if [
            self.state_dim,
            self.action_dim,
            self.chunk_size,
            self.image_grid,
            self.token_dim,
        ]
        .contains(&0)
        {
            return Err(bad("dimensions must be positive"));
        }
        let every = self.self_attn_every_n_layers.max(1);
        Ok(ExpertDims {
            vlm_hidden: self.token_dim,
            hidden: self.hidden,
            intermediate: intermediate_size(self.hidden),
            heads: self.heads,
            kv_heads: self.kv_heads,
            head_dim: self.head_dim,
            rms_eps: self.rms_norm_eps as f32,
            layers: (0..self.layers)
                .map(|i| {
                    if i % every == 0 {
                        LayerKind::SelfAttention
                    } else {
                        LayerKind::CrossAttention
                    }
                })
                .collect(),
            chunk: self.chunk_size,
            action_pad: self.action_dim,
            state_pad: self.state_dim,
            action_dim: self.action_dim,
            state_dim: self.state_dim,
            steps: self.num_steps,
            min_period: self.min_period,
            max_period: self.max_period,
        })
    }

    fn feature_dim(&self) -> usize {
        self.image_grid * self.image_grid * 3
    }
}

const IMAGE_PROJ: &str = "flow_head.image_proj";
const PREFIX_PROJ: &str = "flow_head.prefix";

/// The flow-head model.
pub struct FlowHead {
    config: FlowHeadConfig,
    spec: ModelSpec,
    weights: ExpertWeights,
    expert: SmolVlaExpert,
    encoder: PrefixEncoder,
    image_proj: LinearWeights,
    image_proj_packed: PackedMatrix,
}

impl std::fmt::Debug for FlowHead {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FlowHead")
            .field("config", &self.config)
            .field("backend", &self.expert.description())
            .finish()
    }
}

impl FlowHead {
    fn assemble(
        config: FlowHeadConfig,
        weights: ExpertWeights,
        encoder: PrefixEncoder,
        image_proj: LinearWeights,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let expert = SmolVlaExpert::from_weights(&weights, options)?;
        let spec = ModelSpec {
            cameras: Vec::new(),
            camera_aliases: Default::default(),
            name: config.name.clone(),
            chunk_len: config.chunk_size,
            action_dim: config.action_dim,
            state_dim: config.state_dim,
            steps: config.num_steps,
            max_images: config.max_images,
        };
        let image_proj_packed = PackedMatrix::from_linear_weight(
            &image_proj.weight,
            image_proj.out_dim,
            image_proj.in_dim,
        );
        Ok(FlowHead {
            config,
            spec,
            weights,
            expert,
            encoder,
            image_proj,
            image_proj_packed,
        })
    }

    /// Seeded random weights: the same `seed` gives the same model everywhere.
    pub fn random(
        config: FlowHeadConfig,
        seed: u64,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let dims = config.dims()?;
        let weights = ExpertWeights::random(&dims, seed);
        let encoder = PrefixEncoder::random(seed ^ 0x5EED_0001, config.token_dim, &dims);
        let image_proj = LinearWeights::random(
            seed ^ 0x5EED_0002,
            config.token_dim,
            config.feature_dim(),
            true,
        );
        Self::assemble(config, weights, encoder, image_proj, options)
    }

    /// Load a checkpoint directory (`config.json` + `model.safetensors`).
    pub fn load(dir: &Path, options: &EngineOptions) -> Result<Self, EngineError> {
        let config: FlowHeadConfig = read_json(&dir.join("config.json"))?;
        let dims = config.dims()?;
        let ckpt = Checkpoint::open(&dir.join("model.safetensors"))?;
        let weights = ExpertWeights::load(&ckpt, &dims)?;
        let encoder = PrefixEncoder::load(&ckpt, PREFIX_PROJ, config.token_dim, &dims)?;
        let image_proj = LinearWeights {
            weight: ckpt.tensor(
                &format!("{IMAGE_PROJ}.weight"),
                &[config.token_dim, config.feature_dim()],
            )?,
            bias: Some(ckpt.tensor(&format!("{IMAGE_PROJ}.bias"), &[config.token_dim])?),
            out_dim: config.token_dim,
            in_dim: config.feature_dim(),
        };
        Self::assemble(config, weights, encoder, image_proj, options)
    }

    /// Write a checkpoint directory that [`FlowHead::load`] reads back.
    pub fn save(&self, dir: &Path) -> Result<(), EngineError> {
        let io = |e: std::io::Error| EngineError::Load {
            path: dir.display().to_string(),
            reason: e.to_string(),
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let mut tensors = self.weights.tensors();
        tensors.extend(self.encoder.tensors(PREFIX_PROJ));
        let ip = &self.image_proj;
        tensors.push((
            format!("{IMAGE_PROJ}.weight"),
            vec![ip.out_dim, ip.in_dim],
            &ip.weight,
        ));
        if let Some(b) = &ip.bias {
            tensors.push((format!("{IMAGE_PROJ}.bias"), vec![ip.out_dim], b));
        }
        let owned: Vec<(String, Vec<usize>, &[f32])> = tensors;
        std::fs::write(dir.join("model.safetensors"), serialize_f32(&owned)?).map_err(io)?;
        let json = serde_json::to_string_pretty(&self.config)
            .map_err(|e| EngineError::InvalidInput(e.to_string()))?;
        std::fs::write(dir.join("config.json"), json).map_err(io)
    }

    /// The configuration.
    pub fn config(&self) -> &FlowHeadConfig {
        &self.config
    }

    /// Where and how it runs.
    pub fn description(&self) -> &str {
        self.expert.description()
    }

    /// Observation tokens and their pad mask for one request.
    fn encode(
        &self,
        request: &ActionRequest,
        state_token: &[f32],
    ) -> Result<PrefixKv, EngineError> {
        let c = &self.config;
        let width = c.token_dim;
        let mut tokens = vec![0.0f32; (1 + c.max_images) * width];
        let mut valid = vec![false; 1 + c.max_images];
        tokens[..width].copy_from_slice(state_token);
        valid[0] = true;
        for (i, image) in request.images.iter().enumerate() {
            let features = pooled_features(image, c.image_grid)?;
            let token = &mut tokens[(1 + i) * width..(2 + i) * width];
            let init = self
                .image_proj
                .bias
                .as_deref()
                .map_or(Init::Zero, Init::Bias);
            let (features, token) = (
                MatRef::dense(&features, 1, features.len()),
                MatMut::dense(token, 1, width),
            );
            gemm(
                Isa::detect(),
                features,
                &self.image_proj_packed,
                token,
                init,
            );
            valid[1 + i] = true;
        }
        self.encoder.encode(&tokens, valid)
    }
}

impl ActionModel for FlowHead {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        self.spec.validate(batch)?;
        // The head samples in the robot's units: guidance prefixes need no mapping.
        self.expert
            .generate_requests(batch, |request, state| self.encode(request, state), &|_| {})
    }

    /// `rtc` and `inpaint` in its expert's sampler, and `rtc_vjp` on the Candle path.
    fn chunking(&self) -> crate::ModelChunking {
        crate::ModelChunking {
            guidance: self.expert.guidance_support(),
            action_space: crate::ActionSpace::Unspecified,
        }
    }
}
