//! The finite-difference check of an `rtc_vjp` pullback, shared by every model that serves it.
//!
//! The pullback `rtc_vjp` takes from Candle's autograd is the transposed Jacobian of the
//! velocity applied to the guidance error: its inner product with a direction `e` agrees with a
//! central difference of `<v(x), c>` along `e`. The pullback is read from the sampler's first
//! step, where `rtc` and `rtc_vjp` start from the same noise and velocity and the weight is the
//! cap `w`: `v_vjp - v_rtc = w J^T c` with `c = 1 * err` (time 1). The velocity at a perturbed
//! sample is plain sampling's first step from that noise.
//!
//! The bound, in f32: the difference quotient's rounding, `2 δ Σ|c| / (2h)`, with `δ` the
//! velocity's rounding error, estimated by the gap between two independent f32 implementations
//! of the velocity (fast kernels and Candle); its truncation error `C h²`, bounded by
//! `|D(2h) - D(h)| = 3 C h²`; the pullback's own rounding, the same relative error as the
//! velocity's times `Σ|p e|`, times 16 for the backward pass's own depth; and an ulp of each
//! guided velocity the pullback is read from.

use kairos_engine::GuidanceMode;
use kairos_engine::guidance::RowGuide;

use crate::smolvla_processors::max_abs_diff;

/// Checks the pullback of `model` against a central difference of step `h`.
///
/// `first_velocity(x, guide)` is the velocity of the sampler's first step from noise `x` (guided
/// when a guide is given), on the Candle path; `guide(mode)` the row guide for `mode`; `v_other`
/// the plain first velocity from `noise` on the other, independent implementation.
pub fn vjp_matches_a_finite_difference(
    model: &str,
    noise: &[f32],
    first_velocity: impl Fn(&[f32], Option<RowGuide>) -> Vec<f32>,
    guide: impl Fn(GuidanceMode) -> RowGuide,
    v_other: &[f32],
    h: f32,
) {
    let len = noise.len();
    let v = first_velocity(noise, None);
    let rtc = guide(GuidanceMode::Rtc);
    let w = rtc.max_guidance_weight;
    let v_rtc = first_velocity(noise, Some(rtc.clone()));
    let v_vjp = first_velocity(noise, Some(guide(GuidanceMode::RtcVjp)));
    let pullback: Vec<f64> = v_vjp
        .iter()
        .zip(&v_rtc)
        .map(|(a, b)| f64::from(a - b) / f64::from(w))
        .collect();
    let c: Vec<f64> = rtc
        .error(1.0, noise, &v)
        .into_iter()
        .map(f64::from)
        .collect();
    assert!(
        c.iter().any(|&ci| ci != 0.0),
        "{model}: the error weighs something"
    );
    let e: Vec<f32> = kairos_engine::sampler::gaussian_noise(11, 0, len);
    let dot = |a: &[f32], b: &[f64]| -> f64 {
        a.iter().zip(b).map(|(x, y)| f64::from(*x) * y).sum::<f64>()
    };
    let along = |h: f32| {
        let shifted =
            |s: f32| -> Vec<f32> { noise.iter().zip(&e).map(|(x, ei)| x + s * ei).collect() };
        let up = first_velocity(&shifted(h), None);
        let down = first_velocity(&shifted(-h), None);
        (dot(&up, &c) - dot(&down, &c)) / (2.0 * f64::from(h))
    };
    let (fd, fd2) = (along(h), along(2.0 * h));
    let analytic: f64 = pullback
        .iter()
        .zip(&e)
        .map(|(p, ei)| p * f64::from(*ei))
        .sum();
    let delta = f64::from(max_abs_diff(&v, v_other)).max(f64::from(f32::EPSILON));
    let scale = v.iter().fold(0.0f64, |m, x| m.max(f64::from(x.abs())));
    let sum_c: f64 = c.iter().map(|x| x.abs()).sum();
    let sum_pe: f64 = pullback
        .iter()
        .zip(&e)
        .map(|(p, ei)| (p * f64::from(*ei)).abs())
        .sum();
    // Reading the pullback off `v_vjp - v_rtc` rounds each by an ulp of its magnitude.
    let extraction: f64 = v_vjp
        .iter()
        .zip(&v_rtc)
        .zip(&e)
        .map(|((a, b), ei)| {
            f64::from(f32::EPSILON) * f64::from(a.abs() + b.abs()) * f64::from(ei.abs())
        })
        .sum::<f64>()
        / f64::from(w);
    let bound = delta * sum_c / f64::from(h)
        + (fd2 - fd).abs()
        + 16.0 * delta / scale * sum_pe
        + extraction;
    eprintln!(
        "{model}: vjp . e = {analytic:.6e}, difference quotient {fd:.6e} (2h: {fd2:.6e}), \
         bound {bound:.3e}"
    );
    assert!(
        bound < 0.1 * analytic.abs(),
        "{model}: the bound must be able to fail"
    );
    assert!(
        (fd - analytic).abs() <= bound,
        "{model}: autograd {analytic}, finite difference {fd}, bound {bound}"
    );
}
