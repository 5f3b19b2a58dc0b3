//! Steady motion: execute the chunk for as long as its actions keep doing the same thing, and
//! hand control back a little before the chunk itself changes course.
//!
//! A chunk that moves through free space repeats nearly the same action (a steady velocity
//! command, the gripper unchanged); the chunk's own plan of a contact phase shows up as a change
//! between consecutive actions — it slows down on arrival, turns towards a new target, or
//! switches the gripper. Executing past such a change runs the most precise part of the task
//! open loop, so the policy cuts `margin` actions before the first one.
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit), over the final actions
//! `A[0][n][d]` of sample 0, in `f64` widened from `f32`, no fused multiply-add:
//!
//! 1. For `n ≥ 1`, `jump_n = sqrt(Σ_d (A[0][n][d] − A[0][n−1][d])²)` (dimension order).
//! 2. `change` = the first `n ≥ 1` with `!(jump_n <= delta)` (so a NaN counts as a change), or
//!    `N` if there is none.
//! 3. `prefix = change − margin` if `change > margin`, else 0.
//! 4. `H = min(max(prefix, h_min), h_max)` with `h_min = max(input.h_min, param h_min)` and
//!    `h_max = min(input.h_max, N, param h_max)` (an `h_max` below `h_min` is raised to it).
//!
//! Parameters: `delta` (default 0.25, in action units), `margin` (whole number ≥ 0, default 1),
//! `h_min` (optional), `h_max` (optional cap, whole number ≥ 1).

use super::params::{count, real, reject_unknown, whole};
use super::threshold::clamp_to_input;
use super::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};

/// Default largest change between consecutive actions still counted as steady motion.
pub const DEFAULT_DELTA: f64 = 0.25;
/// Default number of actions cut before the first change.
pub const DEFAULT_MARGIN: usize = 1;

/// The steady-motion policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Steady {
    /// Largest `jump_n` still counted as steady.
    pub delta: f64,
    /// Actions cut before the first change.
    pub margin: usize,
    /// Lower bound on top of the robot's `h_min`.
    pub h_min: Option<usize>,
    /// Upper bound on top of the robot's `h_max`.
    pub h_max: Option<usize>,
}

impl Default for Steady {
    fn default() -> Self {
        Steady {
            delta: DEFAULT_DELTA,
            margin: DEFAULT_MARGIN,
            h_min: None,
            h_max: None,
        }
    }
}

impl Steady {
    /// Reads `delta`, `margin`, `h_min` and `h_max`; any other name is an error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(params, &["delta", "margin", "h_min", "h_max"])?;
        let margin = whole(params, "margin", DEFAULT_MARGIN)?;
        Ok(Steady {
            delta: real(params, "delta", 0.0, Some(DEFAULT_DELTA))?.unwrap_or(DEFAULT_DELTA),
            margin,
            h_min: count(params, "h_min")?,
            h_max: count(params, "h_max")?,
        })
    }
}

/// `jump_n` of step 1 of the module doc: the L2 distance between actions `n − 1` and `n` of
/// sample 0 (`n ≥ 1`).
pub fn action_jump(chunk: &ChunkView<'_>, n: usize) -> f64 {
    let (prev, cur) = (chunk.action(0, n - 1), chunk.action(0, n));
    let mut acc = 0.0f64;
    for (&a, &b) in prev.iter().zip(cur) {
        let x = f64::from(b) - f64::from(a);
        acc += x * x;
    }
    acc.sqrt()
}

/// `change` of step 2 of the module doc: the first action that differs from its predecessor by
/// more than `delta`, or `N`.
pub fn first_change(chunk: &ChunkView<'_>, delta: f64) -> usize {
    (1..chunk.chunk_len)
        .find(|&n| {
            // Written so that a NaN jump also counts as a change.
            let steady = action_jump(chunk, n) <= delta;
            !steady
        })
        .unwrap_or(chunk.chunk_len)
}

impl HorizonPolicy for Steady {
    fn name(&self) -> &str {
        "steady"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let config = if input.params.is_empty() {
            *self
        } else {
            Steady::from_params(input.params)?
        };
        if !input.chunk.is_consistent() {
            return Err(HorizonError::Unsupported(
                "chunk buffers do not match their dimensions".into(),
            ));
        }
        let prefix = first_change(&input.chunk, config.delta).saturating_sub(config.margin);
        clamp_with_cap(prefix, config.h_min, config.h_max, input)
    }
}

/// Step 4 of the module doc: `prefix` clamped to `[h_min, h_max]`, where `extra_min` raises the
/// robot's `h_min` and `cap` lowers its `h_max` (a cap below the lower bound is raised to it).
pub(crate) fn clamp_with_cap(
    prefix: usize,
    extra_min: Option<usize>,
    cap: Option<usize>,
    input: &HorizonInput<'_>,
) -> Result<usize, HorizonError> {
    let capped = HorizonInput {
        h_max: cap.map_or(input.h_max, |cap| {
            input
                .h_max
                .min(cap.max(input.h_min.max(extra_min.unwrap_or(0))))
        }),
        ..*input
    };
    clamp_to_input(prefix, extra_min, &capped)
}
