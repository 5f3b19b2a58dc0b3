//! The robot side of a task: the paper's client shim (`get_obs` / `send_act`) and a runner that
//! executes chunks in real time while the next one is generated (asynchronous inference).
//!
//! # The execution rules
//!
//! - **Control loop.** Actions execute one per control period (`1 / control_hz`). When a chunk
//!   arrives while the robot is idle, its first action executes at once.
//! - **Trigger.** The next request is sent when the executed fraction of the current chunk's
//!   executable actions reaches `trigger` (LeRobot's `chunk_size_threshold`, default 0.5), or at
//!   once if the robot has no actions. With `trigger = 1.0` inference is synchronous; with `0.0` a
//!   request goes out as soon as a chunk arrives. At most one request per task is in flight.
//! - **Alignment.** A chunk's action 0 is the action for the instant its observation was captured
//!   (the latest observation sent, re-fetches included), whatever the round's chunking strategy
//!   (docs/PROTOCOL.md §12). Every action the robot executed since that capture has used up one
//!   of the chunk's time slots, so when the chunk arrives its first `executed since capture`
//!   actions are discarded and execution continues at the next one ([`Alignment::Executed`]).
//!   The reply's `start` is the server's prediction of that count; [`Alignment::ServerStart`]
//!   follows it instead of the robot's own count.
//!   Actions of the previous chunk still queued are dropped: the new chunk, planned from a newer
//!   observation, replaces them (LeRobot instead blends the overlap, 0.3 old + 0.7 new; Kairos
//!   replaces so that `H` means what the horizon policy chose). A robot that sat idle executed
//!   nothing, so nothing is discarded. If every action of the new chunk is already in the past,
//!   the old chunk keeps running and the next request goes out at once.
//! - **Last Exec Info.** Each request reports the chunk being executed: its round, when its
//!   first action executed, how many of its actions are still to execute, the control frequency,
//!   and its actual `d` (actions executed between its observation's capture and its arrival), which
//!   the server compares with the `d` it predicted. The first request of a task has none.
//!
//! [`ChunkExecutor`] holds these rules with time as an argument ([`executor`], pure);
//! [`RobotRunner`] drives it with the tokio clock, a [`Robot`], and a [`RoundTransport`]
//! (normally a [`Task`]) ([`runner`]); [`SimulatedRobot`] is a [`Robot`] for tests, benchmarks
//! and `kairos robot` ([`simulated`]).

pub mod executor;
pub mod runner;
pub mod simulated;

use std::future::Future;

use crate::client::{ClientError, Clock, ObservationSource, RoundReply, RoundRequest, Task};
use crate::protocol::{LastExecInfo, Observation, TaskEnded, TaskOutcome};

pub use executor::{ActionStep, Alignment, ChunkApplied, ChunkExecutor};
pub use runner::{RobotRunner, RoundRecord, RunnerConfig, RunnerError, RunnerEvent, TaskSummary};
pub use simulated::SimulatedRobot;

/// A failure reported by a robot's shim.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("robot: {0}")]
pub struct RobotError(pub String);

/// The robot runtime, in the paper's shim shape.
pub trait Robot: Send {
    /// Captures the current observation. `now_us` is the current time on the client clock;
    /// `captured_at_us` must be on that clock.
    fn get_obs(
        &mut self,
        now_us: u64,
    ) -> impl Future<Output = Result<Observation, RobotError>> + Send;

    /// Sends one action to the controller.
    fn send_act(&mut self, action: &[f32]) -> impl Future<Output = Result<(), RobotError>> + Send;

    /// Whether the robot considers its task finished (checked before each request).
    fn task_done(&self) -> bool {
        false
    }
}

/// What the runner sends rounds through: a [`Task`] in production, a test double in tests.
pub trait RoundTransport: Send + 'static {
    /// The task id.
    fn task_id(&self) -> u64;
    /// The id the next round will get.
    fn next_round(&self) -> u64;
    /// The clock that timestamps requests.
    fn clock(&self) -> Clock;
    /// Runs one round (see [`Task::submit`]).
    fn submit<S: ObservationSource>(
        &mut self,
        request: RoundRequest,
        source: &mut S,
    ) -> impl Future<Output = Result<RoundReply, ClientError>> + Send;
    /// Ends the task (see [`Task::end`]).
    fn end(
        self,
        outcome: TaskOutcome,
        last_exec: Option<LastExecInfo>,
    ) -> impl Future<Output = Result<TaskEnded, ClientError>> + Send;
}

impl RoundTransport for Task {
    fn task_id(&self) -> u64 {
        self.id()
    }

    fn next_round(&self) -> u64 {
        Task::next_round(self)
    }

    fn clock(&self) -> Clock {
        self.client().clock()
    }

    fn submit<S: ObservationSource>(
        &mut self,
        request: RoundRequest,
        source: &mut S,
    ) -> impl Future<Output = Result<RoundReply, ClientError>> + Send {
        Task::submit(self, request, source)
    }

    fn end(
        self,
        outcome: TaskOutcome,
        last_exec: Option<LastExecInfo>,
    ) -> impl Future<Output = Result<TaskEnded, ClientError>> + Send {
        Task::end(self, outcome, last_exec)
    }
}
