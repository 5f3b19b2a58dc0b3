//! Serving the SmolVLA expert through [`ActionModel`] before the VLM exists in Kairos.
//!
//! **The prefix here is a stand-in, not a VLM.** SmolVLA's expert needs the prefix KV cache that
//! SmolVLM2 computes from the images, the instruction and the state. Until the VLM is ported,
//! [`SmolVlaStandIn`] builds a prefix of the real shape (64 tokens per camera, 48 instruction
//! tokens, 1 state token: 177 for two cameras, with LeRobot's pad mask for short instructions
//! and missing cameras) from fixed, seeded random projections of the observation:
//! - camera tokens: each cell of an 8x8 average-pooled grid of the image, projected, plus a
//!   per-cell embedding;
//! - instruction tokens: a random embedding of each of the first 48 UTF-8 bytes;
//! - the state token: the checkpoint's real `state_proj(state)`, projected down;
//!
//! and per-layer keys/values from a random [`PrefixEncoder`]. The chunks therefore depend on the
//! observation and cost exactly what the real expert costs, but they are **not** what the
//! trained SmolVLA would output. For real policies, compute the prefix with the VLM and call
//! [`SmolVlaExpert::sample`] directly.

use std::path::Path;

use crate::image_features::pooled_features;
use crate::kernels::gemm::gemm;
use crate::kernels::{Init, Isa, MatMut, MatRef, PackedMatrix};
use crate::prefix_encoder::PrefixEncoder;
use crate::sampler::gaussian_noise;
use crate::smolvla::{PrefixKv, SmolVlaExpert};
use crate::{ActionChunk, ActionModel, ActionRequest, EngineError, EngineOptions, ModelSpec};

/// Tokens per camera (SmolVLA: 64 after SigLIP and pixel shuffle).
pub const TOKENS_PER_IMAGE: usize = 64;
/// Instruction tokens (LeRobot's `tokenizer_max_length`).
pub const INSTRUCTION_TOKENS: usize = 48;
const TOKEN_DIM: usize = 64;
const GRID: usize = 8;
const SEED: u64 = 0x5714_D117;

/// The SmolVLA expert behind [`ActionModel`], fed by a labelled stand-in prefix (see the module
/// documentation).
pub struct SmolVlaStandIn {
    expert: SmolVlaExpert,
    spec: ModelSpec,
    encoder: PrefixEncoder,
    state_down: PackedMatrix,
    pixel_proj: PackedMatrix,
    cell_embedding: Vec<f32>,
    byte_embedding: Vec<f32>,
}

impl std::fmt::Debug for SmolVlaStandIn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaStandIn")
            .field("spec", &self.spec)
            .field("expert", &self.expert)
            .finish()
    }
}

impl SmolVlaStandIn {
    /// Load a LeRobot SmolVLA checkpoint directory (see [`SmolVlaExpert::load`]) and attach the
    /// stand-in prefix for up to `max_images` cameras.
    pub fn load(
        dir: &Path,
        options: &EngineOptions,
        max_images: usize,
    ) -> Result<Self, EngineError> {
        Ok(Self::new(SmolVlaExpert::load(dir, options)?, max_images))
    }

    /// Wrap an expert.
    pub fn new(expert: SmolVlaExpert, max_images: usize) -> Self {
        let d = expert.dims().clone();
        let random = |seed: u64, rows: usize, cols: usize| -> Vec<f32> {
            let scale = 1.0 / (cols as f32).sqrt();
            gaussian_noise(SEED ^ seed, 0, rows * cols)
                .into_iter()
                .map(|v| v * scale)
                .collect()
        };
        let spec = ModelSpec {
            cameras: Vec::new(),
            camera_aliases: Default::default(),
            name: "smolvla-expert+stand-in-prefix".into(),
            chunk_len: d.chunk,
            action_dim: d.action_dim,
            state_dim: d.state_dim,
            steps: d.steps,
            max_images,
        };
        SmolVlaStandIn {
            encoder: PrefixEncoder::random(SEED, TOKEN_DIM, &d),
            state_down: PackedMatrix::from_linear_weight(
                &random(1, TOKEN_DIM, d.vlm_hidden),
                TOKEN_DIM,
                d.vlm_hidden,
            ),
            pixel_proj: PackedMatrix::from_linear_weight(&random(2, TOKEN_DIM, 3), TOKEN_DIM, 3),
            cell_embedding: gaussian_noise(SEED ^ 3, 0, TOKENS_PER_IMAGE * TOKEN_DIM),
            byte_embedding: gaussian_noise(SEED ^ 4, 0, 256 * TOKEN_DIM),
            expert,
            spec,
        }
    }

    /// The wrapped expert.
    pub fn expert(&self) -> &SmolVlaExpert {
        &self.expert
    }

    /// Prefix length: `64 * max_images + 48 + 1`.
    pub fn prefix_len(&self) -> usize {
        TOKENS_PER_IMAGE * self.spec.max_images + INSTRUCTION_TOKENS + 1
    }

    /// The stand-in prefix of one request (LeRobot's order: images, instruction, state).
    pub fn stand_in_prefix(
        &self,
        request: &ActionRequest,
        state_token: &[f32],
    ) -> Result<PrefixKv, EngineError> {
        let isa = Isa::detect();
        let len = self.prefix_len();
        let mut tokens = vec![0.0f32; len * TOKEN_DIM];
        let mut valid = vec![false; len];
        for (i, image) in request.images.iter().enumerate() {
            let cells = pooled_features(image, GRID)?;
            let at = i * TOKENS_PER_IMAGE;
            let block = &mut tokens[at * TOKEN_DIM..(at + TOKENS_PER_IMAGE) * TOKEN_DIM];
            block.copy_from_slice(&self.cell_embedding);
            let (cells, block) = (
                MatRef::dense(&cells, TOKENS_PER_IMAGE, 3),
                MatMut::dense(block, TOKENS_PER_IMAGE, TOKEN_DIM),
            );
            gemm(isa, cells, &self.pixel_proj, block, Init::Accumulate);
            valid[at..at + TOKENS_PER_IMAGE].fill(true);
        }
        let text = TOKENS_PER_IMAGE * self.spec.max_images;
        for (j, &byte) in request
            .instruction
            .as_bytes()
            .iter()
            .take(INSTRUCTION_TOKENS)
            .enumerate()
        {
            let b = usize::from(byte);
            tokens[(text + j) * TOKEN_DIM..(text + j + 1) * TOKEN_DIM]
                .copy_from_slice(&self.byte_embedding[b * TOKEN_DIM..(b + 1) * TOKEN_DIM]);
            valid[text + j] = true;
        }
        let last = len - 1;
        let d = self.expert.dims();
        let (state, token) = (
            MatRef::dense(state_token, 1, d.vlm_hidden),
            MatMut::dense(&mut tokens[last * TOKEN_DIM..], 1, TOKEN_DIM),
        );
        gemm(isa, state, &self.state_down, token, Init::Zero);
        valid[last] = true;
        self.encoder.encode(&tokens, valid)
    }
}

impl ActionModel for SmolVlaStandIn {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    /// `rtc` and `inpaint` in the expert's sampler.
    fn chunking(&self) -> crate::ModelChunking {
        crate::ModelChunking {
            guidance: self.expert.guidance_support(),
            action_space: crate::ActionSpace::Unspecified,
        }
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        self.spec.validate(batch)?;
        self.expert
            // The stand-in samples in the robot's units: guidance prefixes need no mapping.
            .generate_requests(
                batch,
                |request, state| self.stand_in_prefix(request, state),
                &|_| {},
            )
    }
}
