//! The static horizon: execute `h` actions every round, whatever the chunk says (the baselines'
//! "largest fixed H that keeps the highest accuracy", paper §5.1).
//!
//! Exact semantics: `H = min(max(h, h_min), h_max)` with `h_min = input.h_min` and
//! `h_max = min(input.h_max, N)`. Parameter: `h` (required, whole number ≥ 1).

use super::params::{count, reject_unknown};
use super::threshold::clamp_to_input;
use super::{HorizonError, HorizonInput, HorizonPolicy, PolicyParams};

/// Always the same horizon.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StaticHorizon {
    /// Actions to execute per round.
    pub h: usize,
}

impl StaticHorizon {
    /// Reads the required `h`; any other name is an error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(params, &["h"])?;
        let h = count(params, "h")?.ok_or_else(|| HorizonError::InvalidParam {
            name: "h".into(),
            reason: "required: the number of actions to execute per round".into(),
        })?;
        Ok(StaticHorizon { h })
    }
}

impl HorizonPolicy for StaticHorizon {
    fn name(&self) -> &str {
        "static"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let h = if input.params.is_empty() {
            self.h
        } else {
            StaticHorizon::from_params(input.params)?.h
        };
        clamp_to_input(h, None, input)
    }
}
