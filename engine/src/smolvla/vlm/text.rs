//! SmolVLM's text layers (SmolLM2, Llama-style) over the SmolVLA prefix, on the engine's CPU
//! kernels, producing the [`crate::smolvla::PrefixKv`] the expert consumes.
//!
//! LeRobot's prefix prefill (`VLAFlowMatching.sample_actions` -> `SmolVLMWithExpertModel.forward`
//! with `fill_kv_cache=True`) runs every kept text layer as self-attention over the prefix
//! `[image tokens ; language tokens ; state token]`, with
//! - positions `cumsum(pad_mask) - 1` and LeRobot's own RoPE (`apply_rope`, wavelength 10 000,
//!   not the text config's `rope_theta`);
//! - the mask of `make_att_2d_masks(pad, att)` with `att = [0 .. 0, 1]`: image and language
//!   tokens see every valid image and language token, the state token sees every valid token,
//!   and nothing sees padding.
//!
//! So padding tokens never influence a valid one: this module runs the valid tokens only (in
//! order, which makes their positions `0..n`) and leaves zeros at padding positions of the
//! cache, which the expert never reads. The K/V of the last layer are all the expert needs from
//! it, so its attention output and MLP are skipped; `text_model.norm` is never needed.

use crate::kernels::attention::{AttendScratch, KvSegment, Queries, QueryPositions, attend};
use crate::kernels::gemm::{ActivationRows, gemm_par};
use crate::kernels::{Init, MatMut, MatRef, PackedMatrix, Pool, Precision, SharedMut, vecmath};
use crate::smolvla::config::VlmTextConfig;
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::llama_layer::LayerWeights;
use crate::weights::StoredTensor;

struct TextLayer {
    input_norm: Vec<f32>,
    post_norm: Vec<f32>,
    /// `[q | k | v]` in one GEMM.
    qkv: PackedMatrix,
    o: PackedMatrix,
    /// `[gate | up]` in one GEMM.
    gate_up: PackedMatrix,
    down: PackedMatrix,
}

/// The packed text layers.
pub(crate) struct CpuText {
    config: VlmTextConfig,
    layers: Vec<TextLayer>,
    /// The precision of the weight GEMMs, also that of the attention GEMMs.
    precision: Precision,
}

/// The valid tokens of one observation's prefix: `[tokens][hidden]` embeddings, the last being
/// the state token (which alone sees the state token).
pub(crate) struct ValidPrefix<'a> {
    /// Embeddings of the valid tokens, in prefix order.
    pub(crate) embeddings: &'a [f32],
}

/// Per-layer keys and values of the valid tokens (post-RoPE), `[layer][tokens][kv width]`.
pub(crate) struct ValidKv {
    pub(crate) keys: Vec<Vec<f32>>,
    pub(crate) values: Vec<Vec<f32>>,
}

impl CpuText {
    /// Pack `layers`, the weight GEMMs in `precision` (already resolved for this CPU), straight
    /// from the stored tensors; each layer's are dropped once packed.
    pub(crate) fn new(
        config: &VlmTextConfig,
        layers: Vec<LayerWeights<StoredTensor>>,
        precision: Precision,
    ) -> Self {
        let layers = layers
            .into_iter()
            .map(|l| TextLayer {
                qkv: LinearWeights::pack_stacked(precision, &[&l.q_proj, &l.k_proj, &l.v_proj]),
                gate_up: LinearWeights::pack_stacked(precision, &[&l.gate_proj, &l.up_proj]),
                input_norm: l.input_norm,
                post_norm: l.post_norm,
                o: l.o_proj.into_linear(precision).w,
                down: l.down_proj.into_linear(precision).w,
            })
            .collect();
        CpuText {
            config: config.clone(),
            layers,
            precision,
        }
    }

    /// Number of text layers.
    pub(crate) fn layers(&self) -> usize {
        self.layers.len()
    }

    /// Run the layers over every observation's valid tokens at once (one GEMM per projection
    /// for the whole batch; attention per observation).
    pub(crate) fn forward(&self, pool: &Pool, prefixes: &[ValidPrefix<'_>]) -> Vec<ValidKv> {
        let c = &self.config;
        let (h, hd) = (c.hidden_size, c.head_dim);
        let (qw, kvw) = (c.num_attention_heads * hd, c.num_key_value_heads * hd);
        let ld = qw + 2 * kvw;
        let counts: Vec<usize> = prefixes.iter().map(|p| p.embeddings.len() / h).collect();
        let starts = super::starts(&counts);
        let rows: usize = counts.iter().sum();
        let mut out: Vec<ValidKv> = counts
            .iter()
            .map(|_| ValidKv {
                keys: Vec::with_capacity(self.layers.len()),
                values: Vec::with_capacity(self.layers.len()),
            })
            .collect();
        let mut x: Vec<f32> = prefixes
            .iter()
            .flat_map(|p| p.embeddings.iter().copied())
            .collect();
        // RoPE tables: valid token t of an observation is at position t.
        let half = hd / 2;
        let longest = counts.iter().copied().max().unwrap_or(0);
        let (mut cos, mut sin) = (vec![0.0f32; longest * half], vec![0.0f32; longest * half]);
        for t in 0..longest {
            vecmath::rope_table(
                t as f32,
                hd,
                &mut cos[t * half..(t + 1) * half],
                &mut sin[t * half..(t + 1) * half],
            );
        }
        let eps = c.rms_norm_eps as f32;
        let inter = c.intermediate_size;
        let mut qkv = vec![0.0f32; rows * ld];
        let mut attn = vec![0.0f32; rows * qw];
        let mut gate_up = vec![0.0f32; rows * 2 * inter];
        // The norms and SiLU make the `A` of the GEMM they feed (see `ActivationRows`).
        let mut normed = ActivationRows::new(self.precision, rows, h);
        let mut act = ActivationRows::new(self.precision, rows, inter);
        let isa = pool.isa();
        let norm = |x: &[f32], weight: &[f32], normed: &mut ActivationRows| {
            normed.fill(pool, rows, |r, out| {
                vecmath::rms_norm(isa, &x[r * h..(r + 1) * h], weight, eps, out);
            });
        };
        let last = self.layers.len().saturating_sub(1);
        for (l, layer) in self.layers.iter().enumerate() {
            norm(&x, &layer.input_norm, &mut normed);
            let qkv_rows = MatMut::dense(&mut qkv, rows, ld);
            normed.gemm_par(pool, &layer.qkv, qkv_rows, Init::Zero);
            for (&n, &start) in counts.iter().zip(&starts) {
                for t in 0..n {
                    let (cs, sn) = (&cos[t * half..][..half], &sin[t * half..][..half]);
                    let tok = &mut qkv[(start + t) * ld..][..ld];
                    for head in tok[..qw + kvw].chunks_exact_mut(hd) {
                        vecmath::rope(isa, head, cs, sn);
                    }
                }
            }
            for ((o, &n), &start) in out.iter_mut().zip(&counts).zip(&starts) {
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
            let (heads, residual) = (
                MatRef::dense(&attn, rows, qw),
                MatMut::dense(&mut x, rows, h),
            );
            gemm_par(pool, heads, &layer.o, residual, Init::Accumulate);
            norm(&x, &layer.post_norm, &mut normed);
            let gate_up_rows = MatMut::dense(&mut gate_up, rows, 2 * inter);
            normed.gemm_par(pool, &layer.gate_up, gate_up_rows, Init::Zero);
            act.fill(pool, rows, |r, out| {
                let (g, u) = gate_up[r * 2 * inter..(r + 1) * 2 * inter].split_at(inter);
                vecmath::silu_mul(isa, g, u, out);
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

    /// Attention per observation and query head: tokens `0..n-1` see tokens `0..n-1`; the state
    /// token `n-1` sees all `n`.
    fn attention(
        &self,
        pool: &Pool,
        qkv: &[f32],
        counts: &[usize],
        starts: &[usize],
        attn: &mut [f32],
    ) {
        let c = &self.config;
        let (heads, kv_heads, hd) = (c.num_attention_heads, c.num_key_value_heads, c.head_dim);
        let (qw, kvw) = (heads * hd, kv_heads * hd);
        let ld = qw + 2 * kvw;
        let groups = heads / kv_heads;
        let scale = (hd as f64).powf(-0.5) as f32;
        let tasks = counts.len() * kv_heads;
        let parts = pool.parts_per_unit(tasks);
        let out = SharedMut::new(attn);
        let isa = pool.isa();
        pool.run(parts, |part| {
            let (mut scores, mut tmp) = (AttendScratch::default(), Vec::new());
            let mut packed: [PackedMatrix; 4] =
                std::array::from_fn(|_| PackedMatrix::empty_in(self.precision));
            for task in tasks * part / parts..tasks * (part + 1) / parts {
                let (obs, g) = (task / kv_heads, task % kv_heads);
                let (n, start) = (counts[obs], starts[obs]);
                if n == 0 {
                    continue;
                }
                let base = &qkv[start * ld..(start + n) * ld];
                let main = n - 1;
                let [mk, mv, sk, sv] = &mut packed;
                let k0 = qw + g * hd;
                let v0 = qw + kvw + g * hd;
                mk.pack_transposed(isa, MatRef::new(&base[k0..], main, hd, ld));
                mv.pack_rows(isa, MatRef::new(&base[v0..], main, hd, ld));
                sk.pack_transposed(isa, MatRef::new(&base[main * ld + k0..], 1, hd, ld));
                sv.pack_rows(isa, MatRef::new(&base[main * ld + v0..], 1, hd, ld));
                let main_seg = KvSegment {
                    keys_t: mk,
                    values: mv,
                    causal: false,
                };
                let state_seg = KvSegment {
                    keys_t: sk,
                    values: sv,
                    causal: false,
                };
                for head in g * groups..(g + 1) * groups {
                    // This head's queries, read in place from the `[q | k | v]` rows.
                    let q = &base[head * hd..];
                    tmp.resize(n * hd, 0.0);
                    let all = QueryPositions {
                        offset: 0,
                        period: n,
                    };
                    if main > 0 {
                        attend(
                            isa,
                            Queries::F32(MatRef::new(q, main, hd, ld)),
                            &[main_seg],
                            all,
                            scale,
                            &mut scores,
                            MatMut::dense(&mut tmp, main, hd),
                        );
                    }
                    let (both, only) = ([main_seg, state_seg], [state_seg]);
                    let segs: &[KvSegment<'_>] = if main > 0 { &both } else { &only };
                    attend(
                        isa,
                        Queries::F32(MatRef::new(&q[main * ld..], 1, hd, ld)),
                        segs,
                        all,
                        scale,
                        &mut scores,
                        MatMut::dense(&mut tmp[main * hd..], 1, hd),
                    );
                    // SAFETY: this observation's rows of this head's columns are written by
                    // this task only.
                    unsafe { out.write_rows(&tmp, hd, qw, start, head * hd) };
                }
            }
        });
    }
}
