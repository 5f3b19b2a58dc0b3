//! The π0 / π0.5 network on Candle ops: vision, prefix, action expert and the Euler loop, as
//! LeRobot 0.6.1's `PI0Pytorch` / `PI05Pytorch` compute `sample_actions`:
//!
//! ```text
//! prefix = [image tokens of each present camera ; embed_tokens(valid task tokens) * sqrt(width)]
//!   -> PaliGemma's Gemma layers -> per-layer K/V                 (once per observation)
//! suffix, π0:   [state_proj(state) ; action_time_mlp_out(silu(action_time_mlp_in(
//!                    [action_in_proj(x_t) ; sincos(t)])))]        (1 + chunk tokens)
//! suffix, π0.5: action_in_proj(x_t), with adarms_cond = silu(time_mlp_out(silu(
//!                    time_mlp_in(sincos(t)))))                    (chunk tokens)
//!   -> the expert's layers over [prefix K/V ; own K/V] -> final norm
//!   -> action_out_proj of the last `chunk` tokens = v_t;  x_t += dt v_t, ten times
//! ```
//!
//! Suffix masks (`make_att_2d_masks`): π0's state token sees the prefix and itself, its action
//! tokens see the prefix, the state and every action token; π0.5's action tokens see the prefix
//! and each other. Suffix positions continue after the prefix's valid tokens.

use candle_core::{DType, Device, Tensor};

use super::config::{PiDims, PiFamily, keys};
use super::gemma::{GemmaExpert, GemmaPrefix, PrefixCache, SuffixContext};
use super::layers::Linear;
use super::vars::Vars;
use super::vision::{SiglipTower, VisionOutput};
use crate::EngineError;
use crate::candle_vjp::{self, VjpRows};
use crate::guidance::RowGuide;
use crate::sampler::VelocityField;
use crate::smolvla::ExpertSample;
use crate::smolvla::expert::SampledRows;
use crate::smolvla::expert::weights::time_embedding;
use crate::weights::Checkpoint;

/// One observation as the prefix reads it (after the processors).
#[derive(Clone, Debug)]
pub struct PiObservation<'a> {
    /// Camera slots in LeRobot's order: the pixels `[3][S][S]` in `[-1, 1]`, or `None` for a
    /// missing camera (LeRobot's all `-1` image with a false mask: its tokens are padding).
    pub images: Vec<Option<&'a [f32]>>,
    /// Task token ids.
    pub tokens: &'a [u32],
    /// `true` for real tokens.
    pub token_mask: &'a [bool],
}

/// One request to the expert.
#[derive(Clone, Copy, Debug)]
pub struct SampleInput<'a> {
    /// The observation's prefix.
    pub prefix: &'a PrefixCache,
    /// π0's normalised state (at most `max_state_dim` values, zero-padded here); `None` for
    /// π0.5, whose state is in the prompt.
    pub state: Option<&'a [f32]>,
    /// One initial noise per sample, `[chunk][max_action_dim]` each.
    pub noise: &'a [Vec<f32>],
}

/// The suffix's own layers, by family.
enum Suffix {
    Pi0 {
        state_proj: Linear,
        action_time_mlp_in: Linear,
        action_time_mlp_out: Linear,
    },
    Pi05 {
        time_mlp_in: Linear,
        time_mlp_out: Linear,
    },
}

/// A loaded π0 or π0.5 network on one Candle device.
pub struct PiModel {
    dims: PiDims,
    device: Device,
    vision: SiglipTower,
    /// `[vocab][vlm width]`.
    embed_tokens: Tensor,
    /// `f32(sqrt(width))`, the scaled embedding's factor (`GemmaTextScaledWordEmbedding`).
    embed_scale: f64,
    prefix: GemmaPrefix,
    expert: GemmaExpert,
    action_in_proj: Linear,
    action_out_proj: Linear,
    suffix: Suffix,
}

impl std::fmt::Debug for PiModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PiModel")
            .field("dims", &self.dims)
            .field("device", &self.device)
            .finish()
    }
}

impl PiModel {
    /// Load every tensor the model reads from `ckpt` onto `device` (widened to f32).
    pub fn load(ckpt: &Checkpoint, dims: &PiDims, device: &Device) -> Result<Self, EngineError> {
        let root = Vars::new(ckpt, dims.family, device);
        let (e, w) = (dims.expert.width, dims.vlm.width);
        let m = root.pp("model");
        let suffix = match dims.family {
            PiFamily::Pi0 => Suffix::Pi0 {
                state_proj: Linear::load(&m.pp("state_proj"), e, dims.state_pad, true)?,
                action_time_mlp_in: Linear::load(&m.pp("action_time_mlp_in"), e, 2 * e, true)?,
                action_time_mlp_out: Linear::load(&m.pp("action_time_mlp_out"), e, e, true)?,
            },
            PiFamily::Pi05 => Suffix::Pi05 {
                time_mlp_in: Linear::load(&m.pp("time_mlp_in"), e, e, true)?,
                time_mlp_out: Linear::load(&m.pp("time_mlp_out"), e, e, true)?,
            },
        };
        let language = root.pp(keys::VLM);
        Ok(PiModel {
            dims: dims.clone(),
            device: device.clone(),
            vision: SiglipTower::load(&root, &dims.vision, w)?,
            embed_tokens: language
                .pp("embed_tokens")
                .get(&[dims.vocab, w], "weight")?,
            embed_scale: f64::from((w as f64).sqrt() as f32),
            prefix: GemmaPrefix::load(&language, &dims.vlm)?,
            expert: GemmaExpert::load(
                &root.pp(keys::EXPERT),
                &dims.expert,
                dims.family == PiFamily::Pi05,
            )?,
            action_in_proj: Linear::load(&m.pp("action_in_proj"), e, dims.action_pad, true)?,
            action_out_proj: Linear::load(&m.pp("action_out_proj"), dims.action_pad, e, true)?,
            suffix,
        })
    }

    /// Shapes.
    pub fn dims(&self) -> &PiDims {
        &self.dims
    }

    /// The device it runs on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The vision tower and projector over `images` `[n][3][S][S]`.
    pub fn vision(&self, images: &Tensor) -> Result<VisionOutput, EngineError> {
        self.vision.forward(images)
    }

    /// Each observation's valid prefix embeddings, `[n_i][vlm width]`: the image tokens of its
    /// present cameras in slot order, then its task tokens' scaled embeddings. The present
    /// cameras of the whole batch go through the vision tower together.
    pub fn prefix_embeddings(
        &self,
        observations: &[PiObservation<'_>],
    ) -> Result<Vec<Tensor>, EngineError> {
        let d = &self.dims;
        let side = d.vision.image_size;
        let pixels = 3 * side * side;
        let mut flat = Vec::new();
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
            for (slot, image) in obs.images.iter().enumerate() {
                if let Some(p) = image {
                    if p.len() != pixels {
                        return Err(EngineError::InvalidInput(format!(
                            "observation {o}, camera slot {slot}: {} values, expected \
                             3 x {side} x {side}",
                            p.len()
                        )));
                    }
                    flat.extend_from_slice(p);
                }
            }
        }
        let n_images = flat.len() / pixels;
        let image_tokens = if n_images > 0 {
            let images = Tensor::from_vec(flat, (n_images, 3, side, side), &self.device)?;
            Some(self.vision.forward(&images)?.embeddings)
        } else {
            None
        };
        let mut next_image = 0;
        observations
            .iter()
            .map(|obs| {
                let mut parts = Vec::new();
                for _ in obs.images.iter().flatten() {
                    if let Some(tokens) = &image_tokens {
                        parts.push(tokens.get(next_image)?);
                    }
                    next_image += 1;
                }
                let ids: Vec<u32> = obs
                    .tokens
                    .iter()
                    .zip(obs.token_mask)
                    .filter(|&(_, &m)| m)
                    .map(|(&t, _)| t)
                    .collect();
                if !ids.is_empty() {
                    let ids = Tensor::from_vec(ids.clone(), ids.len(), &self.device)?;
                    parts.push((self.embed_tokens.index_select(&ids, 0)? * self.embed_scale)?);
                }
                if parts.is_empty() {
                    return Err(EngineError::InvalidInput(
                        "an observation without a camera image or a task token has no prefix"
                            .into(),
                    ));
                }
                Ok(Tensor::cat(&parts, 0)?)
            })
            .collect()
    }

    /// Each observation's prefix cache.
    pub fn prefix(
        &self,
        observations: &[PiObservation<'_>],
    ) -> Result<Vec<PrefixCache>, EngineError> {
        self.prefix_embeddings(observations)?
            .into_iter()
            .map(|e| self.prefix.cache(e))
            .collect()
    }

    /// The suffix's attention blocks (`cumsum` of LeRobot's suffix `att_masks`).
    fn suffix_blocks(&self) -> Vec<u32> {
        let n = self.dims.chunk;
        match self.dims.family {
            // state [1], actions [1, 0, ..]: cumsum 1, then 2 for every action.
            PiFamily::Pi0 => std::iter::once(1)
                .chain(std::iter::repeat_n(2, n))
                .collect(),
            PiFamily::Pi05 => vec![1; n],
        }
    }

    /// Run the Euler loop for a batch of requests, one expert pass per step for all of them.
    pub fn sample(&self, inputs: &[SampleInput<'_>]) -> Result<Vec<ExpertSample>, EngineError> {
        self.sample_guided(inputs, &[])
    }

    /// [`PiModel::sample`] with a [`RowGuide`] per row (rows are `[input][sample]`; an empty
    /// `guides` is plain sampling for every row). The velocities recorded are those each step
    /// used: the guided ones on guided rows. `rtc_vjp` rows take the vector–Jacobian product of
    /// the velocity with Candle's autograd, in a forward and backward pass of their own, so the
    /// other rows get the bits they get without them.
    pub fn sample_guided(
        &self,
        inputs: &[SampleInput<'_>],
        guides: &[Option<RowGuide>],
    ) -> Result<Vec<ExpertSample>, EngineError> {
        let d = &self.dims;
        let len = d.chunk * d.action_pad;
        let blocks = self.suffix_blocks();
        let mut contexts = Vec::with_capacity(inputs.len());
        let mut states = Vec::new();
        let mut row_request = Vec::new();
        let mut x = Vec::new();
        for (i, input) in inputs.iter().enumerate() {
            if input.noise.is_empty() {
                return Err(EngineError::InvalidInput(format!(
                    "request {i} asks for no sample"
                )));
            }
            contexts.push(SuffixContext::new(
                input.prefix,
                &blocks,
                &d.expert,
                &self.device,
            )?);
            states.extend(d.expert_state(i, input.state)?);
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
        let row_contexts: Vec<&SuffixContext> = row_request.iter().map(|&i| &contexts[i]).collect();
        // π0's state token, one per row: `state_proj(pad(state))`, `[rows][1][width]`.
        let state_tokens = match &self.suffix {
            Suffix::Pi0 { state_proj, .. } => {
                let per_request =
                    Tensor::from_vec(states.concat(), (inputs.len(), d.state_pad), &self.device)?;
                let rows_idx: Vec<u32> = row_request.iter().map(|&i| i as u32).collect();
                let idx = Tensor::from_vec(rows_idx, rows, &self.device)?;
                Some(
                    state_proj
                        .forward(&per_request)?
                        .index_select(&idx, 0)?
                        .unsqueeze(1)?,
                )
            }
            Suffix::Pi05 { .. } => None,
        };

        let guides = crate::guidance::guides_per_row(guides, rows)?;
        let guides = &guides[..];
        let noise = x.clone();
        let steps = d.steps;
        let mut velocities = vec![0.0f32; rows * steps * len];
        let mut updates = vec![0.0f32; rows * steps * len];
        let mut field = PiField::new(
            self,
            RowInputs {
                state_tokens,
                contexts: row_contexts,
            },
            guides,
        )?;
        crate::sampler::integrate_guided(
            crate::sampler::Schedule { steps },
            rows,
            len,
            &mut x,
            &mut updates,
            guides,
            Some(&mut velocities),
            &mut field,
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

    /// `v_t` for `xt` `[rows][chunk][max_action_dim]` at time `t` (LeRobot's `denoise_step`).
    /// Only `xt` may track gradients: the state tokens, the time embedding and (π0.5) the
    /// adaRMS condition, which depends on `t` only, are constants of a backward pass.
    fn velocity(
        &self,
        xt: &Tensor,
        t: f32,
        state_tokens: Option<&Tensor>,
        contexts: &[&SuffixContext],
    ) -> Result<Tensor, EngineError> {
        let d = &self.dims;
        let e = d.expert.width;
        let time = Tensor::from_vec(
            time_embedding(t, e, d.min_period, d.max_period),
            (1, e),
            &self.device,
        )?;
        let action_emb = self.action_in_proj.forward(xt)?;
        let (suffix, cond) = match (&self.suffix, state_tokens) {
            (
                Suffix::Pi0 {
                    action_time_mlp_in,
                    action_time_mlp_out,
                    ..
                },
                Some(state),
            ) => {
                let time = time.unsqueeze(0)?.broadcast_as(action_emb.shape())?;
                let h = Tensor::cat(&[&action_emb, &time], 2)?;
                let h = action_time_mlp_in.forward(&h)?.silu()?;
                let tokens = action_time_mlp_out.forward(&h)?;
                (Tensor::cat(&[state, &tokens], 1)?, None)
            }
            (
                Suffix::Pi05 {
                    time_mlp_in,
                    time_mlp_out,
                },
                _,
            ) => {
                let h = time_mlp_in.forward(&time)?.silu()?;
                let cond = time_mlp_out.forward(&h)?.silu()?;
                (action_emb, Some(cond))
            }
            (Suffix::Pi0 { .. }, None) => {
                return Err(EngineError::InvalidInput("π0 needs its state token".into()));
            }
        };
        let out = self.expert.forward(&suffix, contexts, cond.as_ref())?;
        let s = out.dim(1)?;
        let actions = out.narrow(1, s - d.chunk, d.chunk)?;
        // LeRobot casts the expert output to f32 before action_out_proj (a no-op in f32).
        self.action_out_proj.forward(&actions.to_dtype(DType::F32)?)
    }
}

/// What the velocity of a set of rows reads besides the samples: π0's state tokens
/// (`[rows][1][width]`) and each row's prefix context.
struct RowInputs<'a> {
    state_tokens: Option<Tensor>,
    contexts: Vec<&'a SuffixContext>,
}

impl<'a> RowInputs<'a> {
    /// The inputs of rows `rows` only, in that order.
    fn select(&self, rows: &[usize], device: &Device) -> Result<RowInputs<'a>, EngineError> {
        let idx: Vec<u32> = rows.iter().map(|&r| r as u32).collect();
        let idx = Tensor::from_vec(idx, rows.len(), device)?;
        Ok(RowInputs {
            state_tokens: self
                .state_tokens
                .as_ref()
                .map(|s| s.index_select(&idx, 0))
                .transpose()?,
            contexts: rows.iter().map(|&r| self.contexts[r]).collect(),
        })
    }
}

/// The model's velocity field over the rows of one `sample` call, with the vector–Jacobian
/// product `rtc_vjp` needs ([`candle_vjp`]: the `rtc_vjp` rows run their own tracked forward
/// pass and one backward pass; the other rows keep their bits). π0's state token and
/// action-time MLP are part of the tracked pass: the gradient reaches `x_t` through the expert's
/// attention between the state and the action tokens as well as through the action tokens.
struct PiField<'a> {
    model: &'a PiModel,
    all: RowInputs<'a>,
    /// The rows guided with `rtc_vjp` and their inputs, and the others' (`None` when no row
    /// needs the backward pass).
    split: Option<(VjpRows, RowInputs<'a>, Option<RowInputs<'a>>)>,
}

impl<'a> PiField<'a> {
    fn new(
        model: &'a PiModel,
        all: RowInputs<'a>,
        guides: &[Option<RowGuide>],
    ) -> Result<Self, EngineError> {
        let split = VjpRows::new(guides)
            .map(|rows| -> Result<_, EngineError> {
                let vjp = all.select(rows.vjp(), &model.device)?;
                let plain = (!rows.plain().is_empty())
                    .then(|| all.select(rows.plain(), &model.device))
                    .transpose()?;
                Ok((rows, vjp, plain))
            })
            .transpose()?;
        Ok(PiField { model, all, split })
    }

    fn forward(&self, inputs: &RowInputs<'_>, t: f32, xt: &Tensor) -> Result<Tensor, EngineError> {
        self.model
            .velocity(xt, t, inputs.state_tokens.as_ref(), &inputs.contexts)
    }
}

impl VelocityField for PiField<'_> {
    fn velocity(&mut self, _k: usize, t: f32, x: &[f32], v: &mut [f32]) -> Result<(), EngineError> {
        let d = &self.model.dims;
        let rows = self.all.contexts.len();
        let xt = Tensor::from_slice(x, (rows, d.chunk, d.action_pad), &self.model.device)?;
        let out = self.forward(&self.all, t, &xt)?;
        v.copy_from_slice(&out.flatten_all()?.to_vec1::<f32>()?);
        Ok(())
    }

    fn velocity_vjp(
        &mut self,
        k: usize,
        t: f32,
        x: &[f32],
        v: &mut [f32],
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
        pullback: &mut [f32],
    ) -> Result<(), EngineError> {
        let Some((rows, vjp, plain)) = &self.split else {
            // No row needs the backward pass: the pullback is zero.
            pullback.fill(0.0);
            return self.velocity(k, t, x, v);
        };
        let d = &self.model.dims;
        candle_vjp::velocity_vjp(
            rows,
            (d.chunk, d.action_pad),
            &self.model.device,
            x,
            v,
            cotangent,
            pullback,
            plain
                .as_ref()
                .map(|inputs| |xt: &Tensor| self.forward(inputs, t, xt)),
            |xt: &Tensor| self.forward(vjp, t, xt),
        )
    }
}
