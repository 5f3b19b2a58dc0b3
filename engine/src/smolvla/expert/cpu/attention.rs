//! The attention block of one expert layer: q/k/v projections, RoPE, attention per KV head
//! over the prefix (and, in self-attention layers, the action tokens' own keys), and the
//! output projection added into the residual stream.

use super::{CpuExpert, Layer, StepContext, Workspace};
use crate::kernels::attention::{KvSegment, Queries, QueryPositions, attend};
use crate::kernels::gemm::{MR, gemm_par};
use crate::kernels::{Init, MatMut, MatRef, Pool, SharedMut, vecmath};
use crate::smolvla::config::LayerKind;

impl CpuExpert {
    /// `x += o_proj(attention(rms_norm(x)))` for layer `l`.
    pub(super) fn attention_block(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        l: usize,
        layer: &Layer,
    ) {
        let d = &self.dims;
        let (h, qw, tokens) = (d.hidden, d.q_width(), ws.tokens);
        self.project_qkv(pool, ws, layer);
        self.rotate_and_pack(pool, ctx, ws, layer);
        self.attend_heads(pool, ctx, ws, l, layer.kind);
        let (attn, x) = (
            MatRef::dense(&ws.attn, tokens, qw),
            MatMut::dense(&mut ws.x, tokens, h),
        );
        gemm_par(pool, attn, &layer.o, x, Init::Accumulate);
    }

    /// `ws.qkv` = the `[q | k | v]` rows (`[q]` in cross-attention layers) of the RMS-normed
    /// hidden states.
    fn project_qkv(&self, pool: &Pool, ws: &mut Workspace, layer: &Layer) {
        let d = &self.dims;
        let (h, eps, tokens, isa) = (d.hidden, d.rms_eps, ws.tokens, pool.isa());
        let x = &ws.x;
        ws.normed.fill(pool, tokens, |r, out| {
            vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], &layer.input_norm, eps, out);
        });
        let qkv = MatMut::dense(&mut ws.qkv, tokens, layer.qkv.n());
        ws.normed.gemm_par(pool, &layer.qkv, qkv, Init::Zero);
    }

    /// RoPE; the queries regrouped head-major per row (`ws.q_heads`), so that each head is one
    /// contiguous `A`; in self-attention layers the action tokens' own keys and values packed
    /// (`ws.suffix_kv`). One unit per row and KV head: it reads `qkv` only (the rotated queries
    /// and keys go to its own heads of `q_heads` and its own buffer, not back) and writes its
    /// own packed pair, so the units run on the pool's threads rather than on the calling
    /// thread alone while the others wait.
    fn rotate_and_pack(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        layer: &Layer,
    ) {
        let d = &self.dims;
        let (hd, n, half) = (d.head_dim, d.chunk, d.head_dim / 2);
        let (qw, kvw) = (d.q_width(), d.kv_width());
        let (ld, isa) = (layer.qkv.n(), pool.isa());
        let groups = d.heads / d.kv_heads;
        let self_attention = layer.kind == LayerKind::SelfAttention;
        let units = ctx.row_prefix.len() * d.kv_heads;
        let parts = pool.parts_per_unit(units);
        let qkv = &ws.qkv[..ws.tokens * ld];
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
                    kt.pack_transposed(isa, MatRef::dense(&keys, n, hd));
                    // The values need no RoPE: packed straight from the rows of `qkv`.
                    let values = &qkv[r * n * ld + qw + kvw + g * hd..];
                    vv.pack_rows(isa, MatRef::new(values, n, hd, ld));
                }
            }
        });
    }

    /// `ws.attn` = the attention output of every head of every row (before `o_proj`). The
    /// queries of the heads that share a KV head form one block of `groups * n` rows (one GEMM
    /// against the shared keys); each block is cut in two tasks so that batch 1 still gives the
    /// threads even work.
    fn attend_heads(
        &self,
        pool: &Pool,
        ctx: &StepContext<'_>,
        ws: &mut Workspace,
        l: usize,
        kind: LayerKind,
    ) {
        let d = &self.dims;
        let (hd, n, qw, isa) = (d.head_dim, d.chunk, d.q_width(), pool.isa());
        let groups = d.heads / d.kv_heads;
        let block = groups * n;
        let splits = if block >= 4 * MR { 2 } else { 1 };
        let tasks = ctx.row_prefix.len() * d.kv_heads * splits;
        let parts = pool.parts(tasks);
        let scale = (hd as f64).powf(-0.5) as f32;
        let out = SharedMut::new(&mut ws.attn);
        let (q_heads, suffix_kv, scratch) = (&ws.q_heads, &ws.suffix_kv, &ws.scores);
        pool.run(parts, |p| {
            let mut guard = scratch[p].lock().unwrap_or_else(|e| e.into_inner());
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
                let with_own;
                let segments: &[KvSegment<'_>] = match kind {
                    LayerKind::SelfAttention => {
                        let (sk, sv) = &suffix_kv[r * d.kv_heads + g];
                        let own = KvSegment {
                            keys_t: sk,
                            values: sv,
                            causal: true,
                        };
                        with_own = [prefix, own];
                        &with_own
                    }
                    LayerKind::CrossAttention => std::slice::from_ref(&prefix),
                };
                let base = (r * d.heads + g * groups) * n * hd;
                let q = &q_heads[base + i0 * hd..base + i1 * hd];
                let positions = QueryPositions {
                    offset: i0 % n,
                    period: n,
                };
                tmp.resize((i1 - i0) * hd, 0.0);
                let (q, rows) = (
                    MatRef::dense(q, i1 - i0, hd),
                    MatMut::dense(tmp, i1 - i0, hd),
                );
                attend(
                    isa,
                    Queries::F32(q),
                    segments,
                    positions,
                    scale,
                    scores,
                    rows,
                );
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
    }
}
