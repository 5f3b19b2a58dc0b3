//! Real-time chunking and inpainting inside the shared flow sampler ([`crate::sampler`]).
//!
//! A [`kairos_engine_types::Guidance`] names the actions a robot committed to while its request
//! is in flight. [`RowGuide::prepare`] turns it into what one row of the sampler needs, in the
//! model's own action space: the target actions padded to the chunk, a weight per action, and
//! the row's initial noise (for the hard prefix). [`RowGuide::guide`] then changes that row's
//! velocity at every Euler step, and [`RowGuide::after_step`] that row's sample; other rows are
//! never read or written, so a batch mixes strategies without one changing another.
//!
//! `rtc` is LeRobot 0.6.1's `RTCProcessor.denoise_step` (`policies/rtc/modeling_rtc.py`),
//! operation for operation in f32:
//!
//! ```text
//! tau  = 1 - time                                   (f64, then f32 as torch.as_tensor makes it)
//! x1   = x - time * v                               (v computed before x needs a gradient)
//! err  = (prev - x1) * w                            (w: get_prefix_weights, per action)
//! corr = d x1 / d x applied to err = err            (v is a constant of the graph: identity VJP)
//! g    = min(nan_to_num(c * inv_r2, posinf = max), max),
//!        c = nan_to_num((1 - tau) / tau, posinf = max), inv_r2 = ((1-tau)^2 + tau^2) / (1-tau)^2
//! v'   = v - g * corr
//! ```
//!
//! `rtc_vjp` is the paper's guidance: the same error pulled back through the velocity network,
//! `corr = err - J_v^T (time * err)`, which needs the model's backward pass
//! ([`crate::sampler::VelocityField::velocity_vjp`]).

use kairos_engine_types::{Guidance, GuidanceMode, PrefixSchedule};

use crate::EngineError;

/// LeRobot's `get_prefix_weights(start, end, total)`: one weight per action of the chunk.
///
/// `start` (the committed actions) is first cut to `end`. `linear` and `exp` fall from 1 to 0
/// over the actions between `start` and `end` as `torch.linspace(1, 0, n + 2)[1:-1]` does (in
/// f32, its two halves computed from either end as ATen's kernel does), `exp` then shaped by
/// `w · expm1(w) / (e − 1)`.
pub fn prefix_weights(
    schedule: PrefixSchedule,
    start: usize,
    end: usize,
    total: usize,
) -> Vec<f32> {
    let start = start.min(end);
    let mut weights = vec![0.0f32; total];
    match schedule {
        PrefixSchedule::Zeros => {
            weights[..start.min(total)].fill(1.0);
        }
        PrefixSchedule::Ones => {
            weights[..end.min(total)].fill(1.0);
        }
        PrefixSchedule::Linear | PrefixSchedule::Exp => {
            let ramp: Vec<f32> = linspace_inner(start, end, total)
                .into_iter()
                .map(|w| match schedule {
                    // expm1 in f64, rounded to f32: that gives torch's f32 expm1 on LeRobot's
                    // goldens (`rtc.exp.*.weights`), where the platform's expm1f is an ulp off.
                    PrefixSchedule::Exp => {
                        w * ((f64::from(w).exp_m1() as f32) / (std::f64::consts::E - 1.0) as f32)
                    }
                    _ => w,
                })
                .collect();
            // [ones(start)] ++ ramp ++ [zeros(total - end)], as LeRobot concatenates them.
            let ones = start.min(total);
            weights[..ones].fill(1.0);
            for (w, r) in weights[ones..].iter_mut().zip(&ramp) {
                *w = *r;
            }
        }
    }
    weights
}

/// `torch.linspace(1, 0, steps + 2)[1:-1]` with `steps = total - max(total - end, 0) - start`
/// (empty when `end <= start` or `steps <= 0`).
fn linspace_inner(start: usize, end: usize, total: usize) -> Vec<f32> {
    let skip_at_end = total.saturating_sub(end);
    let steps = total as i64 - skip_at_end as i64 - start as i64;
    if end <= start || steps <= 0 {
        return Vec::new();
    }
    let n = steps + 2;
    // ATen: step = (end - start) / (n - 1) in the dtype; the first half counts up from start,
    // the second down from end.
    let step = (0.0f32 - 1.0f32) / (n - 1) as f32;
    let halfway = n / 2;
    (1..n - 1)
        .map(|i| {
            if i < halfway {
                1.0f32 + step * i as f32
            } else {
                0.0f32 - step * (n - i - 1) as f32
            }
        })
        .collect()
}

/// LeRobot's guidance weight at sampler time `time` (1 = noise, 0 = actions), capped at
/// `max_weight`; computed in f32 from `tau = 1 - time` as `denoise_step` does.
pub fn guidance_weight(time: f64, max_weight: f32) -> f32 {
    let tau = (1.0 - time) as f32;
    let one_minus = 1.0f32 - tau;
    let squared = one_minus * one_minus;
    let inv_r2 = (squared + tau * tau) / squared;
    let nan_to_num = |value: f32| {
        if value.is_nan() {
            0.0
        } else if value == f32::INFINITY {
            max_weight
        } else if value == f32::NEG_INFINITY {
            f32::MIN
        } else {
            value
        }
    };
    let c = nan_to_num(one_minus / tau);
    nan_to_num(c * inv_r2).min(max_weight)
}

/// One guide per sample row: `guides` itself when it has one per row, no guidance on every row
/// when it is empty (plain sampling), else an error naming both counts. Every model's
/// `sample_guided` takes its guides through this.
pub fn guides_per_row(
    guides: &[Option<RowGuide>],
    rows: usize,
) -> Result<std::borrow::Cow<'_, [Option<RowGuide>]>, EngineError> {
    if guides.is_empty() {
        Ok(std::borrow::Cow::Owned(vec![None; rows]))
    } else if guides.len() == rows {
        Ok(std::borrow::Cow::Borrowed(guides))
    } else {
        Err(EngineError::InvalidInput(format!(
            "{} row guides for {rows} sample rows",
            guides.len()
        )))
    }
}

/// What one row of the sampler needs to apply a request's guidance.
#[derive(Clone, Debug, PartialEq)]
pub struct RowGuide {
    /// The mode.
    pub mode: GuidanceMode,
    /// The previous chunk in the model's action space, `[N][full_dim]`, zero past its rows and
    /// in the padded action values (LeRobot pads `prev_chunk_left_over` with zeros).
    pub target: Vec<f32>,
    /// One weight per action (`rtc`, `rtc_vjp`).
    pub weights: Vec<f32>,
    /// Actions of the chunk the robot executes before it arrives (`inpaint` writes these).
    pub delay: usize,
    /// The cap on the guidance weight.
    pub max_guidance_weight: f32,
    /// Values per action in the model (padded).
    pub full_dim: usize,
    /// The row's initial noise, `[N][full_dim]` (`inpaint` only; empty otherwise).
    pub noise: Vec<f32>,
}

impl RowGuide {
    /// The row guide of `guidance` for a chunk of `chunk_len` actions of `full_dim` values (the
    /// robot's `action_dim` first), whose initial noise is `noise`. `to_model` maps one robot
    /// action (`action_dim` values) into the model's action space in place (normalisation; the
    /// identity for models that sample in the robot's units).
    pub fn prepare(
        guidance: &Guidance,
        chunk_len: usize,
        action_dim: usize,
        full_dim: usize,
        noise: &[f32],
        to_model: &dyn Fn(&mut [f32]),
    ) -> Result<RowGuide, EngineError> {
        let rows = guidance.prefix_rows(action_dim);
        if rows == 0 && !guidance.prefix.is_empty() {
            return Err(EngineError::InvalidInput(format!(
                "guidance: {} prefix values are not whole actions of {action_dim}",
                guidance.prefix.len()
            )));
        }
        if rows > chunk_len || guidance.delay > chunk_len || action_dim > full_dim {
            return Err(EngineError::InvalidInput(format!(
                "guidance: a prefix of {rows} actions and a delay of {} do not fit a chunk of \
                 {chunk_len}",
                guidance.delay
            )));
        }
        if !(guidance.max_guidance_weight.is_finite() && guidance.max_guidance_weight > 0.0) {
            return Err(EngineError::InvalidInput(format!(
                "guidance: max_guidance_weight {} is not a positive number",
                guidance.max_guidance_weight
            )));
        }
        let mut target = vec![0.0f32; chunk_len * full_dim];
        for (row, action) in guidance.prefix.chunks_exact(action_dim).enumerate() {
            let dst = &mut target[row * full_dim..row * full_dim + action_dim];
            dst.copy_from_slice(action);
            to_model(dst);
        }
        // LeRobot cuts the execution horizon to the previous chunk's length.
        let end = guidance.execution_horizon.min(rows);
        let weights = prefix_weights(guidance.schedule, guidance.delay, end, chunk_len);
        let noise = if guidance.mode == GuidanceMode::Inpaint {
            if noise.len() != chunk_len * full_dim {
                return Err(EngineError::InvalidInput(
                    "guidance: the row's noise does not match the chunk".into(),
                ));
            }
            noise.to_vec()
        } else {
            Vec::new()
        };
        Ok(RowGuide {
            mode: guidance.mode,
            target,
            weights,
            // The hard prefix writes only actions the previous chunk has.
            delay: guidance.delay.min(rows),
            max_guidance_weight: guidance.max_guidance_weight,
            full_dim,
            noise,
        })
    }

    /// The weighted error `(target - (x - time * v)) * w` of this row (what `rtc` subtracts,
    /// scaled, and what `rtc_vjp` pulls back).
    pub fn error(&self, time: f32, x: &[f32], v: &[f32]) -> Vec<f32> {
        x.iter()
            .zip(v)
            .zip(&self.target)
            .enumerate()
            .map(|(i, ((&xi, &vi), &prev))| {
                let x1 = xi - time * vi;
                (prev - x1) * self.weights[i / self.full_dim]
            })
            .collect()
    }

    /// Replaces this row's velocity `v` (computed at `x`, step time `time` as f64 and `t32` as
    /// the f32 the model saw) by the guided one. `pullback` is `J_v^T (t32 * err)` for
    /// `rtc_vjp` (from the model's backward pass), `None` for the other modes.
    pub fn guide(&self, time: f64, t32: f32, x: &[f32], v: &mut [f32], pullback: Option<&[f32]>) {
        match self.mode {
            GuidanceMode::Inpaint => {}
            GuidanceMode::Rtc | GuidanceMode::RtcVjp => {
                let weight = guidance_weight(time, self.max_guidance_weight);
                let err = self.error(t32, x, v);
                for (i, (vi, e)) in v.iter_mut().zip(&err).enumerate() {
                    let correction = match pullback {
                        Some(p) => e - p[i],
                        None => *e,
                    };
                    *vi -= weight * correction;
                }
            }
        }
    }

    /// After the Euler step into `next_time` (0 after the last): `inpaint` writes the committed
    /// actions into the sample at that noise level, `next_time · ε + (1 − next_time) · a`, and
    /// makes the step's update `u` what moved the sample. Other modes leave the row alone.
    pub fn after_step(&self, next_time: f32, before: &[f32], x: &mut [f32], u: &mut [f32]) {
        if self.mode != GuidanceMode::Inpaint {
            return;
        }
        let len = self.delay * self.full_dim;
        for i in 0..len {
            let committed = next_time * self.noise[i] + (1.0 - next_time) * self.target[i];
            x[i] = committed;
            u[i] = committed - before[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn guides_per_row_fills_plain_rows_and_refuses_a_miscount() {
        let plain = guides_per_row(&[], 3).unwrap();
        assert_eq!(plain.len(), 3);
        assert!(plain.iter().all(Option::is_none));
        let given = [None, None];
        assert!(matches!(
            guides_per_row(&given, 2).unwrap(),
            std::borrow::Cow::Borrowed(_)
        ));
        let err = guides_per_row(&given, 3).unwrap_err().to_string();
        assert!(err.contains("2 row guides for 3 sample rows"), "{err}");
    }

    #[test]
    fn prefix_weights_follow_lerobot() {
        // Values torch gives for get_prefix_weights with these arguments (LeRobot 0.6.1).
        assert_eq!(
            prefix_weights(PrefixSchedule::Zeros, 3, 6, 8),
            [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        );
        assert_eq!(
            prefix_weights(PrefixSchedule::Ones, 3, 6, 8),
            [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
        );
        // linspace(1, 0, 5)[1:-1] = 0.75, 0.5, 0.25.
        assert_eq!(
            prefix_weights(PrefixSchedule::Linear, 2, 5, 8),
            [1.0, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0, 0.0]
        );
        let exp = prefix_weights(PrefixSchedule::Exp, 2, 5, 8);
        let shaped = |w: f64| w * (w.exp_m1() / (std::f64::consts::E - 1.0));
        for (got, want) in exp[2..5].iter().zip([0.75, 0.5, 0.25]) {
            assert!((f64::from(*got) - shaped(want)).abs() < 1e-6, "{exp:?}");
        }
        assert_eq!(&exp[..2], &[1.0, 1.0]);
        assert_eq!(&exp[5..], &[0.0, 0.0, 0.0]);
        // A delay past the execution horizon is cut to it; an end past the chunk to the chunk.
        assert_eq!(
            prefix_weights(PrefixSchedule::Linear, 7, 4, 6),
            [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
        );
        assert_eq!(prefix_weights(PrefixSchedule::Linear, 0, 9, 3).len(), 3);
    }

    #[test]
    fn the_guidance_weight_is_capped_and_vanishes_at_the_end() {
        // time 1 (pure noise): tau = 0, c = inf -> max.
        assert_eq!(guidance_weight(1.0, 10.0), 10.0);
        // time 0.5: tau = 0.5, c = 1, inv_r2 = 2.
        assert_eq!(guidance_weight(0.5, 10.0), 2.0);
        assert_eq!(guidance_weight(0.5, 1.5), 1.5);
        // time 0 (never reached by the sampler): 0 * inf = nan -> 0.
        assert_eq!(guidance_weight(0.0, 10.0), 0.0);
    }

    fn guide(mode: GuidanceMode, delay: usize) -> RowGuide {
        let guidance = Guidance {
            mode,
            prefix: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            delay,
            execution_horizon: 3,
            schedule: PrefixSchedule::Linear,
            max_guidance_weight: 10.0,
        };
        let noise: Vec<f32> = (0..12).map(|i| i as f32 * 0.1).collect();
        RowGuide::prepare(&guidance, 4, 2, 3, &noise, &|a| a[0] *= 2.0).unwrap()
    }

    #[test]
    fn prepare_pads_maps_and_weighs_the_prefix() {
        let g = guide(GuidanceMode::Rtc, 1);
        assert_eq!(
            g.target,
            [2.0, 2.0, 0.0, 6.0, 4.0, 0.0, 10.0, 6.0, 0.0, 0.0, 0.0, 0.0]
        );
        // delay 1, end min(3, 3 rows) = 3: [1, linspace(1, 0, 4)[1:-1]...] = 1, 2/3, 1/3, 0.
        assert_eq!(g.weights[0], 1.0);
        assert!((g.weights[1] - 2.0 / 3.0).abs() < 1e-7 && (g.weights[2] - 1.0 / 3.0).abs() < 1e-7);
        assert_eq!(g.weights[3], 0.0);
        assert!(g.noise.is_empty());
        let bad = Guidance {
            prefix: vec![0.0; 5],
            ..Guidance {
                mode: GuidanceMode::Rtc,
                prefix: Vec::new(),
                delay: 0,
                execution_horizon: 1,
                schedule: PrefixSchedule::Zeros,
                max_guidance_weight: 1.0,
            }
        };
        assert!(RowGuide::prepare(&bad, 4, 2, 3, &[], &|_| {}).is_err());
    }

    #[test]
    fn rtc_subtracts_the_weighted_error_and_the_vjp_adds_its_pullback() {
        let g = guide(GuidanceMode::Rtc, 1);
        let x = vec![0.5f32; 12];
        let mut v = vec![0.25f32; 12];
        let time = 0.5f64;
        g.guide(time, 0.5, &x, &mut v, None);
        // weight 2 at time 0.5; x1 = 0.5 - 0.5 * 0.25 = 0.375.
        let want0 = 0.25 - 2.0 * ((2.0 - 0.375) * 1.0);
        assert_eq!(v[0], want0);
        // Action 3 has weight 0: untouched.
        assert_eq!(&v[9..], &[0.25, 0.25, 0.25]);
        let vjp = RowGuide {
            mode: GuidanceMode::RtcVjp,
            ..g.clone()
        };
        let mut w = vec![0.25f32; 12];
        let pullback = vec![0.5f32; 12];
        vjp.guide(time, 0.5, &x, &mut w, Some(&pullback));
        assert_eq!(w[0], 0.25 - 2.0 * ((2.0 - 0.375) - 0.5));
    }

    #[test]
    fn inpaint_writes_the_committed_actions_at_the_noise_level() {
        let g = guide(GuidanceMode::Inpaint, 2);
        let before = vec![9.0f32; 12];
        let mut x = before.clone();
        let mut u = vec![0.0f32; 12];
        g.after_step(0.25, &before, &mut x, &mut u);
        for i in 0..6 {
            let want = 0.25 * (i as f32 * 0.1) + 0.75 * g.target[i];
            assert_eq!(x[i], want);
            assert_eq!(u[i], want - 9.0);
        }
        assert_eq!(&x[6..], &before[6..]);
        g.after_step(0.0, &before, &mut x, &mut u);
        assert_eq!(&x[..6], &g.target[..6]);
    }
}
