//! The micro-kernels in portable Rust, for any CPU: f32, and bf16 pairs computed as
//! `vdpbf16ps` does.

use super::NR;
use super::tile::{Rows, Start};

/// [`super::avx2::kernel_avx2`]'s products in scalar code, in the same order per element;
/// without FMA each product is rounded before it is added, so its results differ from the
/// SIMD kernels' by rounding.
///
/// # Safety
/// See [`super::tile::tile`].
pub(super) unsafe fn kernel_portable<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let mut acc = [[0.0f32; NR]; R];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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

/// What [`kernel_bf16_avx512`] computes, in scalar code: per pair, the odd product then the
/// even one added to the accumulator of the pair's parity (each product is exact in f32), the
/// two accumulators summed at the end. Its rounding of the two additions may differ from a given
/// CPU's `vdpbf16ps` by an ulp of the accumulator.
///
/// # Safety
/// See [`super::tile::tile`], with bf16 pair rows.
pub(super) unsafe fn kernel_bf16_portable<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let widen = |pair: f32| {
        let bits = pair.to_bits();
        (
            f32::from_bits(bits << 16),
            f32::from_bits(bits & 0xffff_0000),
        )
    };
    let mut acc = [[[0.0f32; NR]; R]; 2];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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
