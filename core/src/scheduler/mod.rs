//! The execution-aware scheduler: a sans-IO state machine.
//!
//! It owns every task's lifecycle record and every pending round request, decides which
//! requests run next, on which engine instance and in what batch (paper §3.2, Algorithm 1), and
//! asks for stale observations to be re-fetched. It never reads a clock or touches a socket:
//! the live driver and the virtual-time simulator feed it events with a `now` and carry out the
//! [`Dispatch`]es it returns.
//!
//! Event API (the live driver and the simulator both use exactly this):
//! - `Scheduler::new(config, engines, policy)`
//! - `handle_submit(now, RoundSubmit) -> Result<RequestId, AdmitError>`
//! - `handle_cancel(now, RequestId) -> CancelOutcome`: removes a pending request
//! - `poll_dispatch(now) -> Vec<Dispatch>`: one policy decision covering every idle engine
//! - `handle_batch_started(now, BatchId)`: re-fetches done, the forward pass begins (G.start)
//! - `handle_batch_finished(now, BatchId, &[(RequestId, RoundOutcome)])`: G.end, engine idle
//! - `handle_task_end(now, TaskId, RobotId, TaskEnd, Option<ExecReport>) -> Result<TaskSummary, AdmitError>`
//! - `poll_timeout() -> Option<Timestamp>` / `handle_timeout(now) -> Vec<TaskId>`: idle expiry
//! - `task(TaskId) -> Option<&TaskRecord>`: the G/E history, read-only
//!
//! Read-only accessors for drivers, the simulator and metrics: [`Scheduler::pending_len`],
//! [`Scheduler::running_len`], [`Scheduler::engines`], [`Scheduler::last_decision`],
//! [`Scheduler::counters`], [`Scheduler::take_finished`] (finished-task summaries) and
//! [`Scheduler::take_superseded`] (pending requests a newer round replaced).
//!
//! # When a decision happens
//!
//! `poll_dispatch(now)` makes a *decision* iff at least one engine instance is idle and at least
//! one request is pending; otherwise it returns nothing and changes nothing. A decision asks the
//! priority policy once for an order of every pending request, places batches on all idle engine
//! instances at once (edge first, each up to its `profile.max_batch`; cloud only when its latency
//! plus RTT beats the request's edge queueing delay), flags stale observations for re-fetch (when
//! `SchedulerConfig::refetch` is on), and,
//! if it dispatched anything, adds one to the skip counter of every request it left pending. The
//! driver (and the simulator) call `poll_dispatch` after every event that can make work runnable:
//! a submit, a batch end, a cancel. Nothing in the scheduler changes with the mere passage of time
//! except idle expiry, which `poll_timeout`/`handle_timeout` cover.
//!
//! See docs/SCHEDULER.md for Algorithm 1 as implemented and every interpretation made.

mod core;
pub mod fifo;
pub mod kairos;
mod placement;
pub mod plas;
pub mod policy;
pub mod refine;
pub mod registry;
pub mod srw;
#[cfg(test)]
mod tests;

use std::time::Duration;

pub use self::core::{
    CancelOutcome, DecisionStats, EngineStatus, Scheduler, SchedulerCounters, Superseded,
};
pub use crate::lifecycle::{TaskRecord, TaskSummary};
pub use policy::{
    FinishedTask, PendingView, PolicyError, PriorityPolicy, RemainingWork, order_by_indexed_key,
    order_by_key, validate_order,
};
pub use registry::{PolicySpec, PolicySpecError, build as build_policy, refetch_by_default};

use crate::time::Timestamp;

/// The server's load as the scheduler knows it at one instant: what a load-aware horizon policy
/// reads (`kairos:policy@0.3.0` `server-load`). Built by [`Scheduler::load`], its one owner.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServerLoad {
    /// Requests waiting for dispatch.
    pub queued: u32,
    /// Requests in batches whose forward pass has not ended.
    pub running: u32,
    /// Open tasks.
    pub open_tasks: u32,
    /// The work in hand, in time: how long until an engine instance is free again if no new
    /// request came (running batches end at their estimated end, then the queued requests run
    /// in full batches at their profiled latency). A request sent now waits about this long.
    pub backlog: Duration,
}

/// A task: one robot working on one instruction, over many rounds. Chosen by the client,
/// unique per server; the first robot to use an id owns it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct TaskId(pub u64);

/// An authenticated robot identity (index of its entry in the server's robot table).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RobotId(pub u32);

/// One round request inside the scheduler. Never reused within a scheduler's lifetime, so a
/// late event about an old request cannot hit a new one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct RequestId(pub u64);

/// One dispatched batch. Never reused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct BatchId(pub u64);

/// An engine instance: its index in the list given to `Scheduler::new`, then the next number for
/// each instance added later. Never reused within a scheduler's lifetime, so a late event about
/// an instance that left cannot hit a new one (`Scheduler::add_engine`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct EngineId(pub usize);

/// Where an engine instance runs, for Algorithm 1's edge-first placement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Tier {
    /// Co-located with the robots; preferred.
    Edge,
    /// Remote; used only when its latency plus RTT beats the edge queue delay.
    Cloud,
}

/// An engine instance as the scheduler plans with it.
#[derive(Clone, Debug, PartialEq)]
pub struct EngineSpec {
    /// Human-readable name, for logs and metrics.
    pub name: String,
    /// Edge or cloud.
    pub tier: Tier,
    /// Latency by batch size; `profile.max_batch` caps batches on this instance.
    pub profile: kairos_engine_types::EngineProfile,
    /// Network round trip between the server and this instance (zero for local engines).
    pub rtt: Duration,
}

/// Last Exec Info (paper §4), already mapped onto the server clock: the execution phase
/// `E_{i-1}` that was running when round `i` was requested.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExecReport {
    /// When the robot started executing the previous chunk.
    pub started_at: Timestamp,
    /// Actions of that chunk not yet executed when the request was sent.
    pub actions_remaining: u32,
    /// Control frequency, actions per second (> 0).
    pub control_hz: f32,
}

/// A validated round request, on the server clock.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundSubmit {
    /// The task.
    pub task: TaskId,
    /// The authenticated robot that sent it.
    pub robot: RobotId,
    /// The client's round id: strictly increasing per task (gaps allowed).
    pub round: u64,
    /// When the client sent the request.
    pub sent_at: Timestamp,
    /// When the observation in it was captured (staleness is measured from here).
    pub obs_captured_at: Timestamp,
    /// The previous execution phase; `None` on a task's first round.
    pub last_exec: Option<ExecReport>,
    /// The client's remaining-work hint.
    pub remaining: Option<RemainingWork>,
    /// The robot's control rate when the request reported one without an execution report
    /// (`Submit.control_hz` on a task's first round): the idle clock needs it to know how long
    /// the answered chunk executes. `last_exec`'s rate wins when both are present.
    pub control_hz: Option<f32>,
}

/// Why a submit or task end was refused. Each maps to one wire error code.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AdmitError {
    /// The pending queue is at its configured bound.
    #[error("server overloaded: {pending} requests pending")]
    Overloaded {
        /// Requests pending when this one arrived.
        pending: usize,
    },
    /// The task belongs to another robot.
    #[error("task {} belongs to another robot", .task.0)]
    Forbidden {
        /// The task.
        task: TaskId,
    },
    /// The task is not known (never opened, ended or expired) where one was required.
    #[error("unknown task {}", .task.0)]
    UnknownTask {
        /// The task.
        task: TaskId,
    },
    /// The round id is not greater than the last one accepted for this task.
    #[error("round {got} is not after round {last}")]
    RoundOutOfOrder {
        /// The last accepted round id.
        last: u64,
        /// The round id received.
        got: u64,
    },
    /// The same round id is already pending or running (a retry after reconnect): the caller
    /// should attach to `request` instead of submitting twice.
    #[error("round {round} is already in progress")]
    RoundInProgress {
        /// The round id.
        round: u64,
        /// The request already carrying it.
        request: RequestId,
    },
    /// The task has ended; no further rounds are accepted.
    #[error("task {} has ended", .task.0)]
    TaskEnded {
        /// The task.
        task: TaskId,
    },
    /// The exec report is inconsistent (non-positive control frequency, start in the future...).
    #[error("invalid exec info: {0}")]
    InvalidExecInfo(String),
}

/// One request inside a [`Dispatch`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DispatchedRequest {
    /// The request.
    pub request: RequestId,
    /// Its task.
    pub task: TaskId,
    /// Its round id.
    pub round: u64,
    /// Re-fetch is on (`SchedulerConfig::refetch`) and its observation is older than
    /// `SchedulerConfig::stale_after`: fetch a fresh one from the client before the forward pass
    /// (Algorithm 1, `fetch_obs`).
    pub refetch: bool,
}

/// A batch the scheduler decided to run.
#[derive(Clone, Debug, PartialEq)]
pub struct Dispatch {
    /// The batch id to report back in `handle_batch_started` / `handle_batch_finished`.
    pub batch: BatchId,
    /// Where it runs.
    pub engine: EngineId,
    /// The requests, in priority order.
    pub requests: Vec<DispatchedRequest>,
}

/// How one request of a finished batch ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RoundOutcome {
    /// The chunk went back to the robot with this execution horizon.
    Answered {
        /// Actions the robot may execute.
        horizon: u32,
    },
    /// Generation failed; the robot got an error and may retry the round.
    Failed,
}

/// How a task ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskEnd {
    /// The robot finished the task.
    Done,
    /// The robot gave up or failed.
    Failed,
    /// No request for longer than the idle timeout.
    Expired,
}

/// Tunables of the scheduler core.
#[derive(Clone, Debug, PartialEq)]
pub struct SchedulerConfig {
    /// Whether a stale observation is re-fetched from the client before dispatch (Algorithm 1,
    /// line 16). A per-system setting: Kairos's Algorithm 1 re-fetches, the FIFO and Autellix
    /// baselines do not ([`registry::refetch_by_default`]).
    pub refetch: bool,
    /// With `refetch`, an observation older than this at dispatch is re-fetched from the client.
    pub stale_after: Duration,
    /// A task with no request for this long is ended as `Expired`.
    pub task_idle_timeout: Duration,
    /// Most requests pending at once; beyond it submits fail with `Overloaded`.
    pub max_pending: usize,
    /// Rounds of G/E history kept per task (older rounds are folded into running sums, so the
    /// wait ratio stays exact while memory per task stays bounded).
    pub history_rounds: usize,
    /// Ended task ids remembered (so a late round of an ended task gets `TaskEnded` instead of
    /// silently opening a new task), and finished-task summaries kept until
    /// [`Scheduler::take_finished`] drains them. Oldest are forgotten first.
    pub ended_tasks_remembered: usize,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        SchedulerConfig {
            refetch: true,
            stale_after: Duration::from_millis(100),
            task_idle_timeout: Duration::from_secs(60),
            max_pending: 100_000,
            history_rounds: 64,
            ended_tasks_remembered: 65_536,
        }
    }
}
