//! Sample spread: cut the chunk where independently drawn samples for the same observation stop
//! agreeing (FIELD-NOTES, "Signals that did work": 4 samples, threshold 0.1).
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit), over the final actions
//! `A[s][n][d]` of the `S ≥ 2` samples, all in `f64` widened from `f32`, no fused multiply-add:
//!
//! 1. For action `n` and dimension `d`: `mean = (Σ_s A[s][n][d]) / S` (sample order), then
//!    `var_d = (Σ_s (A[s][n][d] − mean)²) / S` (population variance, sample order).
//! 2. `spread_n = sqrt((Σ_d var_d) / D)` (dimension order): the RMS over dimensions of the
//!    per-dimension standard deviation across samples.
//! 3. The prefix is the number of leading actions with `spread_n <= threshold` (a NaN stops it).
//! 4. `H = min(max(prefix, h_min), h_max)` with `h_min = max(input.h_min, param h_min)` and
//!    `h_max = min(input.h_max, N)`.
//!
//! Parameters: `threshold` (default 0.1, in action units, the value that worked in the field
//! notes' toy task), `h_min` (optional). A chunk with one sample is `Unsupported`: the request
//! must ask the engine for at least two.

use super::params::{count, real, reject_unknown};
use super::threshold::clamp_to_input;
use super::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};

/// Default spread threshold.
pub const DEFAULT_THRESHOLD: f64 = 0.1;

/// The sample-spread policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    /// Largest spread of an action still executed.
    pub threshold: f64,
    /// Lower bound on top of the robot's `h_min`.
    pub h_min: Option<usize>,
}

impl Default for Spread {
    fn default() -> Self {
        Spread {
            threshold: DEFAULT_THRESHOLD,
            h_min: None,
        }
    }
}

impl Spread {
    /// Reads `threshold` and `h_min`; any other name is an error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(params, &["threshold", "h_min"])?;
        Ok(Spread {
            threshold: real(params, "threshold", 0.0, Some(DEFAULT_THRESHOLD))?
                .unwrap_or(DEFAULT_THRESHOLD),
            h_min: count(params, "h_min")?,
        })
    }
}

/// `spread_n` of steps 1–2 of the module doc.
pub fn action_spread(chunk: &ChunkView<'_>, n: usize) -> f64 {
    let samples = chunk.samples as f64;
    let mut total = 0.0f64;
    for d in 0..chunk.action_dim {
        let mut sum = 0.0f64;
        for s in 0..chunk.samples {
            sum += f64::from(chunk.action(s, n)[d]);
        }
        let mean = sum / samples;
        let mut sq = 0.0f64;
        for s in 0..chunk.samples {
            let dev = f64::from(chunk.action(s, n)[d]) - mean;
            sq += dev * dev;
        }
        total += sq / samples;
    }
    (total / chunk.action_dim as f64).sqrt()
}

/// The number of leading actions whose spread is at most `threshold`.
pub fn spread_prefix(chunk: &ChunkView<'_>, threshold: f64) -> usize {
    (0..chunk.chunk_len)
        .find(|&n| {
            // Written so that a NaN spread also ends the prefix.
            let agrees = action_spread(chunk, n) <= threshold;
            !agrees
        })
        .unwrap_or(chunk.chunk_len)
}

impl HorizonPolicy for Spread {
    fn name(&self) -> &str {
        "spread"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let config = if input.params.is_empty() {
            *self
        } else {
            Spread::from_params(input.params)?
        };
        if !input.chunk.is_consistent() {
            return Err(HorizonError::Unsupported(
                "chunk buffers do not match their dimensions".into(),
            ));
        }
        if input.chunk.samples < 2 {
            return Err(HorizonError::Unsupported(format!(
                "spread needs at least 2 samples of the chunk, got {}",
                input.chunk.samples
            )));
        }
        clamp_to_input(
            spread_prefix(&input.chunk, config.threshold),
            config.h_min,
            input,
        )
    }
}
