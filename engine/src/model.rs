//! The interface between the server and every model.

use crate::{ActionChunk, EngineError};

/// What a model produces and consumes; the server validates requests against it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelSpec {
    /// A short model name, e.g. `flow-head-small` or `smolvla-expert`.
    pub name: String,
    /// Actions per chunk `N`.
    pub chunk_len: usize,
    /// Dimension of one action `D` as returned to the robot.
    pub action_dim: usize,
    /// Length of the robot state vector the model expects.
    pub state_dim: usize,
    /// Number of flow-matching steps `K`.
    pub steps: usize,
    /// Most camera images one observation may carry.
    pub max_images: usize,
}

/// Most samples one request may ask for.
pub const MAX_SAMPLES: usize = 64;

impl ModelSpec {
    /// Check every request of `batch` against this spec: state length, finite state values,
    /// image count and `1 <= samples <= MAX_SAMPLES`. Errors name the request's index.
    pub fn validate(&self, batch: &[ActionRequest]) -> Result<(), EngineError> {
        for (i, r) in batch.iter().enumerate() {
            let fail = |m: String| Err(EngineError::InvalidInput(format!("request {i}: {m}")));
            if r.state.len() != self.state_dim {
                return fail(format!(
                    "state has {} values, model `{}` needs {}",
                    r.state.len(),
                    self.name,
                    self.state_dim
                ));
            }
            if r.state.iter().any(|v| !v.is_finite()) {
                return fail("state contains a non-finite value".into());
            }
            if r.images.len() > self.max_images {
                return fail(format!(
                    "{} images, at most {}",
                    r.images.len(),
                    self.max_images
                ));
            }
            if r.samples == 0 || r.samples > MAX_SAMPLES {
                return fail(format!(
                    "samples = {}, must be 1..={MAX_SAMPLES}",
                    r.samples
                ));
            }
        }
        Ok(())
    }
}

/// Encodings the engine can decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// JPEG bytes.
    Jpeg,
    /// PNG bytes.
    Png,
}

/// One camera image of an observation.
#[derive(Clone, Debug, PartialEq)]
pub enum ImageInput {
    /// Compressed bytes, decoded on the engine thread.
    Encoded {
        /// The codec.
        format: ImageFormat,
        /// The file bytes.
        bytes: Vec<u8>,
    },
    /// Raw 8-bit pixels, `[height][width][channels]`.
    RawU8 {
        /// Rows.
        height: usize,
        /// Columns.
        width: usize,
        /// 1 (grey), 3 (RGB) or 4 (RGBA).
        channels: usize,
        /// `height * width * channels` bytes.
        data: Vec<u8>,
    },
    /// Raw float pixels in `[0, 1]`, `[height][width][channels]`.
    RawF32 {
        /// Rows.
        height: usize,
        /// Columns.
        width: usize,
        /// 1, 3 or 4.
        channels: usize,
        /// `height * width * channels` values.
        data: Vec<f32>,
    },
}

/// One observation to generate a chunk for.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionRequest {
    /// Robot state vector, `ModelSpec::state_dim` long.
    pub state: Vec<f32>,
    /// Camera images, at most `ModelSpec::max_images`.
    pub images: Vec<ImageInput>,
    /// The task instruction (models without a language backbone may ignore it).
    pub instruction: String,
    /// Samples `S` to draw for this observation (1 = the usual single chunk).
    pub samples: usize,
    /// Seed of the initial noise, so a retried round reproduces its chunk.
    pub seed: u64,
}

/// A loaded model that turns a batch of observations into action chunks.
///
/// Implementations run the whole batch in one forward pass per step where the architecture
/// allows it, and must give each request the same result it would get alone (same seed, same
/// chunk). `generate` is blocking and CPU/GPU-heavy: callers run it on a dedicated thread.
pub trait ActionModel: Send + Sync {
    /// The shapes this model works with.
    fn spec(&self) -> &ModelSpec;

    /// Generate one [`ActionChunk`] per request, in request order.
    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError>;
}
