//! The blocked loop of one GEMM call, or of one thread's share of its panels: cache blocks of
//! `A` (`MC` rows, `KC` deep), the panels of `B` over each block (two at a time where the
//! kernel pairs them), and the row tiles of the block that pass over each panel while it is in
//! L1.

use std::ops::Range;

use super::super::matrix::MatMut;
use super::super::{Isa, SharedMut, vecmath};
use super::pack_a::ASource;
use super::pack_b::PackedMatrix;
use super::tile::{
    Kernel, PairFn, Rows, Start, Tile, TileFn, full_tile_fn, pair_tile_fn, tile, tile_pair,
};
use super::{Init, MC, MR, NR, depth, kc_of};

/// `C` as the parts of one GEMM share it: row `r` starts at `ptr + r * stride`, and each part
/// writes the columns of its own panels only.
#[derive(Clone, Copy)]
pub(super) struct COut {
    ptr: SharedMut<f32>,
    stride: usize,
}

impl COut {
    /// The values of `c`, for one GEMM call (the caller keeps `c` borrowed meanwhile).
    pub(super) fn of(c: &mut MatMut<'_>) -> Self {
        COut {
            stride: c.stride(),
            ptr: SharedMut::new(c.data_mut()),
        }
    }

    /// Columns `cols` of row `r`.
    ///
    /// # Safety
    /// They are inside `C`, and no other thread touches them while the slice lives.
    unsafe fn row<'a>(self, r: usize, cols: Range<usize>) -> &'a mut [f32] {
        // SAFETY: the caller's contract.
        unsafe {
            std::slice::from_raw_parts_mut(
                self.ptr.ptr().add(r * self.stride + cols.start),
                cols.len(),
            )
        }
    }
}

/// `C = init + A · B` on the columns of `panels`.
///
/// # Safety
/// `c` holds `a.rows()` rows of at least `b.n()` values each, no other thread touches the
/// columns of `panels` in those rows meanwhile, and `a` has `b.k()` columns (the entry points
/// check the shapes, the views their bounds).
pub(super) unsafe fn gemm_packed(
    isa: Isa,
    a: ASource<'_>,
    b: &PackedMatrix,
    panels: Range<usize>,
    c: COut,
    init: Init<'_>,
) {
    if panels.is_empty() {
        return;
    }
    let m = a.rows();
    let cols = (panels.start * NR)..(panels.end * NR).min(b.n());
    // Zero-initialised outputs start from zero accumulators, biased ones from the bias itself
    // (the first `k` block's accumulators read it in place, the same vector for every row,
    // rather than a pass that writes it into all of `C` for the kernels to read back). A bias
    // added to an existing `C` goes in first, in one pass per row for all of this call's
    // panels.
    if let Init::AccumulateBias(bias) = init {
        // SAFETY: the caller's contract.
        unsafe { add_bias_rows(isa, c, m, cols.clone(), bias) };
    }
    if b.k() == 0 {
        // SAFETY: the caller's contract.
        unsafe { init_without_products(c, m, cols, init) };
        return;
    }
    let kernel = Kernel::choose(isa, b.precision());
    let blocked = Blocked {
        isa,
        kernel,
        a,
        b,
        c,
        // The kernels of whole tiles, looked up once.
        whole_tile: full_tile_fn(kernel, MR),
        whole_pair: pair_tile_fn(kernel, MR),
    };
    let (k, kcb) = (b.k(), kc_of(b.precision()));
    for m0 in (0..m).step_by(MC) {
        for k0 in (0..k).step_by(kcb) {
            // Where this block's accumulators start: C itself after the first block or when
            // accumulating into it, else the bias (or zero).
            let from_c = k0 > 0 || matches!(init, Init::Accumulate | Init::AccumulateBias(_));
            let block = CacheBlock {
                m0,
                mb: MC.min(m - m0),
                k0,
                kc: kcb.min(k - k0),
                from_c,
                bias: match init {
                    Init::Bias(bias) if !from_c => Some(bias),
                    _ => None,
                },
            };
            // SAFETY: the caller's contract; the block is inside `A` and `C`.
            unsafe { blocked.block(&block, panels.clone()) };
        }
    }
}

/// `C[r][cols] += bias[cols]` for each of the `m` rows: the first step of
/// [`Init::AccumulateBias`].
///
/// # Safety
/// As [`gemm_packed`], `cols` being the columns of its panels.
unsafe fn add_bias_rows(isa: Isa, c: COut, m: usize, cols: Range<usize>, bias: &[f32]) {
    for r in 0..m {
        // SAFETY: row r, columns `cols` are inside C and owned by this call.
        let row = unsafe { c.row(r, cols.clone()) };
        vecmath::add_assign(isa, row, &bias[cols.clone()]);
    }
}

/// `C` of a product with `k = 0`: what `init` starts from, no products added.
///
/// # Safety
/// As [`add_bias_rows`].
unsafe fn init_without_products(c: COut, m: usize, cols: Range<usize>, init: Init<'_>) {
    for r in 0..m {
        // SAFETY: as in `add_bias_rows`.
        let row = unsafe { c.row(r, cols.clone()) };
        match init {
            Init::Zero => row.fill(0.0),
            Init::Bias(bias) => row.copy_from_slice(&bias[cols.clone()]),
            Init::Accumulate | Init::AccumulateBias(_) => {}
        }
    }
}

/// What stays the same through one call's blocked loop.
struct Blocked<'a> {
    isa: Isa,
    kernel: Kernel,
    a: ASource<'a>,
    b: &'a PackedMatrix,
    c: COut,
    /// `kernel`'s micro-kernel for whole tiles of one panel.
    whole_tile: TileFn,
    /// `kernel`'s micro-kernel for whole tiles of two panels, where it has one.
    whole_pair: Option<PairFn>,
}

/// One cache block of `A`: rows `m0..m0 + mb`, depth `k0..k0 + kc`.
struct CacheBlock<'a> {
    m0: usize,
    mb: usize,
    k0: usize,
    kc: usize,
    /// Whether the accumulators start from `C` (else from `bias`, or zero).
    from_c: bool,
    bias: Option<&'a [f32]>,
}

/// The panels of `B` over one cache block that one micro-kernel call covers: one panel, or two
/// full ones side by side.
struct PanelStep {
    /// First column of `C`.
    c0: usize,
    /// Columns of the first panel (`NR`, or fewer at the right edge).
    w: usize,
    /// Whether the step is two full panels.
    pair: bool,
    /// The block's rows of the first panel, and of the second (the first again when unpaired).
    b: *const f32,
    b2: *const f32,
    /// The block's rows of the panels of the next step, to prefetch.
    next: [Option<*const f32>; 2],
}

impl Blocked<'_> {
    /// Cache block `blk` of `A` times the panels of `panels`, one panel step at a time.
    ///
    /// # Safety
    /// As [`gemm_packed`], for a block inside `A`.
    #[inline(always)]
    unsafe fn block(&self, blk: &CacheBlock<'_>, panels: Range<usize>) {
        let n = self.b.n();
        let mut p = panels.start;
        while p < panels.end {
            let c0 = p * NR;
            // Two full panels side by side go to the paired kernel where there is one.
            let pair = self.kernel.pairs() && p + 1 < panels.end && c0 + 2 * NR <= n;
            let next = if pair { p + 2 } else { p + 1 };
            let b = self.b.panel_ptr(p, blk.k0);
            let step = PanelStep {
                c0,
                w: NR.min(n - c0),
                pair,
                b,
                b2: if pair {
                    self.b.panel_ptr(p + 1, blk.k0)
                } else {
                    b
                },
                next: [
                    (next < panels.end).then(|| self.b.panel_ptr(next, blk.k0)),
                    (pair && next + 1 < panels.end).then(|| self.b.panel_ptr(next + 1, blk.k0)),
                ],
            };
            // SAFETY: the caller's contract.
            unsafe { self.tiles(blk, &step) };
            p = next;
        }
    }

    /// The row tiles of cache block `blk` over one panel step.
    ///
    /// # Safety
    /// As [`Self::block`].
    #[inline(always)]
    unsafe fn tiles(&self, blk: &CacheBlock<'_>, step: &PanelStep) {
        let (kernel, ldc) = (self.kernel, self.c.stride);
        let tiles = blk.mb.div_ceil(MR);
        let d = |rows| depth(self.b.precision(), rows);
        for t in 0..tiles {
            let r0 = t * MR;
            let rows = MR.min(blk.mb - r0);
            // Pull the next panels into L1 a slice per tile, spread over these panels' tiles so
            // the misses overlap with computation instead of queueing.
            let (from, to) = (d(blk.kc) * t / tiles, d(blk.kc) * (t + 1) / tiles);
            for next in step.next.into_iter().flatten() {
                prefetch_lines(self.isa, next, from, to);
            }
            let (a, a_stride) = self.a.tile(self.b.k(), blk.m0, blk.k0, blk.kc, t);
            // SAFETY: the tile lies inside C (rows m0+r0.., columns c0..c0+2*NR or c0+w).
            let c = unsafe { self.c.ptr.ptr().add((blk.m0 + r0) * ldc + step.c0) };
            // The next tile's accumulators come from C: start fetching them now.
            if blk.from_c && t + 1 < tiles {
                let next_rows = MR.min(blk.mb - r0 - MR);
                let panels = if step.pair { 2 } else { 1 };
                for s in 0..panels {
                    let cs = c.wrapping_add(MR * ldc + s * NR);
                    prefetch_rows(self.isa, cs, ldc, next_rows);
                }
            }
            let start: Start = if blk.from_c {
                Some(Rows {
                    ptr: c.cast_const(),
                    stride: ldc,
                })
            } else {
                // Stride 0: every row starts from the bias of these columns.
                blk.bias.map(|bias| Rows {
                    ptr: bias[step.c0..].as_ptr(),
                    stride: 0,
                })
            };
            let operands = Tile {
                kc: blk.kc,
                a: Rows {
                    ptr: a,
                    stride: a_stride,
                },
                b: step.b,
                c: Rows {
                    ptr: c,
                    stride: ldc,
                },
                start,
            };
            // The panel (both panels) hold kc rows, the A tile `rows` rows of kc values; C and
            // the bias (`n` values) have the tile's columns (two full panels, or `w`); the
            // looked-up kernels are `kernel`'s.
            match (step.pair, rows == MR, self.whole_pair) {
                // SAFETY: as above, two full panels, `MR` rows.
                (true, true, Some(f)) => unsafe { operands.run_pair(f, step.b2) },
                // SAFETY: as above, two full panels.
                (true, _, _) => unsafe { tile_pair(kernel, rows, operands, step.b2) },
                // SAFETY: as above, one full panel, `MR` rows.
                (false, true, _) if step.w == NR => unsafe { operands.run(self.whole_tile) },
                // SAFETY: as above, one panel of `w` columns.
                (false, _, _) => unsafe { tile(kernel, rows, step.w, operands) },
            }
        }
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
