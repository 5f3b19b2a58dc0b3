//! Rounding `f32` values to bf16 (nearest, ties to even), and the bf16 pairs the bf16 GEMM reads.
//!
//! A pair is two bf16 values in one 32-bit lane, the first (the element with the even `k`) in
//! the low half: the layout of bf16 panels and of a bf16 `A` (see [`super::gemm`]). Producers of
//! a GEMM's `A` (the softmax, the layer norms and activations through
//! [`super::gemm::ActivationRows`]) round into pairs here as they make their rows, so both the
//! GEMM's packing and the element-wise maths depend on this module, and it on neither.
//!
//! Every path (scalar, AVX-512F integer rounding, AVX512_BF16's `vcvtneps2bf16`) gives the bits
//! of [`to_bf16`]: denormals are rounded, not flushed, and NaNs are quieted.

use super::Isa;

/// `x` rounded to bf16 (nearest, ties to even; NaN stays NaN, made quiet), as its 16 bits.
/// Denormals round like any other value (no flush to zero).
#[inline]
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
#[inline]
pub(super) fn bf16_pair(lo: f32, hi: f32) -> f32 {
    f32::from_bits(u32::from(to_bf16(lo)) | (u32::from(to_bf16(hi)) << 16))
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
/// inputs as zero, so a block holding a denormal takes the integer rounding instead. One
/// instruction instead of [`round16`]'s sequence of integer operations, for the rounding that
/// runs on every softmax numerator of the bf16 attention.
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
