//! The f32 micro-kernel for AVX-512F: an `R x NR` tile in `R` 512-bit accumulators.

use super::NR;
use super::tile::{Rows, Start, unroll4};

/// One panel row is one 512-bit vector, so the tile is `R` accumulators; each `A` value is
/// broadcast straight from memory into its FMA (`{1to16}`). Same order of operations as
/// [`super::avx2::kernel_avx2`]: one FMA per product, in increasing `k`.
///
/// # Safety
/// See [`super::tile::tile`]; requires AVX-512F.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn kernel_avx512<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    use std::arch::x86_64::*;
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let mut acc = [_mm512_setzero_ps(); R];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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
