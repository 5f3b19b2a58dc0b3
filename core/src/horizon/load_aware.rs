//! A load-aware horizon: the §3.1 threshold rule, lengthened by the wait the server's load
//! predicts, so a robot keeps executing instead of stalling while its next request queues.
//!
//! Under load a reply comes late and a robot that has executed its `H` actions idles until it
//! arrives. Executing more of the chunk instead hides that wait (the robot stays busy), at the
//! cost of running actions the confidence rule would have cut (open loop, on an older
//! observation). When the server is idle this policy *is* the threshold rule.
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit):
//!
//! 1. `H_thresh` as the threshold policy's steps 1–4 (`threshold::threshold_prefix`) with `t`.
//! 2. `extra = 0` when the input carries no load. Otherwise, in `f64`:
//!    `x = (gain · (backlog_ns / 1e9)) · control_hz` (`backlog_ns` the load's `backlog` in whole
//!    nanoseconds converted to `f64`, `control_hz` widened from `f32`; no fused multiply-add).
//!    `extra = 0` if `!(x > 0)` (also for NaN), `u32::MAX` if `x >= 4294967295`, else `ceil(x)`.
//! 3. `H = min(max(H_thresh + extra, h_min), h_max)` (saturating add), with `h_min` and `h_max` as
//!    the threshold policy's step 5.
//!
//! Parameters: `t` (default 0.4), `h_min` (optional), `gain` (real ≥ 0, default 1: lengthen by
//! exactly the actions the backlog lasts; 0 turns the policy into the threshold rule).

use super::params::{real, reject_unknown};
use super::threshold::{Threshold, clamp_to_input, threshold_prefix};
use super::{HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use crate::scheduler::ServerLoad;

/// Default `gain`.
pub const DEFAULT_GAIN: f64 = 1.0;

/// The load-aware policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadAware {
    /// The threshold rule it lengthens (`t`, `h_min`).
    pub base: Threshold,
    /// Actions added per action the backlog lasts.
    pub gain: f64,
}

impl Default for LoadAware {
    fn default() -> Self {
        LoadAware {
            base: Threshold::default(),
            gain: DEFAULT_GAIN,
        }
    }
}

impl LoadAware {
    /// Reads `t`, `h_min` and `gain`; any other name is an error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(params, &["t", "h_min", "gain"])?;
        let mut base_params = params.clone();
        base_params.remove("gain");
        Ok(LoadAware {
            base: Threshold::from_params(&base_params)?,
            gain: real(params, "gain", 0.0, Some(DEFAULT_GAIN))?.unwrap_or(DEFAULT_GAIN),
        })
    }
}

/// Step 2: the actions added for `load` at `control_hz`.
pub fn extra_actions(load: Option<ServerLoad>, gain: f64, control_hz: f32) -> usize {
    let Some(load) = load else {
        return 0;
    };
    let backlog_ns = crate::time::duration_nanos(load.backlog) as f64;
    let x = (gain * (backlog_ns / 1e9)) * f64::from(control_hz);
    let extra = if x.is_nan() || x <= 0.0 {
        0
    } else if x >= 4_294_967_295.0 {
        u32::MAX
    } else {
        x.ceil() as u32
    };
    extra as usize
}

impl HorizonPolicy for LoadAware {
    fn name(&self) -> &str {
        "load-aware"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let config = if input.params.is_empty() {
            *self
        } else {
            LoadAware::from_params(input.params)?
        };
        let prefix = if input.chunk.is_consistent() {
            threshold_prefix(&input.chunk, config.base.t).saturating_add(extra_actions(
                input.load,
                config.gain,
                input.control_hz,
            ))
        } else {
            0
        };
        clamp_to_input(prefix, config.base.h_min, input)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::horizon::threshold::DEFAULT_T;
    use std::time::Duration;

    fn load(backlog_ms: u64) -> Option<ServerLoad> {
        Some(ServerLoad {
            queued: 3,
            running: 0,
            open_tasks: 10,
            backlog: Duration::from_millis(backlog_ms),
        })
    }

    #[test]
    fn extra_actions_cover_the_backlog_at_the_control_rate() {
        assert_eq!(extra_actions(None, 1.0, 30.0), 0, "no server: no change");
        assert_eq!(extra_actions(load(0), 1.0, 30.0), 0, "idle: no change");
        // 100 ms at 30 Hz is 3 actions; 110 ms is 3.3, rounded up.
        assert_eq!(extra_actions(load(100), 1.0, 30.0), 3);
        assert_eq!(extra_actions(load(110), 1.0, 30.0), 4);
        assert_eq!(extra_actions(load(100), 2.0, 30.0), 6, "gain scales it");
        assert_eq!(extra_actions(load(100), 0.0, 30.0), 0, "gain 0: threshold");
        assert_eq!(extra_actions(load(100), 1.0, f32::NAN), 0);
        assert_eq!(
            extra_actions(load(u64::MAX / 2_000_000), 1.0, 1e9),
            u32::MAX as usize
        );
    }

    #[test]
    fn unknown_parameters_and_negative_gain_are_refused() {
        let p = |k: &str, v: f64| PolicyParams::from([(k.to_string(), v)]);
        assert!(LoadAware::from_params(&p("gain", -1.0)).is_err());
        assert!(LoadAware::from_params(&p("g", 1.0)).is_err());
        let ok = LoadAware::from_params(&p("t", 0.2)).unwrap();
        assert_eq!((ok.base.t, ok.gain), (0.2, DEFAULT_GAIN));
        assert_eq!(DEFAULT_T, Threshold::default().t);
    }
}
