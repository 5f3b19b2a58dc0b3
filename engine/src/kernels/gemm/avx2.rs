//! The f32 micro-kernel for AVX2 with FMA: an `R x NR` tile in `2R` 256-bit accumulators.

use super::NR;
use super::tile::{Rows, Start, unroll4};

/// An `R x NR` tile: per step of `k`, one panel row in two vectors and `R` broadcasts of `A`,
/// one FMA per product, in increasing `k`.
///
/// # Safety
/// See [`super::tile::tile`]; requires AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn kernel_avx2<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    use std::arch::x86_64::*;
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let mut acc = [[_mm256_setzero_ps(); 2]; R];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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
