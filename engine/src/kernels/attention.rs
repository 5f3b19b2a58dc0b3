//! Scaled dot-product attention of one query head over keys given in segments.
//!
//! A segment is a block of keys and values packed for the GEMM ([`KvSegment`]): the keys as
//! `Kᵀ` (`head_dim x len`), the values as `V` (`len x head_dim`). The SmolVLA expert's keys are
//! the VLM prefix (packed once per request) followed, in self-attention layers, by the action
//! tokens of the current step (packed every step, causal). Keys that the attention mask hides
//! are simply absent from the segments: LeRobot's masked scores become exactly 0 after its
//! softmax, so leaving them out changes no sum.

use super::gemm::{Init, PackedMatrix, gemm, gemm_pairs};
use super::matrix::{MatMut, MatRef};
use super::{Isa, Precision, vecmath};

/// Keys and values of one attention segment.
#[derive(Clone, Copy, Debug)]
pub struct KvSegment<'a> {
    /// `Kᵀ`, packed: `k = head_dim`, `n = len`.
    pub keys_t: &'a PackedMatrix,
    /// `V`, packed: `k = len`, `n = head_dim`.
    pub values: &'a PackedMatrix,
    /// Causal segment: query `i` sees keys `0..=i` only (the segment is as long as the queries).
    pub causal: bool,
}

impl KvSegment<'_> {
    fn len(&self) -> usize {
        self.keys_t.n()
    }
}

/// Which keys of a causal segment query `i` sees: keys `0..=(offset + i) % period`. Query rows
/// may hold several heads' queries back to back (`period` rows each).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QueryPositions {
    /// Position of query row 0.
    pub offset: usize,
    /// Positions repeat every `period` rows.
    pub period: usize,
}

/// The query rows of [`attend`], `head_dim` values each.
#[derive(Clone, Copy, Debug)]
pub enum Queries<'a> {
    /// f32 rows (a head's columns read in place from `[q | k | v]` rows, with their stride);
    /// the `q kᵀ` GEMM rounds them to bf16 pairs when the keys are bf16.
    F32(MatRef<'a>),
    /// Rows already rounded to bf16 pairs ([`super::bf16::round_pairs`]), `head_dim / 2`
    /// pairs each: the same bits as the f32 rows they were rounded from (bf16 keys only).
    Pairs(MatRef<'a, u32>),
}

/// Scratch space of [`attend`], grown as needed and reused across calls.
#[derive(Debug, Default)]
pub struct AttendScratch {
    /// The scores (f32), `nq x total`; with f32 values the softmax turns them into the
    /// probabilities in place.
    scores: Vec<f32>,
    /// The softmax numerators rounded to bf16 pairs, per segment, for bf16 values.
    pairs: Vec<u32>,
    /// `1 / sum` of each query row's numerators, for bf16 values.
    factors: Vec<f32>,
}

/// `out[i] = softmax(scale * q[i] · Kᵀ) V` for the query rows of `q` over the concatenation of
/// `segments`: `out` has a row per query and `head_dim` columns (the keys' depth); `scale > 0`.
///
/// With bf16 values, the `P · V` GEMM takes the softmax *numerators* `exp(s - max)` rounded
/// to bf16 (made and rounded in registers, never stored as f32), and each output
/// row is then multiplied by `1 / sum` of its unrounded numerators: `(Σ bf16(e_j) v_j) / Σ e_j`.
/// Rounding `e_j` or `e_j / Σ e` to bf16 has the same relative error (2^-9); the numerators
/// just skip a pass that wrote the f32 probabilities and one that read them back to normalise
/// and round them.
///
/// # Panics
/// If `q` and `out` have different numbers of rows, or the queries' width is not the keys'
/// depth (`head_dim`, or `ceil(head_dim / 2)` pairs).
pub fn attend(
    isa: Isa,
    q: Queries<'_>,
    segments: &[KvSegment<'_>],
    positions: QueryPositions,
    scale: f32,
    scratch: &mut AttendScratch,
    mut out: MatMut<'_>,
) {
    let (nq, head_dim) = (out.rows(), out.cols());
    debug_assert!(segments.iter().all(|seg| seg.keys_t.k() == head_dim));
    let total: usize = segments.iter().map(KvSegment::len).sum();
    let scores = &mut scratch.scores;
    scores.resize(nq * total, 0.0);
    let mut col = 0;
    for seg in segments {
        let out = MatMut::new(&mut scores[col..], nq, seg.len(), total);
        match q {
            Queries::F32(rows) => gemm(isa, rows, seg.keys_t, out, Init::Zero),
            Queries::Pairs(rows) => gemm_pairs(isa, rows, seg.keys_t, out, Init::Zero),
        }
        col += seg.len();
    }
    let rounded = !segments.is_empty()
        && segments
            .iter()
            .all(|seg| seg.values.precision() == Precision::Bf16);
    // Segment `s`'s rounded numerators: `nq` rows of `ceil(len / 2)` pairs from `offset`.
    let pair_rows = |s: usize| {
        let offset: usize = segments[..s].iter().map(|g| nq * g.len().div_ceil(2)).sum();
        (offset, segments[s].len().div_ceil(2))
    };
    if rounded {
        let (end, last) = pair_rows(segments.len() - 1);
        scratch.pairs.resize(end + nq * last, 0);
        scratch.factors.resize(nq, 0.0);
    }
    for i in 0..nq {
        let row = &mut scores[i * total..(i + 1) * total];
        // Visible keys form a prefix of the row when only the last segment is causal, which is
        // how the expert uses it; hidden causal entries are zeroed after the softmax.
        let visible = visible_len(
            segments,
            (positions.offset + i) % positions.period.max(1),
            total,
        );
        if !rounded {
            let (seen, hidden) = row.split_at_mut(visible);
            vecmath::softmax_scaled(isa, seen, scale);
            hidden.fill(0.0);
            continue;
        }
        // bf16 values: the numerators are made and rounded into the pairs in registers (never
        // stored as f32, see `exp_sum_round_into`), and `P · V` is scaled by
        // `1 / sum` after the GEMM, on `head_dim` values per row instead of `total`.
        let max = vecmath::max_scaled(isa, &row[..visible], scale);
        let mut lanes = [0.0f32; 32];
        let mut col = 0;
        for (s, seg) in segments.iter().enumerate() {
            let (offset, ldp) = pair_rows(s);
            let dst = &mut scratch.pairs[offset + i * ldp..offset + (i + 1) * ldp];
            let shown = visible.saturating_sub(col).min(seg.len());
            let (seen, hidden) = dst.split_at_mut(shown.div_ceil(2));
            let src = &row[col..col + shown];
            vecmath::exp_sum_round_into(isa, src, scale, max, seen, &mut lanes);
            // Keys this query does not see (a causal segment's tail) weigh exactly zero.
            hidden.fill(0);
            col += seg.len();
        }
        scratch.factors[i] = 1.0 / vecmath::sum_32_lanes(&lanes);
    }
    let mut col = 0;
    for (s, seg) in segments.iter().enumerate() {
        let init = if s == 0 { Init::Zero } else { Init::Accumulate };
        if rounded {
            let (offset, ldp) = pair_rows(s);
            let pairs = MatRef::dense(&scratch.pairs[offset..offset + nq * ldp], nq, ldp);
            gemm_pairs(isa, pairs, seg.values, out.reborrow(), init);
        } else {
            let probabilities = MatRef::new(&scores[col..], nq, seg.len(), total);
            gemm(isa, probabilities, seg.values, out.reborrow(), init);
        }
        col += seg.len();
    }
    if rounded {
        for (i, &factor) in scratch.factors.iter().enumerate() {
            vecmath::scale_assign(isa, out.row_mut(i), factor);
        }
    }
}

fn visible_len(segments: &[KvSegment<'_>], query: usize, total: usize) -> usize {
    match segments.last() {
        Some(last) if last.causal => total - last.len() + (query + 1).min(last.len()),
        _ => total,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(len: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    /// Keys and values of a non-causal prefix segment (`lp` keys) and of a causal segment
    /// (`nq` keys), packed in `precision`: `[(keys_t, values); 2]`.
    fn packed_segments(
        precision: Precision,
        (kp, vp): (&[f32], &[f32]),
        (ks, vs): (&[f32], &[f32]),
        d: usize,
    ) -> [(PackedMatrix, PackedMatrix); 2] {
        let isa = Isa::detect();
        let pack = |k: &[f32], v: &[f32]| {
            let len = k.len() / d;
            let (mut kt, mut vv) = (
                PackedMatrix::empty_in(precision),
                PackedMatrix::empty_in(precision),
            );
            kt.pack_transposed(isa, MatRef::dense(k, len, d));
            vv.pack_rows(isa, MatRef::dense(v, len, d));
            (kt, vv)
        };
        [pack(kp, vp), pack(ks, vs)]
    }

    /// [`packed_segments`] as attention segments, the second one causal.
    fn segments(packed: &[(PackedMatrix, PackedMatrix); 2]) -> [KvSegment<'_>; 2] {
        [false, true].map(|causal| {
            let (keys_t, values) = &packed[usize::from(causal)];
            KvSegment {
                keys_t,
                values,
                causal,
            }
        })
    }

    /// With bf16 values the numerators are made and rounded 32 at a time (or a chunk at a time
    /// without AVX512_BF16) and `P · V` is normalised afterwards; the result has the bits of
    /// the plain sequence (each segment's numerators in one pass, stored as f32, the GEMM
    /// rounding them, then each row times `1 / sum`), over an odd-length segment longer than
    /// a chunk followed by a causal one.
    #[test]
    fn bf16_numerators_rounded_in_chunks_equal_the_pass_by_pass_definition() {
        let (d, lp, nq) = (16, 2 * 256 + 37, 5);
        let isa = Isa::detect();
        let q = data(nq * d, 11);
        let (kp, vp, ks, vs) = (
            data(lp * d, 12),
            data(lp * d, 13),
            data(nq * d, 14),
            data(nq * d, 15),
        );
        let packed = packed_segments(Precision::Bf16, (&kp, &vp), (&ks, &vs), d);
        let segs = segments(&packed);
        let [(pk, pv), (sk, sv)] = &packed;
        let pos = QueryPositions {
            offset: 0,
            period: nq,
        };
        let mut got = vec![0.0; nq * d];
        let mut scratch = AttendScratch::default();
        attend(
            isa,
            Queries::F32(MatRef::dense(&q, nq, d)),
            &segs,
            pos,
            0.25,
            &mut scratch,
            MatMut::dense(&mut got, nq, d),
        );

        let total = lp + nq;
        let mut s = vec![0.0; nq * total];
        gemm(
            isa,
            MatRef::dense(&q, nq, d),
            pk,
            MatMut::new(&mut s, nq, lp, total),
            Init::Zero,
        );
        gemm(
            isa,
            MatRef::dense(&q, nq, d),
            sk,
            MatMut::new(&mut s[lp..], nq, nq, total),
            Init::Zero,
        );
        let mut e = vec![0.0; nq * total];
        let mut factors = vec![0.0; nq];
        for i in 0..nq {
            let (row, num) = (&s[i * total..(i + 1) * total], &mut e[i * total..]);
            let seen = lp + i + 1;
            let max = vecmath::max_scaled(isa, &row[..seen], 0.25);
            let mut lanes = [0.0f32; 32];
            for range in [0..lp, lp..seen] {
                let (src, dst) = (&row[range.clone()], &mut num[range]);
                vecmath::exp_sum_into(isa, src, 0.25, max, dst, &mut lanes);
            }
            factors[i] = 1.0 / vecmath::sum_32_lanes(&lanes);
        }
        let mut want = vec![0.0; nq * d];
        gemm(
            isa,
            MatRef::new(&e, nq, lp, total),
            pv,
            MatMut::dense(&mut want, nq, d),
            Init::Zero,
        );
        gemm(
            isa,
            MatRef::new(&e[lp..], nq, nq, total),
            sv,
            MatMut::dense(&mut want, nq, d),
            Init::Accumulate,
        );
        for (row, f) in want.chunks_exact_mut(d).zip(&factors) {
            row.iter_mut().for_each(|v| *v *= f);
        }
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&want));
        // Queries given already rounded to pairs (row stride 3 pairs wider): the same bits.
        let ldp = d / 2 + 3;
        let mut q_pairs = vec![0u32; nq * ldp];
        for (row, dst) in q.chunks_exact(d).zip(q_pairs.chunks_exact_mut(ldp)) {
            crate::kernels::bf16::round_pairs(isa, row, &mut dst[..d / 2]);
        }
        let mut from_pairs = vec![0.0; nq * d];
        attend(
            isa,
            Queries::Pairs(MatRef::new(&q_pairs, nq, d / 2, ldp)),
            &segs,
            pos,
            0.25,
            &mut scratch,
            MatMut::dense(&mut from_pairs, nq, d),
        );
        assert_eq!(bits(&from_pairs), bits(&got), "queries as pairs");
        // And it is the softmax: within bf16 rounding of the f32 result.
        let packed32 = packed_segments(Precision::F32, (&kp, &vp), (&ks, &vs), d);
        let mut exact = vec![0.0; nq * d];
        let mut scratch = AttendScratch::default();
        let segs32 = segments(&packed32);
        attend(
            isa,
            Queries::F32(MatRef::dense(&q, nq, d)),
            &segs32,
            pos,
            0.25,
            &mut scratch,
            MatMut::dense(&mut exact, nq, d),
        );
        let worst = got
            .iter()
            .zip(&exact)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(worst < 2e-2, "bf16 attention off by {worst}");
    }

    #[test]
    fn matches_masked_softmax_reference() {
        let (d, lp, nq) = (16, 11, 5);
        let q = data(nq * d, 1);
        let kp = data(lp * d, 2);
        let vp = data(lp * d, 3);
        let ks = data(nq * d, 4);
        let vs = data(nq * d, 5);
        let packed = packed_segments(Precision::F32, (&kp, &vp), (&ks, &vs), d);
        let segs = segments(&packed);
        let mut out = vec![0.0; nq * d];
        let pos = QueryPositions {
            offset: 0,
            period: nq,
        };
        attend(
            Isa::detect(),
            Queries::F32(MatRef::dense(&q, nq, d)),
            &segs,
            pos,
            0.25,
            &mut AttendScratch::default(),
            MatMut::dense(&mut out, nq, d),
        );
        // Two heads' queries back to back: each row sees what its position allows.
        let q2: Vec<f32> = q.iter().chain(&q).copied().collect();
        let mut out2 = vec![0.0; 2 * nq * d];
        attend(
            Isa::detect(),
            Queries::F32(MatRef::dense(&q2, 2 * nq, d)),
            &segs,
            pos,
            0.25,
            &mut AttendScratch::default(),
            MatMut::dense(&mut out2, 2 * nq, d),
        );
        assert_eq!(out2[..nq * d], out[..]);
        assert_eq!(out2[nq * d..], out[..]);
        for i in 0..nq {
            let keys: Vec<(&[f32], &[f32])> = (0..lp)
                .map(|j| (&kp[j * d..(j + 1) * d], &vp[j * d..(j + 1) * d]))
                .chain((0..=i).map(|j| (&ks[j * d..(j + 1) * d], &vs[j * d..(j + 1) * d])))
                .collect();
            let s: Vec<f64> = keys
                .iter()
                .map(|(k, _)| {
                    0.25 * (0..d)
                        .map(|t| f64::from(q[i * d + t]) * f64::from(k[t]))
                        .sum::<f64>()
                })
                .collect();
            let max = s.iter().cloned().fold(f64::MIN, f64::max);
            let z: f64 = s.iter().map(|v| (v - max).exp()).sum();
            for t in 0..d {
                let want: f64 = keys
                    .iter()
                    .zip(&s)
                    .map(|((_, v), sc)| (sc - max).exp() / z * f64::from(v[t]))
                    .sum();
                assert!((f64::from(out[i * d + t]) - want).abs() < 1e-5, "q{i} d{t}");
            }
        }
    }
}
