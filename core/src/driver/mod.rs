//! The driver's state machine: the [`Scheduler`](crate::scheduler::Scheduler) and what the
//! server remembers around it ([`core::DriverCore`]), with its statistics ([`stats`]).
//!
//! The core takes events with `now` as an argument and returns [`core::Effect`]s: answers for
//! the streams waiting for a round, re-fetch asks, batches to run, the next timer. It keeps
//! what the scheduler does not: observations and horizon policies of pending rounds, the streams
//! waiting for each round, each open task's last reply (so a round re-sent after a reconnect gets
//! the same answer instead of a second generation) and clock mapping (to show G/E records on the
//! robot's clock), snapshots of ended tasks, and statistics. It reports what happened as data
//! ([`core::DriverCore::report`]); the server's shell runs it on a thread and exports the report.

pub mod core;
#[cfg(test)]
mod core_tests;
pub mod stats;

use std::collections::BTreeMap;

use kairos_protocol::{ErrorReply, IntervalUs, Reply, RoundRecordWire};

pub use self::core::{BatchJob, ChunkingModel, DriverCore, Effect, Redispatch, RedispatchRule};
pub use self::stats::{
    DriverReport, DriverStats, EngineReport, EngineState, Histogram, LatencySummary,
    RECENT_LATENCIES, RedispatchCounts,
};
use crate::clock_map::ClockMap;
use crate::lifecycle::RoundRecord;
use crate::scheduler::{RobotId, TaskId};
use crate::time::Timestamp;

/// Identifies one stream waiting for a round (a round may have several after reconnects).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct WaiterId(pub u64);

/// The answer to a round: the reply, or the error to send.
pub type RoundAnswer = Result<Reply, ErrorReply>;

/// A snapshot of one task for tests and metrics.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskSnapshot {
    /// The task.
    pub task: TaskId,
    /// Its owner.
    pub owner: RobotId,
    /// Rounds answered.
    pub rounds_completed: u32,
    /// The bounded G/E history on the server clock, oldest first.
    pub history: Vec<RoundRecord>,
    /// The clock mapping of the task's latest request.
    pub clock: ClockMap,
    /// Chunks generated and sent per round id (cached re-sends not counted), for the most recent
    /// rounds (as many as the scheduler's history keeps).
    pub generated: BTreeMap<u64, u32>,
    /// How well the task's `d` was predicted (rounds whose next Last Exec Info came).
    pub delay_errors: crate::chunking::DelayErrorStats,
    /// Whether the task has ended.
    pub ended: bool,
}

impl TaskSnapshot {
    /// The history on the robot's clock, as `TaskEnded` carries it.
    pub fn wire_history(&self) -> Vec<RoundRecordWire> {
        let to_client = |start: Timestamp, end: Timestamp| IntervalUs {
            start_us: self.clock.to_client(start),
            end_us: self.clock.to_client(end),
        };
        self.history
            .iter()
            .map(|r| RoundRecordWire {
                round: r.round,
                generation: Some(to_client(r.generation.start, r.generation.end)),
                execution: r.execution.map(|e| to_client(e.start, e.end)),
                horizon: Some(r.horizon),
            })
            .collect()
    }
}
