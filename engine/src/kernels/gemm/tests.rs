//! The GEMM's results: against an f64 reference, against each other across kernels, thread
//! splits, batch sizes and ways of giving `A`, bit for bit where the order of operations is the
//! same.

use super::super::bf16::round_pairs;
use super::super::{AlignedBuf, Pool};
use super::driver::{COut, gemm_packed};
use super::*;

fn naive(a: &[f32], m: usize, k: usize, w: &[f32], n: usize) -> Vec<f32> {
    let mut c = vec![0.0f64; m * n];
    for i in 0..m {
        for j in 0..n {
            for kk in 0..k {
                c[i * n + j] += f64::from(a[i * k + kk]) * f64::from(w[j * k + kk]);
            }
        }
    }
    c.into_iter().map(|v| v as f32).collect()
}

fn data(len: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..len)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        })
        .collect()
}

#[test]
fn matches_naive_on_ragged_shapes_for_both_isas() {
    for &(m, k, n) in &[
        (1, 1, 1),
        (7, 300, 33),
        (50, 720, 40),
        (13, 5, 16),
        (121, 257, 17),
    ] {
        let a = data(m * k, 1);
        let w = data(n * k, 2);
        let bias = data(n, 3);
        let packed = PackedMatrix::from_linear_weight(&w, n, k);
        let want = naive(&a, m, k, &w, n);
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let pool = Pool::with_isa(2, isa).unwrap();
            let mut c = vec![f32::NAN; m * n];
            gemm_par(
                &pool,
                MatRef::dense(&a, m, k),
                &packed,
                MatMut::dense(&mut c, m, n),
                Init::Zero,
            );
            let mut cb = vec![0.0; m * n];
            gemm(
                isa,
                MatRef::dense(&a, m, k),
                &packed,
                MatMut::dense(&mut cb, m, n),
                Init::Bias(&bias),
            );
            gemm(
                isa,
                MatRef::dense(&a, m, k),
                &packed,
                MatMut::dense(&mut cb, m, n),
                Init::Accumulate,
            );
            let mut cab = cb.clone();
            gemm_par(
                &pool,
                MatRef::dense(&a, m, k),
                &packed,
                MatMut::dense(&mut cab, m, n),
                Init::AccumulateBias(&bias),
            );
            for i in 0..m * n {
                let tol = 1e-5 * (k as f32).sqrt();
                assert!(
                    (c[i] - want[i]).abs() <= tol,
                    "{m}x{k}x{n} {isa:?} [{i}] {} vs {}",
                    c[i],
                    want[i]
                );
                let wb = bias[i % n] + 2.0 * want[i];
                assert!(
                    (cb[i] - wb).abs() <= 2.0 * tol,
                    "bias+acc {m}x{k}x{n} [{i}]"
                );
                let wab = 2.0 * bias[i % n] + 3.0 * want[i];
                assert!(
                    (cab[i] - wab).abs() <= 3.0 * tol,
                    "acc+bias {m}x{k}x{n} [{i}]"
                );
            }
        }
    }
}

/// Which panels the paired kernel takes together depends on where a thread's panel range
/// starts; a range starting at an odd panel pairs them differently (and leaves panel 0 to
/// the one-panel kernel), so equal results mean the two kernels agree bit for bit.
/// `A` rounded into pair rows by the caller (with padding between rows) gives the same
/// bits as the GEMM rounding it itself, on one thread and split, over several `k` blocks
/// and an odd `k`.
#[test]
fn pair_rows_of_a_equal_packing_a_in_the_gemm() {
    for &(m, k, n) in &[(7, 300, 33), (13, 5, 80), (250, 601, 64), (1, 1, 17)] {
        let (a, w, bias) = (data(m * k, 7), data(n * k, 8), data(n, 9));
        let packed = PackedMatrix::from_linear_weight_in(Precision::Bf16, &w, n, k);
        let ldp = k.div_ceil(2) + 3;
        let mut pairs = vec![u32::MAX; m * ldp];
        for r in 0..m {
            let row = &mut pairs[r * ldp..r * ldp + k.div_ceil(2)];
            round_pairs(Isa::detect(), &a[r * k..(r + 1) * k], row);
        }
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let pool = Pool::with_isa(2, isa).unwrap();
            let mut want = vec![0.0; m * n];
            gemm(
                isa,
                MatRef::dense(&a, m, k),
                &packed,
                MatMut::dense(&mut want, m, n),
                Init::Bias(&bias),
            );
            let mut one = vec![0.0; m * n];
            gemm_pairs(
                isa,
                MatRef::new(&pairs, m, k.div_ceil(2), ldp),
                &packed,
                MatMut::dense(&mut one, m, n),
                Init::Bias(&bias),
            );
            let mut split = vec![0.0; m * n];
            gemm_par_pairs(
                &pool,
                MatRef::new(&pairs, m, k.div_ceil(2), ldp),
                &packed,
                MatMut::dense(&mut split, m, n),
                Init::Bias(&bias),
            );
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&one), bits(&want), "{isa:?} {m}x{k}x{n}");
            assert_eq!(bits(&split), bits(&want), "{isa:?} {m}x{k}x{n} split");
        }
    }
}

/// Activation rows made by a producer give the GEMM the bits of the f32 rows it makes,
/// in both precisions.
#[test]
fn activation_rows_equal_the_f32_rows_they_are_made_of() {
    let (m, k, n) = (37, 301, 48);
    let (a, w) = (data(m * k, 21), data(n * k, 22));
    for precision in [Precision::F32, Precision::Bf16] {
        let packed = PackedMatrix::from_linear_weight_in(precision, &w, n, k);
        let pool = Pool::new(2).unwrap();
        let mut rows = ActivationRows::new(precision, m + 3, k);
        rows.fill(&pool, m, |r, out| {
            out.copy_from_slice(&a[r * k..(r + 1) * k])
        });
        let mut got = vec![0.0; m * n];
        rows.gemm_par(&pool, &packed, MatMut::dense(&mut got, m, n), Init::Zero);
        let mut want = vec![0.0; m * n];
        gemm_par(
            &pool,
            MatRef::dense(&a, m, k),
            &packed,
            MatMut::dense(&mut want, m, n),
            Init::Zero,
        );
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got), bits(&want), "{precision:?}");
    }
}

/// The accumulators of a biased GEMM start from the bias in place: the same bits as
/// writing the bias into every row of C and accumulating, in both precisions, on edge
/// panels, paired panels and several `k` blocks.
#[test]
fn bias_start_equals_accumulating_onto_bias_rows() {
    for precision in [Precision::F32, Precision::Bf16] {
        for &(m, k, n) in &[(7, 300, 33), (13, 5, 80), (1, 600, 64), (50, 1, 17)] {
            let (a, w, bias) = (data(m * k, 4), data(n * k, 5), data(n, 6));
            let packed = PackedMatrix::from_linear_weight_in(precision, &w, n, k);
            for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
                .into_iter()
                .filter(|i| i.available())
            {
                let pool = Pool::with_isa(2, isa).unwrap();
                let mut want: Vec<f32> = (0..m * n).map(|i| bias[i % n]).collect();
                gemm(
                    isa,
                    MatRef::dense(&a, m, k),
                    &packed,
                    MatMut::dense(&mut want, m, n),
                    Init::Accumulate,
                );
                let mut got = vec![f32::NAN; m * n];
                gemm_par(
                    &pool,
                    MatRef::dense(&a, m, k),
                    &packed,
                    MatMut::dense(&mut got, m, n),
                    Init::Bias(&bias),
                );
                let (want, got): (Vec<u32>, Vec<u32>) = (
                    want.iter().map(|v| v.to_bits()).collect(),
                    got.iter().map(|v| v.to_bits()).collect(),
                );
                assert_eq!(got, want, "{precision:?} {isa:?} {m}x{k}x{n}");
            }
        }
    }
}

#[test]
fn paired_and_single_panel_kernels_agree_bit_for_bit() {
    let (m, k, n) = (13, 300, 5 * NR + 3);
    let a = data(m * k, 11);
    let w = data(n * k, 12);
    for precision in [Precision::F32, Precision::Bf16] {
        let packed = PackedMatrix::from_linear_weight_in(precision, &w, n, k);
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let mut pack_buf = AlignedBuf::default();
            let a_rows = MatRef::dense(&a, m, k);
            let pa = match precision {
                Precision::F32 => ASource::Rows(a_rows),
                Precision::Bf16 => pack_a_blocks(isa, a_rows, &mut pack_buf),
            };
            let panels = packed.panels();
            let mut whole = vec![0.0; m * n];
            let mut split = vec![0.0; m * n];
            let whole_out = COut::of(&mut MatMut::dense(&mut whole, m, n));
            let split_out = COut::of(&mut MatMut::dense(&mut split, m, n));
            // SAFETY: both outputs hold m rows of n values; one thread writes each.
            unsafe {
                gemm_packed(isa, pa, &packed, 0..panels, whole_out, Init::Zero);
                gemm_packed(isa, pa, &packed, 0..1, split_out, Init::Zero);
                gemm_packed(isa, pa, &packed, 1..panels, split_out, Init::Zero);
            }
            assert_eq!(whole, split, "{precision:?} {isa:?}");
            let reference = naive(&a, m, k, &w, n);
            let worst = whole
                .iter()
                .zip(&reference)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 0.1, "{precision:?} {isa:?}: off by {worst}");
        }
    }
}

#[test]
fn row_results_do_not_depend_on_m_or_threads() {
    let (k, n) = (701, 70);
    let a = data(50 * k, 4);
    let w = data(n * k, 5);
    for precision in [Precision::F32, Precision::Bf16] {
        let packed = PackedMatrix::from_linear_weight_in(precision, &w, n, k);
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let pool = Pool::with_isa(2, isa).unwrap();
            let mut full = vec![0.0; 50 * n];
            gemm_par(
                &pool,
                MatRef::dense(&a, 50, k),
                &packed,
                MatMut::dense(&mut full, 50, n),
                Init::Zero,
            );
            for start in [0, 7, 49] {
                let mut one = vec![0.0; n];
                gemm(
                    isa,
                    MatRef::dense(&a[start * k..], 1, k),
                    &packed,
                    MatMut::dense(&mut one, 1, n),
                    Init::Zero,
                );
                let want = &full[start * n..(start + 1) * n];
                assert_eq!(one, want, "{precision:?} {isa:?} row {start}");
            }
        }
    }
}

#[test]
fn avx512_and_avx2_kernels_agree_bit_for_bit() {
    // Both run one FMA per product in increasing k order, so they round identically.
    if !Isa::Avx512.available() {
        eprintln!("no AVX-512F on this CPU: only the ragged-shape test covers the others");
        return;
    }
    let (m, k, n) = (37, 300, 45);
    let a = data(m * k, 7);
    let w = data(n * k, 8);
    let packed = PackedMatrix::from_linear_weight(&w, n, k);
    let mut c512 = vec![0.0; m * n];
    let mut c2 = vec![0.0; m * n];
    gemm(
        Isa::Avx512,
        MatRef::dense(&a, m, k),
        &packed,
        MatMut::dense(&mut c512, m, n),
        Init::Zero,
    );
    gemm(
        Isa::Avx2Fma,
        MatRef::dense(&a, m, k),
        &packed,
        MatMut::dense(&mut c2, m, n),
        Init::Zero,
    );
    assert_eq!(c512, c2);
}

/// bf16 GEMM vs an f64 reference. Each operand is rounded to bf16 (relative error at most
/// u = 2^-9, round to nearest with 8 significand bits), the products of bf16 values are
/// exact in f32, and the f32 sum of k terms adds at most about k * 2^-24 of `sum |a||b|`:
/// so `|C - C_exact| <= (2u + u^2 + k 2^-24 (1 + 2u)) * sum_k |a_k||b_k|`, checked with a
/// 10% margin on the accumulation term. The result must also differ from the f32 GEMM (the
/// rounding happened).
#[test]
fn bf16_gemm_is_within_its_rounding_bound_of_f64() {
    let kernels: Vec<Isa> = [Isa::Avx512, Isa::Portable]
        .into_iter()
        .filter(|i| i.available())
        .collect();
    for &(m, k, n) in &[
        (1, 1, 1),
        (7, 301, 33),
        (13, 5, 16),
        (121, 257, 17),
        (50, 720, 40),
    ] {
        let a = data(m * k, 11);
        let w = data(n * k, 12);
        let bias = data(n, 13);
        let p32 = PackedMatrix::from_linear_weight(&w, n, k);
        let p16 = PackedMatrix::from_linear_weight_in(Precision::Bf16, &w, n, k);
        assert_eq!(p16.precision(), Precision::Bf16);
        let u = 2f64.powi(-9);
        let rel = 2.0 * u + u * u + 1.1 * k as f64 * 2f64.powi(-24) * (1.0 + 2.0 * u);
        for &isa in &kernels {
            let mut c = vec![f32::NAN; m * n];
            let pool = Pool::with_isa(2, isa).unwrap();
            gemm_par(
                &pool,
                MatRef::dense(&a, m, k),
                &p16,
                MatMut::dense(&mut c, m, n),
                Init::Bias(&bias),
            );
            let mut c32 = vec![0.0; m * n];
            gemm(
                isa,
                MatRef::dense(&a, m, k),
                &p32,
                MatMut::dense(&mut c32, m, n),
                Init::Bias(&bias),
            );
            let mut differs = false;
            for i in 0..m {
                for j in 0..n {
                    let (mut exact, mut mag) = (f64::from(bias[j]), f64::from(bias[j].abs()));
                    for kk in 0..k {
                        let p = f64::from(a[i * k + kk]) * f64::from(w[j * k + kk]);
                        exact += p;
                        mag += p.abs();
                    }
                    let got = f64::from(c[i * n + j]);
                    assert!(
                        (got - exact).abs() <= rel * mag + f64::from(f32::EPSILON) * mag,
                        "{m}x{k}x{n} {isa:?} [{i},{j}]: {got} vs {exact} (bound {})",
                        rel * mag
                    );
                    differs |= c[i * n + j] != c32[i * n + j];
                }
            }
            assert!(
                differs || k == 1,
                "{m}x{k}x{n} {isa:?}: bf16 equals f32 everywhere"
            );
        }
    }
}
