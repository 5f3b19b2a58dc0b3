//! The PaliGemma prefix's Gemma layers on the engine's CPU kernels: the K/V cache of each
//! observation's valid prefix tokens (LeRobot's prefix prefill in `sample_actions`).
//!
//! As on the Candle path ([`crate::pi::gemma`]): LeRobot's prefix-LM mask lets every valid
//! image and language token see every other valid one and nothing see padding, so the layers
//! run on the valid tokens only, at positions `0..n`, with bidirectional attention; the cache
//! holds their post-RoPE keys and values. The last layer's attention output and MLP feed
//! nothing the expert reads and are skipped.
//!
//! Every GEMM runs the whole batch's rows at once; attention runs per observation and query
//! head. Each output row depends on its own input row only, in a fixed order, so an observation
//! gets bit-identical results alone or in a batch.

use super::layer::{GemmaLayerWeights, geglu_row, rope_tables};
use crate::EngineError;
use crate::kernels::attention::{AttendScratch, KvSegment, Queries, QueryPositions, attend};
use crate::kernels::gemm::{ActivationRows, gemm_par};
use crate::kernels::{Init, MatMut, MatRef, PackedMatrix, Pool, Precision, SharedMut, vecmath};
use crate::pi::config::GemmaDims;
use crate::pi::vars::Vars;

/// One observation's prefix cache on the host.
#[derive(Clone, Debug, PartialEq)]
pub struct FastPrefix {
    /// Valid prefix tokens.
    pub len: usize,
    /// The embeddings the layers started from, `[len][vlm width]`.
    pub embeddings: Vec<f32>,
    /// Per layer, `[len][kv_heads * head_dim]`, post-RoPE.
    pub keys: Vec<Vec<f32>>,
    /// Per layer, `[len][kv_heads * head_dim]`.
    pub values: Vec<Vec<f32>>,
}

/// The prefix's packed decoder layers.
pub(crate) struct FastGemmaPrefix {
    dims: GemmaDims,
    layers: Vec<GemmaLayerWeights>,
    precision: Precision,
}

impl FastGemmaPrefix {
    /// `vars` at the language model; the weight GEMMs in `precision`.
    pub(crate) fn load(
        vars: &Vars<'_>,
        d: &GemmaDims,
        precision: Precision,
    ) -> Result<Self, EngineError> {
        let layers = (0..d.depth)
            .map(|i| GemmaLayerWeights::load(&vars.pp("layers").pp(i), d, false, precision))
            .collect::<Result<_, _>>()?;
        Ok(FastGemmaPrefix {
            dims: d.clone(),
            layers,
            precision,
        })
    }

    /// The caches of observations whose valid tokens' embeddings are `embeddings[i]`
    /// (`[n_i][width]` each).
    pub(crate) fn forward(&self, pool: &Pool, embeddings: Vec<Vec<f32>>) -> Vec<FastPrefix> {
        let d = &self.dims;
        let (h, hd, half) = (d.width, d.head_dim, d.head_dim / 2);
        let (qw, kvw) = (d.q_width(), d.kv_width());
        let ld = qw + 2 * kvw;
        let counts: Vec<usize> = embeddings.iter().map(|e| e.len() / h).collect();
        let starts: Vec<usize> = counts
            .iter()
            .scan(0, |acc, &n| {
                let s = *acc;
                *acc += n;
                Some(s)
            })
            .collect();
        let rows: usize = counts.iter().sum();
        let mut x: Vec<f32> = embeddings.concat();
        let mut out: Vec<FastPrefix> = embeddings
            .into_iter()
            .zip(&counts)
            .map(|(embeddings, &len)| FastPrefix {
                len,
                embeddings,
                keys: Vec::with_capacity(d.depth),
                values: Vec::with_capacity(d.depth),
            })
            .collect();
        let longest = counts.iter().copied().max().unwrap_or(0);
        let (cos, sin) = rope_tables(0..longest, hd, d.rope_theta);
        let eps = d.eps as f32;
        let isa = pool.isa();
        let mut qkv = vec![0.0f32; rows * ld];
        let mut attn = vec![0.0f32; rows * qw];
        let mut gate_up = vec![0.0f32; rows * 2 * d.mlp];
        let mut normed = ActivationRows::new(self.precision, rows, h);
        let mut act = ActivationRows::new(self.precision, rows, d.mlp);
        let last = self.layers.len().saturating_sub(1);
        for (l, layer) in self.layers.iter().enumerate() {
            let xs = &x;
            normed.fill(pool, rows, |r, o| {
                layer
                    .input_norm
                    .row(isa, &xs[r * h..(r + 1) * h], eps, None, o);
            });
            normed.gemm_par(
                pool,
                &layer.qkv,
                MatMut::dense(&mut qkv, rows, ld),
                Init::Zero,
            );
            // RoPE on the queries and keys (in place: nothing reads them unrotated).
            for (&n, &start) in counts.iter().zip(&starts) {
                for t in 0..n {
                    let (c, s) = (&cos[t * half..][..half], &sin[t * half..][..half]);
                    let tok = &mut qkv[(start + t) * ld..][..ld];
                    for head in tok[..qw + kvw].chunks_exact_mut(hd) {
                        vecmath::rope(isa, head, c, s);
                    }
                }
            }
            for (o, (&n, &start)) in out.iter_mut().zip(counts.iter().zip(&starts)) {
                let (mut k, mut v) = (Vec::with_capacity(n * kvw), Vec::with_capacity(n * kvw));
                for row in qkv[start * ld..(start + n) * ld].chunks_exact(ld) {
                    k.extend_from_slice(&row[qw..qw + kvw]);
                    v.extend_from_slice(&row[qw + kvw..]);
                }
                o.keys.push(k);
                o.values.push(v);
            }
            if l == last {
                break;
            }
            self.attention(pool, &qkv, &counts, &starts, &mut attn);
            gemm_par(
                pool,
                MatRef::dense(&attn, rows, qw),
                &layer.o,
                MatMut::dense(&mut x, rows, h),
                Init::Accumulate,
            );
            let xs = &x;
            normed.fill(pool, rows, |r, o| {
                layer
                    .post_norm
                    .row(isa, &xs[r * h..(r + 1) * h], eps, None, o);
            });
            normed.gemm_par(
                pool,
                &layer.gate_up,
                MatMut::dense(&mut gate_up, rows, 2 * d.mlp),
                Init::Zero,
            );
            let gu = &gate_up;
            act.fill(pool, rows, |r, o| {
                let (g, u) = gu[r * 2 * d.mlp..(r + 1) * 2 * d.mlp].split_at(d.mlp);
                geglu_row(isa, g, u, o);
            });
            act.gemm_par(
                pool,
                &layer.down,
                MatMut::dense(&mut x, rows, h),
                Init::Accumulate,
            );
        }
        out
    }

    /// Bidirectional attention within each observation, per query head: `attn` rows get
    /// `softmax(q kᵀ / sqrt(hd)) v` of their observation's tokens, each query head reading
    /// the KV head it shares.
    fn attention(
        &self,
        pool: &Pool,
        qkv: &[f32],
        counts: &[usize],
        starts: &[usize],
        attn: &mut [f32],
    ) {
        let d = &self.dims;
        let (heads, kv_heads, hd) = (d.heads, d.kv_heads, d.head_dim);
        let (qw, kvw) = (heads * hd, kv_heads * hd);
        let ld = qw + 2 * kvw;
        let groups = heads / kv_heads;
        let scale = (hd as f64).powf(-0.5) as f32;
        let isa = pool.isa();
        // Keys and values packed once per observation and KV head.
        let units = counts.len() * kv_heads;
        let mut packed: Vec<(PackedMatrix, PackedMatrix)> = (0..units)
            .map(|_| {
                (
                    PackedMatrix::empty_in(self.precision),
                    PackedMatrix::empty_in(self.precision),
                )
            })
            .collect();
        let shared = SharedMut::new(&mut packed);
        let parts = pool.parts_per_unit(units);
        pool.run(parts, |p| {
            for unit in units * p / parts..units * (p + 1) / parts {
                let (obs, g) = (unit / kv_heads, unit % kv_heads);
                let (n, start) = (counts[obs], starts[obs]);
                let base = &qkv[start * ld..(start + n) * ld];
                // SAFETY: `packed` holds `units` pairs and this unit's is written by it only.
                let (kt, v) = unsafe { &mut *shared.ptr().add(unit) };
                kt.pack_transposed(isa, MatRef::new(&base[qw + g * hd..], n, hd, ld));
                v.pack_rows(isa, MatRef::new(&base[qw + kvw + g * hd..], n, hd, ld));
            }
        });
        let tasks = counts.len() * heads;
        let parts = pool.parts_per_unit(tasks);
        let out = SharedMut::new(attn);
        let packed = &packed;
        pool.run(parts, |p| {
            let (mut scores, mut tmp) = (AttendScratch::default(), Vec::new());
            for task in tasks * p / parts..tasks * (p + 1) / parts {
                let (obs, head) = (task / heads, task % heads);
                let (n, start) = (counts[obs], starts[obs]);
                if n == 0 {
                    continue;
                }
                let (kt, v) = &packed[obs * kv_heads + head / groups];
                let segment = KvSegment {
                    keys_t: kt,
                    values: v,
                    causal: false,
                };
                tmp.resize(n * hd, 0.0);
                attend(
                    isa,
                    Queries::F32(MatRef::new(&qkv[start * ld + head * hd..], n, hd, ld)),
                    &[segment],
                    QueryPositions {
                        offset: 0,
                        period: n,
                    },
                    scale,
                    &mut scores,
                    MatMut::dense(&mut tmp, n, hd),
                );
                // SAFETY: this observation's rows of this head's columns are written by this
                // task only.
                unsafe { out.write_rows(&tmp, hd, qw, start, head * hd) };
            }
        });
    }
}
