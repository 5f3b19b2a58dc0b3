//! The expert's tensors under LeRobot's parameter names, as host `f32`, and the `Linear` and
//! Llama-layer weights the VLM shares with it (the VLM keeps its matrices as stored, see
//! [`StoredTensor`]).

use super::config::{ExpertDims, LayerKind};
use super::cpu::Linear;
use crate::EngineError;
use crate::kernels::{PackedMatrix, Precision};
use crate::weights::{Checkpoint, StoredTensor};

/// Prefix of the expert transformer's parameters in a SmolVLA checkpoint.
pub const EXPERT_PREFIX: &str = "model.vlm_with_expert.lm_expert";

/// How a weight matrix is held after loading: widened to `f32` (`Vec<f32>`, what the expert
/// and the Candle backend read), or as the checkpoint stores it ([`StoredTensor`]: bf16 bits
/// stay bf16 until they are packed).
pub trait WeightData: Sized {
    /// Read tensor `key` with `shape`; errors name the key.
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError>;
}

impl WeightData for Vec<f32> {
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError> {
        ckpt.tensor(key, shape)
    }
}

impl WeightData for StoredTensor {
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError> {
        ckpt.tensor_stored(key, shape)
    }
}

/// A `Linear` layer: `weight` is `[out][in]`, PyTorch's layout (as `f32`, or as stored).
#[derive(Clone, Debug)]
pub struct LinearWeights<W = Vec<f32>> {
    /// `[out][in]`.
    pub weight: W,
    /// `[out]`, if the layer has a bias.
    pub bias: Option<Vec<f32>>,
    /// Output features.
    pub out_dim: usize,
    /// Input features.
    pub in_dim: usize,
}

impl<W: WeightData> LinearWeights<W> {
    pub(crate) fn load(
        ckpt: &Checkpoint,
        key: &str,
        out_dim: usize,
        in_dim: usize,
        bias: bool,
    ) -> Result<Self, EngineError> {
        let weight = W::read(ckpt, &format!("{key}.weight"), &[out_dim, in_dim])?;
        let bias = if bias {
            Some(ckpt.tensor(&format!("{key}.bias"), &[out_dim])?)
        } else {
            None
        };
        Ok(LinearWeights {
            weight,
            bias,
            out_dim,
            in_dim,
        })
    }
}

impl LinearWeights {
    /// Seeded random weights (uniform, scaled by `1/sqrt(in)`), for benches and the stand-in.
    pub fn random(seed: u64, out_dim: usize, in_dim: usize, bias: bool) -> Self {
        let scale = 1.0 / (in_dim as f32).sqrt();
        let weight = crate::sampler::gaussian_noise(seed, 0, out_dim * in_dim)
            .into_iter()
            .map(|v| v * scale)
            .collect();
        let bias = bias.then(|| {
            crate::sampler::gaussian_noise(seed, 1, out_dim)
                .into_iter()
                .map(|v| 0.1 * v)
                .collect()
        });
        LinearWeights {
            weight,
            bias,
            out_dim,
            in_dim,
        }
    }

    /// The same layer with its weight held as a [`StoredTensor`] (`f32`).
    pub fn into_stored(self) -> LinearWeights<StoredTensor> {
        LinearWeights {
            weight: StoredTensor::F32(self.weight),
            bias: self.bias,
            out_dim: self.out_dim,
            in_dim: self.in_dim,
        }
    }
}

impl LinearWeights<StoredTensor> {
    /// Pack layers with the same input width side by side (`[w0; w1; ..]` along the output
    /// dimension, e.g. q, k and v into one GEMM) in `precision`, reading each element from the
    /// stored tensor: no `f32` copy of a bf16 weight is made, and bf16 panels hold its bits.
    /// The panels equal [`PackedMatrix::from_linear_weights_in`]'s of the widened weights.
    pub(crate) fn pack_stacked(precision: Precision, parts: &[&Self]) -> PackedMatrix {
        let k = parts.first().map_or(0, |p| p.in_dim);
        debug_assert!(
            parts
                .iter()
                .all(|p| p.in_dim == k && p.weight.len() == p.out_dim * k)
        );
        // Output row -> (part, offset of that row in the part's weight).
        let rows: Vec<(usize, usize)> = parts
            .iter()
            .enumerate()
            .flat_map(|(i, p)| (0..p.out_dim).map(move |r| (i, r * k)))
            .collect();
        PackedMatrix::from_linear_fn_in(precision, rows.len(), k, |j, kk| {
            let (part, row) = rows[j];
            parts[part].weight.get(row + kk)
        })
    }

    /// The layer packed for the GEMM in `precision` (see [`Self::pack_stacked`]); the stored
    /// weight is dropped.
    pub(crate) fn into_linear(self, precision: Precision) -> Linear {
        let w = Self::pack_stacked(precision, &[&self]);
        Linear { w, bias: self.bias }
    }
}

/// One expert decoder layer (a Llama layer; no biases).
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::gemm::gemm;
    use crate::kernels::{Init, Isa, MatMut, MatRef};

    /// `A · B` for an `m x k` `A`.
    fn product(p: &PackedMatrix, a: &[f32], m: usize) -> Vec<f32> {
        let mut c = vec![f32::NAN; m * p.n()];
        gemm(
            Isa::detect(),
            MatRef::new(a, m, p.k(), p.k()),
            p,
            MatMut::new(&mut c, m, p.n(), p.n()),
            Init::Zero,
        );
        c
    }

    /// The packed matrix's values, `B[kk][j]`, as `I_k · B` (exact in both precisions: every
    /// product is a value times 1 or 0).
    fn unpack(p: &PackedMatrix) -> Vec<f32> {
        let k = p.k();
        let mut eye = vec![0.0f32; k * k];
        for i in 0..k {
            eye[i * k + i] = 1.0;
        }
        product(p, &eye, k)
    }

    fn bits(len: usize, seed: u64) -> Vec<u16> {
        crate::sampler::gaussian_noise(seed, 0, len)
            .into_iter()
            .map(|v| half::bf16::from_f32(v).to_bits())
            .collect()
    }

    /// Packing bf16 bits straight from a stored tensor gives exactly the panels of packing the
    /// widened `f32` weight (the old path), in f32 and bf16 panels, for odd shapes, a depth that
    /// spans two cache blocks, and stacked layers of mixed dtypes.
    #[test]
    fn packing_from_bf16_bits_equals_packing_the_widened_f32() {
        for &(n, k) in &[(1, 1), (21, 37), (33, 259), (17, 128)] {
            let w = bits(n * k, n as u64 * 1000 + k as u64);
            let widened: Vec<f32> = w.iter().map(|&b| crate::weights::bf16_to_f32(b)).collect();
            let stored = LinearWeights {
                weight: StoredTensor::Bf16(w),
                bias: None,
                out_dim: n,
                in_dim: k,
            };
            let a = crate::sampler::gaussian_noise(7, 0, 5 * k);
            for precision in [Precision::F32, Precision::Bf16] {
                let ours = LinearWeights::pack_stacked(precision, &[&stored]);
                let old = PackedMatrix::from_linear_weight_in(precision, &widened, n, k);
                assert_eq!((ours.n(), ours.k(), ours.precision()), (n, k, precision));
                let values = unpack(&ours);
                assert_eq!(values, unpack(&old), "{n}x{k} {precision:?}");
                // ...and they are the file's values: B[kk][j] = w[j][kk].
                for kk in 0..k {
                    for j in 0..n {
                        assert_eq!(values[kk * n + j], widened[j * k + kk]);
                    }
                }
                assert_eq!(product(&ours, &a, 5), product(&old, &a, 5));
            }
        }
        // q (bf16), k (f32) and v (bf16) stacked, odd widths.
        let k = 45;
        let q = bits(7 * k, 1);
        let kf = crate::sampler::gaussian_noise(2, 0, 3 * k);
        let v = bits(5 * k, 3);
        let lin = |weight: StoredTensor, n: usize| LinearWeights {
            weight,
            bias: None,
            out_dim: n,
            in_dim: k,
        };
        let parts = [
            lin(StoredTensor::Bf16(q.clone()), 7),
            lin(StoredTensor::F32(kf.clone()), 3),
            lin(StoredTensor::Bf16(v.clone()), 5),
        ];
        let widen =
            |b: &[u16]| -> Vec<f32> { b.iter().map(|&x| crate::weights::bf16_to_f32(x)).collect() };
        let (qw, vw) = (widen(&q), widen(&v));
        for precision in [Precision::F32, Precision::Bf16] {
            let ours = LinearWeights::pack_stacked(precision, &[&parts[0], &parts[1], &parts[2]]);
            let old =
                PackedMatrix::from_linear_weights_in(precision, &[(&qw, 7), (&kf, 3), (&vw, 5)], k);
            assert_eq!(unpack(&ours), unpack(&old), "stacked {precision:?}");
        }
    }

    /// `into_linear` keeps the bias and packs like `Linear::new` on the widened weight.
    #[test]
    fn into_linear_matches_linear_new_on_the_widened_weight() {
        let (n, k) = (19, 31);
        let w = bits(n * k, 9);
        let bias = Some(crate::sampler::gaussian_noise(10, 0, n));
        let f32_weights = LinearWeights {
            weight: w.iter().map(|&b| crate::weights::bf16_to_f32(b)).collect(),
            bias: bias.clone(),
            out_dim: n,
            in_dim: k,
        };
        let stored = LinearWeights {
            weight: StoredTensor::Bf16(w),
            bias,
            out_dim: n,
            in_dim: k,
        };
        for precision in [Precision::F32, Precision::Bf16] {
            let old = Linear::new(&f32_weights, precision);
            let ours = stored.clone().into_linear(precision);
            assert_eq!(ours.bias, old.bias);
            assert_eq!(unpack(&ours.w), unpack(&old.w), "{precision:?}");
        }
    }
}
