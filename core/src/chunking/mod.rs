//! Delay-aware chunk switching: what the server does about the actions a robot executes while
//! its round is in flight (docs/PROTOCOL.md §12, "Chunking strategies").
//!
//! For every round the driver predicts `d` ([`delay`]) when its batch starts, and plans the
//! round with its strategy ([`plan`]): the model input (the observation as is, the state the
//! robot will have on arrival, or guidance toward the actions it committed to) and how the
//! chunk is put in the reply. Every strategy answers a chunk whose action `i` belongs to `i`
//! control steps after the observation's capture, so a robot that discards the actions whose
//! time has passed (§12) executes the right ones whatever the strategy; the reply's `start` is
//! the server's prediction of how many that is.

pub mod delay;
pub mod plan;

use kairos_engine_types::PrefixSchedule;
use kairos_protocol::ChunkingStrategy;

pub use delay::{
    DelayErrorStats, DelayInputs, DelayPrediction, DurationAverage, NetworkEstimate,
    actual_delay_from_times, predict_delay,
};
pub use plan::{PreviousChunk, RoundPlan, plan_round};

/// LeRobot's weight of the previous chunk where two chunks overlap (`weighted_average`,
/// 0.3 × old + 0.7 × new).
pub const ENSEMBLE_OLD_WEIGHT: f32 = 0.3;

/// The server's chunking settings (`[chunking]` in `kairos.toml`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChunkingDefaults {
    /// The strategy of rounds that name none.
    pub strategy: ChunkingStrategy,
    /// `rtc`: the prefix schedule (LeRobot's default is `linear`).
    pub schedule: PrefixSchedule,
    /// `rtc`: the cap on the guidance weight (LeRobot's default is 10).
    pub max_guidance_weight: f32,
    /// `rtc`: how many of the previous chunk's actions guide the new one (LeRobot's default is
    /// 10).
    pub execution_horizon: u32,
}

impl Default for ChunkingDefaults {
    /// `arrival_state`: in closed loop it kept task success under delay where every other
    /// strategy lost it (docs/EVALUATION.md, "Chunk switching under delay"); where it cannot
    /// apply (no forecast, actions that are not absolute positions) a round falls back to `skip`,
    /// today's rule. The real-time chunking settings are LeRobot 0.6.1's defaults.
    fn default() -> Self {
        ChunkingDefaults {
            strategy: ChunkingStrategy::ArrivalState,
            schedule: PrefixSchedule::Linear,
            max_guidance_weight: 10.0,
            execution_horizon: 10,
        }
    }
}

/// A round's chunking, resolved against the server's defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundChunking {
    /// The strategy.
    pub strategy: ChunkingStrategy,
    /// `rtc`, `rtc_vjp`: the prefix schedule.
    pub schedule: PrefixSchedule,
    /// `rtc`, `rtc_vjp`: the cap on the guidance weight.
    pub max_guidance_weight: f32,
    /// `rtc`, `rtc_vjp`: how many previous actions guide the chunk.
    pub execution_horizon: u32,
    /// `arrival_state`: the robot's forecast of its state after each of its next actions
    /// (`[M][state_dim]`, row `j` after `j + 1` actions); `None`: roll the state forward on the
    /// server.
    pub forecast: Option<Vec<Vec<f32>>>,
}

impl RoundChunking {
    /// `strategy` with the server's settings.
    pub fn with_defaults(strategy: ChunkingStrategy, defaults: &ChunkingDefaults) -> RoundChunking {
        RoundChunking {
            strategy,
            schedule: defaults.schedule,
            max_guidance_weight: defaults.max_guidance_weight,
            execution_horizon: defaults.execution_horizon,
            forecast: None,
        }
    }
}

impl Default for RoundChunking {
    fn default() -> Self {
        RoundChunking::with_defaults(ChunkingStrategy::Skip, &ChunkingDefaults::default())
    }
}

/// The protocol's prefix schedule as the engine names it.
pub fn engine_schedule(schedule: kairos_protocol::PrefixSchedule) -> PrefixSchedule {
    match schedule {
        kairos_protocol::PrefixSchedule::Zeros => PrefixSchedule::Zeros,
        kairos_protocol::PrefixSchedule::Ones => PrefixSchedule::Ones,
        kairos_protocol::PrefixSchedule::Linear => PrefixSchedule::Linear,
        kairos_protocol::PrefixSchedule::Exp => PrefixSchedule::Exp,
    }
}

/// Rounds planned per strategy, and those whose strategy could not apply.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct StrategyCounts {
    /// Rounds per strategy, in [`ChunkingStrategy::ALL`]'s order.
    pub rounds: [u64; ChunkingStrategy::ALL.len()],
    /// Rounds that fell back to `skip` because what their strategy needs was missing (the
    /// previous chunk the robot executes was not the server's last reply).
    pub fallbacks: u64,
}

impl StrategyCounts {
    /// Counts one round of `strategy`.
    pub fn count(&mut self, strategy: ChunkingStrategy) {
        if let Some(i) = ChunkingStrategy::ALL.iter().position(|s| *s == strategy) {
            self.rounds[i] += 1;
        }
    }

    /// `(strategy, rounds)` pairs.
    pub fn iter(&self) -> impl Iterator<Item = (ChunkingStrategy, u64)> + '_ {
        ChunkingStrategy::ALL
            .into_iter()
            .zip(self.rounds.iter().copied())
    }
}
