//! One Llama decoder layer's weights ([`LayerWeights`]): the expert's layers and the VLM's
//! text layers have the same tensors under the same names.

use super::config::LayerKind;
use super::linear::{LinearWeights, WeightData};
use crate::EngineError;
use crate::weights::{Checkpoint, StoredTensor};

/// One Llama decoder layer (no biases): an expert layer, or a VLM text layer.
#[derive(Clone, Debug)]
pub struct LayerWeights<W = Vec<f32>> {
    /// Self- or cross-attention.
    pub kind: LayerKind,
    /// `input_layernorm.weight`.
    pub input_norm: Vec<f32>,
    /// `post_attention_layernorm.weight`.
    pub post_norm: Vec<f32>,
    /// `self_attn.q_proj`: hidden -> heads*head_dim.
    pub q_proj: LinearWeights<W>,
    /// `self_attn.k_proj`: hidden -> kv (self) or VLM kv -> kv (cross).
    pub k_proj: LinearWeights<W>,
    /// `self_attn.v_proj`, like `k_proj`.
    pub v_proj: LinearWeights<W>,
    /// `self_attn.o_proj`: heads*head_dim -> hidden.
    pub o_proj: LinearWeights<W>,
    /// `mlp.gate_proj`: hidden -> intermediate.
    pub gate_proj: LinearWeights<W>,
    /// `mlp.up_proj`: hidden -> intermediate.
    pub up_proj: LinearWeights<W>,
    /// `mlp.down_proj`: intermediate -> hidden.
    pub down_proj: LinearWeights<W>,
}

/// Shapes of one Llama decoder layer.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LlamaShape {
    /// Hidden width.
    pub hidden: usize,
    /// `heads * head_dim`.
    pub q: usize,
    /// `kv_heads * head_dim`.
    pub kv: usize,
    /// Input width of `k_proj`/`v_proj` (`hidden`, or the VLM's kv width for cross-attention).
    pub kv_in: usize,
    /// MLP width.
    pub intermediate: usize,
}

impl<W: WeightData> LayerWeights<W> {
    /// Read one Llama decoder layer under `p` (`{p}.input_layernorm.weight`, `{p}.self_attn.*`,
    /// `{p}.mlp.*`): the expert's layers and the VLM's text layers have the same tensors.
    pub(crate) fn load_llama(
        ckpt: &Checkpoint,
        p: &str,
        kind: LayerKind,
        s: LlamaShape,
    ) -> Result<Self, EngineError> {
        let LlamaShape {
            hidden: h,
            q,
            kv,
            kv_in,
            intermediate: i,
        } = s;
        let lin = |name: &str, out: usize, inp: usize| {
            LinearWeights::load(ckpt, &format!("{p}.{name}"), out, inp, false)
        };
        Ok(LayerWeights {
            kind,
            input_norm: ckpt.tensor(&format!("{p}.input_layernorm.weight"), &[h])?,
            post_norm: ckpt.tensor(&format!("{p}.post_attention_layernorm.weight"), &[h])?,
            q_proj: lin("self_attn.q_proj", q, h)?,
            k_proj: lin("self_attn.k_proj", kv, kv_in)?,
            v_proj: lin("self_attn.v_proj", kv, kv_in)?,
            o_proj: lin("self_attn.o_proj", h, q)?,
            gate_proj: lin("mlp.gate_proj", i, h)?,
            up_proj: lin("mlp.up_proj", i, h)?,
            down_proj: lin("mlp.down_proj", h, i)?,
        })
    }
}

impl LayerWeights {
    /// Seeded random layer of the given shape (norm weights near 1).
    pub(crate) fn random_llama(seed: u64, kind: LayerKind, s: LlamaShape) -> Self {
        let mut k = seed.wrapping_mul(16);
        let mut next = || {
            k = k.wrapping_add(1);
            k
        };
        let norm = |seed: u64| -> Vec<f32> {
            crate::sampler::gaussian_noise(seed, 0, s.hidden)
                .into_iter()
                .map(|v| 1.0 + 0.1 * v)
                .collect()
        };
        LayerWeights {
            kind,
            input_norm: norm(next()),
            post_norm: norm(next()),
            q_proj: LinearWeights::random(next(), s.q, s.hidden, false),
            k_proj: LinearWeights::random(next(), s.kv, s.kv_in, false),
            v_proj: LinearWeights::random(next(), s.kv, s.kv_in, false),
            o_proj: LinearWeights::random(next(), s.hidden, s.q, false),
            gate_proj: LinearWeights::random(next(), s.intermediate, s.hidden, false),
            up_proj: LinearWeights::random(next(), s.intermediate, s.hidden, false),
            down_proj: LinearWeights::random(next(), s.hidden, s.intermediate, false),
        }
    }

    /// The same layer with its matrices held as [`StoredTensor`]s (`f32`).
    pub fn into_stored(self) -> LayerWeights<StoredTensor> {
        LayerWeights {
            kind: self.kind,
            input_norm: self.input_norm,
            post_norm: self.post_norm,
            q_proj: self.q_proj.into_stored(),
            k_proj: self.k_proj.into_stored(),
            v_proj: self.v_proj.into_stored(),
            o_proj: self.o_proj.into_stored(),
            gate_proj: self.gate_proj.into_stored(),
            up_proj: self.up_proj.into_stored(),
            down_proj: self.down_proj.into_stored(),
        }
    }
}
