//! The action expert (Gemma 300M) and the Euler loop on the engine's CPU kernels, as
//! [`crate::pi::model::PiModel::sample`] computes them on Candle ops (LeRobot's
//! `sample_actions` / `denoise_step`):
//!
//! ```text
//! suffix, π0:   [state_proj(state) ; action_time_mlp_out(silu(action_time_mlp_in(
//!                    [action_in_proj(x_t) ; sincos(t)])))]        (1 + chunk tokens)
//! suffix, π0.5: action_in_proj(x_t), cond = silu(time_mlp_out(silu(time_mlp_in(sincos(t)))))
//!   -> the expert's layers over [prefix K/V ; own K/V] (adaptive norms and gated residuals
//!      conditioned on `cond` for π0.5) -> final norm -> action_out_proj of the last `chunk`
//!      tokens = v_t;  x_t += dt v_t
//! ```
//!
//! The prefix-dependent work (packing each layer's prefix keys and values, the RoPE tables of
//! the suffix positions after the prefix) is done once per request, not once per step.
//! `action_time_mlp_in` is split by input: its time half is the same for every token of a step,
//! so its product is made once per step and enters the action half's GEMM as a bias.
//!
//! Masks: the suffix tokens form blocks of equal `cumsum(att_masks)` (π0: the state token,
//! then the action tokens; π0.5: the action tokens); a token sees the valid prefix and every
//! block up to its own. Hidden keys are left out of the attention: LeRobot's masked scores are
//! exactly 0 after its softmax, so leaving them out changes no sum.
//!
//! Every GEMM runs all rows at once and each output row depends on its own input row only, in
//! a fixed order; attention runs per row and head. A request gets bit-identical results alone
//! or in a batch.

use std::collections::HashMap;
use std::ops::Range;
use std::sync::{Arc, Mutex};

use super::layer::{GemmaLayerWeights, GemmaNormWeights, Modulation, geglu_row, rope_tables};
use super::prefix::FastPrefix;
use crate::EngineError;
use crate::guidance::RowGuide;
use crate::kernels::attention::{AttendScratch, KvSegment, Queries, QueryPositions, attend};
use crate::kernels::gemm::{ActivationRows, gemm, gemm_par};
use crate::kernels::{
    Init, Isa, MatMut, MatRef, PackedMatrix, Pool, Precision, SharedMut, vecmath,
};
use crate::pi::config::{PiDims, PiFamily, keys};
use crate::pi::vars::Vars;
use crate::sampler::ClosureField;
use crate::smolvla::expert::weights::time_embedding;
use crate::smolvla::linear::Linear;

/// The suffix's own layers, by family.
enum Suffix {
    Pi0 {
        state_proj: Linear,
        /// `action_time_mlp_in`'s action half (`[width][width]`).
        mlp_in_action: PackedMatrix,
        /// Its time half, with the layer's bias.
        mlp_in_time: Linear,
        mlp_out: Linear,
    },
    Pi05 {
        time_mlp_in: Linear,
        time_mlp_out: Linear,
    },
}

/// The packed action expert with its suffix layers.
pub(crate) struct FastGemmaExpert {
    dims: PiDims,
    layers: Vec<GemmaLayerWeights>,
    norm: GemmaNormWeights,
    action_in: Linear,
    action_out: Linear,
    suffix: Suffix,
    /// The weight GEMMs' precision, also that of the attention's packed keys and values.
    precision: Precision,
    /// The suffix's attention blocks, in token order.
    blocks: Vec<Range<usize>>,
    /// π0.5's modulations by time (the bits of `t`), see [`FastGemmaExpert::modulations`].
    modulations: Mutex<HashMap<u32, Arc<StepModulations>>>,
}

/// Times whose modulations are kept (the schedule's `steps`, and room for a few schedules).
const MODULATION_CACHE: usize = 64;

/// Every adaptive norm's modulation at one time: per layer the input and post-attention
/// norms', then the final norm's.
struct StepModulations {
    layers: Vec<(Modulation, Modulation)>,
    norm: Modulation,
}

/// One request's prefix, prepared for the attention kernels.
struct PreparedPrefix {
    /// Per layer, per KV head: packed `Kᵀ` and `V` of the valid prefix tokens.
    layers: Vec<Vec<(PackedMatrix, PackedMatrix)>>,
    /// RoPE tables of the suffix positions (after the prefix's valid tokens).
    cos: Vec<f32>,
    sin: Vec<f32>,
}

/// One expert call's requests.
pub(crate) struct SuffixRequest<'a> {
    pub(crate) prefix: &'a FastPrefix,
    /// π0's padded state (`state_pad` values).
    pub(crate) state: Option<&'a [f32]>,
}

impl FastGemmaExpert {
    /// Load from the checkpoint root; the weight GEMMs in `precision`.
    pub(crate) fn load(
        root: &Vars<'_>,
        dims: &PiDims,
        precision: Precision,
    ) -> Result<Self, EngineError> {
        let d = &dims.expert;
        let e = d.width;
        let adaptive = dims.family == PiFamily::Pi05;
        let vars = root.pp(keys::EXPERT);
        let layers = (0..d.depth)
            .map(|i| GemmaLayerWeights::load(&vars.pp("layers").pp(i), d, adaptive, precision))
            .collect::<Result<_, _>>()?;
        let m = root.pp("model");
        let suffix = match dims.family {
            PiFamily::Pi0 => {
                let mlp_in = m.pp("action_time_mlp_in").linear_weights(e, 2 * e, true)?;
                let half = |offset: usize| {
                    PackedMatrix::from_linear_fn_in(precision, e, e, |j, kk| {
                        mlp_in.weight.get(j * 2 * e + offset + kk)
                    })
                };
                Suffix::Pi0 {
                    state_proj: m
                        .pp("state_proj")
                        .linear_weights(e, dims.state_pad, true)?
                        .into_linear(precision),
                    mlp_in_action: half(0),
                    mlp_in_time: Linear {
                        w: half(e),
                        bias: mlp_in.bias.clone(),
                    },
                    mlp_out: m
                        .pp("action_time_mlp_out")
                        .linear_weights(e, e, true)?
                        .into_linear(precision),
                }
            }
            PiFamily::Pi05 => Suffix::Pi05 {
                time_mlp_in: m
                    .pp("time_mlp_in")
                    .linear_weights(e, e, true)?
                    .into_linear(precision),
                time_mlp_out: m
                    .pp("time_mlp_out")
                    .linear_weights(e, e, true)?
                    .into_linear(precision),
            },
        };
        let n = dims.chunk;
        let blocks = match dims.family {
            PiFamily::Pi0 => vec![0..1, 1..1 + n],
            PiFamily::Pi05 => std::iter::once(0..n).collect(),
        };
        Ok(FastGemmaExpert {
            dims: dims.clone(),
            layers,
            norm: GemmaNormWeights::load(&vars.pp("norm"), e, adaptive, precision)?,
            action_in: m
                .pp("action_in_proj")
                .linear_weights(e, dims.action_pad, true)?
                .into_linear(precision),
            action_out: m
                .pp("action_out_proj")
                .linear_weights(dims.action_pad, e, true)?
                .into_linear(precision),
            suffix,
            precision,
            blocks,
            modulations: Mutex::new(HashMap::new()),
        })
    }

    /// Suffix tokens per sample.
    fn suffix_len(&self) -> usize {
        self.blocks.last().map_or(0, |b| b.end)
    }

    /// Pack one request's prefix keys and values and make its suffix RoPE tables.
    fn prepare(&self, pool: &Pool, prefix: &FastPrefix) -> Result<PreparedPrefix, EngineError> {
        let d = &self.dims.expert;
        let (kvw, hd, p) = (d.kv_width(), d.head_dim, prefix.len);
        if prefix.keys.len() != d.depth
            || prefix.values.len() != d.depth
            || prefix
                .keys
                .iter()
                .chain(&prefix.values)
                .any(|k| k.len() != p * kvw)
        {
            return Err(EngineError::InvalidInput(format!(
                "a prefix cache of {} layers ({p} tokens) for an expert of {} layers of \
                 {kvw} key values",
                prefix.keys.len(),
                d.depth
            )));
        }
        let isa = pool.isa();
        let layers = (0..d.depth)
            .map(|l| {
                (0..d.kv_heads)
                    .map(|g| {
                        let mut kt = PackedMatrix::empty_in(self.precision);
                        kt.pack_transposed(isa, MatRef::new(&prefix.keys[l][g * hd..], p, hd, kvw));
                        let mut v = PackedMatrix::empty_in(self.precision);
                        v.pack_rows(isa, MatRef::new(&prefix.values[l][g * hd..], p, hd, kvw));
                        (kt, v)
                    })
                    .collect()
            })
            .collect();
        let (cos, sin) = rope_tables(p..p + self.suffix_len(), hd, d.rope_theta);
        Ok(PreparedPrefix { layers, cos, sin })
    }

    /// Run the Euler loop for `row_request.len()` rows: row `r` belongs to
    /// `requests[row_request[r]]` and is guided by `guides[r]` (real-time chunking or
    /// inpainting in the shared sampler; one guide per row); `x` holds the noise
    /// (`[rows][chunk][action_pad]`) and receives the actions; `velocities` (those each step
    /// used) and `updates` receive `[rows][steps][chunk][pad]`.
    // The sampler's buffers and the rows' guides, as `integrate_guided` takes them.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn sample(
        &self,
        pool: &Pool,
        requests: &[SuffixRequest<'_>],
        row_request: &[usize],
        x: &mut [f32],
        velocities: &mut [f32],
        updates: &mut [f32],
        guides: &[Option<RowGuide>],
    ) -> Result<(), EngineError> {
        let dims = &self.dims;
        let rows = row_request.len();
        let e = dims.expert.width;
        let prepared = requests
            .iter()
            .map(|r| self.prepare(pool, r.prefix))
            .collect::<Result<Vec<_>, _>>()?;
        // π0's state token of every row, `[rows][width]`.
        let state_tokens = match &self.suffix {
            Suffix::Pi0 { state_proj, .. } => {
                let mut states = Vec::with_capacity(rows * dims.state_pad);
                for &i in row_request {
                    let s = requests[i].state.ok_or_else(|| {
                        EngineError::InvalidInput(format!("request {i}: π0 needs the state"))
                    })?;
                    if s.len() != dims.state_pad {
                        return Err(EngineError::InvalidInput(format!(
                            "request {i}: padded state has {} values, expected {}",
                            s.len(),
                            dims.state_pad
                        )));
                    }
                    states.extend_from_slice(s);
                }
                let mut out = vec![0.0f32; rows * e];
                gemm_par(
                    pool,
                    MatRef::dense(&states, rows, dims.state_pad),
                    &state_proj.w,
                    MatMut::dense(&mut out, rows, e),
                    state_proj.init(),
                );
                out
            }
            Suffix::Pi05 { .. } => Vec::new(),
        };
        let mut ws = Workspace::new(self, rows);
        let ctx = StepContext {
            prepared: &prepared,
            row_request,
            state_tokens: &state_tokens,
        };
        let len = dims.chunk * dims.action_pad;
        let steps = dims.steps;
        // No backward pass here: `FastPiModel::sample_guided` refuses an `rtc_vjp` row before
        // it gets here (and the field's default `velocity_vjp` would).
        let mut field = ClosureField(|_k: usize, t: f32, xt: &[f32], v: &mut [f32]| {
            self.velocity(pool, &ctx, &mut ws, t, xt, v);
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

    /// `v_t` of every row at `xt` and time `t` (LeRobot's `denoise_step`).
    fn velocity(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        t: f32,
        xt: &[f32],
        v: &mut [f32],
    ) {
        let dims = &self.dims;
        let d = &dims.expert;
        let (e, n, s) = (d.width, dims.chunk, self.suffix_len());
        let rows = ctx.row_request.len();
        let tokens = rows * s;
        let isa = pool.isa();
        let eps = d.eps as f32;
        self.embed_suffix(pool, ctx, ws, t, xt);
        let modulations = self.modulations(pool, t);
        for (l, layer) in self.layers.iter().enumerate() {
            let (m1, m2) = match &modulations {
                Some(m) => (Some(&m.layers[l].0), Some(&m.layers[l].1)),
                None => (None, None),
            };
            let x = &ws.x;
            ws.normed.fill(pool, tokens, |r, o| {
                layer
                    .input_norm
                    .row(isa, &x[r * e..(r + 1) * e], eps, m1, o);
            });
            let ld = layer.qkv.n();
            ws.normed.gemm_par(
                pool,
                &layer.qkv,
                MatMut::dense(&mut ws.qkv, tokens, ld),
                Init::Zero,
            );
            self.rotate_and_pack(pool, ctx, ws);
            self.attend_heads(pool, ctx, ws, l);
            let attn = MatRef::dense(&ws.attn, tokens, d.q_width());
            residual(pool, attn, &layer.o, m1, &mut ws.x, &mut ws.y);
            let x = &ws.x;
            ws.normed.fill(pool, tokens, |r, o| {
                layer.post_norm.row(isa, &x[r * e..(r + 1) * e], eps, m2, o);
            });
            ws.normed.gemm_par(
                pool,
                &layer.gate_up,
                MatMut::dense(&mut ws.gate_up, tokens, 2 * d.mlp),
                Init::Zero,
            );
            let gu = &ws.gate_up;
            ws.act.fill(pool, tokens, |r, o| {
                let (g, u) = gu[r * 2 * d.mlp..(r + 1) * 2 * d.mlp].split_at(d.mlp);
                geglu_row(isa, g, u, o);
            });
            let (act, x, y) = (&ws.act, &mut ws.x, &mut ws.y);
            match m2 {
                None => act.gemm_par(
                    pool,
                    &layer.down,
                    MatMut::dense(x, tokens, e),
                    Init::Accumulate,
                ),
                Some(m) => {
                    act.gemm_par(pool, &layer.down, MatMut::dense(y, tokens, e), Init::Zero);
                    add_gated(x, y, &m.gate);
                }
            }
        }
        // The final norm of the action tokens (the last `chunk` of each row), then the output.
        let mf = modulations.as_ref().map(|m| &m.norm);
        let x = &ws.x;
        ws.normed.fill(pool, rows * n, |i, o| {
            let token = (i / n) * s + (s - n) + i % n;
            self.norm
                .row(isa, &x[token * e..(token + 1) * e], eps, mf, o);
        });
        ws.normed.gemm_par(
            pool,
            &self.action_out.w,
            MatMut::dense(v, rows * n, dims.action_pad),
            self.action_out.init(),
        );
    }

    /// π0.5's modulation of every adaptive norm at time `t` (`None` for π0): made once per
    /// time and kept, since it depends on `t` alone and the Euler loop visits the same `steps`
    /// times in every call. About 116 M parameters of Gemma 300M (the norms' `dense` layers)
    /// are thus read once per time, not once per step of every request.
    fn modulations(&self, pool: &Pool, t: f32) -> Option<Arc<StepModulations>> {
        let Suffix::Pi05 {
            time_mlp_in,
            time_mlp_out,
        } = &self.suffix
        else {
            return None;
        };
        let key = t.to_bits();
        let cached = self
            .modulations
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(&key)
            .cloned();
        if let Some(m) = cached {
            return Some(m);
        }
        let dims = &self.dims;
        let e = dims.expert.width;
        let isa = pool.isa();
        let temb = time_embedding(t, e, dims.min_period, dims.max_period);
        let mut h = time_row(isa, time_mlp_in, &temb);
        vecmath::silu_inplace(isa, &mut h);
        let mut cond = time_row(isa, time_mlp_out, &h);
        vecmath::silu_inplace(isa, &mut cond);
        let adaptive =
            |norm: &GemmaNormWeights| -> Option<Modulation> { norm.modulation(pool, &cond) };
        let made = self
            .layers
            .iter()
            .map(|l| Some((adaptive(&l.input_norm)?, adaptive(&l.post_norm)?)))
            .collect::<Option<Vec<_>>>()
            .zip(adaptive(&self.norm))
            .map(|(layers, norm)| Arc::new(StepModulations { layers, norm }))?;
        let mut cache = self.modulations.lock().unwrap_or_else(|e| e.into_inner());
        // Only a caller that samples at ever new times (not the fixed schedule) fills it.
        if cache.len() >= MODULATION_CACHE {
            cache.clear();
        }
        cache.insert(key, Arc::clone(&made));
        Some(made)
    }

    /// The suffix embeddings of every row into `ws.x` (`[rows][suffix][width]`).
    fn embed_suffix(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        t: f32,
        xt: &[f32],
    ) {
        let dims = &self.dims;
        let (e, n, s) = (dims.expert.width, dims.chunk, self.suffix_len());
        let rows = ctx.row_request.len();
        let isa = pool.isa();
        let temb = time_embedding(t, e, dims.min_period, dims.max_period);
        let actions = MatRef::dense(xt, rows * n, dims.action_pad);
        match &self.suffix {
            Suffix::Pi05 { .. } => {
                let x = MatMut::dense(&mut ws.x, rows * n, e);
                gemm_par(pool, actions, &self.action_in.w, x, self.action_in.init());
            }
            Suffix::Pi0 {
                mlp_in_action,
                mlp_in_time,
                mlp_out,
                ..
            } => {
                let time_bias = time_row(isa, mlp_in_time, &temb);
                let emb = MatMut::dense(&mut ws.emb, rows * n, e);
                gemm_par(pool, actions, &self.action_in.w, emb, self.action_in.init());
                let (emb, mid) = (
                    MatRef::dense(&ws.emb, rows * n, e),
                    MatMut::dense(&mut ws.mid, rows * n, e),
                );
                gemm_par(pool, emb, mlp_in_action, mid, Init::Bias(&time_bias));
                vecmath::silu_inplace(isa, &mut ws.mid[..rows * n * e]);
                let (mid, emb) = (
                    MatRef::dense(&ws.mid, rows * n, e),
                    MatMut::dense(&mut ws.emb, rows * n, e),
                );
                gemm_par(pool, mid, &mlp_out.w, emb, mlp_out.init());
                for r in 0..rows {
                    let row = &mut ws.x[r * s * e..(r + 1) * s * e];
                    row[..e].copy_from_slice(&ctx.state_tokens[r * e..(r + 1) * e]);
                    row[e..].copy_from_slice(&ws.emb[r * n * e..(r + 1) * n * e]);
                }
            }
        }
    }

    /// RoPE on the queries and keys of `ws.qkv` (in place), then each row's own keys and
    /// values packed per KV head and block (`ws.own`). One unit per row: it alone touches its
    /// row's tokens and packed pairs.
    fn rotate_and_pack(&self, pool: &Pool, ctx: &StepContext<'_>, ws: &mut Workspace) {
        let d = &self.dims.expert;
        let (hd, half, s) = (d.head_dim, d.head_dim / 2, self.suffix_len());
        let (qw, kvw) = (d.q_width(), d.kv_width());
        let ld = qw + 2 * kvw;
        let rows = ctx.row_request.len();
        let isa = pool.isa();
        let nb = self.blocks.len();
        let per_row = d.kv_heads * nb;
        let parts = pool.parts_per_unit(rows);
        let qkv = SharedMut::new(&mut ws.qkv[..rows * s * ld]);
        let own = SharedMut::new(&mut ws.own);
        pool.run(parts, |p| {
            for r in rows * p / parts..rows * (p + 1) / parts {
                let pre = &ctx.prepared[ctx.row_request[r]];
                // SAFETY: `qkv` holds `rows x s` rows of `ld` values; row `r`'s are this
                // unit's alone.
                let row =
                    unsafe { std::slice::from_raw_parts_mut(qkv.ptr().add(r * s * ld), s * ld) };
                for (t, tok) in row.chunks_exact_mut(ld).enumerate() {
                    let (c, sn) = (&pre.cos[t * half..][..half], &pre.sin[t * half..][..half]);
                    for head in tok[..qw + kvw].chunks_exact_mut(hd) {
                        vecmath::rope(isa, head, c, sn);
                    }
                }
                // SAFETY: `own` holds `rows x kv_heads x blocks` pairs; row `r`'s are this
                // unit's alone.
                let pairs =
                    unsafe { std::slice::from_raw_parts_mut(own.ptr().add(r * per_row), per_row) };
                for g in 0..d.kv_heads {
                    for (b, block) in self.blocks.iter().enumerate() {
                        let (kt, v) = &mut pairs[g * nb + b];
                        let (t0, len) = (block.start, block.len());
                        let keys = &row[t0 * ld + qw + g * hd..];
                        kt.pack_transposed(isa, MatRef::new(keys, len, hd, ld));
                        let values = &row[t0 * ld + qw + kvw + g * hd..];
                        v.pack_rows(isa, MatRef::new(values, len, hd, ld));
                    }
                }
            }
        });
    }

    /// `ws.attn` = every head's attention output of every row (before `o_proj`): the queries
    /// of block `b` over the prefix and the row's own blocks `0..=b`.
    fn attend_heads(&self, pool: &Pool, ctx: &StepContext<'_>, ws: &mut Workspace, l: usize) {
        let d = &self.dims.expert;
        let (hd, s) = (d.head_dim, self.suffix_len());
        let (qw, kvw) = (d.q_width(), d.kv_width());
        let ld = qw + 2 * kvw;
        let groups = d.heads / d.kv_heads;
        let rows = ctx.row_request.len();
        let nb = self.blocks.len();
        let scale = (hd as f64).powf(-0.5) as f32;
        let isa = pool.isa();
        let tasks = rows * d.heads;
        let parts = pool.parts_per_unit(tasks).min(ws.scratch.len());
        let out = SharedMut::new(&mut ws.attn);
        let (qkv, own, scratch) = (&ws.qkv, &ws.own, &ws.scratch);
        pool.run(parts, |p| {
            let mut guard = scratch[p].lock().unwrap_or_else(|e| e.into_inner());
            let (scores, tmp) = &mut *guard;
            let mut segments = Vec::with_capacity(nb + 1);
            for task in tasks * p / parts..tasks * (p + 1) / parts {
                let (r, head) = (task / d.heads, task % d.heads);
                let g = head / groups;
                let (pk, pv) = &ctx.prepared[ctx.row_request[r]].layers[l][g];
                for (b, block) in self.blocks.iter().enumerate() {
                    segments.clear();
                    segments.push(KvSegment {
                        keys_t: pk,
                        values: pv,
                        causal: false,
                    });
                    for (kt, v) in &own[(r * d.kv_heads + g) * nb..][..=b] {
                        segments.push(KvSegment {
                            keys_t: kt,
                            values: v,
                            causal: false,
                        });
                    }
                    let nq = block.len();
                    tmp.resize(nq * hd, 0.0);
                    let q0 = (r * s + block.start) * ld + head * hd;
                    attend(
                        isa,
                        Queries::F32(MatRef::new(&qkv[q0..], nq, hd, ld)),
                        &segments,
                        QueryPositions {
                            offset: 0,
                            period: nq,
                        },
                        scale,
                        scores,
                        MatMut::dense(tmp, nq, hd),
                    );
                    // SAFETY: row r's tokens of this block, this head's columns, are written
                    // by this task only.
                    unsafe { out.write_rows(tmp, hd, qw, r * s + block.start, head * hd) };
                }
            }
        });
    }
}

/// `x += A · B`, or with a modulation's gate `x += (A · B) * gate` (LeRobot's
/// `_gated_residual`, the product made in `y` first).
fn residual(
    pool: &Pool,
    a: MatRef<'_>,
    b: &PackedMatrix,
    modulation: Option<&Modulation>,
    x: &mut [f32],
    y: &mut [f32],
) {
    let (m, n) = (a.rows(), b.n());
    match modulation {
        None => gemm_par(pool, a, b, MatMut::dense(x, m, n), Init::Accumulate),
        Some(md) => {
            gemm_par(pool, a, b, MatMut::dense(y, m, n), Init::Zero);
            add_gated(&mut x[..m * n], &y[..m * n], &md.gate);
        }
    }
}

/// `x[r] += y[r] * gate` for every row of `gate.len()` values.
fn add_gated(x: &mut [f32], y: &[f32], gate: &[f32]) {
    let w = gate.len();
    for (xr, yr) in x.chunks_exact_mut(w).zip(y.chunks_exact(w)) {
        for ((xv, &yv), &g) in xr.iter_mut().zip(yr).zip(gate) {
            *xv += yv * g;
        }
    }
}

/// What every step of one `sample` call shares.
struct StepContext<'a> {
    prepared: &'a [PreparedPrefix],
    row_request: &'a [usize],
    /// π0: `[rows][width]`.
    state_tokens: &'a [f32],
}

/// Buffers reused by every layer of every step; every value is written before it is read.
struct Workspace {
    x: Vec<f32>,
    y: Vec<f32>,
    emb: Vec<f32>,
    mid: Vec<f32>,
    qkv: Vec<f32>,
    attn: Vec<f32>,
    gate_up: Vec<f32>,
    normed: ActivationRows,
    act: ActivationRows,
    /// Per row, KV head and block: the packed own keys and values.
    own: Vec<(PackedMatrix, PackedMatrix)>,
    /// Per attention part: scores and the output block.
    scratch: Vec<Mutex<(AttendScratch, Vec<f32>)>>,
}

impl Workspace {
    fn new(expert: &FastGemmaExpert, rows: usize) -> Self {
        let dims = &expert.dims;
        let d = &dims.expert;
        let tokens = rows * expert.suffix_len();
        let actions = rows * dims.chunk;
        let precision = expert.precision;
        Workspace {
            x: vec![0.0; tokens * d.width],
            y: vec![0.0; tokens * d.width],
            emb: vec![0.0; actions * d.width],
            mid: vec![0.0; actions * d.width],
            qkv: vec![0.0; tokens * (d.q_width() + 2 * d.kv_width())],
            attn: vec![0.0; tokens * d.q_width()],
            gate_up: vec![0.0; tokens * 2 * d.mlp],
            normed: ActivationRows::new(precision, tokens, d.width),
            act: ActivationRows::new(precision, tokens, d.mlp),
            own: (0..rows * d.kv_heads * expert.blocks.len())
                .map(|_| {
                    (
                        PackedMatrix::empty_in(precision),
                        PackedMatrix::empty_in(precision),
                    )
                })
                .collect(),
            // `parts_per_unit` cuts at most 64 parts.
            scratch: (0..64)
                .map(|_| Mutex::new((AttendScratch::default(), Vec::new())))
                .collect(),
        }
    }
}

/// `a W + b` for one row `a` through one of the time MLP's square layers (as wide as `a`).
fn time_row(isa: Isa, l: &Linear, a: &[f32]) -> Vec<f32> {
    let width = a.len();
    let mut out = vec![0.0f32; width];
    gemm(
        isa,
        MatRef::dense(a, 1, width),
        &l.w,
        MatMut::dense(&mut out, 1, width),
        l.init(),
    );
    out
}
