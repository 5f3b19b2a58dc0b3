//! The expert's tensors under LeRobot's parameter names, as host `f32`, and its time embedding.

use crate::EngineError;
use crate::smolvla::config::{ExpertDims, LayerKind};
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::llama_layer::{LayerWeights, LlamaShape};
use crate::weights::Checkpoint;

/// Prefix of the expert transformer's parameters in a SmolVLA checkpoint.
pub const EXPERT_PREFIX: &str = "model.vlm_with_expert.lm_expert";

/// All expert weights.
#[derive(Clone, Debug)]
pub struct ExpertWeights {
    /// Shapes.
    pub dims: ExpertDims,
    /// Decoder layers.
    pub layers: Vec<LayerWeights>,
    /// `lm_expert.norm.weight`.
    pub final_norm: Vec<f32>,
    /// `model.state_proj`: state_pad -> vlm_hidden (feeds the VLM prefix, not the expert).
    pub state_proj: LinearWeights,
    /// `model.action_in_proj`: action_pad -> hidden.
    pub action_in_proj: LinearWeights,
    /// `model.action_time_mlp_in`: 2*hidden -> hidden.
    pub action_time_mlp_in: LinearWeights,
    /// `model.action_time_mlp_out`: hidden -> hidden.
    pub action_time_mlp_out: LinearWeights,
    /// `model.action_out_proj`: hidden -> action_pad.
    pub action_out_proj: LinearWeights,
}

impl ExpertWeights {
    /// Read every tensor the expert needs; errors name the first missing or mis-shaped key.
    pub fn load(ckpt: &Checkpoint, dims: &ExpertDims) -> Result<Self, EngineError> {
        let (h, kv) = (dims.hidden, dims.kv_width());
        let layers = dims
            .layers
            .iter()
            .enumerate()
            .map(|(l, &kind)| {
                let p = format!("{EXPERT_PREFIX}.layers.{l}");
                let kv_in = match kind {
                    LayerKind::SelfAttention => h,
                    LayerKind::CrossAttention => kv,
                };
                let shape = LlamaShape {
                    hidden: h,
                    q: dims.q_width(),
                    kv,
                    kv_in,
                    intermediate: dims.intermediate,
                };
                LayerWeights::load_llama(ckpt, &p, kind, shape)
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(ExpertWeights {
            dims: dims.clone(),
            layers,
            final_norm: ckpt.tensor(&format!("{EXPERT_PREFIX}.norm.weight"), &[h])?,
            state_proj: LinearWeights::load(
                ckpt,
                "model.state_proj",
                dims.vlm_hidden,
                dims.state_pad,
                true,
            )?,
            action_in_proj: LinearWeights::load(
                ckpt,
                "model.action_in_proj",
                h,
                dims.action_pad,
                true,
            )?,
            action_time_mlp_in: LinearWeights::load(
                ckpt,
                "model.action_time_mlp_in",
                h,
                2 * h,
                true,
            )?,
            action_time_mlp_out: LinearWeights::load(
                ckpt,
                "model.action_time_mlp_out",
                h,
                h,
                true,
            )?,
            action_out_proj: LinearWeights::load(
                ckpt,
                "model.action_out_proj",
                dims.action_pad,
                h,
                true,
            )?,
        })
    }

    /// Every tensor under its LeRobot name, for writing a checkpoint.
    pub fn tensors(&self) -> Vec<(String, Vec<usize>, &[f32])> {
        let mut out: Vec<(String, Vec<usize>, &[f32])> = Vec::new();
        fn push<'a>(
            out: &mut Vec<(String, Vec<usize>, &'a [f32])>,
            key: &str,
            l: &'a LinearWeights,
        ) {
            out.push((
                format!("{key}.weight"),
                vec![l.out_dim, l.in_dim],
                &l.weight,
            ));
            if let Some(b) = &l.bias {
                out.push((format!("{key}.bias"), vec![l.out_dim], b));
            }
        }
        let h = self.dims.hidden;
        for (i, l) in self.layers.iter().enumerate() {
            let p = format!("{EXPERT_PREFIX}.layers.{i}");
            out.push((
                format!("{p}.input_layernorm.weight"),
                vec![h],
                &l.input_norm,
            ));
            out.push((
                format!("{p}.post_attention_layernorm.weight"),
                vec![h],
                &l.post_norm,
            ));
            push(&mut out, &format!("{p}.self_attn.q_proj"), &l.q_proj);
            push(&mut out, &format!("{p}.self_attn.k_proj"), &l.k_proj);
            push(&mut out, &format!("{p}.self_attn.v_proj"), &l.v_proj);
            push(&mut out, &format!("{p}.self_attn.o_proj"), &l.o_proj);
            push(&mut out, &format!("{p}.mlp.gate_proj"), &l.gate_proj);
            push(&mut out, &format!("{p}.mlp.up_proj"), &l.up_proj);
            push(&mut out, &format!("{p}.mlp.down_proj"), &l.down_proj);
        }
        out.push((
            format!("{EXPERT_PREFIX}.norm.weight"),
            vec![h],
            &self.final_norm,
        ));
        push(&mut out, "model.state_proj", &self.state_proj);
        push(&mut out, "model.action_in_proj", &self.action_in_proj);
        push(
            &mut out,
            "model.action_time_mlp_in",
            &self.action_time_mlp_in,
        );
        push(
            &mut out,
            "model.action_time_mlp_out",
            &self.action_time_mlp_out,
        );
        push(&mut out, "model.action_out_proj", &self.action_out_proj);
        out
    }

    /// Seeded random weights of the given shapes (benches; the default-size expert).
    pub fn random(dims: &ExpertDims, seed: u64) -> Self {
        let (h, kv, q, i) = (
            dims.hidden,
            dims.kv_width(),
            dims.q_width(),
            dims.intermediate,
        );
        let mut s = seed;
        let mut next = || {
            s = s.wrapping_add(1);
            s
        };
        let norm = |seed: u64| -> Vec<f32> {
            crate::sampler::gaussian_noise(seed, 0, h)
                .into_iter()
                .map(|v| 1.0 + 0.1 * v)
                .collect()
        };
        let layers = dims
            .layers
            .iter()
            .map(|&kind| {
                let kv_in = if kind == LayerKind::SelfAttention {
                    h
                } else {
                    kv
                };
                LayerWeights {
                    kind,
                    input_norm: norm(next()),
                    post_norm: norm(next()),
                    q_proj: LinearWeights::random(next(), q, h, false),
                    k_proj: LinearWeights::random(next(), kv, kv_in, false),
                    v_proj: LinearWeights::random(next(), kv, kv_in, false),
                    o_proj: LinearWeights::random(next(), h, q, false),
                    gate_proj: LinearWeights::random(next(), i, h, false),
                    up_proj: LinearWeights::random(next(), i, h, false),
                    down_proj: LinearWeights::random(next(), h, i, false),
                }
            })
            .collect();
        ExpertWeights {
            dims: dims.clone(),
            layers,
            final_norm: norm(next()),
            state_proj: LinearWeights::random(next(), dims.vlm_hidden, dims.state_pad, true),
            action_in_proj: LinearWeights::random(next(), h, dims.action_pad, true),
            action_time_mlp_in: LinearWeights::random(next(), h, 2 * h, true),
            action_time_mlp_out: LinearWeights::random(next(), h, h, true),
            action_out_proj: LinearWeights::random(next(), dims.action_pad, h, true),
        }
    }
}

/// LeRobot's `create_sinusoidal_pos_embedding(t, dim, min_period, max_period)` for one time,
/// computed in f64 as LeRobot does on CPU, returned as f32: `[sin(2π t / p_i) ; cos(..)]` with
/// periods `p_i = min * (max/min)^(i / (dim/2 - 1))`.
pub fn time_embedding(t: f32, dim: usize, min_period: f64, max_period: f64) -> Vec<f32> {
    let half = dim / 2;
    let t = f64::from(t);
    let mut sin = Vec::with_capacity(dim);
    let mut cos = Vec::with_capacity(half);
    for i in 0..half {
        let fraction = if half > 1 {
            i as f64 / (half - 1) as f64
        } else {
            0.0
        };
        let period = min_period * (max_period / min_period).powf(fraction);
        let x = 1.0 / period * 2.0 * std::f64::consts::PI * t;
        sin.push(x.sin() as f32);
        cos.push(x.cos() as f32);
    }
    sin.extend(cos);
    sin
}
