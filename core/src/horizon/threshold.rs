//! The paper's confidence-threshold policy (§3.1, Fig. "confidence").
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit):
//!
//! 1. Only sample 0 is used. For action `n` in `0..N` and step `k` in `0..K`, `‖U[0][k][n]‖` is the
//!    L2 norm over the `D` dimensions, accumulated in `f64` in dimension order
//!    (`acc += x·x` with `x` widened from `f32`, no fused multiply-add), then `sqrt`.
//! 2. The step read is `r = min(step, K−1)` (`step` defaults to `K−1`: the final step, as in
//!    the paper). `mean_n = (Σ_{k=0}^{r-1} ‖U[0][k][n]‖) / r`, summed in step order in `f64`.
//! 3. Action `n` *exceeds* iff `!(‖U[0][r][n]‖ <= (1 + t) · mean_n)` — so a NaN anywhere counts
//!    as unconverged. With `K = 1` there are no earlier steps and no action exceeds.
//! 4. `H_thresh` = the index of the first exceeding action (the number of actions before it), or
//!    `N` if none exceeds.
//! 5. `H = min(max(H_thresh, h_min), h_max)` where `h_min = max(input.h_min, param h_min)` and
//!    `h_max = min(input.h_max, N)`.
//!
//! Parameters: `t` (default 0.4: the threshold of the paper's worked example, where an action
//! whose final update is 50% above its earlier mean is cut), `h_min` (optional, whole number ≥ 1,
//! the paper's `H_min`; the robot's own `h_min` always applies too), `step` (optional, whole
//! number ≥ 1: which denoising step's update is read, 0-based, so `step = 1` compares the
//! second update with the first; the paper reads the last).

use super::params::{count, real, reject_unknown};
use super::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};

/// Default threshold `t`.
pub const DEFAULT_T: f64 = 0.4;

/// The §3.1 threshold policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Threshold {
    /// Relative margin: an action's final update may be at most `(1+t)×` its earlier mean.
    pub t: f64,
    /// The paper's `H_min`, on top of the robot's.
    pub h_min: Option<usize>,
    /// The denoising step whose update is read (`None`: the last).
    pub step: Option<usize>,
}

impl Default for Threshold {
    fn default() -> Self {
        Threshold {
            t: DEFAULT_T,
            h_min: None,
            step: None,
        }
    }
}

impl Threshold {
    /// Reads `t`, `h_min` and `step`; any other name is an error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(params, &["t", "h_min", "step"])?;
        Ok(Threshold {
            t: real(params, "t", 0.0, Some(DEFAULT_T))?.unwrap_or(DEFAULT_T),
            h_min: count(params, "h_min")?,
            step: count(params, "step")?,
        })
    }
}

/// L2 norm over one update vector, in `f64`, dimension order.
pub fn l2(v: &[f32]) -> f64 {
    let mut acc = 0.0f64;
    for &x in v {
        let x = f64::from(x);
        acc += x * x;
    }
    acc.sqrt()
}

/// `H_thresh` of sample 0 reading the final step (steps 1–4 of the module doc).
pub fn threshold_prefix(chunk: &ChunkView<'_>, t: f64) -> usize {
    threshold_prefix_at(chunk, t, None)
}

/// `H_thresh` of sample 0 reading step `min(step, K−1)` (`None`: the last; steps 1–4 of the
/// module doc).
pub fn threshold_prefix_at(chunk: &ChunkView<'_>, t: f64, step: Option<usize>) -> usize {
    let k = chunk.steps;
    if k < 2 {
        return chunk.chunk_len;
    }
    let read = step.map_or(k - 1, |s| s.min(k - 1));
    let bound = 1.0 + t;
    for n in 0..chunk.chunk_len {
        let mut sum = 0.0f64;
        for earlier in 0..read {
            sum += l2(chunk.update(0, earlier, n));
        }
        let mean = sum / read as f64;
        let last = l2(chunk.update(0, read, n));
        // Written so that a NaN norm also counts as exceeding.
        let converged = last <= bound * mean;
        if !converged {
            return n;
        }
    }
    chunk.chunk_len
}

/// Clamps a policy's raw prefix to `[max(input.h_min, extra_min), min(input.h_max, N)]`, checking
/// the input bounds first.
pub(crate) fn clamp_to_input(
    prefix: usize,
    extra_min: Option<usize>,
    input: &HorizonInput<'_>,
) -> Result<usize, HorizonError> {
    if !input.chunk.is_consistent() {
        return Err(HorizonError::Unsupported(
            "chunk buffers do not match their dimensions".into(),
        ));
    }
    let h_max = input.h_max.min(input.chunk.chunk_len);
    if input.h_min == 0 || input.h_min > h_max {
        return Err(HorizonError::Unsupported(format!(
            "no horizon satisfies 1 <= h_min ({}) <= h_max ({h_max})",
            input.h_min
        )));
    }
    let h_min = input.h_min.max(extra_min.unwrap_or(0)).min(h_max);
    Ok(prefix.max(h_min).min(h_max))
}

impl HorizonPolicy for Threshold {
    fn name(&self) -> &str {
        "threshold"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let config = if input.params.is_empty() {
            *self
        } else {
            Threshold::from_params(input.params)?
        };
        clamp_to_input(
            if input.chunk.is_consistent() {
                threshold_prefix_at(&input.chunk, config.t, config.step)
            } else {
                0
            },
            config.h_min,
            input,
        )
    }
}
