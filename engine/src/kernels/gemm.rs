//! `C = init + A · B` in f32 with `B` packed once into column panels.
//!
//! `A` is any row-major matrix (an activation, read in place); `B` is a [`PackedMatrix`]: the
//! right operand cut into panels of [`NR`] columns, each stored as rows of `NR` contiguous
//! floats (64 bytes: one cache line), in blocks of `KC` rows (see [`offset`]). The micro-kernel keeps an `MR x NR` block of `C` in 12
//! AVX2 registers and streams one panel row (two vector loads) and `MR` broadcasts of `A` per
//! step of `k`: 12 FMAs per 8 loads. Blocking: `KC` rows of a panel (16 KiB) stay in L1 while all
//! row tiles of an `MC`-row block of `A` (in L2) pass over them.
//!
//! On CPUs with AVX-512F the same tile is `MR` 512-bit accumulators (one per row; a panel row
//! is one vector), with `A` broadcast from memory inside each FMA: fewer instructions per FLOP,
//! same packing and the same order of operations, so AVX-512 and AVX2 results are bit-identical.
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
const KC: usize = 128;
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
        for kk in 0..k {
            for p in 0..panels {
                let c0 = p * NR;
                let w = NR.min(n - c0);
                let at = offset(k, panels, p, kk);
                let row = &mut dst[at..at + NR];
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
            for kk in 0..k {
                let at = offset(k, panels, p, kk);
                let row = &mut dst[at..at + NR];
                for (j, v) in row.iter_mut().enumerate() {
                    *v = if j < width {
                        w[(c0 + j) * ldw + kk]
                    } else {
                        0.0
                    };
                }
            }
        }
    }

    /// The `kc` rows of panel `p` from row `k0` (a multiple of `KC`), contiguous.
    fn panel_ptr(&self, p: usize, k0: usize) -> *const f32 {
        self.buf.as_slice()[offset(self.k, self.panels(), p, k0)..].as_ptr()
    }
}

/// Where row `kk` of panel `p` lives. The matrix is stored in `KC`-row blocks, each block all
/// panels one after another, so the kernels' (block, panel) order reads memory sequentially
/// and the hardware prefetcher streams the weights.
fn offset(k: usize, panels: usize, p: usize, kk: usize) -> usize {
    let block = kk / KC;
    let kc = KC.min(k - block * KC);
    block * KC * panels * NR + p * kc * NR + (kk - block * KC) * NR
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

/// `C[..m][..n] = init + A[..m][..k] · B` on the calling thread, with `isa`'s kernels. `A` has
/// row stride `lda`, `C` row stride `ldc`.
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
    if m == 0 || b.n == 0 {
        return;
    }
    // The borrow never spans a wait on other threads, so a worker that steals work while it
    // waits can never find its own buffer borrowed.
    A_PACK.with(|buf| {
        let mut buf = buf.borrow_mut();
        let packed = pack_a_blocks(a, lda, m, b.k, &mut buf);
        // SAFETY: `check` verified the bounds of `c`; this thread owns all of it.
        unsafe { gemm_packed(isa, packed, m, b, 0..b.panels(), c.as_mut_ptr(), ldc, init) }
    });
}

/// [`gemm`] with the output columns split into [`Pool::parts`] parts run by the pool's threads.
/// `A` is packed once, on the calling thread, and shared by all parts.
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
    if m == 0 || b.n == 0 {
        return;
    }
    let panels = b.panels();
    let parts = pool.parts(panels);
    let mut scratch = pool.take_scratch();
    let packed = pack_a_blocks(a, lda, m, b.k, &mut scratch);
    let out = SharedMut::new(c);
    pool.run(parts, |t| {
        let range = panels * t / parts..panels * (t + 1) / parts;
        // SAFETY: `check` verified the bounds; part `t` writes only the columns of its panels.
        unsafe { gemm_packed(pool.isa(), packed, m, b, range, out.ptr(), ldc, init) }
    });
    pool.put_scratch(scratch);
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

thread_local! {
    /// Per-thread buffer for packed `A` of single-threaded calls.
    static A_PACK: std::cell::RefCell<AlignedBuf> = std::cell::RefCell::new(AlignedBuf::default());
}

/// Rows of the `MC` block starting at `m0`, rounded up to whole tiles.
fn padded_rows(m: usize, m0: usize) -> usize {
    MC.min(m - m0).div_ceil(MR) * MR
}

/// Where block `(m0, k0)` of packed `A` starts: blocks are stored `MC` rows at a time, each as
/// its `KC`-deep slices one after another (see [`pack_a`] for one slice).
fn a_block(k: usize, m: usize, m0: usize, k0: usize) -> usize {
    m0 * k + k0 * padded_rows(m, m0)
}

/// Pack all of `A` (`m x k`, row stride `lda`) into `buf` in [`a_block`] order.
fn pack_a_blocks<'a>(
    a: &[f32],
    lda: usize,
    m: usize,
    k: usize,
    buf: &'a mut AlignedBuf,
) -> &'a [f32] {
    let len = m.div_ceil(MR) * MR * k;
    buf.ensure(len);
    let out = &mut buf.as_mut_slice()[..len];
    let mut m0 = 0;
    while m0 < m {
        let mb = MC.min(m - m0);
        let mut k0 = 0;
        while k0 < k {
            let kc = KC.min(k - k0);
            pack_a(
                &a[m0 * lda + k0..],
                lda,
                mb,
                kc,
                &mut out[a_block(k, m, m0, k0)..],
            );
            k0 += kc;
        }
        m0 += mb;
    }
    &buf.as_slice()[..len]
}

/// # Safety
/// `c` points to `m` rows of stride `ldc` with at least `b.n` values each, and no other thread
/// touches the columns of `panels` in those rows; `packed` is `A` packed by [`pack_a_blocks`].
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_packed(
    isa: Isa,
    packed: &[f32],
    m: usize,
    b: &PackedMatrix,
    panels: Range<usize>,
    c: *mut f32,
    ldc: usize,
    init: Init<'_>,
) {
    let k = b.k;
    if panels.is_empty() {
        return;
    }
    // Zero-initialised outputs start from zero accumulators; a bias is written into C first.
    if let Init::Bias(bias) = init {
        for p in panels.clone() {
            let c0 = p * NR;
            let w = NR.min(b.n - c0);
            for r in 0..m {
                // SAFETY: row r, columns c0..c0+w are inside C and owned by this call.
                let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc + c0), w) };
                row.copy_from_slice(&bias[c0..c0 + w]);
            }
        }
    }
    if k == 0 {
        if let Init::Zero = init {
            for p in panels {
                let c0 = p * NR;
                for r in 0..m {
                    // SAFETY: as above.
                    unsafe {
                        std::slice::from_raw_parts_mut(c.add(r * ldc + c0), NR.min(b.n - c0))
                            .fill(0.0)
                    };
                }
            }
        }
        return;
    }
    let mut m0 = 0;
    while m0 < m {
        let mb = MC.min(m - m0);
        let tiles = mb.div_ceil(MR);
        let mut k0 = 0;
        while k0 < k {
            let kc = KC.min(k - k0);
            let load = k0 > 0 || !matches!(init, Init::Zero);
            let block = &packed[a_block(k, m, m0, k0)..];
            for p in panels.clone() {
                let c0 = p * NR;
                let w = NR.min(b.n - c0);
                let bp = b.panel_ptr(p, k0);
                let next = if p + 1 < panels.end {
                    b.panel_ptr(p + 1, k0)
                } else {
                    std::ptr::null()
                };
                for t in 0..tiles {
                    let r0 = t * MR;
                    let rows = MR.min(mb - r0);
                    // Pull the next panel into L1 a slice per tile, spread over this panel's
                    // tiles so the misses overlap with computation instead of queueing.
                    if !next.is_null() {
                        prefetch_lines(isa, next, kc * t / tiles, kc * (t + 1) / tiles);
                    }
                    let ap = block[t * kc * MR..].as_ptr();
                    // SAFETY: the tile lies inside C (rows m0+r0.., columns c0..c0+w).
                    let cp = unsafe { c.add((m0 + r0) * ldc + c0) };
                    // The next tile's accumulators come from C: start fetching them now.
                    if load && t + 1 < tiles {
                        let next_rows = MR.min(mb - r0 - MR);
                        prefetch_rows(isa, cp.wrapping_add(MR * ldc), ldc, next_rows);
                    }
                    // SAFETY: the packed A tile and the panel hold kc rows; C as above.
                    unsafe { tile(isa, rows, kc, ap, bp, cp, ldc, w, load) };
                }
            }
            k0 += kc;
        }
        m0 += mb;
    }
}

/// Prefetch `rows` rows of a C tile (`NR` values each, possibly straddling two lines).
#[inline(always)]
fn prefetch_rows(isa: Isa, c: *const f32, ldc: usize, rows: usize) {
    #[cfg(target_arch = "x86_64")]
    if isa != Isa::Portable {
        for r in 0..rows {
            let row = c.wrapping_add(r * ldc);
            // SAFETY: prefetching never faults.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    row as *const i8,
                );
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    row.wrapping_add(NR - 1) as *const i8,
                );
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (isa, c, ldc, rows);
}

/// Prefetch panel rows `from..to` (one cache line each) into L1.
#[inline(always)]
fn prefetch_lines(isa: Isa, panel: *const f32, from: usize, to: usize) {
    #[cfg(target_arch = "x86_64")]
    if isa != Isa::Portable {
        for line in from..to {
            // SAFETY: prefetching never faults; the address is inside the panel.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    panel.wrapping_add(line * NR) as *const i8,
                )
            };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (isa, panel, from, to);
}

/// Pack `rows x kc` of `A` into row tiles of `MR`: tile `t` is `kc` groups of `MR` values (rows
/// `t*MR..`), zero-padded past `rows`. The kernel then broadcasts from one moving pointer.
fn pack_a(a: &[f32], lda: usize, rows: usize, kc: usize, out: &mut [f32]) {
    for t in 0..rows.div_ceil(MR) {
        let tile = &mut out[t * kc * MR..(t + 1) * kc * MR];
        for r in 0..MR {
            let row = t * MR + r;
            if row < rows {
                let src = &a[row * lda..row * lda + kc];
                for (kk, &v) in src.iter().enumerate() {
                    tile[kk * MR + r] = v;
                }
            } else {
                for kk in 0..kc {
                    tile[kk * MR + r] = 0.0;
                }
            }
        }
    }
}

/// One `rows x w` tile (`rows <= MR`, `w <= NR`): `C = A · B` over `kc`, or `C += A · B` when
/// `load`, with `A` packed by [`pack_a`].
///
/// # Safety
/// `a` has `kc * MR` values, `b` has `kc` rows of `NR` values, `c` has `rows` rows of stride
/// `ldc` with `w` values.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(
    isa: Isa,
    rows: usize,
    kc: usize,
    a: *const f32,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    w: usize,
    load: bool,
) {
    if w < NR {
        // Edge panel: run the full-width kernel on a scratch tile, copy the valid columns.
        let mut scratch = [0.0f32; MR * NR];
        if load {
            for r in 0..rows {
                for j in 0..w {
                    // SAFETY: inside the caller's C tile.
                    scratch[r * NR + j] = unsafe { *c.add(r * ldc + j) };
                }
            }
        }
        // SAFETY: scratch is a full MR x NR tile.
        unsafe { tile(isa, rows, kc, a, b, scratch.as_mut_ptr(), NR, NR, load) };
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
                6 => $f::<6>(kc, a, b, c, ldc, load),
                5 => $f::<5>(kc, a, b, c, ldc, load),
                4 => $f::<4>(kc, a, b, c, ldc, load),
                3 => $f::<3>(kc, a, b, c, ldc, load),
                2 => $f::<2>(kc, a, b, c, ldc, load),
                _ => $f::<1>(kc, a, b, c, ldc, load),
            }
        };
    }
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Isa::Avx2Fma is only reported when the CPU has AVX2 and FMA.
        Isa::Avx2Fma => unsafe { dispatch!(kernel_avx2) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: Isa::Avx512 is only reported when the CPU has AVX-512F.
        Isa::Avx512 => unsafe { dispatch!(kernel_avx512) },
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
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    load: bool,
) {
    use std::arch::x86_64::*;
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    if load {
        for (r, row) in acc.iter_mut().enumerate() {
            // SAFETY: row r of the C tile has NR values.
            unsafe {
                row[0] = _mm256_loadu_ps(c.add(r * ldc));
                row[1] = _mm256_loadu_ps(c.add(r * ldc + 8));
            }
        }
    }
    macro_rules! step {
        ($kk:expr) => {{
            // SAFETY: $kk < kc: inside the panel and the packed A tile.
            unsafe {
                let b0 = _mm256_load_ps(b.add($kk * NR));
                let b1 = _mm256_load_ps(b.add($kk * NR + 8));
                for r in 0..R {
                    let av = _mm256_broadcast_ss(&*a.add($kk * MR + r));
                    acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
                    acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
                }
            }
        }};
    }
    let mut kk = 0;
    while kk + 4 <= kc {
        step!(kk);
        step!(kk + 1);
        step!(kk + 2);
        step!(kk + 3);
        kk += 4;
    }
    while kk < kc {
        step!(kk);
        kk += 1;
    }
    for (r, row) in acc.iter().enumerate() {
        // SAFETY: row r of the C tile has NR values.
        unsafe {
            _mm256_storeu_ps(c.add(r * ldc), row[0]);
            _mm256_storeu_ps(c.add(r * ldc + 8), row[1]);
        }
    }
}

/// One panel row is one 512-bit vector, so the tile is `R` accumulators; each `A` value is
/// broadcast straight from memory into its FMA (`{1to16}`). Same order of operations as
/// [`kernel_avx2`]: one FMA per product, in increasing `k`.
///
/// # Safety
/// See [`tile`]; requires AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn kernel_avx512<const R: usize>(
    kc: usize,
    a: *const f32,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    load: bool,
) {
    use std::arch::x86_64::*;
    let mut acc = [_mm512_setzero_ps(); R];
    if load {
        for (r, row) in acc.iter_mut().enumerate() {
            // SAFETY: row r of the C tile has NR values.
            *row = unsafe { _mm512_loadu_ps(c.add(r * ldc)) };
        }
    }
    macro_rules! step {
        ($kk:expr) => {{
            // SAFETY: $kk < kc: inside the panel (64-byte aligned rows) and the packed A tile.
            unsafe {
                let bv = _mm512_load_ps(b.add($kk * NR));
                for r in 0..R {
                    let av = _mm512_set1_ps(*a.add($kk * MR + r));
                    acc[r] = _mm512_fmadd_ps(av, bv, acc[r]);
                }
            }
        }};
    }
    let mut kk = 0;
    while kk + 4 <= kc {
        step!(kk);
        step!(kk + 1);
        step!(kk + 2);
        step!(kk + 3);
        kk += 4;
    }
    while kk < kc {
        step!(kk);
        kk += 1;
    }
    for (r, row) in acc.iter().enumerate() {
        // SAFETY: row r of the C tile has NR values.
        unsafe { _mm512_storeu_ps(c.add(r * ldc), *row) };
    }
}

/// # Safety
/// See [`tile`].
unsafe fn kernel_portable<const R: usize>(
    kc: usize,
    a: *const f32,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    load: bool,
) {
    let mut acc = [[0.0f32; NR]; R];
    if load {
        for (r, row) in acc.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                // SAFETY: row r of the C tile has NR values.
                *v = unsafe { *c.add(r * ldc + j) };
            }
        }
    }
    for kk in 0..kc {
        // SAFETY: kk < kc: inside the panel and the packed A tile.
        let (brow, arow) = unsafe {
            (
                std::slice::from_raw_parts(b.add(kk * NR), NR),
                std::slice::from_raw_parts(a.add(kk * MR), R),
            )
        };
        for (row, &av) in acc.iter_mut().zip(arow) {
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
            for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
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
        gemm(Isa::Avx512, &a, k, m, &packed, &mut c512, n, Init::Zero);
        gemm(Isa::Avx2Fma, &a, k, m, &packed, &mut c2, n, Init::Zero);
        assert_eq!(c512, c2);
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
