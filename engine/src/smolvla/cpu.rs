//! The expert on the CPU fast path: packed weights, one workspace for all steps, and the
//! prefix-dependent work (cross-attention K/V projections, packed prefix keys, RoPE tables)
//! done once per request instead of once per step.

use std::sync::Mutex;

use super::config::{ExpertDims, LayerKind};
use super::prefix::PrefixKv;
use super::weights::{ExpertWeights, LinearWeights, time_embedding};
use crate::EngineError;
use crate::kernels::attention::{AttendScratch, KvSegment, Queries, QueryPositions, attend};
use crate::kernels::gemm::{ActivationRows, gemm, gemm_par};
use crate::kernels::{Init, MatMut, MatRef, PackedMatrix, Pool, Precision, SharedMut, vecmath};

/// A `Linear` layer packed for the GEMM, with its bias.
pub(crate) struct Linear {
    pub(crate) w: PackedMatrix,
    pub(crate) bias: Option<Vec<f32>>,
}

impl Linear {
    pub(crate) fn new(l: &LinearWeights, precision: Precision) -> Self {
        Linear {
            w: PackedMatrix::from_linear_weight_in(precision, &l.weight, l.out_dim, l.in_dim),
            bias: l.bias.clone(),
        }
    }

    pub(crate) fn init(&self) -> Init<'_> {
        self.bias.as_deref().map_or(Init::Zero, Init::Bias)
    }
}

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
            .map(|l| {
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
            })
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
        let mut out = vec![0.0; rows * self.dims.vlm_hidden];
        gemm_par(
            pool,
            MatRef::new(states, rows, self.state.w.k(), self.dims.state_pad),
            &self.state.w,
            MatMut::new(&mut out, rows, self.state.w.n(), self.dims.vlm_hidden),
            self.state.init(),
        );
        out
    }

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
                    gemm_par(
                        pool,
                        MatRef::new(&k, tokens, wk.k(), kvw),
                        wk,
                        MatMut::new(&mut kp, tokens, wk.n(), kvw),
                        Init::Zero,
                    );
                    gemm_par(
                        pool,
                        MatRef::new(&v, tokens, wv.k(), kvw),
                        wv,
                        MatMut::new(&mut vp, tokens, wv.n(), kvw),
                        Init::Zero,
                    );
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
    pub(crate) fn sample(
        &self,
        pool: &Pool,
        prefixes: &[&PrefixKv],
        row_prefix: &[usize],
        x: &mut [f32],
        velocities: &mut [f32],
        updates: &mut [f32],
    ) -> Result<(), EngineError> {
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
        crate::sampler::integrate(schedule, rows, len, x, updates, |k, t, xt, v| {
            self.velocity(pool, &ctx, &mut ws, t, xt, v);
            for r in 0..rows {
                velocities[(r * steps + k) * len..(r * steps + k + 1) * len]
                    .copy_from_slice(&v[r * len..(r + 1) * len]);
            }
            Ok(())
        })
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
        // Suffix embedding: action_time_mlp_out(silu(action_time_mlp_in([action_in_proj(x); time_emb]))).
        gemm_par(
            pool,
            MatRef::new(xt, tokens, self.action_in.w.k(), d.action_pad),
            &self.action_in.w,
            MatMut::new(&mut ws.h, tokens, self.action_in.w.n(), h),
            self.action_in.init(),
        );
        let temb = time_embedding(t, h, d.min_period, d.max_period);
        gemm(
            isa,
            MatRef::new(&temb, 1, self.time_in_time.w.k(), h),
            &self.time_in_time.w,
            MatMut::new(&mut ws.time_bias, 1, self.time_in_time.w.n(), h),
            self.time_in_time.init(),
        );
        gemm_par(
            pool,
            MatRef::new(&ws.h, tokens, self.time_in_action.k(), h),
            &self.time_in_action,
            MatMut::new(&mut ws.x, tokens, self.time_in_action.n(), h),
            Init::Bias(&ws.time_bias),
        );
        vecmath::silu_inplace(isa, &mut ws.x);
        std::mem::swap(&mut ws.x, &mut ws.h);
        gemm_par(
            pool,
            MatRef::new(&ws.h, tokens, self.time_out.w.k(), h),
            &self.time_out.w,
            MatMut::new(&mut ws.x, tokens, self.time_out.w.n(), h),
            self.time_out.init(),
        );

        let eps = d.rms_eps;
        for (l, layer) in self.layers.iter().enumerate() {
            self.attention_block(pool, ctx, ws, l, layer);
            let (x, i) = (&ws.x, d.intermediate);
            ws.normed.fill(pool, tokens, |r, out| {
                vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &layer.post_norm, eps, out);
            });
            let gate_up = &mut ws.gate_up[..tokens * 2 * i];
            ws.normed.gemm_par(
                pool,
                &layer.gate_up,
                MatMut::new(gate_up, tokens, layer.gate_up.n(), 2 * i),
                Init::Zero,
            );
            let gate_up = &ws.gate_up;
            ws.act.fill(pool, tokens, |r, out| {
                let (g, u) = gate_up[r * 2 * i..(r + 1) * 2 * i].split_at(i);
                vecmath::silu_mul(isa, g, u, out);
            });
            ws.act.gemm_par(
                pool,
                &layer.down,
                MatMut::new(&mut ws.x, tokens, layer.down.n(), h),
                Init::Accumulate,
            );
        }
        let x = &ws.x;
        ws.normed.fill(pool, tokens, |r, out| {
            vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &self.final_norm, eps, out);
        });
        ws.normed.gemm_par(
            pool,
            &self.out.w,
            MatMut::new(v, tokens, self.out.w.n(), d.action_pad),
            self.out.init(),
        );
    }

    fn attention_block(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        l: usize,
        layer: &Layer,
    ) {
        let d = &self.dims;
        let (h, hd, n, tokens) = (d.hidden, d.head_dim, d.chunk, ws.tokens);
        let (qw, kvw, half) = (d.q_width(), d.kv_width(), d.head_dim / 2);
        let isa = pool.isa();
        let (x, eps) = (&ws.x, d.rms_eps);
        ws.normed.fill(pool, tokens, |r, out| {
            vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &layer.input_norm, eps, out);
        });
        let ld = layer.qkv.n();
        let qkv = &mut ws.qkv[..tokens * ld];
        ws.normed.gemm_par(
            pool,
            &layer.qkv,
            MatMut::new(qkv, tokens, layer.qkv.n(), ld),
            Init::Zero,
        );
        let rows = ctx.row_prefix.len();
        let groups = d.heads / d.kv_heads;
        // RoPE; the queries regrouped head-major per row, so that each head is one contiguous
        // `A`; in self-attention layers the action tokens' own keys and values packed. One unit
        // per row and KV head: it reads `qkv` only (the rotated queries and keys go to its own
        // heads of `q_heads` and its own buffer, not back) and writes its own packed pair, so
        // the units run on the pool's threads (on the calling thread alone, they left the other
        // thread spinning for ~3% of a step at batch 4).
        let units = rows * d.kv_heads;
        let parts = pool.parts_per_unit(units);
        let (qkv, self_attention) = (
            &ws.qkv[..tokens * ld],
            layer.kind == LayerKind::SelfAttention,
        );
        let q_heads = SharedMut::new(&mut ws.q_heads);
        let suffix_kv = SharedMut::new(&mut ws.suffix_kv);
        pool.run(parts, |p| {
            let mut keys = Vec::new();
            for unit in units * p / parts..units * (p + 1) / parts {
                let (r, g) = (unit / d.kv_heads, unit % d.kv_heads);
                let (cos, sin) = match layer.kind {
                    LayerKind::SelfAttention => &ctx.self_rope[ctx.row_prefix[r]],
                    LayerKind::CrossAttention => ctx.cross_rope,
                };
                if self_attention {
                    keys.resize(n * hd, 0.0);
                }
                for t in 0..n {
                    let (c, s) = (
                        &cos[t * half..(t + 1) * half],
                        &sin[t * half..(t + 1) * half],
                    );
                    let tok = &qkv[(r * n + t) * ld..(r * n + t + 1) * ld];
                    for head in g * groups..(g + 1) * groups {
                        let dst = ((r * d.heads + head) * n + t) * hd;
                        // SAFETY: `q_heads` holds `tokens x q width` values; (row r, head, token
                        // t) belongs to this unit's KV head `g`, so no other unit writes it.
                        let qh =
                            unsafe { std::slice::from_raw_parts_mut(q_heads.ptr().add(dst), hd) };
                        qh.copy_from_slice(&tok[head * hd..(head + 1) * hd]);
                        vecmath::rope(isa, qh, c, s);
                    }
                    if self_attention {
                        let key = &mut keys[t * hd..(t + 1) * hd];
                        key.copy_from_slice(&tok[qw + g * hd..qw + (g + 1) * hd]);
                        vecmath::rope(isa, key, c, s);
                    }
                }
                if self_attention {
                    // SAFETY: `suffix_kv` holds `rows x kv_heads` pairs; this unit's is its own.
                    let (kt, vv) = unsafe { &mut *suffix_kv.ptr().add(r * d.kv_heads + g) };
                    kt.pack_transposed(isa, MatRef::new(&keys, n, hd, hd));
                    // The values need no RoPE: packed straight from the rows of `qkv`.
                    vv.pack_rows(
                        isa,
                        MatRef::new(&qkv[r * n * ld + qw + kvw + g * hd..], n, hd, ld),
                    );
                }
            }
        });
        // Attention: the queries of the heads that share a KV head form one block of
        // `groups * n` rows (one GEMM against the shared keys). Each block is cut in two tasks
        // so that batch 1 still gives the threads even work.
        let block = groups * n;
        let splits = if block >= 4 * crate::kernels::gemm::MR {
            2
        } else {
            1
        };
        let tasks = rows * d.kv_heads * splits;
        let parts = pool.parts(tasks);
        let scale = (hd as f64).powf(-0.5) as f32;
        let out = SharedMut::new(&mut ws.attn);
        let (q_heads, suffix_kv, scratch) = (&ws.q_heads, &ws.suffix_kv, &ws.scores);
        pool.run(parts, |p| {
            let mut guard = match scratch[p].lock() {
                Ok(g) => g,
                Err(poisoned) => poisoned.into_inner(),
            };
            let (scores, tmp) = &mut *guard;
            for task in tasks * p / parts..tasks * (p + 1) / parts {
                let (r, g, half) = (
                    task / (d.kv_heads * splits),
                    (task / splits) % d.kv_heads,
                    task % splits,
                );
                let (i0, i1) = (block * half / splits, block * (half + 1) / splits);
                let (pk, pv) = &ctx.prepared[ctx.row_prefix[r]].layers[l][g];
                let prefix = KvSegment {
                    keys_t: pk,
                    values: pv,
                    causal: false,
                };
                let base = (r * d.heads + g * groups) * n * hd;
                let q = &q_heads[base + i0 * hd..base + i1 * hd];
                let positions = QueryPositions {
                    offset: i0 % n,
                    period: n,
                };
                tmp.resize((i1 - i0) * hd, 0.0);
                match layer.kind {
                    LayerKind::SelfAttention => {
                        let (sk, sv) = &suffix_kv[r * d.kv_heads + g];
                        let own = KvSegment {
                            keys_t: sk,
                            values: sv,
                            causal: true,
                        };
                        attend(
                            isa,
                            Queries::F32(MatRef::new(q, i1 - i0, hd, hd)),
                            &[prefix, own],
                            positions,
                            scale,
                            scores,
                            MatMut::new(tmp, i1 - i0, hd, hd),
                        );
                    }
                    LayerKind::CrossAttention => attend(
                        isa,
                        Queries::F32(MatRef::new(q, i1 - i0, hd, hd)),
                        &[prefix],
                        positions,
                        scale,
                        scores,
                        MatMut::new(tmp, i1 - i0, hd, hd),
                    ),
                }
                for (i, src) in (i0..i1).zip(tmp.chunks_exact(hd)) {
                    let (head, t) = (g * groups + i / n, i % n);
                    // SAFETY: (row r, token t, head) is written by this task only.
                    let dst = unsafe {
                        std::slice::from_raw_parts_mut(
                            out.ptr().add((r * n + t) * qw + head * hd),
                            hd,
                        )
                    };
                    dst.copy_from_slice(src);
                }
            }
        });
        gemm_par(
            pool,
            MatRef::new(&ws.attn, tokens, layer.o.k(), qw),
            &layer.o,
            MatMut::new(&mut ws.x, tokens, layer.o.n(), h),
            Init::Accumulate,
        );
    }
}

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
