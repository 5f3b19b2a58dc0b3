//! `[chunking]`: the server's chunking strategy for rounds that name none, and the settings of
//! real-time chunking (docs/SERVER.md, "Chunking").

use kairos_core::chunking::{ChunkingDefaults, engine_schedule};
use kairos_sdk::protocol::{ChunkingStrategy, PrefixSchedule};
use serde::{Deserialize, Serialize};

/// `[chunking]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChunkingSection {
    /// Strategy of rounds whose `Submit` names none: `skip`, `from_start`, `arrival_state`,
    /// `rtc`, `rtc_vjp`, `inpaint` or `ensemble` (docs/PROTOCOL.md §12).
    pub strategy: String,
    /// `rtc`: LeRobot's prefix schedule, `zeros`, `ones`, `linear` or `exp`.
    pub schedule: String,
    /// `rtc`: the cap on the guidance weight (LeRobot's `max_guidance_weight`).
    pub max_guidance_weight: f32,
    /// `rtc`: previous actions that guide the new chunk (LeRobot's `execution_horizon`).
    pub execution_horizon: u32,
}

impl Default for ChunkingSection {
    fn default() -> Self {
        let defaults = ChunkingDefaults::default();
        ChunkingSection {
            strategy: defaults.strategy.as_str().into(),
            schedule: "linear".into(),
            max_guidance_weight: defaults.max_guidance_weight,
            execution_horizon: defaults.execution_horizon,
        }
    }
}

impl ChunkingSection {
    /// The settings, or the key (under `chunking.`) that is wrong and why.
    pub fn defaults(&self) -> Result<ChunkingDefaults, (&'static str, String)> {
        let strategy = ChunkingStrategy::from_name(&self.strategy).ok_or_else(|| {
            let known: Vec<&str> = ChunkingStrategy::ALL.iter().map(|s| s.as_str()).collect();
            (
                "strategy",
                format!("`{}` is not one of {}", self.strategy, known.join(", ")),
            )
        })?;
        let schedule = PrefixSchedule::from_name(&self.schedule).ok_or_else(|| {
            (
                "schedule",
                format!("`{}` is not one of zeros, ones, linear, exp", self.schedule),
            )
        })?;
        if !(self.max_guidance_weight.is_finite() && self.max_guidance_weight > 0.0) {
            return Err(("max_guidance_weight", "must be a finite number > 0".into()));
        }
        if self.execution_horizon == 0 {
            return Err(("execution_horizon", "must be at least 1".into()));
        }
        Ok(ChunkingDefaults {
            strategy,
            schedule: engine_schedule(schedule),
            max_guidance_weight: self.max_guidance_weight,
            execution_horizon: self.execution_horizon,
        })
    }
}
