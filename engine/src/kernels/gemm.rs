//! `C = init + A · B` in f32 with `B` packed once into column panels.
//!
//! `A` is any row-major matrix (an activation, read in place); `B` is a [`PackedMatrix`]: the
//! right operand cut into panels of [`NR`] columns, each panel stored as `k` rows of `NR`
//! contiguous floats, 64-byte aligned. The micro-kernel keeps an `MR x NR` block of `C` in 12
//! AVX2 registers and streams one panel row (two vector loads) and `MR` broadcasts of `A` per
//! step of `k`: 12 FMAs per 8 loads. Blocking: `KC` rows of a panel (16 KiB) stay in L1 while all
//! row tiles of an `MC`-row block of `A` (in L2) pass over them.
//!
//! Every element of `C` accumulates its `k` products in increasing `k` order, one FMA each, in
//! `KC`-sized blocks. That order depends on neither `m`, the row tile an element falls in, nor
//! the thread split, so results do not depend on the batch size.

use std::ops::Range;

use super::{AlignedBuf, Isa, Pool, SharedMut};

/// Columns per packed panel (two AVX2 vectors).
pub const NR: usize = 16;
/// Rows per micro-kernel tile.
pub const MR: usize = 6;
/// Depth of one cache block.
const KC: usize = 256;
/// Rows of `A` per cache block (a multiple of `MR`).
const MC: usize = 120;

/// The right-hand operand of a GEMM, packed into `NR`-column panels.
#[derive(Clone, Debug, Default)]
pub struct PackedMatrix {
    k: usize,
    n: usize,
    buf: AlignedBuf,
}

impl PackedMatrix {
    /// Pack the weight of a PyTorch `Linear` (`w` is `[n][k]`, out x in, row-major) so that
    /// `A · B = A · wᵀ`, i.e. `y = x wᵀ`.
    pub fn from_linear_weight(w: &[f32], n: usize, k: usize) -> Self {
        let mut p = PackedMatrix::default();
        p.pack_transposed(w, k, n, k);
        p
    }

    /// Pack several `Linear` weights with the same input size side by side (`[w0; w1; ..]` along
    /// the output dimension), e.g. the q, k and v projections into one GEMM.
    pub fn from_linear_weights(ws: &[(&[f32], usize)], k: usize) -> Self {
        let n: usize = ws.iter().map(|(_, n)| n).sum();
        let mut stacked = Vec::with_capacity(n * k);
        for (w, rows) in ws {
            stacked.extend_from_slice(&w[..rows * k]);
        }
        Self::from_linear_weight(&stacked, n, k)
    }

    /// Depth (rows of `B`).
    pub fn k(&self) -> usize {
        self.k
    }

    /// Width (columns of `B`).
    pub fn n(&self) -> usize {
        self.n
    }

    fn panels(&self) -> usize {
        self.n.div_ceil(NR)
    }

    fn resize(&mut self, k: usize, n: usize) {
        self.k = k;
        self.n = n;
        self.buf.ensure(n.div_ceil(NR) * NR * k);
    }

    /// Pack `B` given as `k` rows of `n` values with row stride `ldb`. Reuses the allocation.
    pub fn pack_rows(&mut self, b: &[f32], ldb: usize, k: usize, n: usize) {
        self.resize(k, n);
        let panels = self.panels();
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let w = NR.min(n - c0);
            let panel = &mut dst[p * k * NR..(p + 1) * k * NR];
            for kk in 0..k {
                let row = &mut panel[kk * NR..kk * NR + NR];
                row[..w].copy_from_slice(&b[kk * ldb + c0..kk * ldb + c0 + w]);
                row[w..].fill(0.0);
            }
        }
    }

    /// Pack `B = wᵀ` where `w` has `n` rows of `k` values with row stride `ldw`. Reuses the
    /// allocation.
    pub fn pack_transposed(&mut self, w: &[f32], ldw: usize, n: usize, k: usize) {
        self.resize(k, n);
        let panels = self.panels();
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            let panel = &mut dst[p * k * NR..(p + 1) * k * NR];
            for j in 0..NR {
                if j < width {
                    let src = &w[(c0 + j) * ldw..(c0 + j) * ldw + k];
                    for (kk, &v) in src.iter().enumerate() {
                        panel[kk * NR + j] = v;
                    }
                } else {
                    for kk in 0..k {
                        panel[kk * NR + j] = 0.0;
                    }
                }
            }
        }
    }

    fn panel_ptr(&self, p: usize, k0: usize) -> *const f32 {
        self.buf.as_slice()[p * self.k * NR + k0 * NR..].as_ptr()
    }
}

/// What `C` starts from.
#[derive(Clone, Copy, Debug)]
pub enum Init<'a> {
    /// `C = A · B`.
    Zero,
    /// `C += A · B` (residual connections).
    Accumulate,
    /// `C = bias + A · B`, `bias` broadcast over rows (`n` values).
    Bias(&'a [f32]),
}

/// `C[..m][..n] = init + A[..m][..k] · B` on the calling thread, with `isa`'s kernels. `A` has row stride `lda`, `C`
/// row stride `ldc`.
#[allow(clippy::too_many_arguments)]
pub fn gemm(
    isa: Isa,
    a: &[f32],
    lda: usize,
    m: usize,
    b: &PackedMatrix,
    c: &mut [f32],
    ldc: usize,
    init: Init<'_>,
) {
    check(a, lda, m, b, c, ldc, init);
    // SAFETY: `check` verified every access stays inside `a` and `c`; one thread owns all of `c`.
    unsafe { gemm_panels(isa, a, lda, m, b, 0..b.panels(), c.as_mut_ptr(), ldc, init) }
}

/// [`gemm`] with the output columns split across the pool's threads.
#[allow(clippy::too_many_arguments)]
pub fn gemm_par(
    pool: &Pool,
    a: &[f32],
    lda: usize,
    m: usize,
    b: &PackedMatrix,
    c: &mut [f32],
    ldc: usize,
    init: Init<'_>,
) {
    check(a, lda, m, b, c, ldc, init);
    let panels = b.panels();
    let parts = pool.threads().min(panels).max(1);
    let out = SharedMut::new(c);
    pool.run(parts, |t| {
        let range = panels * t / parts..panels * (t + 1) / parts;
        // SAFETY: `check` verified the bounds; part `t` writes only the columns of its panels.
        unsafe { gemm_panels(pool.isa(), a, lda, m, b, range, out.ptr(), ldc, init) }
    });
}

fn check(a: &[f32], lda: usize, m: usize, b: &PackedMatrix, c: &[f32], ldc: usize, init: Init<'_>) {
    if m == 0 || b.n == 0 {
        return;
    }
    assert!(lda >= b.k && ldc >= b.n, "gemm strides too small");
    assert!(a.len() >= (m - 1) * lda + b.k, "gemm: A too short");
    assert!(c.len() >= (m - 1) * ldc + b.n, "gemm: C too short");
    if let Init::Bias(bias) = init {
        assert!(bias.len() >= b.n, "gemm: bias too short");
    }
}

/// # Safety
/// `a` holds `m` rows of stride `lda` with at least `b.k` values each, `c` points to `m` rows of
/// stride `ldc` with at least `b.n` values each, and no other thread touches the columns of
/// `panels` in those rows.
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_panels(
    isa: Isa,
    a: &[f32],
    lda: usize,
    m: usize,
    b: &PackedMatrix,
    panels: Range<usize>,
    c: *mut f32,
    ldc: usize,
    init: Init<'_>,
) {
    let k = b.k;
    if m == 0 || panels.is_empty() {
        return;
    }
    // Initialise C: the first K block then always accumulates.
    for p in panels.clone() {
        let c0 = p * NR;
        let w = NR.min(b.n - c0);
        for r in 0..m {
            // SAFETY: row r, columns c0..c0+w are inside C and owned by this call.
            let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc + c0), w) };
            match init {
                Init::Zero => row.fill(0.0),
                Init::Accumulate => {}
                Init::Bias(bias) => row.copy_from_slice(&bias[c0..c0 + w]),
            }
        }
    }
    if k == 0 {
        return;
    }
    let mut m0 = 0;
    while m0 < m {
        let mb = MC.min(m - m0);
        let mut k0 = 0;
        while k0 < k {
            let kc = KC.min(k - k0);
            for p in panels.clone() {
                let c0 = p * NR;
                let w = NR.min(b.n - c0);
                let bp = b.panel_ptr(p, k0);
                let mut r0 = 0;
                while r0 < mb {
                    let rows = MR.min(mb - r0);
                    let ap = a[(m0 + r0) * lda + k0..].as_ptr();
                    // SAFETY: the tile lies inside C (rows m0+r0.., columns c0..c0+w).
                    let cp = unsafe { c.add((m0 + r0) * ldc + c0) };
                    // SAFETY: A rows and the panel hold kc values from k0; C as above.
                    unsafe { tile(isa, rows, kc, ap, lda, bp, cp, ldc, w) };
                    r0 += rows;
                }
            }
            k0 += kc;
        }
        m0 += mb;
    }
}

/// One `rows x w` tile (`rows <= MR`, `w <= NR`): `C += A · B` over `kc`.
///
/// # Safety
/// `a` has `rows` rows of stride `lda` with `kc` values, `b` has `kc` rows of `NR` values, `c`
/// has `rows` rows of stride `ldc` with `w` values.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(
    isa: Isa,
    rows: usize,
    kc: usize,
    a: *const f32,
    lda: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    w: usize,
) {
    if w < NR {
        // Edge panel: run the full-width kernel on a scratch tile, copy the valid columns.
        let mut scratch = [0.0f32; MR * NR];
        for r in 0..rows {
            for j in 0..w {
                // SAFETY: inside the caller's C tile.
                scratch[r * NR + j] = unsafe { *c.add(r * ldc + j) };
            }
        }
        // SAFETY: scratch is a full MR x NR tile.
        unsafe { tile(isa, rows, kc, a, lda, b, scratch.as_mut_ptr(), NR, NR) };
        for r in 0..rows {
            for j in 0..w {
                // SAFETY: inside the caller's C tile.
                unsafe { *c.add(r * ldc + j) = scratch[r * NR + j] };
            }
        }
        return;
    }
    macro_rules! dispatch {
        ($f:ident) => {
            match rows {
                6 => $f::<6>(kc, a, lda, b, c, ldc),
                5 => $f::<5>(kc, a, lda, b, c, ldc),
                4 => $f::<4>(kc, a, lda, b, c, ldc),
                3 => $f::<3>(kc, a, lda, b, c, ldc),
                2 => $f::<2>(kc, a, lda, b, c, ldc),
                _ => $f::<1>(kc, a, lda, b, c, ldc),
            }
        };
    }
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Isa::Avx2Fma is only reported when the CPU has AVX2 and FMA.
        Isa::Avx2Fma => unsafe { dispatch!(kernel_avx2) },
        // SAFETY: same pointer contract.
        _ => unsafe { dispatch!(kernel_portable) },
    }
}

/// # Safety
/// See [`tile`]; requires AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn kernel_avx2<const R: usize>(
    kc: usize,
    a: *const f32,
    lda: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
) {
    use std::arch::x86_64::*;
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    for (r, row) in acc.iter_mut().enumerate() {
        // SAFETY: row r of the C tile has NR values.
        unsafe {
            row[0] = _mm256_loadu_ps(c.add(r * ldc));
            row[1] = _mm256_loadu_ps(c.add(r * ldc + 8));
        }
    }
    let mut ap = [a; R];
    for (r, p) in ap.iter_mut().enumerate() {
        // SAFETY: row r of A.
        *p = unsafe { a.add(r * lda) };
    }
    let mut bp = b;
    for kk in 0..kc {
        // SAFETY: kk < kc: inside the panel rows and the A rows.
        unsafe {
            let b0 = _mm256_load_ps(bp);
            let b1 = _mm256_load_ps(bp.add(8));
            for r in 0..R {
                let av = _mm256_broadcast_ss(&*ap[r].add(kk));
                acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
                acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
            }
            bp = bp.add(NR);
        }
    }
    for (r, row) in acc.iter().enumerate() {
        // SAFETY: row r of the C tile has NR values.
        unsafe {
            _mm256_storeu_ps(c.add(r * ldc), row[0]);
            _mm256_storeu_ps(c.add(r * ldc + 8), row[1]);
        }
    }
}

/// # Safety
/// See [`tile`].
unsafe fn kernel_portable<const R: usize>(
    kc: usize,
    a: *const f32,
    lda: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
) {
    let mut acc = [[0.0f32; NR]; R];
    for (r, row) in acc.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            // SAFETY: row r of the C tile has NR values.
            *v = unsafe { *c.add(r * ldc + j) };
        }
    }
    for kk in 0..kc {
        // SAFETY: kk < kc: inside the panel.
        let brow = unsafe { std::slice::from_raw_parts(b.add(kk * NR), NR) };
        for (r, row) in acc.iter_mut().enumerate() {
            // SAFETY: inside row r of A.
            let av = unsafe { *a.add(r * lda + kk) };
            for (v, &bv) in row.iter_mut().zip(brow) {
                *v += av * bv;
            }
        }
    }
    for (r, row) in acc.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            // SAFETY: row r of the C tile has NR values.
            unsafe { *c.add(r * ldc + j) = *v };
        }
    }
}

#[cfg(test)]
mod tests {
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
            for isa in [Isa::Avx2Fma, Isa::Portable]
                .into_iter()
                .filter(|i| i.available())
            {
                let pool = Pool::with_isa(2, isa).unwrap();
                let mut c = vec![f32::NAN; m * n];
                gemm_par(&pool, &a, k, m, &packed, &mut c, n, Init::Zero);
                let mut cb = vec![0.0; m * n];
                gemm(isa, &a, k, m, &packed, &mut cb, n, Init::Bias(&bias));
                gemm(isa, &a, k, m, &packed, &mut cb, n, Init::Accumulate);
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
                }
            }
        }
    }

    #[test]
    fn row_results_do_not_depend_on_m_or_threads() {
        let (k, n) = (700, 70);
        let a = data(50 * k, 4);
        let w = data(n * k, 5);
        let packed = PackedMatrix::from_linear_weight(&w, n, k);
        let mut full = vec![0.0; 50 * n];
        let pool = Pool::new(2).unwrap();
        gemm_par(&pool, &a, k, 50, &packed, &mut full, n, Init::Zero);
        for start in [0, 7, 49] {
            let mut one = vec![0.0; n];
            gemm(
                pool.isa(),
                &a[start * k..],
                k,
                1,
                &packed,
                &mut one,
                n,
                Init::Zero,
            );
            assert_eq!(one, full[start * n..(start + 1) * n]);
        }
    }

    #[test]
    fn pack_rows_equals_pack_transposed() {
        let (k, n) = (9, 21);
        let w = data(n * k, 6);
        let mut bt = vec![0.0; k * n];
        for j in 0..n {
            for kk in 0..k {
                bt[kk * n + j] = w[j * k + kk];
            }
        }
        let mut p = PackedMatrix::default();
        p.pack_rows(&bt, n, k, n);
        let q = PackedMatrix::from_linear_weight(&w, n, k);
        assert_eq!(
            p.buf.as_slice()[..p.panels() * k * NR],
            q.buf.as_slice()[..q.panels() * k * NR]
        );
    }
}
