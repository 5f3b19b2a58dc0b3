//! The Candle layers the π models and SmolVLA are built from: linear, LayerNorm, Gemma's RMSNorm
//! (plain and adaptive), Llama's RMSNorm, GeGLU and SwiGLU, multi-head attention (one sequence or
//! a batch of them, grouped-query) and Gemma's RoPE tables. Every op is a Candle op, so the
//! models run on any Candle device; activations are `[rows, features]` (or `[batch, rows,
//! features]`) f32 tensors. A [`Linear`] may hold its weight in bf16: its product then runs in
//! bf16 and its output comes back as f32, so norms, softmax and residuals stay in f32.
//!
//! Each layer computes what the PyTorch module it transcribes computes, in the same order of
//! operations where that decides the rounding (the `(1 + w)` of Gemma's norm is made in f32
//! first, the RoPE angle is `position * inv_freq` rounded once); sums are Candle's, so results
//! differ from PyTorch's only in rounding.

use candle_core::{D, DType, Device, Tensor};

use super::vars::Vars;
use crate::EngineError;
use crate::candle_ops;

/// `y = x wᵀ + b` (`nn.Linear`).
pub struct Linear {
    /// `[in][out]`: transposed once at load, so the product reads it in place.
    w_t: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    /// `vars.weight` `[out][in]` and, with `bias`, `vars.bias` `[out]`.
    pub fn load(vars: &Vars<'_>, out: usize, inp: usize, bias: bool) -> Result<Self, EngineError> {
        let w = vars.get(&[out, inp], "weight")?;
        let bias = bias.then(|| vars.get(&[out], "bias")).transpose()?;
        Ok(Linear {
            w_t: w.t()?.contiguous()?,
            bias,
        })
    }

    /// From a weight `[out][in]` and a bias `[out]` already on the device.
    pub fn from_parts(weight: Tensor, bias: Option<Tensor>) -> Result<Self, EngineError> {
        Ok(Linear {
            w_t: weight.t()?.contiguous()?,
            bias,
        })
    }

    /// `x` is `[.., in]`. The rows are one matrix product (one GEMM launch on a GPU), in the
    /// weight's dtype; the output has `x`'s dtype.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        let dims = x.dims();
        let (inp, out) = self.w_t.dims2()?;
        if dims.last() != Some(&inp) {
            return Err(EngineError::InvalidInput(format!(
                "a linear layer of {inp} inputs got a tensor of shape {dims:?}"
            )));
        }
        let rows = x.elem_count() / inp.max(1);
        let flat = x.reshape((rows, inp))?;
        let wd = self.w_t.dtype();
        let y = if x.dtype() == wd {
            flat.matmul(&self.w_t)?
        } else {
            flat.to_dtype(wd)?.matmul(&self.w_t)?.to_dtype(x.dtype())?
        };
        let y = match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        };
        let mut shape = dims.to_vec();
        if let Some(last) = shape.last_mut() {
            *last = out;
        }
        Ok(y.reshape(shape)?)
    }

    /// The dtype the product runs in (the weight's).
    pub fn dtype(&self) -> DType {
        self.w_t.dtype()
    }
}

/// `nn.LayerNorm` with weight and bias.
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f32,
}

impl LayerNorm {
    /// `vars.weight`, `vars.bias`, `[width]` each.
    pub fn load(vars: &Vars<'_>, width: usize, eps: f64) -> Result<Self, EngineError> {
        Ok(LayerNorm {
            weight: vars.get(&[width], "weight")?,
            bias: vars.get(&[width], "bias")?,
            eps: eps as f32,
        })
    }

    /// From `[width]` weight and bias already on the device.
    pub fn from_parts(weight: Tensor, bias: Tensor, eps: f64) -> Self {
        LayerNorm {
            weight,
            bias,
            eps: eps as f32,
        }
    }

    /// Over the last dimension.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        Ok(candle_ops::layer_norm(
            &x.contiguous()?,
            &self.weight,
            &self.bias,
            self.eps,
        )?)
    }
}

/// Gemma's RMSNorm as LeRobot's `PiGemmaRMSNorm` has it: `x / rms(x) * (1 + w)`, or, adaptive
/// (π0.5's expert, `adarms_cond`), `x / rms(x) * (1 + scale) + shift` with
/// `[scale | shift | gate] = dense(cond)` and the `gate` handed to the residual.
pub enum GemmaNorm {
    /// `weight` `[width]`, kept as `1 + weight` (rounded in f32 once, as PyTorch does).
    Plain {
        /// `1 + weight`.
        one_plus_w: Tensor,
        /// Epsilon.
        eps: f32,
    },
    /// `dense` `[3 width][width]` with bias.
    Adaptive {
        /// The modulation layer.
        dense: Linear,
        /// `[width]` ones: the plain normalisation without a scale.
        ones: Tensor,
        /// Width.
        width: usize,
        /// Epsilon.
        eps: f32,
    },
}

/// What an adaptive norm's condition produced for one batch: `[batch, 1, width]` each.
pub struct Modulation {
    scale_plus_one: Tensor,
    shift: Tensor,
    gate: Tensor,
}

impl GemmaNorm {
    /// A plain norm (`vars.weight`) or, when `adaptive`, `vars.dense.{weight,bias}`.
    pub fn load(
        vars: &Vars<'_>,
        width: usize,
        eps: f64,
        adaptive: bool,
    ) -> Result<Self, EngineError> {
        let eps = eps as f32;
        if adaptive {
            Ok(GemmaNorm::Adaptive {
                dense: Linear::load(&vars.pp("dense"), 3 * width, width, true)?,
                ones: Tensor::ones(width, candle_core::DType::F32, vars.device())?,
                width,
                eps,
            })
        } else {
            let w = vars.get(&[width], "weight")?;
            Ok(GemmaNorm::Plain {
                one_plus_w: (w + 1.0)?,
                eps,
            })
        }
    }

    /// The modulation of an adaptive norm for conditions `cond` `[batch, width]`; `None` for a
    /// plain norm.
    pub fn modulation(&self, cond: &Tensor) -> Result<Option<Modulation>, EngineError> {
        let GemmaNorm::Adaptive { dense, width, .. } = self else {
            return Ok(None);
        };
        let m = dense.forward(cond)?.unsqueeze(1)?;
        let w = *width;
        Ok(Some(Modulation {
            scale_plus_one: (m.narrow(D::Minus1, 0, w)? + 1.0)?,
            shift: m.narrow(D::Minus1, w, w)?.contiguous()?,
            gate: m.narrow(D::Minus1, 2 * w, w)?.contiguous()?,
        }))
    }

    /// Normalise `x` (`[batch, rows, width]` when modulated, any rank otherwise); returns the
    /// output and the residual gate (adaptive only).
    pub fn forward(
        &self,
        x: &Tensor,
        modulation: Option<&Modulation>,
    ) -> Result<(Tensor, Option<Tensor>), EngineError> {
        let x = x.contiguous()?;
        match (self, modulation) {
            (GemmaNorm::Plain { one_plus_w, eps }, None) => {
                Ok((candle_ops::rms_norm(&x, one_plus_w, *eps)?, None))
            }
            (GemmaNorm::Adaptive { ones, eps, .. }, Some(m)) => {
                let normed = candle_ops::rms_norm(&x, ones, *eps)?;
                let out = normed
                    .broadcast_mul(&m.scale_plus_one)?
                    .broadcast_add(&m.shift)?;
                Ok((out, Some(m.gate.clone())))
            }
            (GemmaNorm::Plain { .. }, Some(_)) | (GemmaNorm::Adaptive { .. }, None) => {
                Err(EngineError::InvalidInput(
                    "an adaptive norm needs its condition and a plain one takes none".into(),
                ))
            }
        }
    }
}

/// Llama's RMSNorm (`LlamaRMSNorm`: `x / rms(x) * w`), [`candle_ops::rms_norm`].
pub struct RmsNorm {
    weight: Tensor,
    eps: f32,
}

impl RmsNorm {
    /// From a `[width]` weight already on the device.
    pub fn from_parts(weight: Tensor, eps: f64) -> Self {
        RmsNorm {
            weight,
            eps: eps as f32,
        }
    }

    /// Over the last dimension.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        Ok(candle_ops::rms_norm(
            &x.contiguous()?,
            &self.weight,
            self.eps,
        )?)
    }
}

/// LeRobot's `_gated_residual`: `x + y`, or `x + y * gate`.
pub fn gated_residual(
    x: &Tensor,
    y: &Tensor,
    gate: Option<&Tensor>,
) -> Result<Tensor, EngineError> {
    Ok(match gate {
        None => (x + y)?,
        Some(g) => (x + y.broadcast_mul(g)?)?,
    })
}

/// Gemma's MLP: `down(gelu_tanh(gate(x)) * up(x))`.
pub struct GeGlu {
    gate: Linear,
    up: Linear,
    down: Linear,
}

impl GeGlu {
    /// `vars.{gate,up,down}_proj`, no biases.
    pub fn load(vars: &Vars<'_>, width: usize, mlp: usize) -> Result<Self, EngineError> {
        Ok(GeGlu {
            gate: Linear::load(&vars.pp("gate_proj"), mlp, width, false)?,
            up: Linear::load(&vars.pp("up_proj"), mlp, width, false)?,
            down: Linear::load(&vars.pp("down_proj"), width, mlp, false)?,
        })
    }

    /// Over the last dimension.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        let h = (self.gate.forward(x)?.gelu()? * self.up.forward(x)?)?;
        self.down.forward(&h)
    }
}

/// Llama's MLP: `down(silu(gate(x)) * up(x))`.
pub struct SwiGlu {
    gate: Linear,
    up: Linear,
    down: Linear,
}

impl SwiGlu {
    /// From its three projections.
    pub fn from_parts(gate: Linear, up: Linear, down: Linear) -> Self {
        SwiGlu { gate, up, down }
    }

    /// Over the last dimension.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        let h = (candle_ops::silu(&self.gate.forward(x)?)? * self.up.forward(x)?)?;
        self.down.forward(&h)
    }
}

/// Softmax attention over a batch of sequences: `q` `[batch, heads, lq, hd]` over `k`, `v`
/// `[batch, kv_heads, lk, hd]` (each KV head serves `heads / kv_heads` query heads), scaled by
/// `scale`, with an optional additive `mask` broadcastable to `[batch, 1, lq, lk]`. Returns
/// `[batch, lq, heads * hd]`. The whole batch is two batched matrix products and one softmax.
pub fn batched_attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    mask: Option<&Tensor>,
) -> Result<Tensor, EngineError> {
    let (b, heads, lq, hd) = q.dims4()?;
    let (_, kv_heads, lk, _) = k.dims4()?;
    let group = heads / kv_heads.max(1);
    // The query heads that share a KV head are one matrix product against its keys.
    let q = q.contiguous()?.reshape((b, kv_heads, group * lq, hd))?;
    let scores = (q.matmul(&k.contiguous()?.t()?)? * scale)?;
    let scores = match mask {
        Some(m) => {
            let m = m.reshape((m.dim(0)?, 1, 1, lq, lk))?;
            scores
                .reshape((b, kv_heads, group, lq, lk))?
                .broadcast_add(&m)?
                .reshape((b, kv_heads, group * lq, lk))?
        }
        None => scores,
    };
    let probs = candle_ops::softmax_last_dim(&scores)?;
    let out = probs.matmul(&v.contiguous()?)?;
    Ok(out
        .reshape((b, heads, lq, hd))?
        .transpose(1, 2)?
        .reshape((b, lq, heads * hd))?)
}

/// Softmax attention of `q` `[heads, lq, hd]` over `k`, `v` `[kv_heads, lk, hd]` (each KV head
/// serves `heads / kv_heads` query heads), scaled by `scale`, with an optional additive `mask`
/// `[lq, lk]`. Returns `[lq, heads * hd]`: [`batched_attention`] on a batch of one.
pub fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    scale: f64,
    mask: Option<&Tensor>,
) -> Result<Tensor, EngineError> {
    let mask = mask
        .map(|m| -> Result<Tensor, EngineError> {
            let (lq, lk) = m.dims2()?;
            Ok(m.reshape((1, 1, lq, lk))?)
        })
        .transpose()?;
    let out = batched_attention(
        &q.unsqueeze(0)?,
        &k.unsqueeze(0)?,
        &v.unsqueeze(0)?,
        scale,
        mask.as_ref(),
    )?;
    Ok(out.squeeze(0)?)
}

/// `[rows, heads * hd]` -> `[heads, rows, hd]`.
pub fn split_heads(x: &Tensor, heads: usize, hd: usize) -> Result<Tensor, EngineError> {
    let rows = x.dim(0)?;
    Ok(x.reshape((rows, heads, hd))?
        .transpose(0, 1)?
        .contiguous()?)
}

/// Gemma's rotary embedding (`GemmaRotaryEmbedding` + `apply_rotary_pos_emb`, halves layout)
/// for a run of positions.
pub struct Rope {
    cos: Tensor,
    sin: Tensor,
}

impl Rope {
    /// Tables for `positions`: `inv_freq_i = 1 / theta^(2i / hd)` in f32 (the power rounded
    /// once from f64; PyTorch's float `pow` is within an ulp of it), angle `f32(p) * inv_freq_i`
    /// rounded once, as `inv_freq @ position_ids` makes it.
    pub fn new(
        positions: impl IntoIterator<Item = usize>,
        hd: usize,
        theta: f64,
        device: &Device,
    ) -> Result<Self, EngineError> {
        let half = hd / 2;
        let inv_freq: Vec<f32> = (0..half)
            .map(|i| {
                let exponent = (2 * i) as f32 / hd as f32;
                1.0 / (theta.powf(f64::from(exponent)) as f32)
            })
            .collect();
        let (mut cos, mut sin) = (Vec::new(), Vec::new());
        for p in positions {
            for &f in &inv_freq {
                let angle = p as f32 * f;
                cos.push(angle.cos());
                sin.push(angle.sin());
            }
        }
        let rows = cos.len() / half.max(1);
        Ok(Rope {
            cos: Tensor::from_vec(cos, (rows, half), device)?,
            sin: Tensor::from_vec(sin, (rows, half), device)?,
        })
    }

    /// Rotate `x` `[heads, rows, hd]` (rows in this table's position order).
    pub fn apply(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        let x = x.unsqueeze(0)?.contiguous()?;
        Ok(candle_ops::rope(&x, &self.cos, &self.sin)?.squeeze(0)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(seed: u64, shape: &[usize]) -> Tensor {
        let n = shape.iter().product();
        Tensor::from_vec(
            crate::sampler::gaussian_noise(seed, 0, n),
            shape,
            &Device::Cpu,
        )
        .unwrap()
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar()
            .unwrap()
    }

    /// A bf16 weight multiplies in bf16 and answers in f32, within bf16's rounding of the f32
    /// product; an input of the wrong width is an error, not a silent reshape.
    #[test]
    fn linear_runs_in_its_weights_dtype_and_checks_the_width() {
        let (w, b) = (tensor(1, &[6, 8]), tensor(2, &[6]));
        let exact = Linear::from_parts(w.clone(), Some(b.clone())).unwrap();
        let half = Linear::from_parts(w.to_dtype(DType::BF16).unwrap(), Some(b)).unwrap();
        let x = tensor(3, &[2, 5, 8]);
        let (y, y16) = (exact.forward(&x).unwrap(), half.forward(&x).unwrap());
        assert_eq!(y.dims(), [2, 5, 6]);
        assert_eq!(y16.dtype(), DType::F32);
        let d = max_diff(&y, &y16);
        assert!(d > 0.0 && d < 0.1, "{d}");
        assert!(exact.forward(&tensor(4, &[4, 6])).is_err());
    }

    /// Attention over a batch is attention over each sequence, with grouped KV heads and a
    /// per-sequence mask.
    #[test]
    fn batched_attention_is_attention_per_sequence() {
        let (b, heads, kvh, lq, lk, hd) = (3, 4, 2, 5, 7, 8);
        let q = tensor(5, &[b, heads, lq, hd]);
        let k = tensor(6, &[b, kvh, lk, hd]);
        let v = tensor(7, &[b, kvh, lk, hd]);
        let mask: Vec<f32> = (0..b * lq * lk)
            .map(|i| if i % 3 == 0 { f32::NEG_INFINITY } else { 0.0 })
            .collect();
        let mask = Tensor::from_vec(mask, (b, 1, lq, lk), &Device::Cpu).unwrap();
        let all = batched_attention(&q, &k, &v, 0.3, Some(&mask)).unwrap();
        for i in 0..b {
            let m = mask.get(i).unwrap().squeeze(0).unwrap();
            let one = attention(
                &q.get(i).unwrap(),
                &k.get(i).unwrap(),
                &v.get(i).unwrap(),
                0.3,
                Some(&m),
            )
            .unwrap();
            assert!(max_diff(&all.get(i).unwrap(), &one) < 1e-6);
        }
    }
}
