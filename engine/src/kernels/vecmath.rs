//! Element-wise maths of the fast path: exp, softmax, SiLU, RMSNorm, RoPE.
//!
//! Each function body is written once in plain Rust and compiled three times: for the baseline
//! target, via `#[target_feature(enable = "avx2,fma")]` for AVX2, where LLVM vectorises it 8
//! lanes wide, and with AVX-512F added for [`Isa::Avx512`], 16 lanes wide. Rust never contracts
//! `a * b + c` into an FMA on its own, and the reductions fix their own lane structure
//! ([`sum_lanes`]), so all builds round identically and give bit-identical results.

use super::Isa;

/// Generate `$name(isa, ..)` that runs `$body` compiled for AVX2 when `isa` allows it.
macro_rules! multiversion {
    ($(#[$meta:meta])* pub fn $name:ident($($arg:ident: $ty:ty),*) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        pub fn $name(isa: Isa, $($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            /// `body` compiled for AVX2 and FMA.
            ///
            /// # Safety
            /// Call only on a CPU with AVX2 and FMA (`Isa::Avx2Fma`).
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            fn avx2($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
            /// `body` compiled for AVX-512F (and AVX2, FMA).
            ///
            /// # Safety
            /// Call only on a CPU with AVX-512F, AVX2 and FMA (`Isa::Avx512`).
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx2,fma")]
            fn avx512($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }
            match isa {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::Avx512` is only constructed on CPUs with AVX-512F, AVX2 and FMA.
                Isa::Avx512 => unsafe { avx512($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::Avx2Fma` is only constructed on CPUs with AVX2 and FMA.
                Isa::Avx2Fma => unsafe { avx2($($arg),*) },
                _ => body($($arg),*),
            }
        }
    };
}

const LOG2E: f32 = std::f32::consts::LOG2_E;

/// `exp(x)` for `x` in about `[-87, 88]` (clamped outside), max error ~1 ulp (Cephes `expf`:
/// Cody–Waite reduction by ln 2 and a degree-5 minimax polynomial), branch-free so that it
/// vectorises. Written with fused multiply-adds, 19 operations instead of 28, since every
/// softmax runs it once per score. `mul_add` rounds once wherever it runs (an
/// FMA instruction in the AVX2 and AVX-512 builds, a correctly rounded library call in the
/// portable one), so every build still gives the same bits.
#[inline(always)]
pub fn exp_approx(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let fx = x.mul_add(LOG2E, 0.5).floor();
    let r = fx.mul_add(-0.693_359_4, x);
    let r = fx.mul_add(2.121_944_4e-4, r);
    let r2 = r * r;
    let p = 1.987_569_1e-4f32.mul_add(r, 1.398_199_9e-3);
    let p = p.mul_add(r, 8.333_452e-3);
    let p = p.mul_add(r, 4.166_579_6e-2);
    let p = p.mul_add(r, 1.666_666_5e-1);
    let p = p.mul_add(r, 5e-1);
    let y = p.mul_add(r2, r) + 1.0;
    // 2^fx from the bits of `fx + 1.5 * 2^23`, whose low mantissa bits hold the integer `fx`
    // (in -126..=127 after the clamp): the same value as `(fx as i32 + 127) << 23`, but with
    // integer ops only, which LLVM vectorises (the saturating `as i32` kept every loop that
    // calls this scalar).
    let n = (fx + 12_582_912.0).to_bits().wrapping_sub(0x4B40_0000);
    y * f32::from_bits(n.wrapping_add(127) << 23)
}

/// `2^t` to within 3e-6 relative, for numerators that are rounded to bf16 next (whose own
/// rounding is 2^-9, ~2e-3): `round(t)` goes to the exponent bits and `2^f`, `f` in
/// `[-0.5, 0.5]`, to a degree-4 polynomial (minimax-fitted; max relative error 2.7e-6 in f32).
/// About 12 operations where [`exp_approx`] takes 19: after its GEMMs, the softmax's
/// exponentials are the bf16 attention's largest cost. `t` is clamped below at -126 (so
/// `2^round(t)` is a normal number); a NaN stays NaN.
#[inline(always)]
fn exp2_bf16_grade(t: f32) -> f32 {
    let t = if t < -126.0 { -126.0 } else { t };
    let n = t.round_ties_even();
    let f = t - n;
    let p = 9.570_069e-3f32
        .mul_add(f, 5.591_780_7e-2)
        .mul_add(f, 2.402_474_4e-1)
        .mul_add(f, 6.931_218_5e-1)
        .mul_add(f, 9.999_993e-1);
    // 2^n from the bits of `n + 1.5 * 2^23`, as in `exp_approx`.
    let bits = (n + 12_582_912.0).to_bits().wrapping_sub(0x4B40_0000);
    p * f32::from_bits(bits.wrapping_add(127) << 23)
}

/// [`gelu_tanh_one`] to within about 1e-5 relative, for outputs rounded to bf16 next: the
/// same function written as `u σ(2y) = u / (1 + 2^(-2y log2(e)))` with [`exp2_bf16_grade`]
/// (one exponential and one division, no `tanh` assembly: about 20 operations instead of 30).
/// The exponent is clamped above at 127, where `u / (1 + 2^127)` is already 0 to f32 precision.
#[inline(always)]
fn gelu_tanh_bf16_grade_one(u: f32) -> f32 {
    const SQRT_2_OVER_PI: f32 = 0.797_884_6;
    let y = SQRT_2_OVER_PI * (0.044_715 * u * u).mul_add(u, u);
    let t = -2.0 * LOG2E * y;
    let t = if t > 127.0 { 127.0 } else { t };
    u / (1.0 + exp2_bf16_grade(t))
}

/// Sum with 8 independent partial sums (lane `i` takes elements `i mod 8`), so that the loop
/// vectorises; float addition is not associative, so LLVM will not reorder a plain running sum.
#[inline(always)]
fn sum_lanes(x: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            lanes[i] += c[i];
        }
    }
    for (i, &v) in rest.iter().enumerate() {
        lanes[i] += v;
    }
    ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5]))
        + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7]))
}

/// Maximum, vectorised like [`sum_lanes`] but over 32 lanes: four independent chains of
/// 8-lane (or two of 16-lane) `max`, where one chain waited on each `vmaxps`' latency. The
/// maximum of the non-NaN values does not depend on the order they are compared in (NaNs never
/// win a comparison), so the lane count changes no result.
#[inline(always)]
fn max_lanes(x: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; 32];
    let chunks = x.chunks_exact(32);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..32 {
            lanes[i] = if c[i] > lanes[i] { c[i] } else { lanes[i] };
        }
    }
    for (i, &v) in rest.iter().enumerate() {
        lanes[i] = if v > lanes[i] { v } else { lanes[i] };
    }
    lanes
        .iter()
        .fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m })
}

/// The softmax numerators of `row * scale` in place, `exp(row[i] * scale - max)` with `max`
/// the largest `row[i] * scale`, and their sum. `scale > 0`, so `max` is the largest `row[i]`
/// times `scale`, the same value as the maximum of the scaled row: no pass scales the row
/// first. The exponentials are summed as they are made, into 32 lanes (element `i` into lane
/// `i mod 32`, combined by [`sum_32_lanes`]): wide enough that the loop runs 16 lanes at a time
/// with two independent sums (8 lanes kept it 8 wide, and a separate summing pass waited on one
/// chain of additions).
#[inline(always)]
fn numerators(row: &mut [f32], scale: f32) -> f32 {
    debug_assert!(scale > 0.0, "softmax scale must be positive");
    let max = max_lanes(row) * scale;
    let mut lanes = [0.0f32; 32];
    let mut chunks = row.chunks_exact_mut(32);
    for c in &mut chunks {
        for i in 0..32 {
            let e = exp_approx(c[i] * scale - max);
            c[i] = e;
            lanes[i] += e;
        }
    }
    for (i, v) in chunks.into_remainder().iter_mut().enumerate() {
        let e = exp_approx(*v * scale - max);
        *v = e;
        lanes[i] += e;
    }
    sum_32_lanes(&lanes)
}

/// The sum of 32 partial sums in a fixed order: lanes `i` and `i + 16`, then `i + 8`, and so
/// on (a tree of vector halves). [`softmax_scaled`] sums its numerators so, and a caller of
/// [`exp_sum_into`] sums its lanes with it.
#[inline(always)]
pub fn sum_32_lanes(lanes: &[f32; 32]) -> f32 {
    let mut half = [0.0f32; 16];
    for i in 0..16 {
        half[i] = lanes[i] + lanes[i + 16];
    }
    let mut quarter = [0.0f32; 8];
    for i in 0..8 {
        quarter[i] = half[i] + half[i + 8];
    }
    ((quarter[0] + quarter[4]) + (quarter[1] + quarter[5]))
        + ((quarter[2] + quarter[6]) + (quarter[3] + quarter[7]))
}

multiversion! {
    /// Softmax of `row * scale` in place, over the whole row (`scale > 0`).
    pub fn softmax_scaled(row: &mut [f32], scale: f32) {
        let inv = 1.0 / numerators(row, scale);
        for v in row.iter_mut() {
            *v *= inv;
        }
    }
}

multiversion! {
    /// The largest `row[i] * scale` (`scale > 0`, so `max(row) * scale`): the shift of a softmax
    /// of `row * scale`.
    pub fn max_scaled(row: &[f32], scale: f32) -> f32 {
        debug_assert!(scale > 0.0, "softmax scale must be positive");
        max_lanes(row) * scale
    }
}

multiversion! {
    /// Softmax numerators for bf16 rounding: `out[i] = exp(src[i] * scale - max)` to within
    /// 3e-6 relative ([`exp2_bf16_grade`] of `src[i] * scale log2(e) - max log2(e)`), each also
    /// added into `lanes[i mod 32]` (summed like [`softmax_scaled`]'s). A caller that cuts a
    /// row into chunks whose lengths are multiples of 32 (but the last) gets the same values
    /// and the same lane sums as one call over the whole row; [`exp_sum_round_into`] makes
    /// them and rounds them to bf16 in one loop.
    pub fn exp_sum_into(src: &[f32], scale: f32, max: f32, out: &mut [f32], lanes: &mut [f32; 32]) {
        debug_assert_eq!(src.len(), out.len());
        let (a, b) = (scale * LOG2E, -(max * LOG2E));
        // Whole blocks of 32, then the tail, with the lanes starting over at 0.
        for (c, o) in src.chunks(32).zip(out.chunks_mut(32)) {
            exp_sum_block(c, a, b, o, lanes);
        }
    }
}

/// `out[i] = exp2_bf16_grade(src[i] * a + b)`, each added into `lanes[i]`, for up to 32 values:
/// one block of [`exp_sum_into`] and of [`exp_sum_round_into`]'s register loop, so both make
/// the same values and lane sums.
#[inline(always)]
fn exp_sum_block(src: &[f32], a: f32, b: f32, out: &mut [f32], lanes: &mut [f32; 32]) {
    for ((&v, o), lane) in src.iter().zip(out).zip(lanes.iter_mut()) {
        let e = exp2_bf16_grade(v.mul_add(a, b));
        *o = e;
        *lane += e;
    }
}

/// [`exp_sum_into`] followed by [`super::bf16::round_pairs`] of its output, without the f32
/// numerators going to memory: 32 at a time, made in registers and rounded to bf16 pairs from
/// there (`pairs` holds `ceil(src.len() / 2)`). The same values, pairs and lane sums as the two
/// calls. The bf16 attention's softmax numerators: made in one loop with their rounding, they
/// are never stored to an L1 buffer and loaded back by a second pass. With AVX512_BF16
/// (native `vcvtneps2bf16`) the whole step is one loop; elsewhere it is the two calls.
pub fn exp_sum_round_into(
    isa: Isa,
    src: &[f32],
    scale: f32,
    max: f32,
    pairs: &mut [u32],
    lanes: &mut [f32; 32],
) {
    debug_assert_eq!(pairs.len(), src.len().div_ceil(2));
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Avx512 && super::cpu_has_avx512_bf16() {
        // SAFETY: `Isa::Avx512` is only constructed on CPUs with AVX-512F, AVX2 and FMA, and
        // this one has AVX512_BF16.
        done = unsafe { exp_round_avx512_bf16(src, scale, max, pairs, lanes) };
    }
    // The rest (a tail shorter than 32, or all of it without the native rounding) in chunks
    // of an L1 buffer; a multiple of 32 each, so the lanes line up as in one call.
    let mut numerators = [0.0f32; 256];
    for (k, chunk) in src[done..].chunks(numerators.len()).enumerate() {
        let e = &mut numerators[..chunk.len()];
        exp_sum_into(isa, chunk, scale, max, e, lanes);
        let first = done / 2 + k * 128;
        super::bf16::round_pairs(isa, e, &mut pairs[first..first + chunk.len().div_ceil(2)]);
    }
}

/// The whole blocks of 32 of [`exp_sum_round_into`]; returns how many values it took.
///
/// # Safety
/// Requires AVX-512F, AVX2, FMA and AVX512_BF16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma,avx512bf16")]
unsafe fn exp_round_avx512_bf16(
    src: &[f32],
    scale: f32,
    max: f32,
    pairs: &mut [u32],
    lanes: &mut [f32; 32],
) -> usize {
    // `exp_sum_into`'s block, compiled with the same features: the same bits.
    let (a, b) = (scale * LOG2E, -(max * LOG2E));
    let blocks = src.len() / 32;
    for (c, out) in src.chunks_exact(32).zip(pairs.chunks_exact_mut(16)) {
        let mut e = [0.0f32; 32];
        exp_sum_block(c, a, b, &mut e, lanes);
        // SAFETY: this function's features include the rounding's; `e` holds 32 values and
        // `out` their 16 pairs.
        unsafe { super::bf16::round_pairs_avx512_bf16(&e, out) };
    }
    32 * blocks
}

multiversion! {
    /// `x[i] *= factor`.
    pub fn scale_assign(x: &mut [f32], factor: f32) {
        for v in x.iter_mut() {
            *v *= factor;
        }
    }
}

multiversion! {
    /// `x[i] += y[i]`.
    pub fn add_assign(x: &mut [f32], y: &[f32]) {
        for (a, &b) in x.iter_mut().zip(y) {
            *a += b;
        }
    }
}

multiversion! {
    /// `out[i] = silu(gate[i]) * up[i]` with `silu(g) = g / (1 + exp(-g))`.
    pub fn silu_mul(gate: &[f32], up: &[f32], out: &mut [f32]) {
        for ((o, &g), &u) in out.iter_mut().zip(gate).zip(up) {
            *o = g / (1.0 + exp_approx(-g)) * u;
        }
    }
}

multiversion! {
    /// `x[i] = silu(x[i])` in place.
    pub fn silu_inplace(x: &mut [f32]) {
        for v in x.iter_mut() {
            *v = *v / (1.0 + exp_approx(-*v));
        }
    }
}

multiversion! {
    /// RMSNorm of each `weight.len()`-wide row of `x` into `out`, as `LlamaRMSNorm`:
    /// `weight * (x / sqrt(mean(x^2) + eps))`.
    pub fn rms_norm(x: &[f32], weight: &[f32], eps: f32, out: &mut [f32]) {
        let h = weight.len();
        let mut squares = vec![0.0f32; h];
        for (xr, or) in x.chunks_exact(h).zip(out.chunks_exact_mut(h)) {
            for (s, &v) in squares.iter_mut().zip(xr) {
                *s = v * v;
            }
            let ss = sum_lanes(&squares);
            let inv = 1.0 / (ss / h as f32 + eps).sqrt();
            for ((o, &v), &w) in or.iter_mut().zip(xr).zip(weight) {
                *o = w * (v * inv);
            }
        }
    }
}

multiversion! {
    /// Rotate one head vector in place (LeRobot's `apply_rope`: first half `x1`, second half
    /// `x2`; `x1 cos - x2 sin`, `x2 cos + x1 sin`), with `cos`/`sin` of length `x.len() / 2`.
    pub fn rope(x: &mut [f32], cos: &[f32], sin: &[f32]) {
        let half = x.len() / 2;
        let (x1, x2) = x.split_at_mut(half);
        for i in 0..half {
            let a = x1[i];
            let b = x2[i];
            x1[i] = a * cos[i] - b * sin[i];
            x2[i] = b * cos[i] + a * sin[i];
        }
    }
}

multiversion! {
    /// LayerNorm of each `weight.len()`-wide row of `x` into `out`, as `nn.LayerNorm`:
    /// `(x - mean) / sqrt(var + eps) * weight + bias` with the biased variance.
    pub fn layer_norm(x: &[f32], weight: &[f32], bias: &[f32], eps: f32, out: &mut [f32]) {
        let h = weight.len();
        let mut centred = vec![0.0f32; h];
        for (xr, or) in x.chunks_exact(h).zip(out.chunks_exact_mut(h)) {
            let mean = sum_lanes(xr) / h as f32;
            for (c, &v) in centred.iter_mut().zip(xr) {
                *c = v - mean;
            }
            for (o, &c) in or.iter_mut().zip(&centred) {
                *o = c * c;
            }
            let var = sum_lanes(or) / h as f32;
            let inv = 1.0 / (var + eps).sqrt();
            for (((o, &c), &w), &b) in or.iter_mut().zip(&centred).zip(weight).zip(bias) {
                *o = c * inv * w + b;
            }
        }
    }
}

/// `gelu_pytorch_tanh`: `0.5 u (1 + tanh(sqrt(2/π) (u + 0.044715 u³)))`.
#[inline(always)]
fn gelu_tanh_one(u: f32) -> f32 {
    const SQRT_2_OVER_PI: f32 = 0.797_884_6;
    let y = SQRT_2_OVER_PI * (u + 0.044_715 * u * u * u);
    // tanh(y) = sign(y) (1 - e) / (1 + e) with e = exp(-2|y|): never overflows.
    let e = exp_approx(-2.0 * y.abs());
    let t = ((1.0 - e) / (1.0 + e)).copysign(y);
    0.5 * u * (1.0 + t)
}

multiversion! {
    /// `x[i] = gelu_tanh(x[i])` in place (`gelu_pytorch_tanh`):
    /// `0.5 x (1 + tanh(sqrt(2/π) (x + 0.044715 x³)))`.
    pub fn gelu_tanh_inplace(x: &mut [f32]) {
        for v in x.iter_mut() {
            *v = gelu_tanh_one(*v);
        }
    }
}

multiversion! {
    /// `out[i] = gelu_tanh(x[i])` to within about 1e-5 relative, for a GEMM that rounds it to
    /// bf16 (2^-9 relative) next; cheaper than [`gelu_tanh`].
    pub fn gelu_tanh_bf16_grade(x: &[f32], out: &mut [f32]) {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = gelu_tanh_bf16_grade_one(v);
        }
    }
}

multiversion! {
    /// `out[i] = gelu_tanh(x[i])`, as [`gelu_tanh_inplace`].
    pub fn gelu_tanh(x: &[f32], out: &mut [f32]) {
        for (o, &v) in out.iter_mut().zip(x) {
            *o = gelu_tanh_one(v);
        }
    }
}

/// LeRobot's RoPE tables for one position: `radians = pos / 10000^(2i/d)` in f32, as
/// `apply_rope` computes them. Writes `d/2` cosines and sines.
pub fn rope_table(position: f32, head_dim: usize, cos: &mut [f32], sin: &mut [f32]) {
    let half = head_dim / 2;
    let step = (2.0f64 / head_dim as f64) as f32;
    for i in 0..half {
        let exponent = step * i as f32;
        let timescale = 10_000f32.powf(exponent);
        let radians = position / timescale;
        cos[i] = radians.cos();
        sin[i] = radians.sin();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_is_within_two_ulp_of_libm() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x < 88.0 {
            let want = f64::from(x).exp();
            let got = f64::from(exp_approx(x));
            worst = worst.max(((got - want) / want).abs());
            x += 0.0137;
        }
        assert!(worst < 2.5e-7, "relative error {worst}");
        assert_eq!(exp_approx(0.0), 1.0);
        assert!(exp_approx(-1e30) > 0.0 && exp_approx(-1e30) < 1e-37);
    }

    /// The softmax without a scaling pass, its exponentials summed as they are made, gives the
    /// bits of the pass-by-pass definition (scale, maximum, exponentials, a 32-lane sum,
    /// normalisation), and the numerators times their factor are the softmax.
    #[test]
    fn fused_softmax_equals_the_pass_by_pass_softmax() {
        let reference = |row: &mut [f32], scale: f32| {
            for v in row.iter_mut() {
                *v *= scale;
            }
            let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
            for v in row.iter_mut() {
                *v = exp_approx(*v - max);
            }
            let mut lanes = [0.0f32; 32];
            for (i, &v) in row.iter().enumerate() {
                lanes[i % 32] += v;
            }
            let inv = 1.0 / sum_32_lanes(&lanes);
            for v in row.iter_mut() {
                *v *= inv;
            }
        };
        for len in [0, 1, 7, 8, 9, 64, 1000, 1024] {
            let data: Vec<f32> = (0..len)
                .map(|i| ((i * 7919) % 1000) as f32 / 9.0 - 50.0)
                .collect();
            for scale in [0.125, 0.3, 1.0] {
                let mut want = data.clone();
                reference(&mut want, scale);
                for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
                    .into_iter()
                    .filter(|i| i.available())
                {
                    let mut got = data.clone();
                    softmax_scaled(isa, &mut got, scale);
                    assert_eq!(bits(&got), bits(&want), "{isa:?} len {len} scale {scale}");
                    // bf16-grade numerators: made in chunks of 64 or in one call, the same bits
                    // and sums; within 2e-5 relative of the exact probabilities once normalised.
                    let max = max_scaled(isa, &data, scale);
                    let (mut num, mut lanes) = (vec![0.0; len], [0.0f32; 32]);
                    for (src, dst) in data.chunks(64).zip(num.chunks_mut(64)) {
                        exp_sum_into(isa, src, scale, max, dst, &mut lanes);
                    }
                    let (mut whole, mut whole_lanes) = (vec![0.0; len], [0.0f32; 32]);
                    exp_sum_into(isa, &data, scale, max, &mut whole, &mut whole_lanes);
                    assert_eq!(bits(&num), bits(&whole), "{isa:?} len {len} chunks");
                    assert_eq!(bits(&lanes), bits(&whole_lanes), "{isa:?} len {len} lanes");
                    if len > 0 {
                        scale_assign(isa, &mut num, 1.0 / sum_32_lanes(&lanes));
                        let exact = exact_softmax(&data, scale);
                        for (i, (&got, &p)) in num.iter().zip(&exact).enumerate() {
                            // 2.7e-6 from the polynomial, the rest from rounding `t` (an
                            // ulp of `max * scale * log2(e)`, ~1e-5 at this data's range).
                            let tol = 2e-5 * p + 1e-30;
                            assert!((f64::from(got) - p).abs() <= tol, "{isa:?} len {len} [{i}]");
                        }
                    }
                }
            }
        }
    }

    /// The numerators made and rounded 32 at a time in registers are exactly those made in
    /// one pass and rounded after, pairs and lane sums alike: over lengths with and without a
    /// tail, odd ones (the last pair's high half zero), and scores so far below the maximum
    /// that their numerators are denormal (which the native rounding would flush, so those
    /// blocks take the integer rounding).
    #[test]
    fn numerators_rounded_in_registers_equal_exp_then_round() {
        for len in [0, 1, 31, 32, 33, 255, 256, 257, 1000, 1024] {
            let data: Vec<f32> = (0..len)
                .map(|i| match i % 97 {
                    // exp(-88 - ...) and 2^-126 x p: denormal numerators.
                    0 => -95.0,
                    1 => -87.5,
                    _ => ((i * 7919) % 1000) as f32 / 9.0 - 50.0,
                })
                .collect();
            for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
                .into_iter()
                .filter(|i| i.available())
            {
                let (scale, max) = (1.0, max_scaled(isa, &data, 1.0));
                let (mut e, mut want_lanes) = (vec![0.0; len], [0.0f32; 32]);
                exp_sum_into(isa, &data, scale, max, &mut e, &mut want_lanes);
                let mut want = vec![0u32; len.div_ceil(2)];
                super::super::bf16::round_pairs(isa, &e, &mut want);
                let (mut got, mut lanes) = (vec![0u32; len.div_ceil(2)], [0.0f32; 32]);
                exp_sum_round_into(isa, &data, scale, max, &mut got, &mut lanes);
                assert_eq!(got, want, "{isa:?} len {len}");
                assert_eq!(bits(&lanes), bits(&want_lanes), "{isa:?} len {len} lanes");
                if len > 97 {
                    assert!(
                        e[0] != 0.0 && !e[0].is_normal(),
                        "a denormal numerator is covered"
                    );
                }
            }
        }
    }

    /// `softmax(row * scale)` in f64.
    fn exact_softmax(row: &[f32], scale: f32) -> Vec<f64> {
        let s: Vec<f64> = row
            .iter()
            .map(|&v| f64::from(v) * f64::from(scale))
            .collect();
        let max = s.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let e: Vec<f64> = s.iter().map(|v| (v - max).exp()).collect();
        let sum: f64 = e.iter().sum();
        e.iter().map(|v| v / sum).collect()
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn simd_and_portable_builds_agree_bit_for_bit() {
        let data: Vec<f32> = (0..999)
            .map(|i| ((i * 7919) % 1000) as f32 / 37.0 - 13.0)
            .collect();
        let w: Vec<f32> = (0..111).map(|i| 0.5 + i as f32 / 100.0).collect();
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let mut a = data.clone();
            softmax_scaled(isa, &mut a, 0.125);
            let mut b = data.clone();
            softmax_scaled(Isa::Portable, &mut b, 0.125);
            assert_eq!(a, b);
            assert!((a.iter().sum::<f32>() - 1.0).abs() < 1e-5);
            let mut s1 = vec![0.0; 999];
            let mut s2 = vec![0.0; 999];
            silu_mul(isa, &data, &data, &mut s1);
            silu_mul(Isa::Portable, &data, &data, &mut s2);
            assert_eq!(s1, s2);
            let mut r1 = vec![0.0; 999];
            let mut r2 = vec![0.0; 999];
            rms_norm(isa, &data, &w, 1e-5, &mut r1);
            rms_norm(Isa::Portable, &data, &w, 1e-5, &mut r2);
            assert_eq!(r1, r2);
            let (mut g1, mut g2) = (data.clone(), data.clone());
            gelu_tanh_inplace(isa, &mut g1);
            gelu_tanh_inplace(Isa::Portable, &mut g2);
            assert_eq!(g1, g2);
            let mut g3 = vec![0.0; 999];
            gelu_tanh(isa, &data, &mut g3);
            assert_eq!(bits(&g3), bits(&g1));
            let mut s3 = data.clone();
            let mut s4 = data.clone();
            silu_inplace(isa, &mut s3);
            silu_inplace(Isa::Portable, &mut s4);
            assert_eq!(s3, s4);
            let bias: Vec<f32> = w.iter().map(|v| v - 1.0).collect();
            let (mut l1, mut l2) = (vec![0.0; 999], vec![0.0; 999]);
            layer_norm(isa, &data, &w, &bias, 1e-6, &mut l1);
            layer_norm(Isa::Portable, &data, &w, &bias, 1e-6, &mut l2);
            assert_eq!(l1, l2);
            let (cos, sin): (Vec<f32>, Vec<f32>) = (0..32)
                .map(|i| ((i as f32 * 0.3).cos(), (i as f32 * 0.3).sin()))
                .unzip();
            let (mut q1, mut q2) = (data[..64].to_vec(), data[..64].to_vec());
            rope(isa, &mut q1, &cos, &sin);
            rope(Isa::Portable, &mut q2, &cos, &sin);
            assert_eq!(q1, q2);
        }
    }

    #[test]
    fn silu_and_rms_norm_match_definitions() {
        let x = [-3.0f32, -0.5, 0.0, 0.7, 4.0];
        let mut out = [0.0; 5];
        silu_mul(Isa::detect(), &x, &[1.0; 5], &mut out);
        for (o, v) in out.iter().zip(x) {
            let want = f64::from(v) / (1.0 + (-f64::from(v)).exp());
            assert!((f64::from(*o) - want).abs() < 1e-6);
        }
        let mut n = [0.0; 5];
        rms_norm(Isa::detect(), &x, &[2.0; 5], 0.0, &mut n);
        let rms = (x.iter().map(|v| v * v).sum::<f32>() / 5.0).sqrt();
        for (o, v) in n.iter().zip(x) {
            assert!((o - 2.0 * v / rms).abs() < 1e-6);
        }
    }

    #[test]
    fn layer_norm_and_gelu_match_definitions() {
        let x = [-3.0f32, -0.5, 0.0, 0.7, 4.0, 1.5];
        let (w, b) = (
            [0.5f32, 1.0, 2.0, -1.0, 1.5, 0.25],
            [0.1f32, 0.0, -0.2, 0.3, 0.0, 1.0],
        );
        for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
            .into_iter()
            .filter(|i| i.available())
        {
            let mut out = [0.0f32; 12];
            let xx: Vec<f32> = x.iter().chain(&x).copied().collect();
            layer_norm(isa, &xx, &w, &b, 1e-6, &mut out);
            let mean = x.iter().map(|&v| f64::from(v)).sum::<f64>() / 6.0;
            let var = x
                .iter()
                .map(|&v| (f64::from(v) - mean).powi(2))
                .sum::<f64>()
                / 6.0;
            for i in 0..12 {
                let want = (f64::from(x[i % 6]) - mean) / (var + 1e-6).sqrt() * f64::from(w[i % 6])
                    + f64::from(b[i % 6]);
                assert!(
                    (f64::from(out[i]) - want).abs() < 1e-5,
                    "{i}: {} vs {want}",
                    out[i]
                );
            }
            let mut g: Vec<f32> = (-80..80).map(|i| i as f32 / 8.0).collect();
            let src = g.clone();
            gelu_tanh_inplace(isa, &mut g);
            let exact = |v: f64| {
                0.5 * v
                    * (1.0
                        + ((2.0 / std::f64::consts::PI).sqrt() * (v + 0.044715 * v * v * v)).tanh())
            };
            for (o, &v) in g.iter().zip(&src) {
                let want = exact(f64::from(v));
                assert!(
                    (f64::from(*o) - want).abs() < 2e-6 * (1.0 + want.abs()),
                    "{v}: {o} vs {want}"
                );
            }
            // The bf16-grade GELU: within 1e-5 relative (plus 1e-7 absolute near 0), from far
            // negative (an exponent past 2^127) to far positive.
            let wide: Vec<f32> = src
                .iter()
                .copied()
                .chain([-1e4, -100.0, 100.0, 1e4])
                .collect();
            let mut cheap = vec![0.0f32; wide.len()];
            gelu_tanh_bf16_grade(isa, &wide, &mut cheap);
            for (o, &v) in cheap.iter().zip(&wide) {
                let want = exact(f64::from(v));
                assert!(
                    (f64::from(*o) - want).abs() <= 1e-5 * want.abs() + 1e-7,
                    "bf16 grade {v}: {o} vs {want}"
                );
            }
        }
    }

    #[test]
    fn rope_rotates_pairs_by_position() {
        let (mut c, mut s) = ([0.0; 2], [0.0; 2]);
        rope_table(3.0, 4, &mut c, &mut s);
        assert!((c[0] - 3.0f32.cos()).abs() < 1e-7 && (s[1] - (3.0f32 / 100.0).sin()).abs() < 1e-7);
        let mut x = [1.0, 0.0, 0.0, 1.0];
        rope(Isa::detect(), &mut x, &c, &s);
        assert!((x[0] - c[0]).abs() < 1e-7 && (x[2] - s[0]).abs() < 1e-7);
        assert!((x[1] + s[1]).abs() < 1e-7 && (x[3] - c[1]).abs() < 1e-7);
    }
}
