//! The expert in plain Candle tensor ops, for any Candle device (CUDA with `--features cuda`).
//!
//! This is a direct transcription of LeRobot's modules: prefixes are padded to the longest in
//! the batch and hidden by an additive `-inf` mask built with LeRobot's rules, GQA expands the
//! KV heads, and every op runs in f32. On the CPU it is the reference the fast path is tested
//! against (besides the LeRobot golden files).

use candle_core::{DType, Device, Tensor};

use super::weights::{ExpertWeights, time_embedding};
use crate::EngineError;
use crate::guidance::RowGuide;
use crate::sampler::ClosureField;
use crate::smolvla::config::{ExpertDims, LayerKind};
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::prefix::PrefixKv;

struct Linear {
    /// `[in][out]` (transposed once at load so the matmul needs no strided view).
    w_t: Tensor,
    bias: Option<Tensor>,
}

impl Linear {
    fn new(l: &LinearWeights, dev: &Device) -> Result<Self, EngineError> {
        let w = Tensor::from_slice(&l.weight, (l.out_dim, l.in_dim), dev)?;
        let bias = l
            .bias
            .as_ref()
            .map(|b| Tensor::from_slice(b, l.out_dim, dev))
            .transpose()?;
        Ok(Linear {
            w_t: w.t()?.contiguous()?,
            bias,
        })
    }

    /// `x wᵀ + b` for `x` of shape `[.., in]`.
    fn forward(&self, x: &Tensor) -> Result<Tensor, EngineError> {
        let y = x.broadcast_matmul(&self.w_t)?;
        Ok(match &self.bias {
            Some(b) => y.broadcast_add(b)?,
            None => y,
        })
    }
}

struct Layer {
    kind: LayerKind,
    input_norm: Tensor,
    post_norm: Tensor,
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    gate: Linear,
    up: Linear,
    down: Linear,
}

/// The expert's weights on a Candle device.
pub(crate) struct CandleExpert {
    dims: ExpertDims,
    device: Device,
    layers: Vec<Layer>,
    final_norm: Tensor,
    action_in: Linear,
    time_in: Linear,
    time_out: Linear,
    out: Linear,
    state: Linear,
}

impl CandleExpert {
    pub(crate) fn new(w: &ExpertWeights, device: &Device) -> Result<Self, EngineError> {
        let h = w.dims.hidden;
        let layers = w
            .layers
            .iter()
            .map(|l| {
                Ok(Layer {
                    kind: l.kind,
                    input_norm: Tensor::from_slice(&l.input_norm, h, device)?,
                    post_norm: Tensor::from_slice(&l.post_norm, h, device)?,
                    q: Linear::new(&l.q_proj, device)?,
                    k: Linear::new(&l.k_proj, device)?,
                    v: Linear::new(&l.v_proj, device)?,
                    o: Linear::new(&l.o_proj, device)?,
                    gate: Linear::new(&l.gate_proj, device)?,
                    up: Linear::new(&l.up_proj, device)?,
                    down: Linear::new(&l.down_proj, device)?,
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(CandleExpert {
            dims: w.dims.clone(),
            device: device.clone(),
            layers,
            final_norm: Tensor::from_slice(&w.final_norm, h, device)?,
            action_in: Linear::new(&w.action_in_proj, device)?,
            time_in: Linear::new(&w.action_time_mlp_in, device)?,
            time_out: Linear::new(&w.action_time_mlp_out, device)?,
            out: Linear::new(&w.action_out_proj, device)?,
            state: Linear::new(&w.state_proj, device)?,
        })
    }

    pub(crate) fn embed_state(&self, states: &[f32], rows: usize) -> Result<Vec<f32>, EngineError> {
        let s = Tensor::from_slice(states, (rows, self.dims.state_pad), &self.device)?;
        Ok(self.state.forward(&s)?.flatten_all()?.to_vec1()?)
    }

    /// Same contract as the CPU expert's `sample`.
    pub(crate) fn sample(
        &self,
        prefixes: &[&PrefixKv],
        row_prefix: &[usize],
        x: &mut [f32],
        velocities: &mut [f32],
        updates: &mut [f32],
        guides: &[Option<RowGuide>],
    ) -> Result<(), EngineError> {
        let d = &self.dims;
        let dev = &self.device;
        let (rows, n) = (row_prefix.len(), d.chunk);
        let context = self.attention_context(prefixes, row_prefix)?;
        let len = n * d.action_pad;
        let steps = d.steps;
        // An `rtc_vjp` row is refused by the field's default `velocity_vjp`: candle_nn's fused
        // softmax, RMSNorm and RoPE ops, which this expert runs, have no backward pass.
        let mut field = ClosureField(|_k: usize, t: f32, xt: &[f32], v: &mut [f32]| {
            let xt = Tensor::from_slice(xt, (rows, n, d.action_pad), dev)?;
            let out = self.velocity(&xt, t, &context)?;
            v.copy_from_slice(&out.flatten_all()?.to_vec1::<f32>()?);
            Ok(())
        });
        crate::sampler::integrate_guided(
            crate::sampler::Schedule { steps },
            rows,
            len,
            x,
            updates,
            guides,
            Some(velocities),
            &mut field,
        )
    }

    /// The prefix keys and values, masks and RoPE tables that every step of a `sample` call
    /// attends with (row `r` is a sample of the request `row_prefix[r]`).
    fn attention_context(
        &self,
        prefixes: &[&PrefixKv],
        row_prefix: &[usize],
    ) -> Result<AttentionContext, EngineError> {
        let d = &self.dims;
        let dev = &self.device;
        let (rows, hd, n) = (row_prefix.len(), d.head_dim, d.chunk);
        let max_len = prefixes.iter().map(|p| p.len()).max().unwrap_or(0);
        // Masks (additive, [rows, 1, chunk, keys]) with LeRobot's rules: action tokens see every
        // valid prefix token, and each other causally (cumsum of all-ones att_masks).
        let mut cross_mask = vec![f32::NEG_INFINITY; rows * n * max_len];
        let mut self_mask = vec![f32::NEG_INFINITY; rows * n * (max_len + n)];
        let mut positions = vec![0.0f32; rows * n];
        for (r, &p) in row_prefix.iter().enumerate() {
            let prefix = prefixes[p];
            for i in 0..n {
                for (j, &valid) in prefix.valid().iter().enumerate() {
                    if valid {
                        cross_mask[(r * n + i) * max_len + j] = 0.0;
                        self_mask[(r * n + i) * (max_len + n) + j] = 0.0;
                    }
                }
                for j in 0..=i {
                    self_mask[(r * n + i) * (max_len + n) + max_len + j] = 0.0;
                }
                positions[r * n + i] = (prefix.valid_len() + i) as f32;
            }
        }
        let cross_positions: Vec<f32> = (0..rows).flat_map(|_| (0..n).map(|i| i as f32)).collect();
        Ok(AttentionContext {
            prefix_kv: self.padded_prefix_kv(prefixes, row_prefix, max_len)?,
            self_mask: Tensor::from_vec(self_mask, (rows, 1, n, max_len + n), dev)?,
            cross_mask: Tensor::from_vec(cross_mask, (rows, 1, n, max_len), dev)?,
            self_rope: rope_tables(&positions, rows, n, hd, dev)?,
            cross_rope: rope_tables(&cross_positions, rows, n, hd, dev)?,
        })
    }

    /// Prefix K/V per layer, padded to `max_len` tokens, `[rows, kv_heads, max_len, head_dim]`
    /// (row `r` from prefix `row_prefix[r]`).
    fn padded_prefix_kv(
        &self,
        prefixes: &[&PrefixKv],
        row_prefix: &[usize],
        max_len: usize,
    ) -> Result<Vec<(Tensor, Tensor)>, EngineError> {
        let d = &self.dims;
        let dev = &self.device;
        let (rows, kvh, hd) = (row_prefix.len(), d.kv_heads, d.head_dim);
        let idx: Vec<u32> = row_prefix.iter().map(|&p| p as u32).collect();
        let idx = Tensor::from_slice(&idx, rows, dev)?;
        let mut prefix_kv = Vec::with_capacity(self.layers.len());
        for (l, layer) in self.layers.iter().enumerate() {
            let pad = |get: &dyn Fn(&PrefixKv) -> &[f32]| -> Result<Tensor, EngineError> {
                let mut flat = vec![0.0f32; prefixes.len() * max_len * d.kv_width()];
                for (i, p) in prefixes.iter().enumerate() {
                    let t = get(p);
                    flat[i * max_len * d.kv_width()..i * max_len * d.kv_width() + t.len()]
                        .copy_from_slice(t);
                }
                Ok(
                    Tensor::from_vec(flat, (prefixes.len(), max_len, d.kv_width()), dev)?
                        .index_select(&idx, 0)?,
                )
            };
            let (k, v) = (pad(&|p| p.keys(l))?, pad(&|p| p.values(l))?);
            // Cross-attention layers project the cached prefix K/V with the expert's own
            // k_proj/v_proj (LeRobot does this every step; it does not depend on the step).
            let (k, v) = match layer.kind {
                LayerKind::SelfAttention => (k, v),
                LayerKind::CrossAttention => (layer.k.forward(&k)?, layer.v.forward(&v)?),
            };
            let heads = |t: Tensor| -> Result<Tensor, EngineError> {
                Ok(t.reshape((rows, max_len, kvh, hd))?
                    .transpose(1, 2)?
                    .contiguous()?)
            };
            prefix_kv.push((heads(k)?, heads(v)?));
        }
        Ok(prefix_kv)
    }

    /// The velocity of the action tokens `xt` (`[rows, chunk, action_pad]`) at time `t`.
    fn velocity(
        &self,
        xt: &Tensor,
        t: f32,
        context: &AttentionContext,
    ) -> Result<Tensor, EngineError> {
        let AttentionContext {
            prefix_kv,
            self_mask,
            cross_mask,
            self_rope,
            cross_rope,
        } = context;
        let d = &self.dims;
        let (rows, n, _) = xt.dims3()?;
        let (heads, kvh, hd) = (d.heads, d.kv_heads, d.head_dim);
        let action_emb = self.action_in.forward(xt)?;
        let temb = Tensor::from_vec(
            time_embedding(t, d.hidden, d.min_period, d.max_period),
            (1, 1, d.hidden),
            &self.device,
        )?;
        let temb = temb.broadcast_as(action_emb.shape())?;
        let h = Tensor::cat(&[&action_emb, &temb], 2)?;
        let h = candle_nn::ops::silu(&self.time_in.forward(&h)?)?;
        let mut x = self.time_out.forward(&h)?;
        let scale = (hd as f64).powf(-0.5);
        for (layer, (pk, pv)) in self.layers.iter().zip(prefix_kv) {
            let h = candle_nn::ops::rms_norm(&x, &layer.input_norm, d.rms_eps)?;
            let to_heads = |t: Tensor, nh: usize| -> Result<Tensor, EngineError> {
                Ok(t.reshape((rows, n, nh, hd))?
                    .transpose(1, 2)?
                    .contiguous()?)
            };
            let (rope, keys, values, mask) = match layer.kind {
                LayerKind::SelfAttention => {
                    let k = to_heads(layer.k.forward(&h)?, kvh)?;
                    let k = candle_nn::rotary_emb::rope(&k, &self_rope.0, &self_rope.1)?;
                    let v = to_heads(layer.v.forward(&h)?, kvh)?;
                    (
                        self_rope,
                        Tensor::cat(&[pk, &k], 2)?,
                        Tensor::cat(&[pv, &v], 2)?,
                        self_mask,
                    )
                }
                LayerKind::CrossAttention => (cross_rope, pk.clone(), pv.clone(), cross_mask),
            };
            let q = to_heads(layer.q.forward(&h)?, heads)?;
            let q = candle_nn::rotary_emb::rope(&q, &rope.0, &rope.1)?;
            let expand = |t: &Tensor| -> Result<Tensor, EngineError> {
                let (b, g, s, e) = t.dims4()?;
                Ok(t.unsqueeze(2)?
                    .broadcast_as((b, g, heads / kvh, s, e))?
                    .reshape((b, heads, s, e))?)
            };
            let (keys, values) = (expand(&keys)?, expand(&values)?);
            let scores = (q.matmul(&keys.t()?)? * scale)?.broadcast_add(mask)?;
            let probs = candle_nn::ops::softmax_last_dim(&scores)?;
            let att = probs
                .matmul(&values)?
                .transpose(1, 2)?
                .reshape((rows, n, heads * hd))?;
            x = (layer.o.forward(&att)? + &x)?;
            let h = candle_nn::ops::rms_norm(&x, &layer.post_norm, d.rms_eps)?;
            let mlp = (candle_nn::ops::silu(&layer.gate.forward(&h)?)? * layer.up.forward(&h)?)?;
            x = (layer.down.forward(&mlp)? + &x)?;
        }
        let h = candle_nn::ops::rms_norm(&x, &self.final_norm, d.rms_eps)?;
        // LeRobot upcasts the expert output to f32 before action_out_proj (a no-op in f32).
        self.out.forward(&h.to_dtype(DType::F32)?)
    }
}

/// What every step of one `sample` call attends with: per layer the prefix keys and values
/// (`[rows, kv_heads, len, head_dim]`), the additive masks and the RoPE tables of the self- and
/// cross-attention layers.
struct AttentionContext {
    prefix_kv: Vec<(Tensor, Tensor)>,
    self_mask: Tensor,
    cross_mask: Tensor,
    self_rope: (Tensor, Tensor),
    cross_rope: (Tensor, Tensor),
}

/// LeRobot's RoPE cos/sin for `[rows][n]` positions, `[rows, n, head_dim/2]`.
fn rope_tables(
    positions: &[f32],
    rows: usize,
    n: usize,
    hd: usize,
    dev: &Device,
) -> Result<(Tensor, Tensor), EngineError> {
    let half = hd / 2;
    let (mut c, mut s) = (vec![0.0f32; rows * n * half], vec![0.0f32; rows * n * half]);
    for (i, &p) in positions.iter().enumerate() {
        crate::kernels::vecmath::rope_table(
            p,
            hd,
            &mut c[i * half..(i + 1) * half],
            &mut s[i * half..(i + 1) * half],
        );
    }
    Ok((
        Tensor::from_vec(c, (rows, n, half), dev)?,
        Tensor::from_vec(s, (rows, n, half), dev)?,
    ))
}
