//! A Gemma decoder layer packed for the engine's CPU kernels (the prefix's and the expert's are
//! the same layer), its RMSNorm in both forms, GeGLU's activation and Gemma's RoPE tables.
//!
//! The maths is that of the Candle layers in [`crate::pi::layers`], which transcribe LeRobot's
//! `PiGemmaRMSNorm`, `GemmaMLP` and `GemmaRotaryEmbedding`: the same operations in the same
//! order wherever that decides the rounding (`1 + w` made once in f32; the adaptive norm's
//! `normed * (1 + scale) + shift` as a product, then a sum; the RoPE angle `f32(p) * inv_freq`
//! rounded once). Only sums are ordered differently (the kernels' fixed order).

use crate::EngineError;
use crate::kernels::gemm::gemm_par;
use crate::kernels::{Isa, MatMut, MatRef, PackedMatrix, Pool, Precision, vecmath};
use crate::pi::config::GemmaDims;
use crate::pi::vars::Vars;
use crate::smolvla::linear::{Linear, LinearWeights};

/// Gemma's RMSNorm: plain, `x / rms(x) * (1 + w)`; or adaptive (π0.5's expert),
/// `x / rms(x) * (1 + scale) + shift` with `[scale | shift | gate] = dense(cond)`.
pub(crate) enum GemmaNormWeights {
    /// `1 + weight`, rounded in f32 once.
    Plain(Vec<f32>),
    /// `dense`: `[3 width][width]` with bias, packed; `ones`: the plain norm without a scale.
    Adaptive { dense: Linear, ones: Vec<f32> },
}

/// What an adaptive norm's condition gives for one step: `1 + scale`, `shift` and the residual
/// `gate`, `[width]` each (the condition is the time's, the same for every token of a step).
pub(crate) struct Modulation {
    pub(crate) scale_plus_one: Vec<f32>,
    pub(crate) shift: Vec<f32>,
    pub(crate) gate: Vec<f32>,
}

impl GemmaNormWeights {
    /// `vars.weight` `[width]`, or, when `adaptive`, `vars.dense.{weight,bias}`.
    pub(crate) fn load(
        vars: &Vars<'_>,
        width: usize,
        adaptive: bool,
        precision: Precision,
    ) -> Result<Self, EngineError> {
        Ok(if adaptive {
            GemmaNormWeights::Adaptive {
                dense: vars
                    .pp("dense")
                    .linear_weights(3 * width, width, true)?
                    .into_linear(precision),
                ones: vec![1.0; width],
            }
        } else {
            let w = vars.values(&[width], "weight")?;
            GemmaNormWeights::Plain(w.into_iter().map(|w| 1.0 + w).collect())
        })
    }

    /// The modulation of an adaptive norm for the condition `cond` `[width]`; `None` for a
    /// plain norm.
    pub(crate) fn modulation(&self, pool: &Pool, cond: &[f32]) -> Option<Modulation> {
        let GemmaNormWeights::Adaptive { dense, ones } = self else {
            return None;
        };
        let w = ones.len();
        let mut m = vec![0.0f32; 3 * w];
        let (a, c) = (MatRef::dense(cond, 1, w), MatMut::dense(&mut m, 1, 3 * w));
        gemm_par(pool, a, &dense.w, c, dense.init());
        Some(Modulation {
            scale_plus_one: m[..w].iter().map(|s| s + 1.0).collect(),
            shift: m[w..2 * w].to_vec(),
            gate: m[2 * w..].to_vec(),
        })
    }

    /// Normalise one row `x` into `out` (with `modulation` for an adaptive norm; a plain norm
    /// ignores it).
    #[inline]
    pub(crate) fn row(
        &self,
        isa: Isa,
        x: &[f32],
        eps: f32,
        modulation: Option<&Modulation>,
        out: &mut [f32],
    ) {
        match (self, modulation) {
            (GemmaNormWeights::Plain(one_plus_w), _) => {
                vecmath::rms_norm(isa, x, one_plus_w, eps, out);
            }
            (GemmaNormWeights::Adaptive { ones, .. }, m) => {
                vecmath::rms_norm(isa, x, ones, eps, out);
                if let Some(m) = m {
                    for ((o, &s), &b) in out.iter_mut().zip(&m.scale_plus_one).zip(&m.shift) {
                        *o = *o * s + b;
                    }
                }
            }
        }
    }
}

/// One Gemma decoder layer, packed: `[q | k | v]` and `[gate | up]` each one GEMM.
pub(crate) struct GemmaLayerWeights {
    pub(crate) input_norm: GemmaNormWeights,
    pub(crate) qkv: PackedMatrix,
    pub(crate) o: PackedMatrix,
    pub(crate) post_norm: GemmaNormWeights,
    pub(crate) gate_up: PackedMatrix,
    pub(crate) down: PackedMatrix,
}

impl GemmaLayerWeights {
    /// The layer at `vars` (`...layers.{i}`), packed in `precision` straight from the stored
    /// tensors (no f32 copy of a bf16 weight); `adaptive` for π0.5's expert norms.
    pub(crate) fn load(
        vars: &Vars<'_>,
        d: &GemmaDims,
        adaptive: bool,
        precision: Precision,
    ) -> Result<Self, EngineError> {
        let attn = vars.pp("self_attn");
        let mlp = vars.pp("mlp");
        let (w, qw, kvw) = (d.width, d.q_width(), d.kv_width());
        let q = attn.pp("q_proj").linear_weights(qw, w, false)?;
        let k = attn.pp("k_proj").linear_weights(kvw, w, false)?;
        let v = attn.pp("v_proj").linear_weights(kvw, w, false)?;
        let qkv = LinearWeights::pack_stacked(precision, &[&q, &k, &v]);
        drop((q, k, v));
        let o = attn.pp("o_proj").linear_weights(w, qw, false)?;
        let gate = mlp.pp("gate_proj").linear_weights(d.mlp, w, false)?;
        let up = mlp.pp("up_proj").linear_weights(d.mlp, w, false)?;
        let gate_up = LinearWeights::pack_stacked(precision, &[&gate, &up]);
        drop((gate, up));
        Ok(GemmaLayerWeights {
            input_norm: GemmaNormWeights::load(
                &vars.pp("input_layernorm"),
                w,
                adaptive,
                precision,
            )?,
            qkv,
            o: o.into_linear(precision).w,
            post_norm: GemmaNormWeights::load(
                &vars.pp("post_attention_layernorm"),
                w,
                adaptive,
                precision,
            )?,
            gate_up,
            down: mlp
                .pp("down_proj")
                .linear_weights(w, d.mlp, false)?
                .into_linear(precision)
                .w,
        })
    }
}

/// GeGLU's activation of one row: `out = gelu_tanh(gate) * up`.
#[inline]
pub(crate) fn geglu_row(isa: Isa, gate: &[f32], up: &[f32], out: &mut [f32]) {
    vecmath::gelu_tanh(isa, gate, out);
    for (o, &u) in out.iter_mut().zip(up) {
        *o *= u;
    }
}

/// Gemma's RoPE tables (`cos`, `sin`, `[positions][head_dim / 2]` each) for `positions`, as
/// [`crate::pi::layers::Rope::new`] makes them.
pub(crate) fn rope_tables(
    positions: impl IntoIterator<Item = usize>,
    hd: usize,
    theta: f64,
) -> (Vec<f32>, Vec<f32>) {
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
    (cos, sin)
}
