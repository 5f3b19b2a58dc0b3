//! The five normalisation, activation and position ops of the Candle path, in one place:
//! RMSNorm, LayerNorm, SiLU, softmax over the last dimension and rotary position embeddings.
//!
//! # Why this module exists
//!
//! `candle-nn` has each of these as one fused kernel (`candle_nn::ops`,
//! `candle_nn::rotary_emb`). On a GPU that matters: a composed RMSNorm is six kernel launches
//! and five intermediate tensors, the fused one is one launch, and at the small batches a robot
//! policy serves launch overhead is a large share of a forward pass. On the CPU the Candle path
//! is the reference the fast kernels are tested against (and π0/π0.5's only path). There a
//! composition is a few passes over the tensor where the fused kernel makes one: little next to
//! the matrix products around it, except for a softmax over a large attention matrix (SigLIP's
//! image tokens), whose three elementwise passes each go through candle-core's thread pool.
//!
//! So `candle-nn` is a dependency of a CUDA build only (the engine's `cuda` feature), and
//! nothing that serves on the CPU carries it. Every caller in the engine goes through the
//! functions here, and each picks its implementation by the tensor's device:
//!
//! - on a CUDA device (only possible with the `cuda` feature) it runs `candle-nn`'s fused
//!   kernel, unless the input tracks gradients (below);
//! - everywhere else it runs a composition of candle-core ops with the same semantics.
//!
//! Choosing by device rather than by feature keeps a CPU run's numbers the same whether the
//! binary was built with the feature or without it.
//!
//! # What "the same semantics" means, op by op
//!
//! The compositions follow what `candle-nn` 0.11's CPU kernels compute, and where those
//! accumulate in f32 the compositions do too:
//!
//! - [`rms_norm`]: `x / sqrt(mean(x²) + eps) * alpha`. The mean of squares and the division run
//!   in f32 for bf16/f16 input (as the kernel's f32 sum of squares), the product with `alpha`
//!   in the input's dtype (as the kernel's).
//! - [`layer_norm`]: `(x - mean) / sqrt(var + eps) * alpha + beta`, all in f32 for bf16/f16
//!   input and rounded once at the end, as the kernel. The variance is the two-pass
//!   `mean((x - mean)²)`, which is never less accurate than the kernel's one-pass
//!   `mean(x²) - mean²`.
//! - [`softmax_last_dim`]: `exp(x - max) / sum(exp(x - max))`; bf16/f16 input is computed in
//!   f32 and rounded once (the kernel sums in the input's dtype; f32 is at least as accurate).
//! - [`rope`]: the non-interleaved ("rotate half") variant of `candle_nn::rotary_emb::rope`,
//!   not `rope_i`: with `x = [x1 | x2]` split at half the head dimension,
//!   `[x1·cos - x2·sin | x1·sin + x2·cos]`, each product and sum rounded in the input's dtype
//!   exactly as the kernel rounds them, so the two agree bit for bit.
//! - [`silu`]: `x * sigmoid(x)`. `candle_nn::ops::silu` is itself candle-core's unary op (one
//!   kernel on every device), so this one needs no second implementation.
//!
//! The unit tests below compare every composition with `candle-nn`'s kernel on the CPU, in f32
//! and bf16, at the models' shapes, each within a bound derived from the rounding of the two
//! (zero for RoPE and SiLU).
//!
//! # Gradients
//!
//! Unlike the fused kernels, the compositions have a backward pass (candle-core's ops each have
//! one), and `rtc_vjp` needs it: the SmolVLA expert (and the flow head built on it) and π0/π0.5
//! take the vector–Jacobian product of their velocity with Candle's `backward`. So an input that tracks
//! gradients (`Tensor::track_op`: a `Var`, or anything computed from one) takes the composition
//! on CUDA too. The alternative, refusing `rtc_vjp` on CUDA, would leave the GPU, where a
//! backward pass is cheapest, as the one Candle device that cannot serve it; the price of this
//! choice is paid only by tracked tensors (the `rtc_vjp` rows of a batch, which the expert runs
//! apart from the other rows, so those keep the fused kernels and their bits), in kernel
//! launches and intermediate tensors, not in results beyond the rounding bounds the tests below
//! derive.

use candle_core::{D, DType, Result, Tensor, bail};

/// Llama's RMSNorm over the last dimension: `x / sqrt(mean(x²) + eps) * alpha`, `alpha` of the
/// last dimension's size. The fused `candle_nn::ops::rms_norm` on CUDA, composed elsewhere.
pub fn rms_norm(x: &Tensor, alpha: &Tensor, eps: f32) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    if fused(x) {
        return candle_nn::ops::rms_norm(x, alpha, eps);
    }
    rms_norm_composed(x, alpha, eps)
}

/// LayerNorm over the last dimension: `(x - mean) / sqrt(var + eps) * alpha + beta`, `alpha`
/// and `beta` of the last dimension's size. The fused `candle_nn::ops::layer_norm` on CUDA,
/// composed elsewhere.
pub fn layer_norm(x: &Tensor, alpha: &Tensor, beta: &Tensor, eps: f32) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    if fused(x) {
        return candle_nn::ops::layer_norm(x, alpha, beta, eps);
    }
    layer_norm_composed(x, alpha, beta, eps)
}

/// Softmax over the last dimension. The fused `candle_nn::ops::softmax_last_dim` on CUDA,
/// composed elsewhere.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    if fused(x) {
        return candle_nn::ops::softmax_last_dim(x);
    }
    softmax_last_dim_composed(x)
}

/// Rotary position embedding, non-interleaved: `x` `[batch, heads, rows, head_dim]`, `cos` and
/// `sin` `[rows', head_dim / 2]` (shared by the batch) or `[batch, rows', head_dim / 2]` (one
/// table per batch entry), with `rows' >= rows` (the first `rows` are used). The fused
/// `candle_nn::rotary_emb::rope` on CUDA (which needs all three contiguous), composed
/// elsewhere.
pub fn rope(x: &Tensor, cos: &Tensor, sin: &Tensor) -> Result<Tensor> {
    #[cfg(feature = "cuda")]
    if fused(x) {
        return candle_nn::rotary_emb::rope(x, cos, sin);
    }
    rope_composed(x, cos, sin)
}

/// Whether `x` runs `candle-nn`'s fused kernel: on a CUDA device, unless `x` tracks gradients
/// (the fused kernels have no backward pass; module doc).
#[cfg(feature = "cuda")]
fn fused(x: &Tensor) -> bool {
    x.device().is_cuda() && !x.track_op()
}

/// SiLU (`x * sigmoid(x)`), candle-core's own unary op on every device: `candle_nn::ops::silu`
/// is this same call.
pub fn silu(x: &Tensor) -> Result<Tensor> {
    x.silu()
}

/// The dtype a normalisation or softmax accumulates in: f32 for the half-precision dtypes, the
/// input's own otherwise (as `candle-nn`'s CPU kernels).
fn accumulation_dtype(dtype: DType) -> DType {
    match dtype {
        DType::BF16 | DType::F16 => DType::F32,
        d => d,
    }
}

/// Fails as the fused kernels do when a weight vector does not match the last dimension.
fn check_weight(op: &str, x: &Tensor, weight: &Tensor) -> Result<()> {
    let width = x.dim(D::Minus1)?;
    if weight.dims1()? != width {
        bail!(
            "shape mismatch in {op} {:?} {:?}",
            x.shape(),
            weight.shape()
        )
    }
    Ok(())
}

fn rms_norm_composed(x: &Tensor, alpha: &Tensor, eps: f32) -> Result<Tensor> {
    check_weight("rms-norm", x, alpha)?;
    let dtype = x.dtype();
    let xa = x.to_dtype(accumulation_dtype(dtype))?;
    let mean_square = xa.sqr()?.mean_keepdim(D::Minus1)?;
    let rms = (mean_square + f64::from(eps))?.sqrt()?;
    xa.broadcast_div(&rms)?
        .to_dtype(dtype)?
        .broadcast_mul(alpha)
}

fn layer_norm_composed(x: &Tensor, alpha: &Tensor, beta: &Tensor, eps: f32) -> Result<Tensor> {
    check_weight("layer-norm", x, alpha)?;
    check_weight("layer-norm", x, beta)?;
    let dtype = x.dtype();
    let acc = accumulation_dtype(dtype);
    let xa = x.to_dtype(acc)?;
    let centred = xa.broadcast_sub(&xa.mean_keepdim(D::Minus1)?)?;
    let variance = centred.sqr()?.mean_keepdim(D::Minus1)?;
    let std = (variance + f64::from(eps))?.sqrt()?;
    centred
        .broadcast_div(&std)?
        .broadcast_mul(&alpha.to_dtype(acc)?)?
        .broadcast_add(&beta.to_dtype(acc)?)?
        .to_dtype(dtype)
}

fn softmax_last_dim_composed(x: &Tensor) -> Result<Tensor> {
    let dtype = x.dtype();
    let xa = x.to_dtype(accumulation_dtype(dtype))?;
    let exp = xa.broadcast_sub(&xa.max_keepdim(D::Minus1)?)?.exp()?;
    exp.broadcast_div(&exp.sum_keepdim(D::Minus1)?)?
        .to_dtype(dtype)
}

/// A cos/sin table's first `rows` rows, shaped to broadcast against `[batch, heads, rows,
/// head_dim / 2]`.
fn rope_table(table: &Tensor, batch: usize, rows: usize, half: usize) -> Result<Tensor> {
    match *table.dims() {
        [r, h] if h == half && r >= rows => table.narrow(0, 0, rows)?.reshape((1, 1, rows, half)),
        [b, r, h] if b == batch && h == half && r >= rows => table.narrow(1, 0, rows)?.unsqueeze(1),
        _ => bail!(
            "rope: a cos/sin table {:?} does not fit {batch} batch entries of {rows} rows \
             and head dimension {}",
            table.shape(),
            2 * half
        ),
    }
}

fn rope_composed(x: &Tensor, cos: &Tensor, sin: &Tensor) -> Result<Tensor> {
    let (batch, _heads, rows, head_dim) = x.dims4()?;
    if head_dim % 2 != 0 {
        bail!("rope: odd head dimension {head_dim}")
    }
    let half = head_dim / 2;
    let cos = rope_table(cos, batch, rows, half)?;
    let sin = rope_table(sin, batch, rows, half)?;
    let x1 = x.narrow(D::Minus1, 0, half)?;
    let x2 = x.narrow(D::Minus1, half, half)?;
    let first = (x1.broadcast_mul(&cos)? - x2.broadcast_mul(&sin)?)?;
    let second = (x1.broadcast_mul(&sin)? + x2.broadcast_mul(&cos)?)?;
    Tensor::cat(&[first, second], D::Minus1)
}

#[cfg(test)]
mod tests {
    //! Each composition against `candle-nn`'s fused CPU kernel, at the shapes the models run
    //! (SmolVLA: width 960, expert 720, head dimension 64; π0/π0.5: Gemma width 2048 and 1024,
    //! head dimension 256, SigLIP width 1152), on seeded normal inputs.
    //!
    //! The bounds, with `u` the unit roundoff (f32: 2⁻²⁴; bf16: 2⁻⁸) and `n` the row length:
    //!
    //! - RoPE, SiLU: 0. The same products and sums, in the same order, rounded in the same
    //!   dtype (Rust does not contract `a*b - c*d` into a fused multiply-add).
    //! - Softmax, f32: the two differ only in the order of the row's sum, a sum of `n`
    //!   positive terms, so each sum is within `(n-1)u` of the exact one (relative) and each
    //!   output, one division later, within `(2n+2)u·|out|` of the other.
    //! - Softmax, bf16: the kernel rounds `x - max` to bf16 (an absolute error of up to
    //!   `u·|x - max|` in the exponent, so `u·|x - max|` relative after `exp`), rounds `exp` and
    //!   adds the row in bf16 (`(n-1)u` relative); the composition works in f32 and rounds once
    //!   (`u`). Bound: `(|x - max| + n + 3)·u·|out|`.
    //! - RMSNorm, f32: the sums of squares differ by order (`2(n-1)u` relative, positive terms),
    //!   half of that after the square root, plus a rounding each for the mean, `+ eps`, the
    //!   square root, the division and the product: `(n + 8)u·|out|`.
    //! - RMSNorm, bf16: the f32 part as above, then the kernel rounds the rms, the quotient and
    //!   the product to bf16 (`3u`), the composition the quotient and the product (`2u`):
    //!   `6u·|out|` plus the f32 term, which is far smaller.
    //! - LayerNorm, f32: the kernel's one-pass variance `E[x²] - mean²` carries an absolute
    //!   error of up to about `2n·u·E[x²]`, that is `2n·u·κ` relative to the variance with
    //!   `κ = E[x²] / var` (the row's), and the mean an absolute error of `n·u·E|x|`. Through
    //!   `1/sqrt(var)` and `alpha`, each output moves by at most
    //!   `(n·u·κ + 8u)·|alpha|·|z| + n·u·(E|x| / std)·|alpha| + 2u·|beta|` with `z` the
    //!   normalised input; the test allows twice that.
    //! - LayerNorm, bf16: as f32 (both compute in f32), plus one bf16 rounding on each side:
    //!   `2u_bf16·|out|` more.

    use candle_core::{DType, Device, Tensor};
    use rand::SeedableRng;
    use rand::rngs::StdRng;
    use rand_distr::{Distribution, Normal};

    const U_F32: f32 = f32::EPSILON / 2.0;
    const U_BF16: f32 = 1.0 / 256.0;

    fn normal(rng: &mut StdRng, n: usize, mean: f32, std: f32) -> Vec<f32> {
        let dist = Normal::new(mean, std).unwrap();
        (0..n).map(|_| dist.sample(rng)).collect()
    }

    fn tensor(values: Vec<f32>, dims: &[usize], dtype: DType) -> Tensor {
        Tensor::from_vec(values, dims, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
    }

    fn host(t: &Tensor) -> Vec<f32> {
        t.to_dtype(DType::F32)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    }

    /// Asserts `|composed - fused| <= bound(i, fused)` elementwise, naming the worst element.
    fn assert_within(
        what: &str,
        composed: &Tensor,
        fused: &Tensor,
        bound: impl Fn(usize, f32) -> f32,
    ) {
        assert_eq!(composed.shape(), fused.shape(), "{what}: shapes");
        assert_eq!(composed.dtype(), fused.dtype(), "{what}: dtypes");
        let (c, f) = (host(composed), host(fused));
        for (i, (&a, &b)) in c.iter().zip(&f).enumerate() {
            assert!(
                a.is_finite() && b.is_finite(),
                "{what}: element {i} {a} vs {b}"
            );
            let allowed = bound(i, b);
            assert!(
                (a - b).abs() <= allowed,
                "{what}: element {i}: composed {a}, fused {b}, |diff| {} > bound {allowed}",
                (a - b).abs()
            );
        }
    }

    #[test]
    fn rope_is_bit_identical_to_candle_nn() {
        let mut rng = StdRng::seed_from_u64(7);
        // (batch, heads, rows, head_dim, batched tables, table rows)
        let cases = [
            (2, 15, 37, 64, false, 40), // SmolVLA's text model, longest prefix 37
            (3, 5, 50, 64, true, 50),   // SmolVLA's expert: one table per row
            (1, 8, 19, 256, false, 19), // π's Gemma (a batch of one, heads first)
            (4, 1, 1, 256, false, 1),   // one row per sequence
            (2, 2, 1, 64, true, 1),
        ];
        for dtype in [DType::F32, DType::BF16] {
            for &(b, h, t, d, batched, tr) in &cases {
                let x = tensor(
                    normal(&mut rng, b * h * t * d, 0.0, 1.0),
                    &[b, h, t, d],
                    dtype,
                );
                let table_dims: Vec<usize> = if batched {
                    vec![b, tr, d / 2]
                } else {
                    vec![tr, d / 2]
                };
                let count = table_dims.iter().product();
                let angles = normal(&mut rng, count, 0.0, 3.0);
                let cos = tensor(angles.iter().map(|a| a.cos()).collect(), &table_dims, dtype);
                let sin = tensor(angles.iter().map(|a| a.sin()).collect(), &table_dims, dtype);
                let composed = super::rope_composed(&x, &cos, &sin).unwrap();
                let fused = candle_nn::rotary_emb::rope(&x, &cos, &sin).unwrap();
                let what = format!("rope {dtype:?} {:?}", x.shape());
                assert_within(&what, &composed, &fused, |_, _| 0.0);
            }
        }
    }

    #[test]
    fn rope_refuses_a_table_that_does_not_fit() {
        let x = Tensor::zeros((2, 3, 5, 8), DType::F32, &Device::Cpu).unwrap();
        let short = Tensor::zeros((4, 4), DType::F32, &Device::Cpu).unwrap();
        assert!(super::rope(&x, &short, &short).is_err());
        let wrong_batch = Tensor::zeros((3, 5, 4), DType::F32, &Device::Cpu).unwrap();
        assert!(super::rope(&x, &wrong_batch, &wrong_batch).is_err());
        let odd = Tensor::zeros((2, 3, 5, 7), DType::F32, &Device::Cpu).unwrap();
        let table = Tensor::zeros((5, 3), DType::F32, &Device::Cpu).unwrap();
        assert!(super::rope(&odd, &table, &table).is_err());
    }

    #[test]
    fn silu_is_candle_nn_silu() {
        let mut rng = StdRng::seed_from_u64(11);
        for dtype in [DType::F32, DType::BF16] {
            let x = tensor(normal(&mut rng, 3 * 2048, 0.0, 4.0), &[3, 2048], dtype);
            let ours = super::silu(&x).unwrap();
            let theirs = candle_nn::ops::silu(&x).unwrap();
            assert_within("silu", &ours, &theirs, |_, _| 0.0);
        }
    }

    #[test]
    fn softmax_matches_candle_nn_within_the_summation_bound() {
        let mut rng = StdRng::seed_from_u64(13);
        // Attention scores: [batch, heads, queries, keys].
        let shapes: [&[usize]; 4] = [&[2, 5, 150, 87], &[1, 8, 19, 19], &[3, 15, 4, 300], &[4, 7]];
        for dtype in [DType::F32, DType::BF16] {
            for dims in shapes {
                let count = dims.iter().product();
                let x = tensor(normal(&mut rng, count, 0.0, 3.0), dims, dtype);
                let composed = super::softmax_last_dim_composed(&x).unwrap();
                let fused = candle_nn::ops::softmax_last_dim(&x).unwrap();
                let n = *dims.last().unwrap();
                let xs = host(&x);
                let row_max: Vec<f32> = xs
                    .chunks(n)
                    .map(|r| r.iter().copied().fold(f32::NEG_INFINITY, f32::max))
                    .collect();
                let what = format!("softmax {dtype:?} {dims:?}");
                assert_within(&what, &composed, &fused, |i, out| match dtype {
                    DType::F32 => (2 * n + 2) as f32 * U_F32 * out.abs(),
                    _ => {
                        let spread = xs[i] - row_max[i / n];
                        (spread.abs() + n as f32 + 3.0) * U_BF16 * out.abs()
                    }
                });
                // Each row still sums to one, within the final rounding of its terms (`u`
                // relative each) and an f32 sum of them here.
                let u = if dtype == DType::F32 { U_F32 } else { U_BF16 };
                for row in host(&composed).chunks(n) {
                    let sum: f32 = row.iter().sum();
                    let allowed = u + 2.0 * n as f32 * U_F32;
                    assert!((sum - 1.0).abs() <= allowed, "{what}: a row sums to {sum}");
                }
            }
        }
    }

    #[test]
    fn softmax_keeps_an_additive_minus_infinity_mask() {
        let x = Tensor::new(
            &[[1.0f32, f32::NEG_INFINITY, 3.0, f32::NEG_INFINITY]],
            &Device::Cpu,
        )
        .unwrap();
        let composed = host(&super::softmax_last_dim(&x).unwrap());
        let fused = host(&candle_nn::ops::softmax_last_dim(&x).unwrap());
        assert_eq!(composed[1], 0.0);
        assert_eq!(composed[3], 0.0);
        for (a, b) in composed.iter().zip(&fused) {
            assert!(
                (a - b).abs() <= 4.0 * U_F32 * b.abs(),
                "{composed:?} vs {fused:?}"
            );
        }
    }

    #[test]
    fn rms_norm_matches_candle_nn_within_the_summation_bound() {
        let mut rng = StdRng::seed_from_u64(17);
        for dtype in [DType::F32, DType::BF16] {
            for (rows, n) in [(37, 960), (50, 720), (19, 2048), (51, 1024), (3, 64)] {
                let x = tensor(normal(&mut rng, rows * n, 0.3, 2.0), &[rows, n], dtype);
                let alpha = tensor(normal(&mut rng, n, 1.0, 0.5), &[n], dtype);
                let composed = super::rms_norm_composed(&x, &alpha, 1e-6).unwrap();
                let fused = candle_nn::ops::rms_norm(&x, &alpha, 1e-6).unwrap();
                let f32_part = (n + 8) as f32 * U_F32;
                let relative = match dtype {
                    DType::F32 => f32_part,
                    _ => 6.0 * U_BF16 + f32_part,
                };
                let what = format!("rms_norm {dtype:?} [{rows}, {n}]");
                assert_within(&what, &composed, &fused, |_, out| {
                    relative * out.abs() + f32::MIN_POSITIVE
                });
            }
        }
    }

    #[test]
    fn layer_norm_matches_candle_nn_within_the_variance_bound() {
        let mut rng = StdRng::seed_from_u64(19);
        for dtype in [DType::F32, DType::BF16] {
            for (rows, n) in [(64, 1152), (7, 768), (2, 64)] {
                let values = normal(&mut rng, rows * n, 0.5, 1.5);
                let x = tensor(values, &[rows, n], dtype);
                let alpha = tensor(normal(&mut rng, n, 1.0, 0.5), &[n], dtype);
                let beta = tensor(normal(&mut rng, n, 0.0, 0.5), &[n], dtype);
                let composed = super::layer_norm_composed(&x, &alpha, &beta, 1e-6).unwrap();
                let fused = candle_nn::ops::layer_norm(&x, &alpha, &beta, 1e-6).unwrap();
                // The row statistics the bound needs, from the input as the kernels see it.
                let (xs, al, be) = (host(&x), host(&alpha), host(&beta));
                let stats: Vec<(f32, f32, f32, f32)> = xs
                    .chunks(n)
                    .map(|r| {
                        let m = r.iter().sum::<f32>() / n as f32;
                        let ex2 = r.iter().map(|v| v * v).sum::<f32>() / n as f32;
                        let var = r.iter().map(|v| (v - m) * (v - m)).sum::<f32>() / n as f32;
                        let abs_mean = r.iter().map(|v| v.abs()).sum::<f32>() / n as f32;
                        (m, var.sqrt(), ex2 / var, abs_mean)
                    })
                    .collect();
                let nu = n as f32 * U_F32;
                let what = format!("layer_norm {dtype:?} [{rows}, {n}]");
                assert_within(&what, &composed, &fused, |i, out| {
                    let (mean, std, kappa, abs_mean) = stats[i / n];
                    let (a, b) = (al[i % n].abs(), be[i % n].abs());
                    let z = ((xs[i] - mean) / std).abs();
                    let f32_bound = (nu * kappa + 8.0 * U_F32) * a * z
                        + nu * (abs_mean / std) * a
                        + 2.0 * U_F32 * b;
                    let rounding = if dtype == DType::F32 {
                        0.0
                    } else {
                        2.0 * U_BF16 * out.abs()
                    };
                    2.0 * f32_bound + rounding
                });
            }
        }
    }

    #[test]
    fn the_norms_refuse_a_weight_of_the_wrong_width() {
        let x = Tensor::zeros((2, 8), DType::F32, &Device::Cpu).unwrap();
        let w = Tensor::ones(7, DType::F32, &Device::Cpu).unwrap();
        let ok = Tensor::ones(8, DType::F32, &Device::Cpu).unwrap();
        assert!(super::rms_norm(&x, &w, 1e-6).is_err());
        assert!(super::layer_norm(&x, &w, &ok, 1e-6).is_err());
        assert!(super::layer_norm(&x, &ok, &w, 1e-6).is_err());
    }
}
