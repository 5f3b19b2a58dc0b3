//! The expert in plain Candle tensor ops, for any Candle device (CUDA with `--features cuda`),
//! built from the shared Candle layers ([`crate::pi::layers`]).
//!
//! This is a direct transcription of LeRobot's modules: prefixes are padded to the longest in
//! the batch and hidden by an additive `-inf` mask built with LeRobot's rules, and attention is
//! grouped-query over the KV heads. The weight products run in the precision's dtype (f32, or
//! bf16 with f32 norms, softmax and residuals). On the CPU in f32 it is the reference the fast
//! path is tested against (besides the LeRobot golden files).
//!
//! Per `sample` call the prefix keys and values (projected once for the cross-attention
//! layers), the masks, the RoPE tables and the time embeddings go to the device once and serve
//! all Euler steps, and the Euler loop itself runs on the device.

use candle_core::{DType, Device, Tensor};

use super::weights::{ExpertWeights, time_embedding};
use crate::EngineError;
use crate::candle_ops;
use crate::candle_vjp::{self, VjpRows};
use crate::guidance::RowGuide;
use crate::kernels::Precision;
use crate::pi::layers::{Linear, RmsNorm, SwiGlu, batched_attention};
use crate::sampler::VelocityField;
use crate::smolvla::candle_weights::{linear, matmul_dtype, vector};
use crate::smolvla::config::{ExpertDims, LayerKind};
use crate::smolvla::prefix::PrefixKv;

struct Layer {
    kind: LayerKind,
    input_norm: RmsNorm,
    post_norm: RmsNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    mlp: SwiGlu,
}

/// The expert's weights on a Candle device.
pub(crate) struct CandleExpert {
    dims: ExpertDims,
    device: Device,
    layers: Vec<Layer>,
    final_norm: RmsNorm,
    action_in: Linear,
    time_in: Linear,
    time_out: Linear,
    out: Linear,
    state: Linear,
    /// The Euler loop's CUDA graphs, when [`crate::EngineOptions::cuda_graphs`] asks for them.
    graphs: Option<Graphs>,
}

#[cfg(feature = "cuda")]
type Graphs = super::cuda_graph::EulerGraphs;
/// Without CUDA there are no graphs: the option is refused at load (CPU) or CUDA is (no feature).
#[cfg(not(feature = "cuda"))]
type Graphs = std::convert::Infallible;

impl CandleExpert {
    /// The expert's weights on `device`; with `cuda_graphs`, its Euler loop replays CUDA graphs
    /// (`device` must then be a CUDA device).
    pub(crate) fn new(
        w: &ExpertWeights,
        device: &Device,
        precision: Precision,
        cuda_graphs: bool,
    ) -> Result<Self, EngineError> {
        // Before any tensor is made: the graphs change how the device tracks its buffers.
        let graphs = cuda_graphs.then(|| euler_graphs(device)).transpose()?;
        let dtype = matmul_dtype(precision);
        let eps = f64::from(w.dims.rms_eps);
        let layers = w
            .layers
            .iter()
            .map(|l| {
                Ok(Layer {
                    kind: l.kind,
                    input_norm: RmsNorm::from_parts(vector(&l.input_norm, device)?, eps),
                    post_norm: RmsNorm::from_parts(vector(&l.post_norm, device)?, eps),
                    q: linear(&l.q_proj, dtype, device)?,
                    k: linear(&l.k_proj, dtype, device)?,
                    v: linear(&l.v_proj, dtype, device)?,
                    o: linear(&l.o_proj, dtype, device)?,
                    mlp: SwiGlu::from_parts(
                        linear(&l.gate_proj, dtype, device)?,
                        linear(&l.up_proj, dtype, device)?,
                        linear(&l.down_proj, dtype, device)?,
                    ),
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(CandleExpert {
            dims: w.dims.clone(),
            device: device.clone(),
            layers,
            final_norm: RmsNorm::from_parts(vector(&w.final_norm, device)?, eps),
            action_in: linear(&w.action_in_proj, dtype, device)?,
            time_in: linear(&w.action_time_mlp_in, dtype, device)?,
            time_out: linear(&w.action_time_mlp_out, dtype, device)?,
            // LeRobot upcasts the expert's output to f32 before `action_out_proj`, and the
            // state token is the VLM's input: both stay f32.
            out: linear(&w.action_out_proj, DType::F32, device)?,
            state: linear(&w.state_proj, DType::F32, device)?,
            graphs,
        })
    }

    /// What the Euler loop's CUDA graphs have done (`None` without graphs).
    pub(crate) fn graph_stats(&self) -> Option<super::CudaGraphStats> {
        match &self.graphs {
            #[cfg(feature = "cuda")]
            Some(graphs) => Some(graphs.stats()),
            _ => None,
        }
    }

    pub(crate) fn embed_state(&self, states: &[f32], rows: usize) -> Result<Vec<f32>, EngineError> {
        let s = Tensor::from_slice(states, (rows, self.dims.state_pad), &self.device)?;
        Ok(self.state.forward(&s)?.flatten_all()?.to_vec1()?)
    }

    /// Same contract as the CPU expert's `sample`. The Euler loop stays on the device: `x_t`,
    /// the velocities and the updates never leave it between steps (the same f32 operations
    /// as `sampler::integrate`, `u = dt v`, `x += u`), and come back to the host in one copy
    /// each at the end.
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
        let schedule = crate::sampler::Schedule { steps: d.steps };
        let steps = schedule.steps;
        // Every step's time embedding, uploaded once.
        let temb: Vec<f32> = (0..steps)
            .flat_map(|k| time_embedding(schedule.time(k), d.hidden, d.min_period, d.max_period))
            .collect();
        let temb = Tensor::from_vec(temb, (steps, 1, 1, d.hidden), dev)?;
        if guides.iter().any(Option::is_some) {
            // Guidance reads and changes each row's velocity and sample between steps, on the
            // host, in the shared sampler (the same operations as the loop below, so a row
            // without guidance gets the same bits here as in a batch without any).
            let mut field = GuidedField::new(self, &context, &temb, guides)?;
            return crate::sampler::integrate_guided(
                schedule,
                rows,
                len,
                x,
                updates,
                guides,
                Some(velocities),
                &mut field,
            );
        }
        let xt = Tensor::from_slice(x, (rows, n, d.action_pad), dev)?;
        let dt = f64::from(schedule.dt());
        let run = |x0: &Tensor, temb: &Tensor, context: &AttentionContext| {
            self.euler(x0, temb, context, steps, dt)
        };
        let host = match &self.graphs {
            #[cfg(feature = "cuda")]
            Some(graphs) => graphs.sample(&xt, &temb, &context, &run)?,
            _ => run(&xt, &temb, &context)?.to_host()?,
        };
        x.copy_from_slice(&host.x);
        // `[steps][rows][len]` on the device -> `[rows][steps][len]` on the host.
        for (all, out) in [(host.velocities, velocities), (host.updates, updates)] {
            for k in 0..steps {
                for r in 0..rows {
                    out[(r * steps + k) * len..][..len]
                        .copy_from_slice(&all[(k * rows + r) * len..][..len]);
                }
            }
        }
        Ok(())
    }

    /// The Euler loop on the device from `x0` (`[rows, chunk, action_pad]`): the same f32
    /// operations as `sampler::integrate` (`u = dt v`, `x += u`), nothing copied to or from the
    /// host (so a CUDA graph can capture it).
    fn euler(
        &self,
        x0: &Tensor,
        temb: &Tensor,
        context: &AttentionContext,
        steps: usize,
        dt: f64,
    ) -> Result<DeviceLoop, EngineError> {
        let mut xt = x0.clone();
        let (mut vs, mut us) = (Vec::with_capacity(steps), Vec::with_capacity(steps));
        for k in 0..steps {
            let v = self.velocity(&xt, &temb.get(k)?, context)?;
            let u = (&v * dt)?;
            xt = (&xt + &u)?;
            vs.push(v);
            us.push(u);
        }
        Ok(DeviceLoop {
            x: xt,
            velocities: Tensor::stack(&vs, 0)?,
            updates: Tensor::stack(&us, 0)?,
        })
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

    /// The velocity of the action tokens `xt` (`[rows, chunk, action_pad]`) at the time whose
    /// embedding is `temb` (`[1, 1, hidden]`).
    fn velocity(
        &self,
        xt: &Tensor,
        temb: &Tensor,
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
        let temb = temb.broadcast_as(action_emb.shape())?;
        let h = Tensor::cat(&[&action_emb, &temb], 2)?;
        let h = candle_ops::silu(&self.time_in.forward(&h)?)?;
        let mut x = self.time_out.forward(&h)?;
        let scale = (hd as f64).powf(-0.5);
        for (layer, (pk, pv)) in self.layers.iter().zip(prefix_kv) {
            let h = layer.input_norm.forward(&x)?;
            let to_heads = |t: Tensor, nh: usize| -> Result<Tensor, EngineError> {
                Ok(t.reshape((rows, n, nh, hd))?
                    .transpose(1, 2)?
                    .contiguous()?)
            };
            let (rope, keys, values, mask) = match layer.kind {
                LayerKind::SelfAttention => {
                    let k = to_heads(layer.k.forward(&h)?, kvh)?;
                    let k = candle_ops::rope(&k, &self_rope.0, &self_rope.1)?;
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
            let q = candle_ops::rope(&q, &rope.0, &rope.1)?;
            let att = batched_attention(&q, &keys, &values, scale, Some(mask))?;
            x = (layer.o.forward(&att)? + &x)?;
            x = (layer.mlp.forward(&layer.post_norm.forward(&x)?)? + &x)?;
        }
        let h = self.final_norm.forward(&x)?;
        self.out.forward(&h)
    }
}

/// The expert's velocity field over the rows of one guided `sample` call, with the
/// vector–Jacobian product `rtc_vjp` needs ([`candle_vjp`]: the `rtc_vjp` rows run their own
/// tracked forward pass and one backward pass; the other rows keep their bits).
struct GuidedField<'a> {
    expert: &'a CandleExpert,
    temb: &'a Tensor,
    /// The context of every row.
    all: &'a AttentionContext,
    /// The rows guided with `rtc_vjp`, and the others, each with its rows' context (`None`
    /// when no row needs the backward pass).
    split: Option<RowSplit>,
}

/// The rows of a batch split by whether they need the backward pass, with their contexts.
struct RowSplit {
    rows: VjpRows,
    vjp_context: AttentionContext,
    plain_context: Option<AttentionContext>,
}

impl<'a> GuidedField<'a> {
    fn new(
        expert: &'a CandleExpert,
        all: &'a AttentionContext,
        temb: &'a Tensor,
        guides: &[Option<RowGuide>],
    ) -> Result<Self, EngineError> {
        let split = VjpRows::new(guides)
            .map(|rows| -> Result<RowSplit, EngineError> {
                Ok(RowSplit {
                    vjp_context: all.select(rows.vjp(), &expert.device)?,
                    plain_context: (!rows.plain().is_empty())
                        .then(|| all.select(rows.plain(), &expert.device))
                        .transpose()?,
                    rows,
                })
            })
            .transpose()?;
        Ok(GuidedField {
            expert,
            temb,
            all,
            split,
        })
    }
}

impl VelocityField for GuidedField<'_> {
    fn velocity(&mut self, k: usize, _t: f32, x: &[f32], v: &mut [f32]) -> Result<(), EngineError> {
        let d = &self.expert.dims;
        let rows = x.len() / (d.chunk * d.action_pad);
        let xt = Tensor::from_slice(x, (rows, d.chunk, d.action_pad), &self.expert.device)?;
        let out = self.expert.velocity(&xt, &self.temb.get(k)?, self.all)?;
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
        let Some(split) = &self.split else {
            // No row needs the backward pass: the pullback is zero.
            pullback.fill(0.0);
            return self.velocity(k, t, x, v);
        };
        let expert = self.expert;
        let temb = self.temb.get(k)?;
        candle_vjp::velocity_vjp(
            &split.rows,
            (expert.dims.chunk, expert.dims.action_pad),
            &expert.device,
            x,
            v,
            cotangent,
            pullback,
            split
                .plain_context
                .as_ref()
                .map(|context| |xt: &Tensor| expert.velocity(xt, &temb, context)),
            |xt: &Tensor| expert.velocity(xt, &temb, &split.vjp_context),
        )
    }
}

/// The CUDA graphs of an expert on `device`.
#[cfg(feature = "cuda")]
fn euler_graphs(device: &Device) -> Result<Graphs, EngineError> {
    match device {
        Device::Cuda(cuda) => {
            // SAFETY: cudarc records an event at each use of a buffer only to order its uses
            // across streams, and every buffer of this device is used on Candle's one stream for
            // it (no other stream is made on its context). Without the tracking a buffer costs
            // no event creation, and nothing in the captured loop records or waits on an event
            // made outside the capture.
            unsafe { cuda.disable_event_tracking() };
            Ok(super::cuda_graph::EulerGraphs::new(cuda.clone()))
        }
        _ => Err(crate::options::cuda_graphs_need_cuda()),
    }
}

#[cfg(not(feature = "cuda"))]
fn euler_graphs(_device: &Device) -> Result<Graphs, EngineError> {
    Err(crate::options::cuda_graphs_need_cuda())
}

/// The result of the Euler loop on the device: the final sample `[rows, chunk, action_pad]`,
/// and every step's velocity and update, `[steps, rows, chunk, action_pad]`.
pub(super) struct DeviceLoop {
    pub(super) x: Tensor,
    pub(super) velocities: Tensor,
    pub(super) updates: Tensor,
}

/// A [`DeviceLoop`] copied to the host, flat in the same layouts.
pub(super) struct HostLoop {
    pub(super) x: Vec<f32>,
    pub(super) velocities: Vec<f32>,
    pub(super) updates: Vec<f32>,
}

impl DeviceLoop {
    /// One copy to the host each.
    pub(super) fn to_host(&self) -> Result<HostLoop, EngineError> {
        let host = |t: &Tensor| t.flatten_all()?.to_vec1::<f32>();
        Ok(HostLoop {
            x: host(&self.x)?,
            velocities: host(&self.velocities)?,
            updates: host(&self.updates)?,
        })
    }
}

/// What every step of one `sample` call attends with: per layer the prefix keys and values
/// (`[rows, kv_heads, len, head_dim]`), the additive masks and the RoPE tables of the self- and
/// cross-attention layers.
#[derive(Clone)]
pub(super) struct AttentionContext {
    prefix_kv: Vec<(Tensor, Tensor)>,
    self_mask: Tensor,
    /// `[rows, 1, chunk, prefix_len]`.
    pub(super) cross_mask: Tensor,
    self_rope: (Tensor, Tensor),
    cross_rope: (Tensor, Tensor),
}

impl AttentionContext {
    /// Every tensor, in a fixed order.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    pub(super) fn tensors(&self) -> Vec<&Tensor> {
        let mut all: Vec<&Tensor> = self.prefix_kv.iter().flat_map(|(k, v)| [k, v]).collect();
        all.extend([
            &self.self_mask,
            &self.cross_mask,
            &self.self_rope.0,
            &self.self_rope.1,
            &self.cross_rope.0,
            &self.cross_rope.1,
        ]);
        all
    }

    /// The context of rows `rows` only, in that order.
    fn select(&self, rows: &[usize], device: &Device) -> Result<AttentionContext, EngineError> {
        let idx: Vec<u32> = rows.iter().map(|&r| r as u32).collect();
        let idx = Tensor::from_vec(idx, rows.len(), device)?;
        let pick = |t: &Tensor| t.index_select(&idx, 0);
        Ok(AttentionContext {
            prefix_kv: self
                .prefix_kv
                .iter()
                .map(|(k, v)| Ok((pick(k)?, pick(v)?)))
                .collect::<Result<_, candle_core::Error>>()?,
            self_mask: pick(&self.self_mask)?,
            cross_mask: pick(&self.cross_mask)?,
            self_rope: (pick(&self.self_rope.0)?, pick(&self.self_rope.1)?),
            cross_rope: (pick(&self.cross_rope.0)?, pick(&self.cross_rope.1)?),
        })
    }
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
