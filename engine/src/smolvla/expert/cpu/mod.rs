//! The expert on the CPU fast path: packed weights, one workspace for all steps, and the
//! prefix-dependent work (cross-attention K/V projections, packed prefix keys, RoPE tables)
//! done once per request instead of once per step. The attention block of a layer is in
//! `attention`.

mod attention;

use std::sync::Mutex;

use super::weights::{ExpertWeights, time_embedding};
use crate::EngineError;
use kairos_engine_types::GuidanceMode;

use crate::guidance::RowGuide;
use crate::kernels::attention::AttendScratch;
use crate::kernels::gemm::{ActivationRows, gemm, gemm_par};
use crate::kernels::{Init, MatMut, MatRef, PackedMatrix, Pool, Precision, vecmath};
use crate::sampler::ClosureField;
use crate::smolvla::config::{ExpertDims, LayerKind};
use crate::smolvla::linear::Linear;
use crate::smolvla::llama_layer::LayerWeights;
use crate::smolvla::prefix::PrefixKv;

/// One decoder layer, packed.
struct Layer {
    kind: LayerKind,
    input_norm: Vec<f32>,
    post_norm: Vec<f32>,
    /// Self-attention: `[q | k | v]` in one GEMM; cross-attention: `q` only.
    qkv: PackedMatrix,
    /// Cross-attention: the projections applied to the prefix K/V once per request.
    kv_cross: Option<(PackedMatrix, PackedMatrix)>,
    o: PackedMatrix,
    /// `[gate | up]` in one GEMM.
    gate_up: PackedMatrix,
    down: PackedMatrix,
}

impl Layer {
    /// Pack layer `l` of hidden width `h` in `precision`: q, k and v side by side in one GEMM
    /// for self-attention (q alone for cross-attention, whose k and v project the prefix once
    /// per request), gate and up side by side.
    fn pack(l: &LayerWeights, h: usize, precision: Precision) -> Layer {
        let qkv = match l.kind {
            LayerKind::SelfAttention => PackedMatrix::from_linear_weights_in(
                precision,
                &[
                    (&l.q_proj.weight, l.q_proj.out_dim),
                    (&l.k_proj.weight, l.k_proj.out_dim),
                    (&l.v_proj.weight, l.v_proj.out_dim),
                ],
                h,
            ),
            LayerKind::CrossAttention => PackedMatrix::from_linear_weight_in(
                precision,
                &l.q_proj.weight,
                l.q_proj.out_dim,
                h,
            ),
        };
        let kv_cross = (l.kind == LayerKind::CrossAttention).then(|| {
            (
                PackedMatrix::from_linear_weight_in(
                    precision,
                    &l.k_proj.weight,
                    l.k_proj.out_dim,
                    l.k_proj.in_dim,
                ),
                PackedMatrix::from_linear_weight_in(
                    precision,
                    &l.v_proj.weight,
                    l.v_proj.out_dim,
                    l.v_proj.in_dim,
                ),
            )
        });
        Layer {
            kind: l.kind,
            input_norm: l.input_norm.clone(),
            post_norm: l.post_norm.clone(),
            qkv,
            kv_cross,
            o: PackedMatrix::from_linear_weight_in(
                precision,
                &l.o_proj.weight,
                l.o_proj.out_dim,
                l.o_proj.in_dim,
            ),
            gate_up: PackedMatrix::from_linear_weights_in(
                precision,
                &[
                    (&l.gate_proj.weight, l.gate_proj.out_dim),
                    (&l.up_proj.weight, l.up_proj.out_dim),
                ],
                h,
            ),
            down: PackedMatrix::from_linear_weight_in(
                precision,
                &l.down_proj.weight,
                l.down_proj.out_dim,
                l.down_proj.in_dim,
            ),
        }
    }
}

/// The packed expert.
pub(crate) struct CpuExpert {
    dims: ExpertDims,
    layers: Vec<Layer>,
    final_norm: Vec<f32>,
    action_in: Linear,
    /// `action_time_mlp_in` split by input: the action half, and the time half plus bias (the
    /// time embedding is the same for every token of a step, so its product is computed once).
    time_in_action: PackedMatrix,
    time_in_time: Linear,
    time_out: Linear,
    out: Linear,
    state: Linear,
    /// The precision of the weight GEMMs, also that of the attention GEMMs (keys and values
    /// packed in it).
    precision: Precision,
}

/// One request's prefix, prepared for the attention kernels.
struct PreparedPrefix {
    /// Position of the first action token.
    offset: usize,
    /// Per layer, per KV head: packed `Kᵀ` and `V` of the valid prefix tokens (after the
    /// expert's projection for cross-attention layers).
    layers: Vec<Vec<(PackedMatrix, PackedMatrix)>>,
}

impl CpuExpert {
    /// Pack `w`, the weight GEMMs in `precision` (already resolved for this CPU).
    pub(crate) fn new(w: &ExpertWeights, precision: Precision) -> Self {
        let h = w.dims.hidden;
        let layers = w
            .layers
            .iter()
            .map(|l| Layer::pack(l, h, precision))
            .collect();
        let mlp_in = &w.action_time_mlp_in;
        let (mut wa, mut wt) = (Vec::with_capacity(h * h), Vec::with_capacity(h * h));
        for row in mlp_in.weight.chunks_exact(2 * h) {
            wa.extend_from_slice(&row[..h]);
            wt.extend_from_slice(&row[h..]);
        }
        CpuExpert {
            dims: w.dims.clone(),
            layers,
            final_norm: w.final_norm.clone(),
            action_in: Linear::new(&w.action_in_proj, precision),
            time_in_action: PackedMatrix::from_linear_weight_in(precision, &wa, h, h),
            time_in_time: Linear {
                w: PackedMatrix::from_linear_weight_in(precision, &wt, h, h),
                bias: mlp_in.bias.clone(),
            },
            time_out: Linear::new(&w.action_time_mlp_out, precision),
            out: Linear::new(&w.action_out_proj, precision),
            state: Linear::new(&w.state_proj, precision),
            precision,
        }
    }

    /// `state_proj` of padded states, `[rows][vlm_hidden]`.
    pub(crate) fn embed_state(&self, pool: &Pool, states: &[f32], rows: usize) -> Vec<f32> {
        let d = &self.dims;
        let mut out = vec![0.0; rows * d.vlm_hidden];
        let (a, c) = (
            MatRef::dense(states, rows, d.state_pad),
            MatMut::dense(&mut out, rows, d.vlm_hidden),
        );
        gemm_par(pool, a, &self.state.w, c, self.state.init());
        out
    }

    /// Project (cross-attention layers) and pack one request's prefix keys and values.
    fn prepare(&self, pool: &Pool, prefix: &PrefixKv) -> PreparedPrefix {
        let d = &self.dims;
        let (kvw, hd) = (d.kv_width(), d.head_dim);
        let layers = self
            .layers
            .iter()
            .enumerate()
            .map(|(l, layer)| {
                let (mut k, mut v) = prefix.compact(l, kvw);
                let tokens = k.len() / kvw;
                if let Some((wk, wv)) = &layer.kv_cross {
                    let (mut kp, mut vp) = (vec![0.0; tokens * kvw], vec![0.0; tokens * kvw]);
                    let (ka, kc) = (
                        MatRef::dense(&k, tokens, kvw),
                        MatMut::dense(&mut kp, tokens, kvw),
                    );
                    gemm_par(pool, ka, wk, kc, Init::Zero);
                    let (va, vc) = (
                        MatRef::dense(&v, tokens, kvw),
                        MatMut::dense(&mut vp, tokens, kvw),
                    );
                    gemm_par(pool, va, wv, vc, Init::Zero);
                    (k, v) = (kp, vp);
                }
                (0..d.kv_heads)
                    .map(|g| {
                        let mut kt = PackedMatrix::empty_in(self.precision);
                        kt.pack_transposed(pool.isa(), MatRef::new(&k[g * hd..], tokens, hd, kvw));
                        let mut vv = PackedMatrix::empty_in(self.precision);
                        vv.pack_rows(pool.isa(), MatRef::new(&v[g * hd..], tokens, hd, kvw));
                        (kt, vv)
                    })
                    .collect()
            })
            .collect();
        PreparedPrefix {
            offset: prefix.valid_len(),
            layers,
        }
    }

    /// Run the sampler for `rows` samples. `row_prefix[r]` is the request of row `r`; `x` holds
    /// the noise (`[rows][chunk][action_pad]`) and receives the result; `velocities` and
    /// `updates` receive `[rows][K][chunk][action_pad]`.
    // The sampler's buffers and the rows' guides, as `integrate_guided` takes them.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn sample(
        &self,
        pool: &Pool,
        prefixes: &[&PrefixKv],
        row_prefix: &[usize],
        x: &mut [f32],
        velocities: &mut [f32],
        updates: &mut [f32],
        guides: &[Option<RowGuide>],
    ) -> Result<(), EngineError> {
        // No backward pass here: an `rtc_vjp` row is refused, naming the path that serves it.
        if let Some(g) = guides
            .iter()
            .flatten()
            .find(|g| g.mode == GuidanceMode::RtcVjp)
        {
            return Err(EngineError::InvalidInput(format!(
                "guidance `{}`: the fast kernels have no backward pass through SmolVLA's \
                 expert; {}",
                g.mode.as_str(),
                crate::candle_vjp::VJP_PATH
            )));
        }
        let d = &self.dims;
        let rows = row_prefix.len();
        let prepared: Vec<PreparedPrefix> =
            prefixes.iter().map(|p| self.prepare(pool, p)).collect();
        let mut ws = Workspace::new(d, rows, pool.threads(), self.precision);
        // RoPE tables: self-attention positions continue after each prefix; cross-attention
        // positions restart at 0 (LeRobot subtracts the minimum position).
        let half = d.head_dim / 2;
        let table = |offset: usize| -> (Vec<f32>, Vec<f32>) {
            let (mut c, mut s) = (vec![0.0; d.chunk * half], vec![0.0; d.chunk * half]);
            for n in 0..d.chunk {
                let (cn, sn) = (
                    &mut c[n * half..(n + 1) * half],
                    &mut s[n * half..(n + 1) * half],
                );
                vecmath::rope_table((offset + n) as f32, d.head_dim, cn, sn);
            }
            (c, s)
        };
        let self_rope: Vec<(Vec<f32>, Vec<f32>)> =
            prepared.iter().map(|p| table(p.offset)).collect();
        let cross_rope = table(0);
        let ctx = StepContext {
            prepared: &prepared,
            row_prefix,
            self_rope: &self_rope,
            cross_rope: &cross_rope,
        };
        let len = d.chunk * d.action_pad;
        let steps = d.steps;
        let schedule = crate::sampler::Schedule { steps };
        let mut field = ClosureField(|_k: usize, t: f32, xt: &[f32], v: &mut [f32]| {
            self.velocity(pool, &ctx, &mut ws, t, xt, v);
            Ok(())
        });
        crate::sampler::integrate_guided(
            schedule,
            rows,
            len,
            x,
            updates,
            guides,
            Some(velocities),
            &mut field,
        )
    }

    /// One evaluation of the velocity field for all rows at time `t`.
    fn velocity(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        t: f32,
        xt: &[f32],
        v: &mut [f32],
    ) {
        let d = &self.dims;
        let (h, tokens) = (d.hidden, ws.tokens);
        let isa = pool.isa();
        self.embed_suffix(pool, ws, t, xt);

        let eps = d.rms_eps;
        for (l, layer) in self.layers.iter().enumerate() {
            self.attention_block(pool, ctx, ws, l, layer);
            let (x, i) = (&ws.x, d.intermediate);
            ws.normed.fill(pool, tokens, |r, out| {
                vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &layer.post_norm, eps, out);
            });
            let gate_up = MatMut::dense(&mut ws.gate_up, tokens, 2 * i);
            ws.normed
                .gemm_par(pool, &layer.gate_up, gate_up, Init::Zero);
            let gate_up = &ws.gate_up;
            ws.act.fill(pool, tokens, |r, out| {
                let (g, u) = gate_up[r * 2 * i..(r + 1) * 2 * i].split_at(i);
                vecmath::silu_mul(isa, g, u, out);
            });
            let x = MatMut::dense(&mut ws.x, tokens, h);
            ws.act.gemm_par(pool, &layer.down, x, Init::Accumulate);
        }
        let x = &ws.x;
        ws.normed.fill(pool, tokens, |r, out| {
            vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &self.final_norm, eps, out);
        });
        let v = MatMut::dense(v, tokens, d.action_pad);
        ws.normed.gemm_par(pool, &self.out.w, v, self.out.init());
    }

    /// The action tokens' embedding, into `ws.x`:
    /// `action_time_mlp_out(silu(action_time_mlp_in([action_in_proj(x_t) ; time_emb(t)])))`,
    /// the time half of `action_time_mlp_in` computed once for all tokens.
    fn embed_suffix(&self, pool: &Pool, ws: &mut Workspace, t: f32, xt: &[f32]) {
        let d = &self.dims;
        let (h, tokens, isa) = (d.hidden, ws.tokens, pool.isa());
        let xt = MatRef::dense(xt, tokens, d.action_pad);
        let actions = MatMut::dense(&mut ws.h, tokens, h);
        gemm_par(pool, xt, &self.action_in.w, actions, self.action_in.init());
        let temb = time_embedding(t, h, d.min_period, d.max_period);
        let (temb, time_bias) = (
            MatRef::dense(&temb, 1, h),
            MatMut::dense(&mut ws.time_bias, 1, h),
        );
        gemm(
            isa,
            temb,
            &self.time_in_time.w,
            time_bias,
            self.time_in_time.init(),
        );
        let (actions, x) = (
            MatRef::dense(&ws.h, tokens, h),
            MatMut::dense(&mut ws.x, tokens, h),
        );
        gemm_par(
            pool,
            actions,
            &self.time_in_action,
            x,
            Init::Bias(&ws.time_bias),
        );
        vecmath::silu_inplace(isa, &mut ws.x);
        std::mem::swap(&mut ws.x, &mut ws.h);
        let (hidden, x) = (
            MatRef::dense(&ws.h, tokens, h),
            MatMut::dense(&mut ws.x, tokens, h),
        );
        gemm_par(pool, hidden, &self.time_out.w, x, self.time_out.init());
    }
}

/// What every step of one `sample` call shares.
struct StepContext<'a> {
    prepared: &'a [PreparedPrefix],
    row_prefix: &'a [usize],
    self_rope: &'a [(Vec<f32>, Vec<f32>)],
    cross_rope: &'a (Vec<f32>, Vec<f32>),
}

/// Buffers reused by every layer of every step.
struct Workspace {
    tokens: usize,
    x: Vec<f32>,
    h: Vec<f32>,
    time_bias: Vec<f32>,
    qkv: Vec<f32>,
    q_heads: Vec<f32>,
    attn: Vec<f32>,
    gate_up: Vec<f32>,
    /// The RMS-normed rows that feed the q/k/v, gate/up and output GEMMs.
    normed: ActivationRows,
    /// `silu(gate) * up`, which feeds the down projection.
    act: ActivationRows,
    suffix_kv: Vec<(PackedMatrix, PackedMatrix)>,
    /// Per attention part: scores and the output block.
    scores: Vec<Mutex<(AttendScratch, Vec<f32>)>>,
}

impl Workspace {
    fn new(d: &ExpertDims, rows: usize, threads: usize, precision: Precision) -> Self {
        let tokens = rows * d.chunk;
        Workspace {
            tokens,
            x: vec![0.0; tokens * d.hidden],
            h: vec![0.0; tokens * d.hidden],
            time_bias: vec![0.0; d.hidden],
            qkv: vec![0.0; tokens * (d.q_width() + 2 * d.kv_width())],
            q_heads: vec![0.0; tokens * d.q_width()],
            attn: vec![0.0; tokens * d.q_width()],
            gate_up: vec![0.0; tokens * 2 * d.intermediate],
            normed: ActivationRows::new(precision, tokens, d.hidden),
            act: ActivationRows::new(precision, tokens, d.intermediate),
            suffix_kv: (0..rows * d.kv_heads)
                .map(|_| {
                    (
                        PackedMatrix::empty_in(precision),
                        PackedMatrix::empty_in(precision),
                    )
                })
                .collect(),
            scores: (0..4 * threads.max(1))
                .map(|_| Mutex::new((AttendScratch::default(), Vec::new())))
                .collect(),
        }
    }
}
