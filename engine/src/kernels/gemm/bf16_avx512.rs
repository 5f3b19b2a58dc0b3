//! The bf16 micro-kernels for AVX512_BF16: `vdpbf16ps` on bf16 pairs, one panel or two side
//! by side, with the `A` pair broadcast from memory inside the instruction.

use super::NR;
use super::tile::{Rows, Start};

/// `ceil(kc / 2)` steps of one `vdpbf16ps` per row: the panel row (16 lanes of bf16 pairs) times
/// the row's broadcast `A` pair, both products added to an f32 accumulator. Even and odd pairs
/// go to two accumulators per row (summed at the end), so that 2R independent chains hide the
/// instruction's latency (6 cycles on Zen 4, where R = 6 alone would stall).
///
/// # Safety
/// See [`super::tile::tile`], with bf16 pair rows; requires AVX-512F and AVX512_BF16.
#[target_feature(enable = "avx512f,avx512bf16")]
pub(super) unsafe fn kernel_bf16_avx512<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    use std::arch::x86_64::*;
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let mut even = [_mm512_setzero_ps(); R];
    let mut odd = [_mm512_setzero_ps(); R];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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
                    // costs a vector uop per product, competing with the products themselves.
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
    // Indexed, not zipped: borrowing the accumulator arrays as slices keeps them in memory (a
    // store after every `vdpbf16ps`) instead of in registers.
    #[allow(clippy::needless_range_loop)]
    for r in 0..R {
        // SAFETY: row r of the C tile has NR values.
        unsafe { _mm512_storeu_ps(c.add(r * ldc), _mm512_add_ps(even[r], odd[r])) };
    }
}

/// [`kernel_bf16_avx512`] over two panels: even and odd accumulators for each (`4R` in all,
/// the same pairing as the one-panel kernel, so the same bits), each `A` pair broadcast from
/// memory into both panels' instructions.
///
/// # Safety
/// See [`super::tile::tile_pair`], with bf16 pair rows; requires AVX-512F and AVX512_BF16.
#[target_feature(enable = "avx512f,avx512bf16")]
pub(super) unsafe fn kernel_bf16_avx512_pair<const R: usize>(
    kc: usize,
    a: Rows<*const f32>,
    b: *const f32,
    b2: *const f32,
    c: Rows<*mut f32>,
    start: Start,
) {
    use std::arch::x86_64::*;
    let (a, ars, c, ldc) = (a.ptr, a.stride, c.ptr, c.stride);
    let mut even = [_mm512_setzero_ps(); R];
    let mut odd = [_mm512_setzero_ps(); R];
    let mut even2 = [_mm512_setzero_ps(); R];
    let mut odd2 = [_mm512_setzero_ps(); R];
    if let Some(Rows {
        ptr: src,
        stride: lds,
    }) = start
    {
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
