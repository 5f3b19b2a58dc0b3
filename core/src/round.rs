//! A round after validation: what the driver core queues, batches and answers.
//!
//! The server's validator (`kairos_server::validation`) builds these from wire messages; the
//! simulator and the core's tests build them directly. They hold plain data and the built
//! horizon policy, nothing of the transport.

use kairos_engine_types::ActionRequest;

use crate::action::RoundPolicy;
use crate::chunking::RoundChunking;
use crate::clock_map::ClockMap;
use crate::scheduler::{ExecReport, RoundSubmit, TaskEnd, TaskId};
use crate::time::Timestamp;

/// An observation that fits the served model, on the server clock.
#[derive(Clone, Debug, PartialEq)]
pub struct ValidObservation {
    /// When it was captured.
    pub captured_at: Timestamp,
    /// The model input (`samples` and `seed` are set per round).
    pub request: ActionRequest,
}

/// A round request that passed every check.
#[derive(Debug)]
pub struct ValidSubmit {
    /// What the scheduler sees.
    pub round: RoundSubmit,
    /// The observation.
    pub observation: ValidObservation,
    /// The horizon policy, built.
    pub policy: RoundPolicy,
    /// Samples to draw.
    pub samples: usize,
    /// The robot's control frequency, if this request reported it.
    pub control_hz: Option<f32>,
    /// This request's clock mapping.
    pub clock: ClockMap,
    /// The round's chunking strategy, resolved against the server's defaults.
    pub chunking: RoundChunking,
    /// The round whose chunk the robot executes, as its Last Exec Info names it (`None`: not
    /// said, the task's last reply is assumed).
    pub exec_round: Option<u64>,
    /// The actual `d` of that round, as the robot reported it.
    pub exec_delay: Option<u32>,
}

/// An `EndTask` that passed every check.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValidEndTask {
    /// The task.
    pub task: TaskId,
    /// How it ended.
    pub end: TaskEnd,
    /// The final execution phase.
    pub exec: Option<ExecReport>,
    /// When the message was sent, on the server clock.
    pub sent_at: Timestamp,
    /// Its clock mapping.
    pub clock: ClockMap,
}

/// The seed of a round's initial noise: a fixed mix of task and round, so a retried round
/// reproduces its chunk.
pub fn round_seed(task: u64, round: u64) -> u64 {
    fn splitmix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    splitmix(task ^ splitmix(round))
}
