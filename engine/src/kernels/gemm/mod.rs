//! `C = init + A · B` in f32 with `B` packed once into column panels.
//!
//! `A` is any row-major matrix (an activation, read in place); `B` is a [`PackedMatrix`]: the
//! right operand cut into panels of [`NR`] columns, each stored as rows of `NR` contiguous
//! floats (64 bytes: one cache line), in blocks of `KC` rows. The micro-kernel keeps an
//! `MR x NR` block of `C` in 12 AVX2 registers and streams one panel row (two vector loads) and
//! `MR` broadcasts of `A` per step of `k`: 12 FMAs per 8 loads. Blocking: `KC` rows of a panel
//! (16 KiB) stay in L1 while all row tiles of an `MC`-row block of `A` (in L2) pass over them.
//! The kernel reads a tile's `MR` rows of `A` through pointers that advance together: f32 rows
//! straight from the caller's matrix, bf16 rows from a packed copy (rounded into pairs per
//! `MC x KC_BF16` block, each row contiguous, so that the rounding stores whole vectors where an
//! interleaved layout would scatter single values). [`gemm_par`] packs a bf16 `A` on the pool's
//! threads, one block per unit.
//!
//! On CPUs with AVX-512F the same tile is `MR` 512-bit accumulators (one per row; a panel row
//! is one vector), with `A` broadcast from memory inside each FMA: fewer instructions per FLOP,
//! same packing and the same order of operations, so AVX-512 and AVX2 results are bit-identical.
//! In bf16, two full panels side by side run together in one call (`MR x 2 NR`): each broadcast
//! `A` pair then feeds two products and twice as many chains hide the latency of `vdpbf16ps`;
//! the order of operations per element is unchanged, so the pairing, which depends on where a
//! thread's panels start, changes no bit.
//!
//! In [`Precision::Bf16`] the panels hold bf16 pairs instead: row `i` of a panel is the 32-bit
//! lanes `(B[2i][j], B[2i+1][j])` for its `NR` columns (still one cache line, now covering two
//! values of `k`), and `A` is rounded to bf16 (nearest, ties to even, [`super::bf16`]) when
//! packed, as pairs `(A[r][2i], A[r][2i+1])`. The AVX512_BF16 kernel multiplies a pair by a pair
//! and adds both products to an f32 accumulator in one `vdpbf16ps`; a portable kernel does the
//! same in scalar code on other CPUs. The products of two bf16 values are exact in f32, so the
//! error is the rounding of the operands (relative 2^-9 each) plus f32 accumulation. A bf16
//! block is `KC_BF16` values of `k` deep (16 KiB of panel).
//!
//! Every element of `C` accumulates its `k` products in increasing `k` order, one FMA each, in
//! `KC`-sized blocks (`KC_BF16` in bf16). That order depends on neither `m`, the row tile an
//! element falls in, nor the thread split, so results do not depend on the batch size.
//!
//! The parts: this file holds the entry points and the split over threads; `pack_b` packs `B`
//! ([`PackedMatrix`]), `pack_a` packs a bf16 `A`, `activation_rows` makes `A` row by row
//! ([`ActivationRows`]); `driver` runs the blocked loop over cache blocks, panels and row
//! tiles, and `tile` picks the micro-kernel of a tile: `avx512`, `avx2`, `bf16_avx512`
//! (`vdpbf16ps`) or `portable`.

mod activation_rows;
mod avx2;
mod avx512;
mod bf16_avx512;
mod driver;
mod pack_a;
mod pack_b;
mod portable;
mod tile;

#[cfg(test)]
mod tests;

pub use activation_rows::{ActivationRows, round_rows_par};
pub use pack_b::PackedMatrix;

use super::matrix::{MatMut, MatRef};
use super::{Isa, Pool, Precision};
use driver::{COut, gemm_packed};
use pack_a::{A_PACK, ASource, pack_a_blocks, pack_a_blocks_par};
use tile::Kernel;

/// Columns per packed panel (two AVX2 vectors).
pub const NR: usize = 16;
/// Rows per micro-kernel tile.
pub const MR: usize = 6;
/// Depth of one cache block in f32 (`KC` rows of a 64-byte panel row: 16 KiB, half of L1).
/// 256 rather than 128: each micro-kernel call then runs twice the FMAs per load and store of
/// its `C` tile and per pass through the driver loop. The block depth changes no f32 bit: a `C`
/// value carries over between blocks exactly.
const KC: usize = 256;
/// Depth of one cache block in bf16: `KC_BF16 / 2` pair rows (16 KiB of panel; the paired
/// kernel's two panels fill L1). Even, so a pair never straddles two blocks. (Here the depth is
/// part of the result: the even and odd pair accumulators are summed at the end of each
/// block.) 512 rather than 256: half the passes of each `C` tile through the cache and half
/// the kernel calls.
const KC_BF16: usize = 512;
/// Rows of `A` per cache block (a multiple of `MR`): 240 x `KC` f32 values (240 KiB, 240 x
/// `KC_BF16` in bf16) stay in L2, and a batch of four expert requests (200 rows) is one block,
/// so each weight panel streams from memory once per GEMM.
const MC: usize = 240;

/// The depth of one cache block of a matrix stored in `precision`.
#[inline]
fn kc_of(precision: Precision) -> usize {
    match precision {
        Precision::F32 => KC,
        Precision::Bf16 => KC_BF16,
    }
}

/// Packed rows that `k` rows of a matrix take: one per row in f32, one per pair in bf16.
#[inline]
fn depth(precision: Precision, k: usize) -> usize {
    match precision {
        Precision::F32 => k,
        Precision::Bf16 => k.div_ceil(2),
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
    /// `C += bias + A · B`: `bias` (`n` values) added to each row of `C` first, then the
    /// products accumulated, as a separate bias pass followed by [`Init::Accumulate`] would,
    /// but on the threads that own each part of `C`.
    AccumulateBias(&'a [f32]),
}

/// `C = init + A · B` on the calling thread, with `isa`'s kernels: `A` is `m x k` (`k` =
/// `b.k()`), `C` is `m x n` (`n` = `b.n()`).
///
/// # Panics
/// If the shapes of `a`, `b` and `c` do not fit together, or a bias has fewer than `n` values.
pub fn gemm(isa: Isa, a: MatRef<'_>, b: &PackedMatrix, mut c: MatMut<'_>, init: Init<'_>) {
    check(a.rows(), a.cols(), b, &c, init);
    if a.rows() == 0 || b.n() == 0 {
        return;
    }
    let out = COut::of(&mut c);
    if b.precision() == Precision::F32 {
        // SAFETY: `check` verified the shapes (the views their bounds); this thread owns all of
        // `c`.
        unsafe { gemm_packed(isa, ASource::Rows(a), b, 0..b.panels(), out, init) };
        return;
    }
    // The borrow never spans a wait on other threads, so a worker that steals work while it
    // waits can never find its own buffer borrowed.
    A_PACK.with(|buf| {
        let mut buf = buf.borrow_mut();
        let packed = pack_a_blocks(isa, a, &mut buf);
        // SAFETY: as above.
        unsafe { gemm_packed(isa, packed, b, 0..b.panels(), out, init) }
    });
}

/// [`gemm`] for a bf16 `B` whose `A` is already rounded: `m` rows of `ceil(k / 2)` bf16 pairs
/// as [`super::bf16::round_pairs`] writes them, read in place. A loop that produces `A` row by
/// row (a softmax, an activation) rounds each row while it is still in L1, instead of this GEMM
/// reading the whole f32 `A` back to round it; the rounding is the same, so are the bits.
///
/// # Panics
/// If `b` is not bf16, or as [`gemm`].
pub fn gemm_pairs(
    isa: Isa,
    a: MatRef<'_, u32>,
    b: &PackedMatrix,
    mut c: MatMut<'_>,
    init: Init<'_>,
) {
    check_pairs(a, b, &c, init);
    if a.rows() == 0 || b.n() == 0 {
        return;
    }
    let out = COut::of(&mut c);
    // SAFETY: `check_pairs` verified the shapes; this thread owns all of `c`.
    unsafe { gemm_packed(isa, ASource::Pairs(a), b, 0..b.panels(), out, init) };
}

/// [`gemm`] with the output columns split into [`Pool::parts`] parts run by the pool's threads.
/// A bf16 `A` is packed once, by the pool's threads too, and shared by all parts; an f32 `A` is
/// read in place.
///
/// # Panics
/// As [`gemm`].
pub fn gemm_par(pool: &Pool, a: MatRef<'_>, b: &PackedMatrix, mut c: MatMut<'_>, init: Init<'_>) {
    check(a.rows(), a.cols(), b, &c, init);
    if a.rows() == 0 || b.n() == 0 {
        return;
    }
    let mut scratch = pool.take_scratch();
    let src = match b.precision() {
        Precision::F32 => ASource::Rows(a),
        Precision::Bf16 => pack_a_blocks_par(pool, a, &mut scratch),
    };
    run_parts(pool, src, b, COut::of(&mut c), init);
    pool.put_scratch(scratch);
}

/// [`gemm_pairs`] with the output columns split over the pool's threads, as [`gemm_par`].
///
/// # Panics
/// As [`gemm_pairs`].
pub fn gemm_par_pairs(
    pool: &Pool,
    a: MatRef<'_, u32>,
    b: &PackedMatrix,
    mut c: MatMut<'_>,
    init: Init<'_>,
) {
    check_pairs(a, b, &c, init);
    if a.rows() == 0 || b.n() == 0 {
        return;
    }
    run_parts(pool, ASource::Pairs(a), b, COut::of(&mut c), init);
}

/// Run the GEMM of `src` (checked by the caller, `c` borrowed by it for the call) with the
/// output panels split over the pool's threads.
fn run_parts(pool: &Pool, src: ASource<'_>, b: &PackedMatrix, c: COut, init: Init<'_>) {
    let panels = b.panels();
    // Parts own whole pairs of panels where the kernel pairs them: a part starting or ending
    // at an odd panel would leave that panel to the slower one-panel kernel.
    let unit = if Kernel::choose(pool.isa(), b.precision()).pairs() {
        2
    } else {
        1
    };
    let units = panels.div_ceil(unit);
    let parts = pool.parts(units);
    pool.run(parts, |t| {
        let range = (units * t / parts * unit)..(units * (t + 1) / parts * unit).min(panels);
        // SAFETY: the caller checked the shapes; part `t` writes only its panels' columns.
        unsafe { gemm_packed(pool.isa(), src, b, range, c, init) }
    });
}

/// The shapes of an `m x k` `A`, `b` and `c` fit together, and so does the bias.
fn check(m: usize, k: usize, b: &PackedMatrix, c: &MatMut<'_>, init: Init<'_>) {
    assert_eq!(k, b.k(), "gemm: A has {k} columns, B {} rows", b.k());
    check_out(m, b, c, init);
}

/// [`check`] for `A` given as bf16 pair rows (which needs a bf16 `B`).
fn check_pairs(a: MatRef<'_, u32>, b: &PackedMatrix, c: &MatMut<'_>, init: Init<'_>) {
    assert!(
        b.precision() == Precision::Bf16,
        "gemm: bf16 pair rows of A need a bf16 B"
    );
    let kp = depth(Precision::Bf16, b.k());
    assert_eq!(
        a.cols(),
        kp,
        "gemm: A has {} pairs per row, B {kp}",
        a.cols()
    );
    check_out(a.rows(), b, c, init);
}

/// `C` has the `m` rows of `A` and the `n` columns of `B`, and a bias has `n` values.
fn check_out(m: usize, b: &PackedMatrix, c: &MatMut<'_>, init: Init<'_>) {
    assert_eq!(c.rows(), m, "gemm: C has {} rows, A {m}", c.rows());
    assert_eq!(
        c.cols(),
        b.n(),
        "gemm: C has {} columns, B {}",
        c.cols(),
        b.n()
    );
    if let Init::Bias(bias) | Init::AccumulateBias(bias) = init {
        assert!(bias.len() >= b.n(), "gemm: bias too short");
    }
}
