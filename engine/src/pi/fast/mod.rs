//! π0 and π0.5 on the engine's fast CPU kernels ([`FastPiModel`]): the same network as
//! [`crate::pi::PiModel`] computes on Candle ops, on packed weights, a fixed thread pool and
//! reused buffers, in f32 or with bf16 weight GEMMs.
//!
//! - `vision`: the SigLIP tower and projector (SmolVLA's fast tower, given π's tensors);
//! - `prefix`: the PaliGemma prefix's Gemma layers, which fill the K/V cache ([`FastPrefix`]);
//! - `expert`: the action expert and the Euler loop;
//! - `layer`: the Gemma layer both stacks are made of (RMSNorm with `1 + w` or adaptive,
//!   GeGLU with tanh-GELU, one KV head, RoPE).
//!
//! The weights stay as the checkpoint stores them until they are packed (a bf16 checkpoint's
//! bits go straight into bf16 panels; no f32 copy of a bf16 weight is made); the token
//! embedding stays as stored and its rows are widened when looked up. Norms, softmax, RoPE,
//! activations and residuals compute in f32 in both precisions.

mod expert;
mod layer;
mod prefix;
mod vision;

pub use prefix::FastPrefix;

use crate::EngineError;
use crate::guidance::RowGuide;
use crate::kernels::{Pool, Precision};
use crate::pi::config::{PiDims, keys};
use crate::pi::model::PiObservation;
use crate::pi::vars::Vars;
use crate::smolvla::ExpertSample;
use crate::smolvla::expert::SampledRows;
use crate::smolvla::vlm::vision::{CpuVision, VisionImage, VisionOutput};
use crate::weights::{Checkpoint, StoredTensor};
use expert::{FastGemmaExpert, SuffixRequest};
use prefix::FastGemmaPrefix;

/// One request to the expert on the fast path.
#[derive(Clone, Copy, Debug)]
pub struct FastSampleInput<'a> {
    /// The observation's prefix.
    pub prefix: &'a FastPrefix,
    /// π0's normalised state (at most `max_state_dim` values, zero-padded here); `None` for
    /// π0.5, whose state is in the prompt.
    pub state: Option<&'a [f32]>,
    /// One initial noise per sample, `[chunk][max_action_dim]` each.
    pub noise: &'a [Vec<f32>],
}

/// A loaded π0 or π0.5 network on the fast CPU kernels.
pub struct FastPiModel {
    dims: PiDims,
    pool: Pool,
    precision: Precision,
    vision: CpuVision,
    /// `[vocab][vlm width]`, as stored.
    embed_tokens: StoredTensor,
    /// `f32(sqrt(width))` (`GemmaTextScaledWordEmbedding`'s factor).
    embed_scale: f32,
    prefix: FastGemmaPrefix,
    expert: FastGemmaExpert,
}

impl std::fmt::Debug for FastPiModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FastPiModel")
            .field("dims", &self.dims)
            .field("pool", &self.pool)
            .field("precision", &self.precision)
            .finish()
    }
}

impl FastPiModel {
    /// Load and pack every tensor the model reads from `ckpt`, its weight GEMMs in
    /// `precision` as this pool's kernels resolve it ([`Precision::resolve`]).
    pub fn load(
        ckpt: &Checkpoint,
        dims: &PiDims,
        pool: Pool,
        precision: Precision,
    ) -> Result<Self, EngineError> {
        let precision = precision.resolve(pool.isa());
        let root = Vars::new(ckpt, dims.family, &candle_core::Device::Cpu);
        let language = root.pp(keys::VLM);
        let w = dims.vlm.width;
        Ok(FastPiModel {
            vision: vision::load(&root, dims, precision)?,
            embed_tokens: language
                .pp("embed_tokens")
                .stored(&[dims.vocab, w], "weight")?,
            embed_scale: (w as f64).sqrt() as f32,
            prefix: FastGemmaPrefix::load(&language, &dims.vlm, precision)?,
            expert: FastGemmaExpert::load(&root, dims, precision)?,
            dims: dims.clone(),
            pool,
            precision,
        })
    }

    /// Shapes.
    pub fn dims(&self) -> &PiDims {
        &self.dims
    }

    /// The precision the weight GEMMs run in (bf16 only where this CPU runs it natively).
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// The thread pool.
    pub fn pool(&self) -> &Pool {
        &self.pool
    }

    /// The vision tower and projector over `images` (`[3][S][S]` each, in `[-1, 1]`):
    /// per image, SigLIP's output `[patches][hidden]` and the image tokens
    /// `[patches][vlm width]`.
    pub fn vision(&self, images: &[&[f32]]) -> Result<VisionOutput, EngineError> {
        let side = self.dims.vision.image_size;
        let pixels = 3 * side * side;
        let views = images
            .iter()
            .enumerate()
            .map(|(i, p)| {
                if p.len() == pixels {
                    Ok(VisionImage { side, pixels: p })
                } else {
                    Err(EngineError::InvalidInput(format!(
                        "image {i}: {} values, expected 3 x {side} x {side}",
                        p.len()
                    )))
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        self.vision.forward(&self.pool, &views)
    }

    /// Each observation's valid prefix embeddings, `[n_i][vlm width]`: the image tokens of its
    /// present cameras in slot order, then its valid task tokens' embeddings `x sqrt(width)`.
    /// The present cameras of the whole batch go through the vision tower together.
    pub fn prefix_embeddings(
        &self,
        observations: &[PiObservation<'_>],
    ) -> Result<Vec<Vec<f32>>, EngineError> {
        let d = &self.dims;
        let w = d.vlm.width;
        let mut images = Vec::new();
        for (o, obs) in observations.iter().enumerate() {
            if obs.tokens.len() != obs.token_mask.len() {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: {} tokens but {} mask values",
                    obs.tokens.len(),
                    obs.token_mask.len()
                )));
            }
            if let Some(&bad) = obs.tokens.iter().find(|&&t| t as usize >= d.vocab) {
                return Err(EngineError::InvalidInput(format!(
                    "observation {o}: token id {bad} is outside the vocabulary of {}",
                    d.vocab
                )));
            }
            let side = d.vision.image_size;
            for (slot, image) in obs.images.iter().enumerate() {
                if let Some(p) = image {
                    if p.len() != 3 * side * side {
                        return Err(EngineError::InvalidInput(format!(
                            "observation {o}, camera slot {slot}: {} values, expected \
                             3 x {side} x {side}",
                            p.len()
                        )));
                    }
                    images.push(*p);
                }
            }
        }
        let image_tokens = if images.is_empty() {
            Vec::new()
        } else {
            self.vision(&images)?.embeddings
        };
        let mut next_image = image_tokens.into_iter();
        observations
            .iter()
            .map(|obs| {
                let mut rows = Vec::new();
                for _ in obs.images.iter().flatten() {
                    rows.extend(next_image.next().unwrap_or_default());
                }
                for (&t, _) in obs.tokens.iter().zip(obs.token_mask).filter(|(_, m)| **m) {
                    let t = t as usize;
                    rows.extend(
                        self.embed_tokens
                            .widened(t * w..(t + 1) * w)
                            .iter()
                            .map(|&v| v * self.embed_scale),
                    );
                }
                if rows.is_empty() {
                    return Err(EngineError::InvalidInput(
                        "an observation without a camera image or a task token has no prefix"
                            .into(),
                    ));
                }
                Ok(rows)
            })
            .collect()
    }

    /// Each observation's prefix cache (all observations through each layer together).
    pub fn prefix(
        &self,
        observations: &[PiObservation<'_>],
    ) -> Result<Vec<FastPrefix>, EngineError> {
        let embeddings = self.prefix_embeddings(observations)?;
        Ok(self.prefix.forward(&self.pool, embeddings))
    }

    /// Run the Euler loop for a batch of requests, one expert pass per step for all of them.
    pub fn sample(&self, inputs: &[FastSampleInput<'_>]) -> Result<Vec<ExpertSample>, EngineError> {
        self.sample_guided(inputs, &[])
    }

    /// [`FastPiModel::sample`] with a [`RowGuide`] per row (rows are `[input][sample]`; an
    /// empty `guides` is plain sampling for every row). The velocities recorded are those each
    /// step used: the guided ones on guided rows.
    pub fn sample_guided(
        &self,
        inputs: &[FastSampleInput<'_>],
        guides: &[Option<RowGuide>],
    ) -> Result<Vec<ExpertSample>, EngineError> {
        let d = &self.dims;
        let len = d.chunk * d.action_pad;
        let mut states = Vec::with_capacity(inputs.len());
        let mut row_request = Vec::new();
        let mut x = Vec::new();
        for (i, input) in inputs.iter().enumerate() {
            if input.noise.is_empty() {
                return Err(EngineError::InvalidInput(format!(
                    "request {i} asks for no sample"
                )));
            }
            states.push(d.expert_state(i, input.state)?);
            for noise in input.noise {
                if noise.len() != len {
                    return Err(EngineError::InvalidInput(format!(
                        "request {i}: noise has {} values, expected {len}",
                        noise.len()
                    )));
                }
                x.extend_from_slice(noise);
                row_request.push(i);
            }
        }
        let rows = row_request.len();
        if rows == 0 {
            return Ok(Vec::new());
        }
        let requests: Vec<SuffixRequest<'_>> = inputs
            .iter()
            .zip(&states)
            .map(|(input, state)| SuffixRequest {
                prefix: input.prefix,
                state: state.as_deref(),
            })
            .collect();
        let guides = crate::guidance::guides_per_row(guides, rows)?;
        let guides = &guides[..];
        // No backward pass here: an `rtc_vjp` row is refused, naming the path that serves it.
        if let Some(g) = guides
            .iter()
            .flatten()
            .find(|g| g.mode == kairos_engine_types::GuidanceMode::RtcVjp)
        {
            return Err(EngineError::InvalidInput(format!(
                "guidance `{}`: the fast kernels have no backward pass through π's expert; {}",
                g.mode.as_str(),
                crate::candle_vjp::VJP_PATH
            )));
        }
        let noise = x.clone();
        let steps = d.steps;
        let mut velocities = vec![0.0f32; rows * steps * len];
        let mut updates = vec![0.0f32; rows * steps * len];
        self.expert.sample(
            &self.pool,
            &requests,
            &row_request,
            &mut x,
            &mut velocities,
            &mut updates,
            guides,
        )?;
        let rows = SampledRows {
            noise: &noise,
            actions: &x,
            velocities: &velocities,
            updates: &updates,
            len,
            steps,
        };
        Ok(rows.split(inputs.iter().map(|input| input.noise.len())))
    }
}
