//! `C = init + A · B` in f32 with `B` packed once into column panels.
//!
//! `A` is any row-major matrix (an activation, read in place); `B` is a [`PackedMatrix`]: the
//! right operand cut into panels of [`NR`] columns, each stored as rows of `NR` contiguous
//! floats (64 bytes: one cache line), in blocks of `KC` rows (see [`offset`]). The micro-kernel keeps an `MR x NR` block of `C` in 12
//! AVX2 registers and streams one panel row (two vector loads) and `MR` broadcasts of `A` per
//! step of `k`: 12 FMAs per 8 loads. Blocking: `KC` rows of a panel (16 KiB) stay in L1 while all
//! row tiles of an `MC`-row block of `A` (in L2) pass over them. The kernel reads a tile's `MR`
//! rows of `A` through pointers that advance together: f32 rows straight from the caller's
//! matrix, bf16 rows from a packed copy (rounded into pairs per `MC x KC_BF16` block, each row
//! contiguous; an interleaved layout cost a scalar scatter of 4-5% of the vision tower).
//! [`gemm_par`] packs a bf16 `A` on the pool's threads, one block per unit.
//!
//! On CPUs with AVX-512F the same tile is `MR` 512-bit accumulators (one per row; a panel row
//! is one vector), with `A` broadcast from memory inside each FMA: fewer instructions per FLOP,
//! same packing and the same order of operations, so AVX-512 and AVX2 results are bit-identical.
//! In bf16, two full panels side by side run together in one call ([`tile_pair`],
//! `MR x 2 NR`): each broadcast `A` pair then feeds two products and twice as many chains hide
//! the latency (measured: the bf16 prefix 15% faster than one panel per call); the order of
//! operations per element is unchanged, so the pairing, which depends on where a thread's
//! panels start, changes no bit.
//!
//! In [`Precision::Bf16`] the panels hold bf16 pairs instead: row `i` of a panel is the 32-bit
//! lanes `(B[2i][j], B[2i+1][j])` for its `NR` columns (still one cache line, now covering two
//! values of `k`), and `A` is rounded to bf16 (nearest, ties to even) when packed, as pairs
//! `(A[r][2i], A[r][2i+1])`. The AVX512_BF16 kernel multiplies a pair by a pair and adds both
//! products to an f32 accumulator in one `vdpbf16ps`; a portable kernel does the same in scalar
//! code on other CPUs. The products of two bf16 values are exact in f32, so the error is the
//! rounding of the operands (relative 2^-9 each) plus f32 accumulation. A bf16 block is
//! `KC_BF16` values of `k` deep (16 KiB of panel).
//!
//! Every element of `C` accumulates its `k` products in increasing `k` order, one FMA each, in
//! `KC`-sized blocks (`KC_BF16` in bf16). That order depends on neither `m`, the row tile an element falls in, nor
//! the thread split, so results do not depend on the batch size.

use std::ops::Range;

use super::{AlignedBuf, Isa, Pool, Precision, SharedMut, grown};

/// Columns per packed panel (two AVX2 vectors).
pub const NR: usize = 16;
/// Rows per micro-kernel tile.
pub const MR: usize = 6;
/// Depth of one cache block in f32 (`KC` rows of a 64-byte panel row: 16 KiB, half of L1).
/// 256 rather than 128: each micro-kernel call then runs twice the FMAs per load and store of
/// its `C` tile and per pass through the driver loop, which measured 3-5% faster (release
/// build: `gemm_timing` 1024x768x3072 and 200x720x4096, the expert at B = 4). The block depth
/// changes no f32 bit: a `C` value carries over between blocks exactly.
const KC: usize = 256;
/// Depth of one cache block in bf16: `KC_BF16 / 2` pair rows (16 KiB of panel; the paired
/// kernel's two panels fill L1). Even, so a pair never straddles two blocks. (Here the depth is
/// part of the result: the even and odd pair accumulators are summed at the end of each
/// block.) 512 rather than 256: half the passes of each `C` tile through the cache and half
/// the kernel calls; the bf16 vision tower measured 2-3% faster (release, `vision_timing
/// --cameras 1`, alternating), the expert the same.
const KC_BF16: usize = 512;

/// The depth of one cache block of a matrix stored in `precision`.
fn kc_of(precision: Precision) -> usize {
    match precision {
        Precision::F32 => KC,
        Precision::Bf16 => KC_BF16,
    }
}
/// Rows of `A` per cache block (a multiple of `MR`): 240 x `KC` f32 values (240 KiB, 240 x
/// `KC_BF16` in bf16) stay in L2, and a batch of four expert requests (200 rows) is one block,
/// so each weight panel streams from memory once per GEMM.
const MC: usize = 240;

/// The right-hand operand of a GEMM, packed into `NR`-column panels.
///
/// Its [`Precision`] says how the values are stored: f32, or bf16 pairs (half the memory; the
/// GEMM then rounds `A` to bf16 too). bf16 pairs live in the same 32-bit buffer, as raw bits.
#[derive(Clone, Debug, Default)]
pub struct PackedMatrix {
    k: usize,
    n: usize,
    precision: Precision,
    buf: AlignedBuf,
}

/// Packed rows that `k` rows of a matrix take: one per row in f32, one per pair in bf16.
fn depth(precision: Precision, k: usize) -> usize {
    match precision {
        Precision::F32 => k,
        Precision::Bf16 => k.div_ceil(2),
    }
}

/// `x` rounded to bf16 (nearest, ties to even; NaN stays NaN, made quiet), as its 16 bits.
/// Denormals round like any other value (no flush to zero).
pub fn to_bf16(x: f32) -> u16 {
    bf16_bits(x.to_bits()) as u16
}

/// [`to_bf16`] on the bits of an f32, branch-free (so that loops over it vectorise), in the low
/// 16 bits of the result; the vector packing of `A` computes exactly this per lane.
#[inline(always)]
fn bf16_bits(bits: u32) -> u32 {
    let nan = (bits & 0x7fff_ffff) > 0x7f80_0000;
    let rounded = bits.wrapping_add(0x7fff + ((bits >> 16) & 1)) >> 16;
    let quiet = (bits >> 16) | 0x40;
    if nan { quiet } else { rounded }
}

/// Two bf16 values in one 32-bit lane, `lo` in the low half (the element with the even `k`),
/// stored as the bits of an f32 so that bf16 panels share the f32 buffer type.
fn bf16_pair(lo: f32, hi: f32) -> f32 {
    f32::from_bits(u32::from(to_bf16(lo)) | (u32::from(to_bf16(hi)) << 16))
}

impl PackedMatrix {
    /// Pack the weight of a PyTorch `Linear` (`w` is `[n][k]`, out x in, row-major) so that
    /// `A · B = A · wᵀ`, i.e. `y = x wᵀ`.
    pub fn from_linear_weight(w: &[f32], n: usize, k: usize) -> Self {
        Self::from_linear_weight_in(Precision::F32, w, n, k)
    }

    /// [`Self::from_linear_weight`] stored in `precision` (bf16 values are rounded to nearest).
    pub fn from_linear_weight_in(precision: Precision, w: &[f32], n: usize, k: usize) -> Self {
        Self::from_linear_fn_in(precision, n, k, |row, col| w[row * k + col])
    }

    /// Pack several `Linear` weights with the same input size side by side (`[w0; w1; ..]` along
    /// the output dimension), e.g. the q, k and v projections into one GEMM.
    pub fn from_linear_weights(ws: &[(&[f32], usize)], k: usize) -> Self {
        Self::from_linear_weights_in(Precision::F32, ws, k)
    }

    /// [`Self::from_linear_weights`] stored in `precision`.
    pub fn from_linear_weights_in(precision: Precision, ws: &[(&[f32], usize)], k: usize) -> Self {
        // Where each stacked row lives, so that the panels are packed straight from the parts
        // (no stacked copy of the weights, which briefly doubled them at load).
        let rows: Vec<&[f32]> = ws
            .iter()
            .flat_map(|&(w, n)| (0..n).map(move |r| &w[r * k..(r + 1) * k]))
            .collect();
        Self::from_linear_fn_in(precision, rows.len(), k, |j, kk| rows[j][kk])
    }

    /// An empty matrix that [`Self::pack_rows`] and [`Self::pack_transposed`] fill in
    /// `precision` (e.g. attention keys and values packed per request).
    pub fn empty_in(precision: Precision) -> Self {
        PackedMatrix {
            precision,
            ..PackedMatrix::default()
        }
    }

    /// How the values are stored.
    pub fn precision(&self) -> Precision {
        self.precision
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
        self.buf
            .ensure(n.div_ceil(NR) * NR * depth(self.precision, k));
    }

    /// Pack `B` given as `k` rows of `n` values with row stride `ldb`, in the matrix's
    /// precision (bf16 rounding with `isa`'s vector code). Reuses the allocation.
    pub fn pack_rows(&mut self, isa: Isa, b: &[f32], ldb: usize, k: usize, n: usize) {
        match self.precision {
            Precision::F32 => self.pack_with(k, n, |kk, j| b[kk * ldb + j]),
            Precision::Bf16 => self.pack_rows_bf16(isa, b, ldb, k, n),
        }
    }

    /// [`Self::pack_rows`] in bf16: each pair of rows is interleaved (`b[2i][j], b[2i+1][j]`
    /// side by side), rounded into pairs by the vector code ([`round_pairs`]) and copied into the
    /// panels. Same bits as [`Self::pack_with`], which rounded element by element (packing the
    /// attention values took ~2.5% of the vision tower).
    fn pack_rows_bf16(&mut self, isa: Isa, b: &[f32], ldb: usize, k: usize, n: usize) {
        ROW_PAIRS.with(|buf| {
            // Every pair is written below: clearing and refilling the buffer per call zeroed
            // ~18 MB per camera (the attention's values, packed per head).
            let mut buf = buf.borrow_mut();
            let pairs = grown(&mut buf, k.div_ceil(2) * n);
            let mut both = vec![0.0f32; 2 * n];
            for (i, out) in pairs.chunks_exact_mut(n).enumerate() {
                let (kk, lo) = (2 * i, &b[2 * i * ldb..2 * i * ldb + n]);
                for (two, &v) in both.chunks_exact_mut(2).zip(lo) {
                    two[0] = v;
                    two[1] = 0.0;
                }
                if kk + 1 < k {
                    let hi = &b[(kk + 1) * ldb..(kk + 1) * ldb + n];
                    for (two, &v) in both.chunks_exact_mut(2).zip(hi) {
                        two[1] = v;
                    }
                }
                round_pairs(isa, &both, out);
            }
            self.store_pairs(k, n, |i, j| pairs[i * n + j]);
        });
    }

    /// Pack `B = wᵀ` where `w` has `n` rows of `k` values with row stride `ldw`, in the
    /// matrix's precision (bf16 rounding with `isa`'s vector code). Reuses the allocation.
    pub fn pack_transposed(&mut self, isa: Isa, w: &[f32], ldw: usize, n: usize, k: usize) {
        match self.precision {
            Precision::F32 => self.pack_with(k, n, |kk, j| w[j * ldw + kk]),
            Precision::Bf16 => self.pack_transposed_bf16(isa, w, ldw, n, k),
        }
    }

    /// [`Self::pack_transposed`] in bf16: each row of `w` is rounded into pairs with the vector
    /// code ([`round_pairs`]), then the pairs are transposed into the panels. Rounding element by
    /// element while gathering down the columns of `w` made packing the attention keys ~4% of
    /// the vision tower. Same bits as [`Self::pack_with`].
    fn pack_transposed_bf16(&mut self, isa: Isa, w: &[f32], ldw: usize, n: usize, k: usize) {
        let kp = k.div_ceil(2);
        ROW_PAIRS.with(|buf| {
            // Every pair is written below (see `pack_rows_bf16`).
            let mut buf = buf.borrow_mut();
            let pairs = grown(&mut buf, n * kp);
            for (j, out) in pairs.chunks_exact_mut(kp).enumerate() {
                round_pairs(isa, &w[j * ldw..j * ldw + k], out);
            }
            self.pack_transposed_pairs(pairs, kp, n, k);
        });
    }

    /// [`Self::pack_transposed`] of rows already rounded to bf16 pairs ([`round_pairs`]; `n`
    /// rows of `ceil(k / 2)` pairs, row stride `ldp` pairs): the same panels as packing the
    /// f32 rows they were rounded from, without rounding them again.
    ///
    /// # Panics
    /// If the matrix is not bf16.
    pub fn pack_transposed_pairs(&mut self, pairs: &[u32], ldp: usize, n: usize, k: usize) {
        assert_eq!(self.precision, Precision::Bf16, "pairs pack into bf16 only");
        self.store_pairs(k, n, |i, j| pairs[j * ldp + i]);
    }

    /// [`Self::pack_rows`] of rows already rounded to bf16 pairs ([`round_pairs`]; `k` rows
    /// of `n` values as `ceil(n / 2)` pairs, row stride `ldp` pairs): a panel pairs two *rows*,
    /// so each value's 16 bits move from its row's pair into the pair of its two rows. The
    /// same panels as packing the f32 rows they were rounded from.
    ///
    /// # Panics
    /// If the matrix is not bf16.
    pub fn pack_rows_pairs(&mut self, pairs: &[u32], ldp: usize, k: usize, n: usize) {
        assert_eq!(self.precision, Precision::Bf16, "pairs pack into bf16 only");
        let half = |r: usize, j: usize| (pairs[r * ldp + j / 2] >> (16 * (j % 2))) & 0xffff;
        self.store_pairs(k, n, |i, j| {
            let hi = if 2 * i + 1 < k { half(2 * i + 1, j) } else { 0 };
            half(2 * i, j) | hi << 16
        });
    }

    /// Fill the bf16 panels of a `k x n` matrix from already rounded pairs: `pair(i, j)` is
    /// the pair of rows `2i, 2i + 1` in column `j` (zero past `n`).
    fn store_pairs(&mut self, k: usize, n: usize, pair: impl Fn(usize, usize) -> u32) {
        debug_assert_eq!(self.precision, Precision::Bf16);
        self.resize(k, n);
        let panels = self.panels();
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            for i in 0..k.div_ceil(2) {
                let start = offset(Precision::Bf16, k, panels, p, 2 * i);
                let row = &mut dst[start..start + NR];
                for (jj, v) in row[..width].iter_mut().enumerate() {
                    *v = f32::from_bits(pair(i, c0 + jj));
                }
                row[width..].fill(0.0);
            }
        }
    }

    /// Pack the `k x n` matrix whose element `(kk, j)` is `at(kk, j)`.
    fn pack_with(&mut self, k: usize, n: usize, at: impl Fn(usize, usize) -> f32) {
        self.resize(k, n);
        let panels = self.panels();
        let precision = self.precision;
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            // The precision and the panel's width are decided outside the inner loop, so that
            // it is a plain copy (vectorised when `at` reads a contiguous row).
            match precision {
                Precision::F32 => {
                    for kk in 0..k {
                        let start = offset(precision, k, panels, p, kk);
                        let row = &mut dst[start..start + NR];
                        for (j, v) in row[..width].iter_mut().enumerate() {
                            *v = at(kk, c0 + j);
                        }
                        row[width..].fill(0.0);
                    }
                }
                // bf16 rows are pairs of `k`; blocks start at multiples of the even `KC_BF16`, so a
                // pair never straddles two blocks.
                Precision::Bf16 => {
                    for kk in (0..k).step_by(2) {
                        let start = offset(precision, k, panels, p, kk);
                        let row = &mut dst[start..start + NR];
                        // A ragged `k` pairs its last row with zeros; decided per row, so the
                        // inner loop is branch-free.
                        if kk + 1 < k {
                            for (j, v) in row[..width].iter_mut().enumerate() {
                                *v = bf16_pair(at(kk, c0 + j), at(kk + 1, c0 + j));
                            }
                        } else {
                            for (j, v) in row[..width].iter_mut().enumerate() {
                                *v = bf16_pair(at(kk, c0 + j), 0.0);
                            }
                        }
                        row[width..].fill(0.0);
                    }
                }
            }
        }
    }

    /// The rows of panel `p` from row `k0` (a multiple of `KC`) to the end of its block,
    /// contiguous.
    fn panel_ptr(&self, p: usize, k0: usize) -> *const f32 {
        self.buf.as_slice()[offset(self.precision, self.k, self.panels(), p, k0)..].as_ptr()
    }

    /// Pack a `Linear` weight of `n` rows (outputs) of `k` (inputs) whose element `(row, col)`
    /// is `w(row, col)`, as [`Self::from_linear_weight_in`] packs the same values, but without a
    /// row-major `f32` copy of the weight: a loader reads each element straight from the stored
    /// tensor (a checkpoint's bf16 bits widen to `f32` exactly, and rounding them back to bf16
    /// is the identity, so bf16 panels hold the file's bits).
    pub fn from_linear_fn_in(
        precision: Precision,
        n: usize,
        k: usize,
        w: impl Fn(usize, usize) -> f32,
    ) -> Self {
        let mut p = Self::empty_in(precision);
        p.pack_with(k, n, |kk, j| w(j, kk));
        p
    }
}

/// Where row `kk` of panel `p` lives (`kk` even in bf16: the row of the pair it starts). The
/// matrix is stored in `KC`-row blocks, each block all panels one after another, so the
/// kernels' (block, panel) order reads memory sequentially and the hardware prefetcher streams
/// the weights.
fn offset(precision: Precision, k: usize, panels: usize, p: usize, kk: usize) -> usize {
    let kcb = kc_of(precision);
    let block = kk / kcb;
    let kc = kcb.min(k - block * kcb);
    let d = |rows| depth(precision, rows);
    block * d(kcb) * panels * NR + p * d(kc) * NR + d(kk - block * kcb) * NR
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
    /// `C += bias + A · B`: `bias` (`n` values) added to each row of `C` first, then the
    /// products accumulated, as a separate bias pass followed by [`Init::Accumulate`] would,
    /// but on the threads that own each part of `C`.
    AccumulateBias(&'a [f32]),
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
    if b.precision == Precision::F32 {
        let src = ASource::Rows(a, lda);
        // SAFETY: `check` verified the bounds of `a` and `c`; this thread owns all of `c`.
        unsafe { gemm_packed(isa, src, m, b, 0..b.panels(), c.as_mut_ptr(), ldc, init) };
        return;
    }
    // The borrow never spans a wait on other threads, so a worker that steals work while it
    // waits can never find its own buffer borrowed.
    A_PACK.with(|buf| {
        let mut buf = buf.borrow_mut();
        let packed = ASource::Packed(pack_a_blocks(isa, a, lda, m, b.k, &mut buf));
        // SAFETY: `check` verified the bounds of `c`; this thread owns all of it.
        unsafe { gemm_packed(isa, packed, m, b, 0..b.panels(), c.as_mut_ptr(), ldc, init) }
    });
}

/// [`gemm`] for a bf16 `B` whose `A` is already rounded: `m` rows of bf16 pairs as
/// [`round_pairs`] writes them (`ceil(k / 2)` pairs, row stride `ldp` pairs), read in place.
/// A loop that produces `A` row by row (a softmax, an activation) rounds each row while it is
/// still in L1, instead of this GEMM reading the whole f32 `A` back to round it; the rounding
/// is the same, so are the bits.
///
/// # Panics
/// If `b` is not bf16, or a stride or length is too small.
#[allow(clippy::too_many_arguments)]
pub fn gemm_pairs(
    isa: Isa,
    a: &[u32],
    ldp: usize,
    m: usize,
    b: &PackedMatrix,
    c: &mut [f32],
    ldc: usize,
    init: Init<'_>,
) {
    check_pairs(a, ldp, m, b, c, ldc, init);
    if m == 0 || b.n == 0 {
        return;
    }
    let src = ASource::Pairs(a, ldp);
    // SAFETY: `check_pairs` verified the bounds of `a` and `c`; this thread owns all of `c`.
    unsafe { gemm_packed(isa, src, m, b, 0..b.panels(), c.as_mut_ptr(), ldc, init) };
}

/// [`gemm_pairs`] with the output columns split over the pool's threads, as [`gemm_par`].
#[allow(clippy::too_many_arguments)]
pub fn gemm_par_pairs(
    pool: &Pool,
    a: &[u32],
    ldp: usize,
    m: usize,
    b: &PackedMatrix,
    c: &mut [f32],
    ldc: usize,
    init: Init<'_>,
) {
    check_pairs(a, ldp, m, b, c, ldc, init);
    if m == 0 || b.n == 0 {
        return;
    }
    run_parts(pool, ASource::Pairs(a, ldp), m, b, c, ldc, init);
}

/// Make the `A` of a [`gemm_par_pairs`] on the pool's threads: `f(r, row)` writes f32 row `r`
/// (`width` values) into `row`, which is rounded into row `r` of `pairs` (rows of
/// `ceil(width / 2)` pairs, back to back) while it is in L1. A layer norm or an activation
/// that feeds a bf16 GEMM thus never writes its f32 output to memory, nor does the GEMM read
/// it back to round it.
pub fn round_rows_par(
    pool: &Pool,
    width: usize,
    pairs: &mut [u32],
    f: impl Fn(usize, &mut [f32]) + Sync,
) {
    let kp = width.div_ceil(2);
    let isa = pool.isa();
    pool.for_row_chunks(pairs, kp, |r0, chunk| {
        let mut row = vec![0.0f32; width];
        for (i, dst) in chunk.chunks_exact_mut(kp).enumerate() {
            f(r0 + i, &mut row);
            round_pairs(isa, &row, dst);
        }
    });
}

/// The `A` of GEMMs in some precision, made row by row by a producer (a norm, an
/// activation): f32 rows for f32 weights; for bf16 weights, rows rounded into bf16 pairs as
/// they are made ([`round_rows_par`]), so the f32 values never go to memory. The results are
/// the same as giving the f32 rows to [`gemm_par`].
#[derive(Debug)]
pub struct ActivationRows {
    width: usize,
    rows: usize,
    precision: Precision,
    values: Vec<f32>,
    pairs: Vec<u32>,
}

impl ActivationRows {
    /// Room for `rows` rows of `width` values, for GEMMs whose `B` is in `precision`.
    pub fn new(precision: Precision, rows: usize, width: usize) -> Self {
        let (values, pairs) = match precision {
            Precision::F32 => (vec![0.0; rows * width], Vec::new()),
            Precision::Bf16 => (Vec::new(), vec![0; rows * width.div_ceil(2)]),
        };
        ActivationRows {
            width,
            rows,
            precision,
            values,
            pairs,
        }
    }

    /// Whether this holds at least `rows` rows of `width` values for `precision` weights (and
    /// can be filled again for them instead of allocating new rows).
    pub fn fits(&self, precision: Precision, rows: usize, width: usize) -> bool {
        self.precision == precision && self.width == width && self.rows >= rows
    }

    /// Make the first `m` rows: `f(r, row)` writes row `r`'s `width` f32 values, on the pool's
    /// threads.
    ///
    /// # Panics
    /// If `m` exceeds the rows this was made for.
    pub fn fill(&mut self, pool: &Pool, m: usize, f: impl Fn(usize, &mut [f32]) + Sync) {
        assert!(m <= self.rows, "activation rows: {m} > {}", self.rows);
        let width = self.width;
        match self.precision {
            Precision::F32 => {
                pool.for_row_chunks(&mut self.values[..m * width], width, |r0, chunk| {
                    for (i, row) in chunk.chunks_exact_mut(width.max(1)).enumerate() {
                        f(r0 + i, row);
                    }
                });
            }
            Precision::Bf16 => {
                round_rows_par(pool, width, &mut self.pairs[..m * width.div_ceil(2)], f);
            }
        }
    }

    /// `C = init + A · B` over the first `m` rows, split over the pool's threads.
    ///
    /// # Panics
    /// If `b`'s precision or input size is not this matrix's, or as [`gemm_par`].
    #[allow(clippy::too_many_arguments)]
    pub fn gemm_par(
        &self,
        pool: &Pool,
        m: usize,
        b: &PackedMatrix,
        c: &mut [f32],
        ldc: usize,
        init: Init<'_>,
    ) {
        assert!(
            b.precision == self.precision && b.k == self.width,
            "activation rows ({:?}, width {}) vs B ({:?}, k {})",
            self.precision,
            self.width,
            b.precision,
            b.k
        );
        match self.precision {
            Precision::F32 => gemm_par(pool, &self.values, self.width, m, b, c, ldc, init),
            Precision::Bf16 => {
                let ldp = self.width.div_ceil(2);
                gemm_par_pairs(pool, &self.pairs, ldp, m, b, c, ldc, init);
            }
        }
    }
}

/// Where the micro-kernels read `A`.
#[derive(Clone, Copy)]
enum ASource<'a> {
    /// Packed by [`pack_a_blocks`] (bf16: rounded into pairs).
    Packed(&'a [f32]),
    /// f32 rows read in place, `A[r][kk]` at `a[r * lda + kk]`: packing them would only copy
    /// each row (~3% of the f32 vision tower, plus a parallel region per GEMM to do it in).
    Rows(&'a [f32], usize),
    /// bf16 pair rows read in place, pair `(A[r][2i], A[r][2i + 1])` at `a[r * ldp + i]`.
    Pairs(&'a [u32], usize),
}

/// [`gemm`] with the output columns split into [`Pool::parts`] parts run by the pool's threads.
/// A bf16 `A` is packed once, by the pool's threads too (see [`pack_a_blocks_par`]), and shared
/// by all parts; an f32 `A` is read in place.
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
    let mut scratch = pool.take_scratch();
    let src = match b.precision {
        Precision::F32 => ASource::Rows(a, lda),
        Precision::Bf16 => ASource::Packed(pack_a_blocks_par(pool, a, lda, m, b.k, &mut scratch)),
    };
    run_parts(pool, src, m, b, c, ldc, init);
    pool.put_scratch(scratch);
}

/// Run the GEMM of `src` (checked by the caller) with the output panels split over the
/// pool's threads.
fn run_parts(
    pool: &Pool,
    src: ASource<'_>,
    m: usize,
    b: &PackedMatrix,
    c: &mut [f32],
    ldc: usize,
    init: Init<'_>,
) {
    let panels = b.panels();
    // Parts own whole pairs of panels where the kernel pairs them: a part starting or ending
    // at an odd panel would leave that panel to the slower one-panel kernel.
    let unit = if Kernel::choose(pool.isa(), b.precision).pairs() {
        2
    } else {
        1
    };
    let units = panels.div_ceil(unit);
    let parts = pool.parts(units);
    let out = SharedMut::new(c);
    pool.run(parts, |t| {
        let range = (units * t / parts * unit)..(units * (t + 1) / parts * unit).min(panels);
        // SAFETY: the caller checked the bounds; part `t` writes only its panels' columns.
        unsafe { gemm_packed(pool.isa(), src, m, b, range, out.ptr(), ldc, init) }
    });
}

fn check(a: &[f32], lda: usize, m: usize, b: &PackedMatrix, c: &[f32], ldc: usize, init: Init<'_>) {
    if m == 0 || b.n == 0 {
        return;
    }
    assert!(lda >= b.k, "gemm: A stride too small");
    assert!(a.len() >= (m - 1) * lda + b.k, "gemm: A too short");
    check_out(m, b, c, ldc, init);
}

/// [`check`] for `A` given as bf16 pair rows (which needs a bf16 `B`).
fn check_pairs(
    a: &[u32],
    ldp: usize,
    m: usize,
    b: &PackedMatrix,
    c: &[f32],
    ldc: usize,
    init: Init<'_>,
) {
    assert!(
        b.precision == Precision::Bf16,
        "gemm: bf16 pair rows of A need a bf16 B"
    );
    if m == 0 || b.n == 0 {
        return;
    }
    let kp = depth(Precision::Bf16, b.k);
    assert!(ldp >= kp, "gemm: A stride too small");
    assert!(a.len() >= (m - 1) * ldp + kp, "gemm: A too short");
    check_out(m, b, c, ldc, init);
}

/// The bounds of `C` and the bias, for `m > 0` rows.
fn check_out(m: usize, b: &PackedMatrix, c: &[f32], ldc: usize, init: Init<'_>) {
    assert!(ldc >= b.n, "gemm: C stride too small");
    assert!(c.len() >= (m - 1) * ldc + b.n, "gemm: C too short");
    if let Init::Bias(bias) | Init::AccumulateBias(bias) = init {
        assert!(bias.len() >= b.n, "gemm: bias too short");
    }
}

thread_local! {
    /// Per-thread buffer for the rounded rows of [`PackedMatrix::pack_transposed`] in bf16.
    static ROW_PAIRS: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
    /// Per-thread buffer for packed `A` of single-threaded calls.
    static A_PACK: std::cell::RefCell<AlignedBuf> = std::cell::RefCell::new(AlignedBuf::default());
}

/// Rows of the `MC` block starting at `m0`, rounded up to whole tiles.
fn padded_rows(m: usize, m0: usize) -> usize {
    MC.min(m - m0).div_ceil(MR) * MR
}

/// Where block `(m0, k0)` of packed (bf16) `A` starts: blocks are stored `MC` rows at a time,
/// each as its `KC_BF16`-deep slices one after another (see [`pack_a_bf16`] for one slice).
/// Only bf16 `A` is packed: f32 rows are read in place ([`ASource::Rows`]).
fn a_block(k: usize, m: usize, m0: usize, k0: usize) -> usize {
    m0 * depth(Precision::Bf16, k) + depth(Precision::Bf16, k0) * padded_rows(m, m0)
}

/// Pack all of `A` (`m x k`, row stride `lda`) into `buf` in [`a_block`] order, as bf16
/// pairs.
fn pack_a_blocks<'a>(
    isa: Isa,
    a: &[f32],
    lda: usize,
    m: usize,
    k: usize,
    buf: &'a mut AlignedBuf,
) -> &'a [f32] {
    let (units, len) = a_layout(m, k);
    buf.ensure(len);
    let out = &mut buf.as_mut_slice()[..len];
    for unit in 0..units {
        let u = AUnit::new(m, k, unit);
        pack_a_unit(isa, a, lda, &u, &mut out[u.start..u.start + u.size]);
    }
    &buf.as_slice()[..len]
}

/// Below this many values of `A`, packing stays on the calling thread: waking the pool costs
/// more than the copy.
const PAR_PACK_MIN: usize = 32 * 1024;

/// [`pack_a_blocks`] with its `(MC, KC)` blocks split over the pool's threads. Each block is
/// written by one part, the same way as on one thread, so the result is identical.
fn pack_a_blocks_par<'a>(
    pool: &Pool,
    a: &[f32],
    lda: usize,
    m: usize,
    k: usize,
    buf: &'a mut AlignedBuf,
) -> &'a [f32] {
    let (units, len) = a_layout(m, k);
    if m * k < PAR_PACK_MIN || units == 1 || pool.threads() == 1 {
        return pack_a_blocks(pool.isa(), a, lda, m, k, buf);
    }
    buf.ensure(len);
    let out = SharedMut::new(&mut buf.as_mut_slice()[..len]);
    let parts = pool.parts(units);
    pool.run(parts, |t| {
        for unit in units * t / parts..units * (t + 1) / parts {
            let u = AUnit::new(m, k, unit);
            // SAFETY: the units' ranges are disjoint and inside the `len` values of `out`
            // (see `AUnit`); each is written by the one part that owns the unit.
            let dst = unsafe { std::slice::from_raw_parts_mut(out.ptr().add(u.start), u.size) };
            pack_a_unit(pool.isa(), a, lda, &u, dst);
        }
    });
    &buf.as_slice()[..len]
}

/// How many `(MC, KC_BF16)` blocks packed `A` has, and how many values it takes.
fn a_layout(m: usize, k: usize) -> (usize, usize) {
    (
        m.div_ceil(MC) * k.div_ceil(KC_BF16),
        m.div_ceil(MR) * MR * depth(Precision::Bf16, k),
    )
}

/// One block of packed `A`: rows `m0..m0 + mb`, columns `k0..k0 + kc`, stored at
/// `start..start + size` (see [`a_block`]).
struct AUnit {
    m0: usize,
    k0: usize,
    mb: usize,
    kc: usize,
    start: usize,
    size: usize,
}

impl AUnit {
    /// Block number `unit`, `k`-blocks fastest.
    fn new(m: usize, k: usize, unit: usize) -> Self {
        let kcb = KC_BF16;
        let kblocks = k.div_ceil(kcb);
        let (m0, k0) = ((unit / kblocks) * MC, (unit % kblocks) * kcb);
        let (mb, kc) = (MC.min(m - m0), kcb.min(k - k0));
        AUnit {
            m0,
            k0,
            mb,
            kc,
            start: a_block(k, m, m0, k0),
            size: padded_rows(m, m0) * depth(Precision::Bf16, kc),
        }
    }
}

/// Pack block `u` of `A` into `dst`, which holds exactly that block.
fn pack_a_unit(isa: Isa, a: &[f32], lda: usize, u: &AUnit, dst: &mut [f32]) {
    pack_a_bf16(isa, &a[u.m0 * lda + u.k0..], lda, u.mb, u.kc, dst);
}

/// # Safety
/// `c` points to `m` rows of stride `ldc` with at least `b.n` values each, and no other thread
/// touches the columns of `panels` in those rows; `a` holds `m` rows of `b.k` values (packed by
/// [`pack_a_blocks`] in `b`'s precision, or f32 rows in place).
#[allow(clippy::too_many_arguments)]
unsafe fn gemm_packed(
    isa: Isa,
    a: ASource<'_>,
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
    let kernel = Kernel::choose(isa, b.precision);
    // The kernels of whole tiles, looked up once.
    let (whole_tile, whole_pair) = (full_tile_fn(kernel, MR), pair_tile_fn(kernel, MR));
    let d = |rows| depth(b.precision, rows);
    // Zero-initialised outputs start from zero accumulators, biased ones from the bias itself
    // (the first `k` block's accumulators read it in place, the same vector for every row:
    // copying it into C first wrote and read back all of C, 12 MB per MLP layer of the vision
    // tower, and cost 1-2% of it). A bias added to an existing C goes in first, in one pass per
    // row for all of this call's panels.
    if let Init::AccumulateBias(bias) = init {
        let (c0, c1) = (panels.start * NR, (panels.end * NR).min(b.n));
        for r in 0..m {
            // SAFETY: row r, columns c0..c1 are inside C and owned by this call.
            let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc + c0), c1 - c0) };
            super::vecmath::add_assign(isa, row, &bias[c0..c1]);
        }
    }
    if k == 0 {
        let (c0, c1) = (panels.start * NR, (panels.end * NR).min(b.n));
        for r in 0..m {
            // SAFETY: as above.
            let row = unsafe { std::slice::from_raw_parts_mut(c.add(r * ldc + c0), c1 - c0) };
            match init {
                Init::Zero => row.fill(0.0),
                Init::Bias(bias) => row.copy_from_slice(&bias[c0..c1]),
                Init::Accumulate | Init::AccumulateBias(_) => {}
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
            let kc = kc_of(b.precision).min(k - k0);
            // Where this block's accumulators start: C itself after the first block or when
            // accumulating into it, else the bias (or zero).
            let from_c = k0 > 0 || matches!(init, Init::Accumulate | Init::AccumulateBias(_));
            let bias = match init {
                Init::Bias(bias) if !from_c => Some(bias),
                _ => None,
            };
            let mut p = panels.start;
            while p < panels.end {
                let c0 = p * NR;
                let w = NR.min(b.n - c0);
                // Two full panels side by side go to the paired kernel where there is one.
                let pair = kernel.pairs() && p + 1 < panels.end && c0 + 2 * NR <= b.n;
                let step = if pair { 2 } else { 1 };
                let bp = b.panel_ptr(p, k0);
                let bp2 = if pair { b.panel_ptr(p + 1, k0) } else { bp };
                let next = p + step;
                let (next1, next2) = (
                    (next < panels.end).then(|| b.panel_ptr(next, k0)),
                    (pair && next + 1 < panels.end).then(|| b.panel_ptr(next + 1, k0)),
                );
                for t in 0..tiles {
                    let r0 = t * MR;
                    let rows = MR.min(mb - r0);
                    // Pull the next panels into L1 a slice per tile, spread over these panels'
                    // tiles so the misses overlap with computation instead of queueing.
                    let (from, to) = (d(kc) * t / tiles, d(kc) * (t + 1) / tiles);
                    for next in [next1, next2].into_iter().flatten() {
                        prefetch_lines(isa, next, from, to);
                    }
                    // Tile t's first row, and how far apart its rows are.
                    let (ap, ars) = match a {
                        ASource::Packed(packed) => {
                            let start = a_block(k, m, m0, k0) + t * d(kc) * MR;
                            (packed[start..].as_ptr(), d(kc))
                        }
                        ASource::Rows(rows, lda) => (rows[(m0 + r0) * lda + k0..].as_ptr(), lda),
                        // k0 is even (a multiple of KC_BF16): pair k0 / 2 starts the block.
                        ASource::Pairs(rows, ldp) => {
                            (rows[(m0 + r0) * ldp + k0 / 2..].as_ptr().cast::<f32>(), ldp)
                        }
                    };
                    // SAFETY: the tile lies inside C (rows m0+r0.., columns c0..c0+step*w).
                    let cp = unsafe { c.add((m0 + r0) * ldc + c0) };
                    // The next tile's accumulators come from C: start fetching them now.
                    if from_c && t + 1 < tiles {
                        let next_rows = MR.min(mb - r0 - MR);
                        for s in 0..step {
                            let cs = cp.wrapping_add(MR * ldc + s * NR);
                            prefetch_rows(isa, cs, ldc, next_rows);
                        }
                    }
                    let start: Start = if from_c {
                        Some((cp.cast_const(), ldc))
                    } else {
                        // Stride 0: every row starts from the bias of these columns.
                        bias.map(|bias| (bias[c0..].as_ptr(), 0))
                    };
                    // The panel (both panels) hold kc rows, the A tile `rows` rows of kc
                    // values; C and the bias (`n` values) have the tile's columns (two full
                    // panels, or `w`); the looked-up kernels are `kernel`'s.
                    match (pair, rows == MR, whole_pair) {
                        // SAFETY: as above, two full panels, `MR` rows.
                        (true, true, Some(f)) => unsafe { f(kc, ap, ars, bp, bp2, cp, ldc, start) },
                        // SAFETY: as above, two full panels.
                        (true, _, _) => unsafe {
                            tile_pair(kernel, rows, kc, ap, ars, bp, bp2, cp, ldc, start)
                        },
                        // SAFETY: as above, one full panel, `MR` rows.
                        (false, true, _) if w == NR => unsafe {
                            whole_tile(kc, ap, ars, bp, cp, ldc, start)
                        },
                        // SAFETY: as above, one panel of `w` columns.
                        (false, _, _) => unsafe {
                            tile(kernel, rows, kc, ap, ars, bp, cp, ldc, w, start)
                        },
                    }
                }
                p += step;
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

/// Pack `rows x kc` of `A` into row tiles of `MR` bf16 pairs: row `r` of tile `t` (row
/// `t*MR + r` of `A`) is the `ceil(kc / 2)` pairs `(A[r][2i], A[r][2i+1])`, contiguous, rounded
/// straight into place (16 values per instruction with AVX-512F); zero rows past `rows`. The
/// kernel reads a tile's rows through pointers that move together.
fn pack_a_bf16(isa: Isa, a: &[f32], lda: usize, rows: usize, kc: usize, out: &mut [f32]) {
    debug_assert!(kc <= KC_BF16);
    let kp = kc.div_ceil(2);
    for t in 0..rows.div_ceil(MR) {
        let tile = &mut out[t * kp * MR..(t + 1) * kp * MR];
        for (r, dst) in tile.chunks_exact_mut(kp).enumerate() {
            let row = t * MR + r;
            if row < rows {
                round_pairs(isa, &a[row * lda..row * lda + kc], as_pair_bits(dst));
            } else {
                dst.fill(0.0);
            }
        }
    }
}

/// The packed bf16 pairs of a tile row as the `u32` bit patterns [`round_pairs`] writes.
fn as_pair_bits(values: &mut [f32]) -> &mut [u32] {
    // SAFETY: f32 and u32 have the same size and alignment, and every bit pattern is valid for
    // both; the returned slice borrows `values` exclusively for its lifetime.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<u32>(), values.len()) }
}

/// `pairs[i] = bf16(src[2i]) | bf16(src[2i + 1]) << 16` ([`to_bf16`] rounding; a missing last
/// odd value is 0). `pairs` holds `ceil(src.len() / 2)` values. The vector path runs with
/// `isa`'s kernels (the same bits either way).
pub fn round_pairs(isa: Isa, src: &[f32], pairs: &mut [u32]) {
    debug_assert_eq!(pairs.len(), src.len().div_ceil(2));
    round_pairs_with(isa, super::cpu_has_avx512_bf16(), src, pairs);
}

/// [`round_pairs`], with `vcvtneps2bf16` where `native_bf16` (the CPU has AVX512_BF16).
fn round_pairs_with(isa: Isa, native_bf16: bool, src: &[f32], pairs: &mut [u32]) {
    debug_assert_eq!(pairs.len(), src.len().div_ceil(2));
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 {
        done = if native_bf16 {
            // SAFETY: `Isa::Avx512` is only chosen on a CPU with AVX-512F; the caller says
            // this one has AVX512_BF16.
            unsafe { round_pairs_avx512_bf16(src, pairs) }
        } else {
            // SAFETY: `Isa::Avx512` is only chosen on a CPU with AVX-512F.
            unsafe { round_pairs_avx512(src, pairs) }
        };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (isa, native_bf16);
    let (src, pairs) = (&src[2 * done..], &mut pairs[done..]);
    let whole = src.chunks_exact(2);
    let last = whole.remainder().first().copied();
    let n = whole.len();
    for (p, two) in pairs.iter_mut().zip(whole) {
        *p = bf16_pair(two[0], two[1]).to_bits();
    }
    if let Some(x) = last {
        pairs[n] = bf16_pair(x, 0.0).to_bits();
    }
}

/// [`round_pairs`] for the leading multiple of 16 values of `src`; returns the pairs written.
/// Per lane, exactly [`bf16_bits`] (integer rounding, so no DAZ/FTZ as `vcvtne2ps2bf16` would
/// apply to denormals); `vpmovdw` then keeps each lane's low 16 bits, in order, which packs the
/// bf16 values of `src[2i]` and `src[2i + 1]` into the 32-bit lane `i`.
///
/// # Safety
/// Requires AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn round_pairs_avx512(src: &[f32], pairs: &mut [u32]) -> usize {
    use std::arch::x86_64::*;
    let blocks = src.len() / 16;
    for b in 0..blocks {
        // SAFETY: values 16b..16b+16 are inside `src`; pairs 8b..8b+8 inside `pairs` (which
        // holds ceil(len / 2) values); both accesses are unaligned.
        unsafe {
            let v = _mm512_loadu_si512(src.as_ptr().add(16 * b) as *const _);
            let packed = round16(v);
            _mm256_storeu_si256(pairs.as_mut_ptr().add(8 * b) as *mut __m256i, packed);
        }
    }
    8 * blocks
}

/// [`bf16_bits`] on the 16 lanes of `v`, packed into 16 bf16 values in order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
fn round16(v: std::arch::x86_64::__m512i) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let high = _mm512_srli_epi32::<16>(v);
    let round = _mm512_add_epi32(
        _mm512_set1_epi32(0x7fff),
        _mm512_and_si512(high, _mm512_set1_epi32(1)),
    );
    let rounded = _mm512_srli_epi32::<16>(_mm512_add_epi32(v, round));
    let magnitude = _mm512_and_si512(v, _mm512_set1_epi32(0x7fff_ffff));
    let nan = _mm512_cmpgt_epu32_mask(magnitude, _mm512_set1_epi32(0x7f80_0000));
    let quiet = _mm512_or_si512(high, _mm512_set1_epi32(0x40));
    _mm512_cvtepi32_epi16(_mm512_mask_blend_epi32(nan, rounded, quiet))
}

/// [`round_pairs_avx512`] with one `vcvtneps2bf16` per 16 values where it gives the same bits:
/// it rounds to nearest even and quiets NaNs exactly as [`bf16_bits`] does, but reads denormal
/// inputs as zero, so a block holding a denormal takes the integer rounding instead. Once the
/// rounding of the attention probabilities moved into L1 (the softmax's last pass), its
/// instruction count was what remained of its cost.
///
/// # Safety
/// Requires AVX-512F and AVX512_BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
pub(crate) unsafe fn round_pairs_avx512_bf16(src: &[f32], pairs: &mut [u32]) -> usize {
    use std::arch::x86_64::*;
    let blocks = src.len() / 16;
    let exponent = _mm512_set1_epi32(0x7f80_0000);
    let mantissa = _mm512_set1_epi32(0x007f_ffff);
    let (src, dst) = (src.as_ptr(), pairs.as_mut_ptr());
    for b in 0..blocks {
        // SAFETY: values 16b..16b+16 are inside `src`; pairs 8b..8b+8 inside `pairs` (which
        // holds ceil(len / 2) values); both accesses are unaligned. The asm only converts
        // registers.
        unsafe {
            let v = _mm512_loadu_si512(src.add(16 * b) as *const _);
            let denormal =
                _mm512_testn_epi32_mask(v, exponent) & _mm512_test_epi32_mask(v, mantissa);
            let packed = if denormal == 0 {
                let out: __m256i;
                std::arch::asm!(
                    "vcvtneps2bf16 {out}, {v}",
                    out = lateout(ymm_reg) out,
                    v = in(zmm_reg) v,
                    options(pure, nomem, nostack, preserves_flags),
                );
                out
            } else {
                round16(v)
            };
            _mm256_storeu_si256(dst.add(8 * b) as *mut __m256i, packed);
        }
    }
    8 * blocks
}

/// Where a micro-kernel's accumulators start: zero (`None`), or row `r` from the values at
/// `ptr + r * stride` (`C` itself to accumulate into it; a bias, stride 0, for every row).
type Start = Option<(*const f32, usize)>;

/// Which micro-kernel multiplies a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kernel {
    /// f32 panels with this instruction set's kernel.
    F32(Isa),
    /// bf16 panels with `vdpbf16ps` (AVX512_BF16).
    Bf16Avx512,
    /// bf16 panels in portable code.
    Bf16Portable,
}

impl Kernel {
    fn choose(isa: Isa, precision: Precision) -> Kernel {
        match precision {
            Precision::F32 => Kernel::F32(isa),
            Precision::Bf16 if isa == Isa::Avx512 && super::cpu_has_avx512_bf16() => {
                Kernel::Bf16Avx512
            }
            Precision::Bf16 => Kernel::Bf16Portable,
        }
    }

    /// Whether [`tile_pair`] has a kernel for two panels at once: the AVX512_BF16 one. There
    /// one panel row is a single register, so a one-panel tile has only `MR` (x 2 for even and
    /// odd pairs) accumulators and spends a load of `A` on every product; two panels share
    /// each broadcast `A` pair between two products and double the independent chains. An f32
    /// AVX-512 pair kernel measured no faster at M = 1024 and ~5% slower at the expert's
    /// M = 50 (`gemm_timing`), so f32 keeps one panel per call.
    fn pairs(self) -> bool {
        matches!(self, Kernel::Bf16Avx512)
    }
}

/// `$step!(kk)` for `kk` in `0..$n`, in order, four per loop iteration (the f32 kernels' loop).
macro_rules! unroll4 {
    ($n:expr, $step:ident) => {{
        let mut kk = 0;
        while kk + 4 <= $n {
            $step!(kk);
            $step!(kk + 1);
            $step!(kk + 2);
            $step!(kk + 3);
            kk += 4;
        }
        while kk < $n {
            $step!(kk);
            kk += 1;
        }
    }};
}

/// One `rows x w` tile (`rows <= MR`, `w <= NR`): `C = S + A · B` over `kc`, where `S` is
/// `start`'s rows (zero for `None`). Row `r` of the tile's `A` starts at `a + r * ars`: f32 rows
/// in place, or bf16 pair rows packed by [`pack_a_bf16`].
///
/// # Safety
/// `a` has `rows` rows `ars` apart of `kc` values (bf16: `ceil(kc / 2)` pairs), `b` has `kc`
/// rows of `NR` values (pair rows in bf16), `c` has `rows` rows of stride `ldc` with `w`
/// values, and so has `start` (rows `stride` apart) when given.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(
    kernel: Kernel,
    rows: usize,
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    w: usize,
    start: Start,
) {
    if w < NR {
        // Edge panel: run the full-width kernel on a scratch tile, copy the valid columns.
        let mut scratch = [0.0f32; MR * NR];
        if let Some((src, lds)) = start {
            for r in 0..rows {
                for j in 0..w {
                    // SAFETY: inside the caller's start rows (`w` values each).
                    scratch[r * NR + j] = unsafe { *src.add(r * lds + j) };
                }
            }
        }
        // SAFETY: scratch is a full MR x NR tile.
        unsafe {
            tile(
                kernel,
                rows,
                kc,
                a,
                ars,
                b,
                scratch.as_mut_ptr(),
                NR,
                NR,
                start.map(|_| (scratch.as_ptr(), NR)),
            )
        };
        for r in 0..rows {
            for j in 0..w {
                // SAFETY: inside the caller's C tile.
                unsafe { *c.add(r * ldc + j) = scratch[r * NR + j] };
            }
        }
        return;
    }
    // SAFETY: the caller's contract, for a full-width tile of `rows` rows.
    unsafe { full_tile_fn(kernel, rows)(kc, a, ars, b, c, ldc, start) }
}

/// A micro-kernel on a full-width tile: `(kc, a, ars, b, c, ldc, start)` as [`tile`] takes them.
type TileFn = unsafe fn(usize, *const f32, usize, *const f32, *mut f32, usize, Start);

/// The micro-kernel of `kernel` for full-width tiles of `rows` rows (`1..=MR`). The driver
/// loop looks it up once per GEMM for whole tiles and calls it directly: going through
/// [`tile`]'s dispatch for every tile (a large stack frame, kept for the edge panels' scratch
/// tile) was 2-3% of an f32 forward pass.
fn full_tile_fn(kernel: Kernel, rows: usize) -> TileFn {
    macro_rules! pick {
        ($f:ident) => {
            match rows {
                6 => $f::<6> as TileFn,
                5 => $f::<5>,
                4 => $f::<4>,
                3 => $f::<3>,
                2 => $f::<2>,
                _ => $f::<1>,
            }
        };
    }
    // Each kernel's CPU requirement holds for the `Kernel` it is picked for: `Isa::Avx2Fma`
    // and `Isa::Avx512` are only reported on CPUs with those features, and `Kernel::choose`
    // picks `Bf16Avx512` only on a CPU with AVX-512F and AVX512_BF16.
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::F32(Isa::Avx2Fma) => pick!(kernel_avx2),
        #[cfg(target_arch = "x86_64")]
        Kernel::F32(Isa::Avx512) => pick!(kernel_avx512),
        #[cfg(target_arch = "x86_64")]
        Kernel::Bf16Avx512 => pick!(kernel_bf16_avx512),
        Kernel::Bf16Portable => pick!(kernel_bf16_portable),
        _ => pick!(kernel_portable),
    }
}

/// A micro-kernel on two full-width panels: `(kc, a, ars, b, b2, c, ldc, start)` as
/// [`tile_pair`] takes them.
type PairFn = unsafe fn(usize, *const f32, usize, *const f32, *const f32, *mut f32, usize, Start);

/// The two-panel micro-kernel of `kernel` for `rows` rows, where it has one
/// ([`Kernel::pairs`]; the CPU requirement as in [`full_tile_fn`]).
fn pair_tile_fn(kernel: Kernel, rows: usize) -> Option<PairFn> {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Bf16Avx512 => Some(match rows {
            6 => kernel_bf16_avx512_pair::<6> as PairFn,
            5 => kernel_bf16_avx512_pair::<5>,
            4 => kernel_bf16_avx512_pair::<4>,
            3 => kernel_bf16_avx512_pair::<3>,
            2 => kernel_bf16_avx512_pair::<2>,
            _ => kernel_bf16_avx512_pair::<1>,
        }),
        _ => None,
    }
}

/// Two full-width panels side by side (`C` columns `0..2 * NR`), `rows <= MR` rows: the same
/// products in the same order per output value as two [`tile`] calls, so the same bits.
///
/// # Safety
/// As [`tile`] for each panel (`b` and `b2` each hold `kc` rows of `NR` values), `c` has
/// `rows` rows of `2 * NR` values; `kernel.pairs()`.
#[allow(clippy::too_many_arguments)]
unsafe fn tile_pair(
    kernel: Kernel,
    rows: usize,
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    b2: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    match pair_tile_fn(kernel, rows) {
        // SAFETY: the caller's contract.
        Some(f) => unsafe { f(kc, a, ars, b, b2, c, ldc, start) },
        _ => {
            // SAFETY: the caller's contract, one panel at a time.
            unsafe {
                tile(kernel, rows, kc, a, ars, b, c, ldc, NR, start);
                tile(
                    kernel,
                    rows,
                    kc,
                    a,
                    ars,
                    b2,
                    c.add(NR),
                    ldc,
                    NR,
                    start.map(|(p, s)| (p.wrapping_add(NR), s)),
                );
            }
        }
    }
}

/// # Safety
/// See [`tile`]; requires AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn kernel_avx2<const R: usize>(
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    use std::arch::x86_64::*;
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    if let Some((src, lds)) = start {
        for (r, row) in acc.iter_mut().enumerate() {
            // SAFETY: start row r has NR values.
            unsafe {
                row[0] = _mm256_loadu_ps(src.add(r * lds));
                row[1] = _mm256_loadu_ps(src.add(r * lds + 8));
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
                    let av = _mm256_broadcast_ss(&*a.add(r * ars + $kk));
                    acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
                    acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
                }
            }
        }};
    }
    unroll4!(kc, step);
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
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    use std::arch::x86_64::*;
    let mut acc = [_mm512_setzero_ps(); R];
    if let Some((src, lds)) = start {
        for (r, row) in acc.iter_mut().enumerate() {
            // SAFETY: start row r has NR values.
            *row = unsafe { _mm512_loadu_ps(src.add(r * lds)) };
        }
    }
    macro_rules! step {
        ($kk:expr) => {{
            // SAFETY: $kk < kc: inside the panel (64-byte aligned rows) and the packed A tile.
            unsafe {
                let bv = _mm512_load_ps(b.add($kk * NR));
                for r in 0..R {
                    let av = _mm512_set1_ps(*a.add(r * ars + $kk));
                    acc[r] = _mm512_fmadd_ps(av, bv, acc[r]);
                }
            }
        }};
    }
    unroll4!(kc, step);
    for (r, row) in acc.iter().enumerate() {
        // SAFETY: row r of the C tile has NR values.
        unsafe { _mm512_storeu_ps(c.add(r * ldc), *row) };
    }
}

/// [`kernel_bf16_avx512`] over two panels: even and odd accumulators for each (`4R` in all,
/// the same pairing as the one-panel kernel, so the same bits), each `A` pair broadcast from
/// memory into both panels' instructions.
///
/// # Safety
/// See [`tile_pair`], with bf16 pair rows; requires AVX-512F and AVX512_BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn kernel_bf16_avx512_pair<const R: usize>(
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    b2: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    use std::arch::x86_64::*;
    let mut even = [_mm512_setzero_ps(); R];
    let mut odd = [_mm512_setzero_ps(); R];
    let mut even2 = [_mm512_setzero_ps(); R];
    let mut odd2 = [_mm512_setzero_ps(); R];
    if let Some((src, lds)) = start {
        for r in 0..R {
            // SAFETY: start row r has 2 * NR values.
            unsafe {
                even[r] = _mm512_loadu_ps(src.add(r * lds));
                even2[r] = _mm512_loadu_ps(src.add(r * lds + NR));
            }
        }
    }
    let kp = kc.div_ceil(2);
    macro_rules! step {
        ($acc:ident, $acc2:ident, $i:expr) => {{
            // SAFETY: $i < ceil(kc / 2): inside both panels (64-byte aligned rows) and the A
            // tile; raw bits as in the one-panel kernel. The asm reads the 4-byte A pair of
            // row r and writes only its two accumulator registers.
            unsafe {
                let bl = _mm512_load_ps(b.add($i * NR));
                let br = _mm512_load_ps(b2.add($i * NR));
                for r in 0..R {
                    std::arch::asm!(
                        "vdpbf16ps {acc}, {b}, dword ptr [{p}]{{1to16}}",
                        "vdpbf16ps {acc2}, {b2}, dword ptr [{p}]{{1to16}}",
                        acc = inout(zmm_reg) $acc[r],
                        acc2 = inout(zmm_reg) $acc2[r],
                        b = in(zmm_reg) bl,
                        b2 = in(zmm_reg) br,
                        p = in(reg) a.add(r * ars + $i),
                        options(nostack, readonly, preserves_flags),
                    );
                }
            }
        }};
    }
    let mut i = 0;
    while i + 2 <= kp {
        step!(even, even2, i);
        step!(odd, odd2, i + 1);
        i += 2;
    }
    if i < kp {
        step!(even, even2, i);
    }
    // Indexed, not zipped: see the one-panel kernel.
    for r in 0..R {
        // SAFETY: row r of the C tile has 2 * NR values.
        unsafe {
            _mm512_storeu_ps(c.add(r * ldc), _mm512_add_ps(even[r], odd[r]));
            _mm512_storeu_ps(c.add(r * ldc + NR), _mm512_add_ps(even2[r], odd2[r]));
        }
    }
}

/// `ceil(kc / 2)` steps of one `vdpbf16ps` per row: the panel row (16 lanes of bf16 pairs) times
/// the row's broadcast `A` pair, both products added to an f32 accumulator. Even and odd pairs
/// go to two accumulators per row (summed at the end), so that 2R independent chains hide the
/// instruction's latency (6 cycles on Zen 4, where R = 6 alone would stall).
///
/// # Safety
/// See [`tile`], with bf16 pair rows; requires AVX-512F and AVX512_BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn kernel_bf16_avx512<const R: usize>(
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    use std::arch::x86_64::*;
    let mut even = [_mm512_setzero_ps(); R];
    let mut odd = [_mm512_setzero_ps(); R];
    if let Some((src, lds)) = start {
        for (r, row) in even.iter_mut().enumerate() {
            // SAFETY: start row r has NR values.
            *row = unsafe { _mm512_loadu_ps(src.add(r * lds)) };
        }
    }
    let kp = kc.div_ceil(2);
    macro_rules! step {
        ($acc:ident, $i:expr) => {{
            // SAFETY: $i < ceil(kc / 2): inside the panel (64-byte aligned rows) and the A
            // tile; the load moves raw bits (bf16 pairs stored as f32 bit patterns). The asm
            // reads the 4-byte A pair of row r and writes only its accumulator register.
            unsafe {
                let bv = _mm512_load_ps(b.add($i * NR));
                for r in 0..R {
                    // The A pair is broadcast from memory inside the instruction (`{1to16}`):
                    // LLVM emits a separate `vbroadcastss` for the intrinsic, which on Zen 4
                    // costs a vector uop per product and 30% of the kernel's speed.
                    std::arch::asm!(
                        "vdpbf16ps {acc}, {b}, dword ptr [{p}]{{1to16}}",
                        acc = inout(zmm_reg) $acc[r],
                        b = in(zmm_reg) bv,
                        p = in(reg) a.add(r * ars + $i),
                        options(nostack, readonly, preserves_flags),
                    );
                }
            }
        }};
    }
    let mut i = 0;
    while i + 4 <= kp {
        step!(even, i);
        step!(odd, i + 1);
        step!(even, i + 2);
        step!(odd, i + 3);
        i += 4;
    }
    while i + 2 <= kp {
        step!(even, i);
        step!(odd, i + 1);
        i += 2;
    }
    if i < kp {
        step!(even, i);
    }
    // Indexed, not zipped: borrowing the accumulator arrays as slices kept them in memory
    // (a store after every `vdpbf16ps`) and cost a third of the kernel's speed.
    #[allow(clippy::needless_range_loop)]
    for r in 0..R {
        // SAFETY: row r of the C tile has NR values.
        unsafe { _mm512_storeu_ps(c.add(r * ldc), _mm512_add_ps(even[r], odd[r])) };
    }
}

/// What [`kernel_bf16_avx512`] computes, in scalar code: per pair, the odd product then the
/// even one added to the accumulator of the pair's parity (each product is exact in f32), the
/// two accumulators summed at the end. Its rounding of the two additions may differ from a given
/// CPU's `vdpbf16ps` by an ulp of the accumulator.
///
/// # Safety
/// See [`tile`], with bf16 pair rows.
unsafe fn kernel_bf16_portable<const R: usize>(
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    let widen = |pair: f32| {
        let bits = pair.to_bits();
        (
            f32::from_bits(bits << 16),
            f32::from_bits(bits & 0xffff_0000),
        )
    };
    let mut acc = [[[0.0f32; NR]; R]; 2];
    if let Some((src, lds)) = start {
        for (r, row) in acc[0].iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                // SAFETY: start row r has NR values.
                *v = unsafe { *src.add(r * lds + j) };
            }
        }
    }
    let kp = kc.div_ceil(2);
    for i in 0..kp {
        // SAFETY: i < ceil(kc / 2): inside the panel and each row of the packed A tile.
        let (brow, arow) = unsafe {
            (
                std::slice::from_raw_parts(b.add(i * NR), NR),
                std::array::from_fn::<f32, R, _>(|r| *a.add(r * ars + i)),
            )
        };
        for (row, &ap) in acc[i % 2].iter_mut().zip(&arow) {
            let (a0, a1) = widen(ap);
            for (v, &bp) in row.iter_mut().zip(brow) {
                let (b0, b1) = widen(bp);
                *v += a1 * b1;
                *v += a0 * b0;
            }
        }
    }
    for (r, (e, o)) in acc[0].iter().zip(&acc[1]).enumerate() {
        for (j, (x, y)) in e.iter().zip(o).enumerate() {
            // SAFETY: row r of the C tile has NR values.
            unsafe { *c.add(r * ldc + j) = x + y };
        }
    }
}

/// # Safety
/// See [`tile`].
unsafe fn kernel_portable<const R: usize>(
    kc: usize,
    a: *const f32,
    ars: usize,
    b: *const f32,
    c: *mut f32,
    ldc: usize,
    start: Start,
) {
    let mut acc = [[0.0f32; NR]; R];
    if let Some((src, lds)) = start {
        for (r, row) in acc.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                // SAFETY: start row r has NR values.
                *v = unsafe { *src.add(r * lds + j) };
            }
        }
    }
    for kk in 0..kc {
        // SAFETY: kk < kc: inside the panel and the packed A tile.
        let (brow, arow) = unsafe {
            (
                std::slice::from_raw_parts(b.add(kk * NR), NR),
                std::array::from_fn::<f32, R, _>(|r| *a.add(r * ars + kk)),
            )
        };
        for (row, &av) in acc.iter_mut().zip(&arow) {
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
                let mut cab = cb.clone();
                gemm_par(
                    &pool,
                    &a,
                    k,
                    m,
                    &packed,
                    &mut cab,
                    n,
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
                gemm(isa, &a, k, m, &packed, &mut want, n, Init::Bias(&bias));
                let mut one = vec![0.0; m * n];
                gemm_pairs(isa, &pairs, ldp, m, &packed, &mut one, n, Init::Bias(&bias));
                let mut split = vec![0.0; m * n];
                gemm_par_pairs(
                    &pool,
                    &pairs,
                    ldp,
                    m,
                    &packed,
                    &mut split,
                    n,
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
            rows.gemm_par(&pool, m, &packed, &mut got, n, Init::Zero);
            let mut want = vec![0.0; m * n];
            gemm_par(&pool, &a, k, m, &packed, &mut want, n, Init::Zero);
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
                    gemm(isa, &a, k, m, &packed, &mut want, n, Init::Accumulate);
                    let mut got = vec![f32::NAN; m * n];
                    gemm_par(&pool, &a, k, m, &packed, &mut got, n, Init::Bias(&bias));
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
                let pa = match precision {
                    Precision::F32 => ASource::Rows(&a, k),
                    Precision::Bf16 => {
                        ASource::Packed(pack_a_blocks(isa, &a, k, m, k, &mut pack_buf))
                    }
                };
                let panels = packed.panels();
                let mut whole = vec![0.0; m * n];
                let mut split = vec![0.0; m * n];
                // SAFETY: both outputs hold m rows of n values; one thread writes each.
                unsafe {
                    gemm_packed(
                        isa,
                        pa,
                        m,
                        &packed,
                        0..panels,
                        whole.as_mut_ptr(),
                        n,
                        Init::Zero,
                    );
                    gemm_packed(isa, pa, m, &packed, 0..1, split.as_mut_ptr(), n, Init::Zero);
                    gemm_packed(
                        isa,
                        pa,
                        m,
                        &packed,
                        1..panels,
                        split.as_mut_ptr(),
                        n,
                        Init::Zero,
                    );
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
                gemm_par(&pool, &a, k, 50, &packed, &mut full, n, Init::Zero);
                for start in [0, 7, 49] {
                    let mut one = vec![0.0; n];
                    gemm(isa, &a[start * k..], k, 1, &packed, &mut one, n, Init::Zero);
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
        gemm(Isa::Avx512, &a, k, m, &packed, &mut c512, n, Init::Zero);
        gemm(Isa::Avx2Fma, &a, k, m, &packed, &mut c2, n, Init::Zero);
        assert_eq!(c512, c2);
    }

    /// bf16 GEMM vs an f64 reference. Each operand is rounded to bf16 (relative error at most
    /// u = 2^-9, round to nearest with 8 significand bits), the products of bf16 values are
    /// exact in f32, and the f32 sum of k terms adds at most about k * 2^-24 of `sum |a||b|`:
    /// so `|C - C_exact| <= (2u + u^2 + k 2^-24 (1 + 2u)) * sum_k |a_k||b_k|`, checked with a
    /// 10% margin on the accumulation term. The result must also differ from the f32 GEMM (the
    /// rounding happened) and the packed weights take half the f32 memory.
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
            assert_eq!(
                p16.buf.as_slice().len(),
                n.div_ceil(NR) * NR * k.div_ceil(2)
            );
            let u = 2f64.powi(-9);
            let rel = 2.0 * u + u * u + 1.1 * k as f64 * 2f64.powi(-24) * (1.0 + 2.0 * u);
            for &isa in &kernels {
                let mut c = vec![f32::NAN; m * n];
                let pool = Pool::with_isa(2, isa).unwrap();
                gemm_par(&pool, &a, k, m, &p16, &mut c, n, Init::Bias(&bias));
                let mut c32 = vec![0.0; m * n];
                gemm(isa, &a, k, m, &p32, &mut c32, n, Init::Bias(&bias));
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

    #[test]
    fn to_bf16_rounds_to_nearest_even() {
        assert_eq!(to_bf16(1.0), 0x3f80);
        // 1 + 2^-8 is halfway between 1 and 1 + 2^-7: ties go to the even 1.0.
        assert_eq!(to_bf16(1.0 + 2f32.powi(-8)), 0x3f80);
        assert_eq!(to_bf16(1.0 + 3.0 * 2f32.powi(-8)), 0x3f82);
        assert_eq!(to_bf16(-2.0), 0xc000);
        assert!(f32::from_bits(u32::from(to_bf16(f32::NAN)) << 16).is_nan());
        assert_eq!(to_bf16(f32::INFINITY), 0x7f80);
    }

    /// The vector rounding of `A` (AVX-512F where present) gives exactly `to_bf16` on every
    /// kind of value: ties both ways, denormals (not flushed), infinities, NaNs (quieted), the
    /// largest finite values (rounding up to infinity), and a trailing odd value.
    #[test]
    fn round_pairs_equals_to_bf16_on_special_values() {
        let mut vals = vec![
            0.0,
            -0.0,
            1.0,
            1.0 + 2f32.powi(-8),
            1.0 + 3.0 * 2f32.powi(-8),
            -1.0 - 2f32.powi(-8),
            f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x0000_8000),
            f32::from_bits(0x0001_8000),
            -f32::from_bits(0x007f_ffff),
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::from_bits(0x7f80_0001),
            f32::from_bits(0xff80_0001),
            f32::from_bits(0x7fbf_ffff),
        ];
        vals.extend(data(77, 9).iter().map(|v| v * 1e-39));
        vals.extend(data(64, 10));
        // The same values with the denormals moved to the end, so that the first blocks run
        // the `vcvtneps2bf16` path and the last ones its integer fallback.
        let mut normal_first = vals.clone();
        normal_first.sort_by_key(|v| v.is_subnormal());
        let native = crate::kernels::cpu_has_avx512_bf16();
        let paths = [
            (Isa::detect(), false),
            (Isa::detect(), native),
            (Isa::Portable, false),
        ];
        for (vals, (isa, native), len) in [&vals, &normal_first].into_iter().flat_map(|vals| {
            paths.into_iter().flat_map(move |path| {
                [0, 1, 15, 16, 17, 31, 32, 33, vals.len()].map(move |len| (vals, path, len))
            })
        }) {
            let src = &vals[..len];
            let mut pairs = vec![0u32; len.div_ceil(2)];
            round_pairs_with(isa, native, src, &mut pairs);
            for (i, &x) in src.iter().enumerate() {
                let got = (pairs[i / 2] >> (16 * (i % 2))) as u16;
                assert_eq!(
                    got,
                    to_bf16(x),
                    "{isa:?} native bf16 {native} len {len} [{i}] {x:e} ({:#x})",
                    x.to_bits()
                );
            }
            if len % 2 == 1 {
                assert_eq!(
                    pairs[len / 2] >> 16,
                    0,
                    "{isa:?} len {len}: the missing odd value is 0"
                );
            }
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
        p.pack_rows(Isa::detect(), &bt, n, k, n);
        let q = PackedMatrix::from_linear_weight(&w, n, k);
        assert_eq!(
            p.buf.as_slice()[..p.panels() * k * NR],
            q.buf.as_slice()[..q.panels() * k * NR]
        );
    }

    /// The bf16 transposed and row packings (rounded by the vector code) against the
    /// element-by-element packing, bit for bit, with ragged `k` (a lone last pair), ragged
    /// `n` (an edge panel), more than one `KC_BF16` block, and a row stride wider than `k`.
    #[test]
    fn bf16_pack_transposed_equals_elementwise_packing() {
        for &(n, k, ldw) in &[(21, 9, 9), (40, 64, 200), (17, KC_BF16 + 37, KC_BF16 + 40)] {
            let mut w = data(n * ldw, 13);
            w[3] = f32::NAN;
            w[4] = 1.0 + 2f32.powi(-8);
            w[5] = f32::from_bits(1);
            let want = {
                let mut m = PackedMatrix::empty_in(Precision::Bf16);
                m.pack_with(k, n, |kk, j| w[j * ldw + kk]);
                m
            };
            for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
                .into_iter()
                .filter(|i| i.available())
            {
                let mut got = PackedMatrix::empty_in(Precision::Bf16);
                got.pack_transposed(isa, &w, ldw, n, k);
                let len = want.panels() * NR * depth(Precision::Bf16, k);
                let bits = |m: &PackedMatrix| -> Vec<u32> {
                    m.buf.as_slice()[..len]
                        .iter()
                        .map(|v| v.to_bits())
                        .collect()
                };
                assert_eq!(bits(&got), bits(&want), "{isa:?} n={n} k={k}");
                // The same matrix given row by row (`k` rows of `n`, stride `n + 3`).
                let ldb = n + 3;
                let mut rows = vec![0.0f32; k * ldb];
                for kk in 0..k {
                    for j in 0..n {
                        rows[kk * ldb + j] = w[j * ldw + kk];
                    }
                }
                let mut by_rows = PackedMatrix::empty_in(Precision::Bf16);
                by_rows.pack_rows(isa, &rows, ldb, k, n);
                assert_eq!(bits(&by_rows), bits(&want), "rows {isa:?} n={n} k={k}");
                // From rows already rounded to pairs (row strides of 5 and 2 spare pairs): the
                // same panels, transposed and by rows.
                let round = |src: &[f32], count: usize, width: usize, ld: usize, ldp: usize| {
                    let mut pairs = vec![0u32; count * ldp];
                    for r in 0..count {
                        let dst = &mut pairs[r * ldp..r * ldp + width.div_ceil(2)];
                        round_pairs(isa, &src[r * ld..r * ld + width], dst);
                    }
                    pairs
                };
                let ldp = k.div_ceil(2) + 5;
                let mut from_pairs = PackedMatrix::empty_in(Precision::Bf16);
                from_pairs.pack_transposed_pairs(&round(&w, n, k, ldw, ldp), ldp, n, k);
                assert_eq!(bits(&from_pairs), bits(&want), "pairs {isa:?} n={n} k={k}");
                let ldp = n.div_ceil(2) + 2;
                let mut rows_pairs = PackedMatrix::empty_in(Precision::Bf16);
                rows_pairs.pack_rows_pairs(&round(&rows, k, n, ldb, ldp), ldp, k, n);
                assert_eq!(
                    bits(&rows_pairs),
                    bits(&want),
                    "row pairs {isa:?} n={n} k={k}"
                );
            }
        }
    }
}
