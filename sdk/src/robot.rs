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
//! [`ChunkExecutor`] holds these rules with time as an argument; [`RobotRunner`] drives it with the
//! tokio clock, a [`Robot`], and a [`RoundTransport`] (normally a [`Task`]).

use std::future::Future;
use std::time::Duration;

use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;

use crate::client::{ClientError, Clock, ObservationSource, RoundReply, RoundRequest, Task};
use crate::protocol::{
    ChunkingSelection, FetchObservation, HorizonSelection, Image, ImagePayload, LastExecInfo,
    Observation, RemainingHint, TaskEnded, TaskOutcome, Tensor, Timing,
};

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

/// The chunk being executed.
#[derive(Clone, Debug)]
struct ActiveChunk {
    round: u64,
    actions: Vec<Vec<f32>>,
    /// Index of the first executable action (the number discarded on arrival).
    first: usize,
    /// Index of the next action to execute.
    next: usize,
    started_at_us: Option<u64>,
    /// Actions the robot executed between the capture of the chunk's observation and its
    /// arrival (the round's actual `d`).
    delay: u32,
}

impl ActiveChunk {
    fn executable(&self) -> usize {
        self.actions.len() - self.first
    }

    fn executed(&self) -> usize {
        self.next - self.first
    }

    fn remaining(&self) -> usize {
        self.actions.len() - self.next
    }
}

#[derive(Clone, Copy, Debug)]
struct Pending {
    round: u64,
    executed_at_capture: u64,
}

/// Where a robot starts executing a chunk that arrives (module docs, "Alignment").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Alignment {
    /// At the robot's own count of the actions it executed since the chunk's observation was
    /// captured: exact, whatever the server predicted.
    #[default]
    Executed,
    /// At the reply's `start`, the server's prediction of that count (the robot's own count
    /// when the server sends none).
    ServerStart,
}

/// How a new chunk was applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChunkApplied {
    /// Actions of the new chunk discarded because their time had passed.
    pub discarded: u32,
    /// Actions of the new chunk that will execute (0 if it was entirely stale).
    pub executable: u32,
    /// The chunk that stopped executing because of this one: (round, actions executed, actions
    /// dropped unexecuted). `None` if no chunk was executing (none yet, or it had run out).
    pub replaced: Option<(u64, u32, u32)>,
}

/// One action to execute.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionStep<'a> {
    /// The round whose chunk it comes from.
    pub round: u64,
    /// Its index in that chunk.
    pub index: u32,
    /// The action vector.
    pub action: &'a [f32],
    /// True if it is the chunk's last action.
    pub last_of_chunk: bool,
}

/// The execution rules of the module docs, with time as an argument (sans-IO).
#[derive(Clone, Debug)]
pub struct ChunkExecutor {
    control_hz: f32,
    trigger: f32,
    alignment: Alignment,
    chunk: Option<ActiveChunk>,
    executed_total: u64,
    pending: Option<Pending>,
}

impl ChunkExecutor {
    /// An executor for a robot at `control_hz` that requests at `trigger` ∈ [0, 1].
    pub fn new(control_hz: f32, trigger: f32) -> ChunkExecutor {
        ChunkExecutor {
            control_hz,
            trigger: trigger.clamp(0.0, 1.0),
            alignment: Alignment::default(),
            chunk: None,
            executed_total: 0,
            pending: None,
        }
    }

    /// The same executor aligning arriving chunks by `alignment`.
    pub fn with_alignment(mut self, alignment: Alignment) -> ChunkExecutor {
        self.alignment = alignment;
        self
    }

    /// The robot's control rate, actions per second.
    pub fn control_hz(&self) -> f32 {
        self.control_hz
    }

    /// Actions executed since the task began.
    pub fn executed_total(&self) -> u64 {
        self.executed_total
    }

    /// Actions queued for execution.
    pub fn remaining(&self) -> usize {
        self.chunk.as_ref().map_or(0, ActiveChunk::remaining)
    }

    /// Whether a request is in flight.
    pub fn in_flight(&self) -> bool {
        self.pending.is_some()
    }

    /// Whether the next request is due: none in flight, and the current chunk has reached the
    /// trigger or run out.
    pub fn wants_request(&self) -> bool {
        if self.pending.is_some() {
            return false;
        }
        match &self.chunk {
            None => true,
            Some(chunk) => {
                let trigger_point = (self.trigger * chunk.executable() as f32).ceil() as usize;
                chunk.remaining() == 0 || chunk.executed() >= trigger_point
            }
        }
    }

    /// Records that round `round` was requested now, with an observation captured now. Returns
    /// the Last Exec Info to send with it.
    pub fn request_sent(&mut self, round: u64, now_us: u64) -> Option<LastExecInfo> {
        self.pending = Some(Pending {
            round,
            executed_at_capture: self.executed_total,
        });
        self.last_exec(now_us)
    }

    /// Last Exec Info describing the current (or last) chunk at `now_us`.
    pub fn last_exec(&self, now_us: u64) -> Option<LastExecInfo> {
        self.chunk.as_ref().map(|chunk| LastExecInfo {
            exec_started_at_us: chunk.started_at_us.unwrap_or(now_us),
            actions_remaining: u32::try_from(chunk.remaining()).unwrap_or(u32::MAX),
            control_hz: self.control_hz,
            round: Some(chunk.round),
            delay: Some(chunk.delay),
        })
    }

    /// Records that the in-flight round's observation was replaced by one captured now.
    pub fn observation_refreshed(&mut self) {
        if let Some(pending) = &mut self.pending {
            pending.executed_at_capture = self.executed_total;
        }
    }

    /// Records that the in-flight request failed; the next one may be sent.
    pub fn request_failed(&mut self) {
        self.pending = None;
    }

    /// Applies the chunk of `round` that arrived now, aligned by the robot's own count.
    pub fn reply_arrived(&mut self, round: u64, actions: Vec<Vec<f32>>) -> ChunkApplied {
        self.reply_arrived_from(round, actions, None)
    }

    /// Applies the chunk of `round` that arrived now; `server_start` is the reply's `start`,
    /// which [`Alignment::ServerStart`] follows.
    pub fn reply_arrived_from(
        &mut self,
        round: u64,
        actions: Vec<Vec<f32>>,
        server_start: Option<u32>,
    ) -> ChunkApplied {
        let executed_at_capture = match self.pending.take() {
            Some(pending) if pending.round == round => Some(pending.executed_at_capture),
            // A reply nobody waits for: treat its observation as captured now.
            _ => None,
        };
        let since_capture =
            executed_at_capture.map_or(0, |at| self.executed_total.saturating_sub(at));
        let own = usize::try_from(since_capture).unwrap_or(usize::MAX);
        let first = match (self.alignment, server_start) {
            (Alignment::ServerStart, Some(start)) => usize::try_from(start).unwrap_or(usize::MAX),
            // A reply nobody waits for has no capture to count from: the server's index.
            (Alignment::Executed, Some(start)) if executed_at_capture.is_none() => {
                usize::try_from(start).unwrap_or(usize::MAX)
            }
            _ => own,
        };
        let discarded = first.min(actions.len());
        let as_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        if discarded == actions.len() {
            return ChunkApplied {
                discarded: as_u32(discarded),
                executable: 0,
                replaced: None,
            };
        }
        // A chunk that already ran out ended then; only one still executing is replaced.
        let replaced = self
            .chunk
            .take()
            .filter(|old| old.remaining() > 0)
            .map(|old| (old.round, as_u32(old.executed()), as_u32(old.remaining())));
        let executable = actions.len() - discarded;
        self.chunk = Some(ActiveChunk {
            round,
            actions,
            first: discarded,
            next: discarded,
            started_at_us: None,
            delay: u32::try_from(since_capture).unwrap_or(u32::MAX),
        });
        ChunkApplied {
            discarded: as_u32(discarded),
            executable: as_u32(executable),
            replaced,
        }
    }

    /// The action to execute now, if any.
    pub fn next_action(&mut self, now_us: u64) -> Option<ActionStep<'_>> {
        let chunk = self.chunk.as_mut()?;
        if chunk.remaining() == 0 {
            return None;
        }
        let index = chunk.next;
        chunk.next += 1;
        chunk.started_at_us.get_or_insert(now_us);
        self.executed_total += 1;
        let last_of_chunk = chunk.remaining() == 0;
        Some(ActionStep {
            round: chunk.round,
            index: u32::try_from(index).unwrap_or(u32::MAX),
            action: &chunk.actions[index],
            last_of_chunk,
        })
    }

    /// Drops what is left of the current chunk (the task ended before it ran out). Returns the
    /// chunk's round, how many of its actions executed and how many were dropped, if any were.
    pub fn drop_rest(&mut self) -> Option<(u64, u32, u32)> {
        let chunk = self.chunk.take().filter(|c| c.remaining() > 0)?;
        let as_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        Some((
            chunk.round,
            as_u32(chunk.executed()),
            as_u32(chunk.remaining()),
        ))
    }

    /// The current chunk's round and how many of its actions executed.
    pub fn current_chunk(&self) -> Option<(u64, u32)> {
        self.chunk.as_ref().map(|chunk| {
            (
                chunk.round,
                u32::try_from(chunk.executed()).unwrap_or(u32::MAX),
            )
        })
    }
}

/// How a [`RobotRunner`] runs a task.
#[derive(Clone, Debug, PartialEq)]
pub struct RunnerConfig {
    /// Actions per second.
    pub control_hz: f32,
    /// Executed fraction of a chunk at which the next request goes out, in [0, 1].
    pub trigger: f32,
    /// Rounds (replies) the task takes.
    pub rounds: u64,
    /// Horizon policy sent with every round; `None` = the server's default.
    pub horizon: Option<HorizonSelection>,
    /// Answer the server's re-fetches with a new observation (otherwise the submitted one is
    /// sent again).
    pub refetch: bool,
    /// Retryable round failures in a row (e.g. `overloaded`) before the task is abandoned.
    pub max_consecutive_failures: u32,
    /// Wait before re-requesting after a retryable failure, unless the server says otherwise.
    pub retry_delay: Duration,
    /// Chunking strategy sent with every round; `None` = the server's default.
    pub chunking: Option<ChunkingSelection>,
    /// Where an arriving chunk starts executing.
    pub alignment: Alignment,
}

impl Default for RunnerConfig {
    fn default() -> RunnerConfig {
        RunnerConfig {
            control_hz: 30.0,
            trigger: 0.5,
            rounds: 10,
            horizon: None,
            refetch: true,
            max_consecutive_failures: 5,
            retry_delay: Duration::from_millis(100),
            chunking: None,
            alignment: Alignment::default(),
        }
    }
}

/// What happened during a task, in order, for traces and progress displays. Times are on the
/// client clock, µs.
#[derive(Clone, Debug, PartialEq)]
pub enum RunnerEvent {
    /// A round was requested.
    RequestSent {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// The Last Exec Info sent.
        last_exec: Option<LastExecInfo>,
    },
    /// The server asked for a fresher observation and got one. The round's chunk is aligned to
    /// this capture from now on (see the module docs).
    ObservationRefetched {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// Actions the task had executed when the fresh observation was captured: the action
        /// index the chunk's action 0 now corresponds to.
        actions_executed: u64,
    },
    /// A round's chunk arrived and was aligned.
    ReplyReceived {
        /// Task id.
        task: u64,
        /// The round's record so far (`executed` is 0 until the chunk ends).
        record: RoundRecord,
    },
    /// A round failed.
    RoundFailed {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// What went wrong.
        error: String,
        /// Whether the runner will request again.
        retrying: bool,
    },
    /// A chunk stopped executing: it ran out or a newer chunk replaced it.
    ChunkEnded {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// Actions executed.
        executed: u32,
        /// Actions dropped unexecuted (replaced by a newer chunk).
        dropped: u32,
    },
    /// The robot had nothing to execute from `from_us` to `to_us`.
    Idle {
        /// Task id.
        task: u64,
        /// Start of the gap.
        from_us: u64,
        /// End of the gap.
        to_us: u64,
    },
    /// The task is over.
    TaskFinished(TaskSummary),
}

/// One round as the robot saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundRecord {
    /// Round id.
    pub round: u64,
    /// When the round was first sent.
    pub sent_at_us: u64,
    /// When its reply arrived.
    pub received_at_us: u64,
    /// Sends (more than 1 after a lost connection).
    pub attempts: u32,
    /// Fresh observations sent for it.
    pub refetches: u32,
    /// `H`.
    pub horizon: u32,
    /// `N`.
    pub chunk_len: u32,
    /// Actions discarded on arrival (their time had passed).
    pub discarded: u32,
    /// Actions executed.
    pub executed: u32,
    /// The horizon policy that answered.
    pub policy: String,
    /// The server's timing.
    pub timing: Timing,
}

impl RoundRecord {
    /// Round latency as the robot saw it, µs.
    pub fn latency_us(&self) -> u64 {
        self.received_at_us.saturating_sub(self.sent_at_us)
    }
}

/// A finished task.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskSummary {
    /// Task id.
    pub task: u64,
    /// Its rounds, in order.
    pub rounds: Vec<RoundRecord>,
    /// When the first request was sent.
    pub started_at_us: u64,
    /// When the last action was executed.
    pub finished_at_us: u64,
    /// Actions executed.
    pub actions_executed: u64,
    /// Total time the robot had nothing to execute, µs (the wait before the first chunk
    /// included).
    pub idle_us: u64,
    /// Rounds that failed (and were retried).
    pub failed_rounds: u32,
    /// The server's record, if `EndTask` succeeded.
    pub server_record: Option<TaskEnded>,
    /// Why `EndTask` failed, if it did (then `server_record` is `None`): the task may still be
    /// open on the server until its idle timeout, e.g. after a server restart forgot it
    /// (`unknown_task`) or the connection was lost. Reports count these.
    pub end_error: Option<String>,
}

impl TaskSummary {
    /// Task latency: first request to last action, µs.
    pub fn latency_us(&self) -> u64 {
        self.finished_at_us.saturating_sub(self.started_at_us)
    }
}

/// Why a task could not be run.
#[derive(Debug, thiserror::Error)]
pub enum RunnerError {
    /// The robot's shim failed.
    #[error(transparent)]
    Robot(#[from] RobotError),
    /// A round failed for good.
    #[error("round {round} failed: {source}")]
    Round {
        /// The round.
        round: u64,
        /// Why.
        source: ClientError,
    },
    /// The server's reply is not an `[H, D]` chunk of f32.
    #[error("bad chunk in round {round}: {reason}")]
    BadChunk {
        /// The round.
        round: u64,
        /// What is wrong.
        reason: String,
    },
    /// The round task panicked or was cancelled.
    #[error("round task failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// Answers the server's re-fetches by asking the runner loop, which owns the robot.
struct RunnerSource {
    requests: mpsc::Sender<oneshot::Sender<Observation>>,
}

impl ObservationSource for RunnerSource {
    fn fresh_observation(
        &mut self,
        _fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send {
        let requests = self.requests.clone();
        async move {
            let (reply, answer) = oneshot::channel();
            requests.send(reply).await.ok()?;
            answer.await.ok()
        }
    }
}

type InFlight<T> = tokio::task::JoinHandle<(T, u64, Result<RoundReply, ClientError>)>;

/// Runs one task on one robot: the control loop, asynchronous inference, alignment.
#[derive(Clone, Debug)]
pub struct RobotRunner {
    config: RunnerConfig,
}

impl RobotRunner {
    /// A runner with `config`.
    pub fn new(config: RunnerConfig) -> RobotRunner {
        RobotRunner { config }
    }

    /// Runs the task to its end (`config.rounds` replies executed, or `robot.task_done()`), then
    /// sends `EndTask`. `on_event` sees every [`RunnerEvent`].
    pub async fn run<R: Robot, T: RoundTransport, E: FnMut(&RunnerEvent) + Send>(
        &self,
        robot: &mut R,
        transport: T,
        on_event: E,
    ) -> Result<TaskSummary, RunnerError> {
        let (fetch_tx, mut fetch_rx) = mpsc::channel(1);
        let mut run = Run {
            config: &self.config,
            task: transport.task_id(),
            clock: transport.clock(),
            period: Duration::from_secs_f64(1.0 / f64::from(self.config.control_hz.max(1e-3))),
            executor: ChunkExecutor::new(self.config.control_hz, self.config.trigger)
                .with_alignment(self.config.alignment),
            robot,
            transport: Some(transport),
            in_flight: None,
            fetch_tx,
            on_event,
            next_tick: None,
            idle_since: None,
            retry_at: None,
            records: Vec::new(),
            replies: 0,
            failures_in_row: 0,
            failed_rounds: 0,
            idle_us: 0,
            started_at_us: None,
            last_action_at_us: None,
        };
        loop {
            let now = Instant::now();
            let task_done = run.robot.task_done();
            if task_done {
                // The robot reached its goal: the rest of the chunk is not executed (executing
                // it would lengthen the task by up to a whole horizon). A round still in flight
                // is awaited so that it is answered exactly once, but nothing more runs.
                run.next_tick = None;
                run.idle_since = None;
                if let Some((round, executed, dropped)) = run.executor.drop_rest() {
                    run.chunk_ended(round, executed, dropped);
                }
            }
            let stop_requesting = run.replies >= run.config.rounds || task_done;
            if !stop_requesting
                && run.retry_at.is_none_or(|at| now >= at)
                && run.executor.wants_request()
            {
                run.send_request(now).await?;
            }
            if stop_requesting && run.in_flight.is_none() && run.executor.remaining() == 0 {
                break;
            }
            tokio::select! {
                Some(answer) = fetch_rx.recv() => run.refetch(answer).await?,
                joined = async {
                    match run.in_flight.as_mut() {
                        Some(handle) => handle.await,
                        None => std::future::pending().await,
                    }
                } => {
                    run.in_flight = None;
                    let (transport, round, result) = joined?;
                    run.transport = Some(transport);
                    run.round_done(round, result).await?;
                }
                () = sleep_until_some(run.next_tick) => run.tick().await?,
                () = sleep_until_some(run.retry_at) => {}
            }
        }
        run.finish().await
    }
}

/// The state of one [`RobotRunner::run`].
struct Run<'a, R, T, E> {
    config: &'a RunnerConfig,
    task: u64,
    clock: Clock,
    period: Duration,
    executor: ChunkExecutor,
    robot: &'a mut R,
    /// The transport, while no round is in flight (the round's task holds it meanwhile).
    transport: Option<T>,
    in_flight: Option<InFlight<T>>,
    fetch_tx: mpsc::Sender<oneshot::Sender<Observation>>,
    on_event: E,
    /// When the next action is due; `None` while the robot idles.
    next_tick: Option<Instant>,
    /// Since when the robot has had nothing to execute.
    idle_since: Option<Instant>,
    retry_at: Option<Instant>,
    records: Vec<RoundRecord>,
    replies: u64,
    failures_in_row: u32,
    failed_rounds: u32,
    idle_us: u64,
    started_at_us: Option<u64>,
    last_action_at_us: Option<u64>,
}

impl<R: Robot, T: RoundTransport, E: FnMut(&RunnerEvent) + Send> Run<'_, R, T, E> {
    /// Captures an observation and starts the next round in its own tokio task.
    async fn send_request(&mut self, now: Instant) -> Result<(), RunnerError> {
        let Some(mut transport) = self.transport.take() else {
            return Ok(());
        };
        self.retry_at = None;
        let now_us = self.clock.to_us(now);
        let observation = self.robot.get_obs(now_us).await?;
        let round = transport.next_round();
        let last_exec = self.executor.request_sent(round, now_us);
        self.started_at_us.get_or_insert(now_us);
        if self.started_at_us == Some(now_us) && self.executor.remaining() == 0 {
            // Nothing to execute until the first chunk arrives.
            self.idle_since = Some(now);
        }
        (self.on_event)(&RunnerEvent::RequestSent {
            task: self.task,
            round,
            at_us: now_us,
            last_exec,
        });
        let request = RoundRequest {
            observation,
            last_exec,
            horizon: self.config.horizon.clone(),
            remaining: Some(RemainingHint {
                rounds: u32::try_from(self.config.rounds.saturating_sub(self.replies)).ok(),
                seconds: None,
            }),
            control_hz: Some(self.config.control_hz),
            seed: None,
            chunking: self.config.chunking.clone(),
        };
        let refetch = self.config.refetch;
        let requests = self.fetch_tx.clone();
        self.in_flight = Some(tokio::spawn(async move {
            let result = if refetch {
                transport
                    .submit(request, &mut RunnerSource { requests })
                    .await
            } else {
                transport
                    .submit(request, &mut crate::client::NoRefetch)
                    .await
            };
            (transport, round, result)
        }));
        Ok(())
    }

    /// The server re-fetches the in-flight round's observation.
    async fn refetch(&mut self, answer: oneshot::Sender<Observation>) -> Result<(), RunnerError> {
        let now_us = self.clock.now_us();
        let observation = self.robot.get_obs(now_us).await?;
        self.executor.observation_refreshed();
        if let Some(pending) = self.executor.pending {
            (self.on_event)(&RunnerEvent::ObservationRefetched {
                task: self.task,
                round: pending.round,
                at_us: now_us,
                actions_executed: self.executor.executed_total(),
            });
        }
        // The round may have ended meanwhile; then nobody needs the observation.
        let _ = answer.send(observation);
        Ok(())
    }

    /// The in-flight round finished.
    async fn round_done(
        &mut self,
        round: u64,
        result: Result<RoundReply, ClientError>,
    ) -> Result<(), RunnerError> {
        match result {
            Ok(reply) => {
                self.failures_in_row = 0;
                self.replies += 1;
                let actions =
                    chunk_rows(&reply).map_err(|reason| RunnerError::BadChunk { round, reason })?;
                let applied = self
                    .executor
                    .reply_arrived_from(round, actions, reply.reply.start);
                if let Some((old, executed, dropped)) = applied.replaced {
                    self.chunk_ended(old, executed, dropped);
                }
                let record = RoundRecord {
                    round,
                    sent_at_us: reply.sent_at_us,
                    received_at_us: reply.received_at_us,
                    attempts: reply.attempts,
                    refetches: reply.refetches,
                    horizon: reply.reply.horizon,
                    chunk_len: reply.reply.chunk_len,
                    discarded: applied.discarded,
                    executed: 0,
                    policy: reply.reply.policy,
                    timing: reply.reply.timing,
                };
                (self.on_event)(&RunnerEvent::ReplyReceived {
                    task: self.task,
                    record: record.clone(),
                });
                self.records.push(record);
                if applied.executable == 0 {
                    self.chunk_ended(round, 0, 0);
                } else if self.next_tick.is_none() {
                    // Idle robot: the chunk's first action runs now.
                    self.next_tick = Some(Instant::now());
                }
                Ok(())
            }
            Err(error) => {
                self.executor.request_failed();
                self.failed_rounds += 1;
                self.failures_in_row += 1;
                let retrying = error.is_retryable()
                    && self.failures_in_row <= self.config.max_consecutive_failures;
                (self.on_event)(&RunnerEvent::RoundFailed {
                    task: self.task,
                    round,
                    at_us: self.clock.now_us(),
                    error: error.to_string(),
                    retrying,
                });
                if !retrying {
                    if let Some(transport) = self.transport.take() {
                        let last_exec = self.executor.last_exec(self.clock.now_us());
                        // The task failed either way; the round's error is the one to report.
                        let _ = transport.end(TaskOutcome::Failed, last_exec).await;
                    }
                    return Err(RunnerError::Round {
                        round,
                        source: error,
                    });
                }
                let delay = match &error {
                    ClientError::Server(reply) => {
                        reply.retry_after_ms.map_or(self.config.retry_delay, |ms| {
                            Duration::from_millis(u64::from(ms))
                        })
                    }
                    _ => self.config.retry_delay,
                };
                self.retry_at = Some(Instant::now() + delay);
                Ok(())
            }
        }
    }

    /// An action is due.
    async fn tick(&mut self) -> Result<(), RunnerError> {
        let tick = self.next_tick.unwrap_or_else(Instant::now);
        let tick_us = self.clock.to_us(tick);
        let Some(step) = self.executor.next_action(tick_us) else {
            // An action was due and there is none: the robot idles from here.
            self.idle_since = Some(tick);
            self.next_tick = None;
            return Ok(());
        };
        let (round, last) = (step.round, step.last_of_chunk);
        self.robot.send_act(step.action).await?;
        if let Some(since) = self.idle_since.take() {
            let from_us = self.clock.to_us(since);
            self.idle_us += tick_us.saturating_sub(from_us);
            (self.on_event)(&RunnerEvent::Idle {
                task: self.task,
                from_us,
                to_us: tick_us,
            });
        }
        self.last_action_at_us = Some(tick_us);
        if last {
            let executed = self.executor.current_chunk().map_or(0, |(_, n)| n);
            self.chunk_ended(round, executed, 0);
        }
        self.next_tick = Some(tick + self.period);
        Ok(())
    }

    fn chunk_ended(&mut self, round: u64, executed: u32, dropped: u32) {
        if let Some(record) = self.records.iter_mut().rev().find(|r| r.round == round) {
            record.executed = executed;
        }
        (self.on_event)(&RunnerEvent::ChunkEnded {
            task: self.task,
            round,
            executed,
            dropped,
        });
    }

    /// Sends `EndTask` and builds the summary.
    async fn finish(mut self) -> Result<TaskSummary, RunnerError> {
        let now_us = self.clock.now_us();
        let finished_at_us = self.last_action_at_us.unwrap_or(now_us);
        let last_exec = self.executor.last_exec(now_us);
        let (server_record, end_error) = match self.transport.take() {
            Some(transport) => match transport.end(TaskOutcome::Done, last_exec).await {
                Ok(record) => (Some(record), None),
                Err(error) => {
                    tracing::warn!(task = self.task, %error, "EndTask failed");
                    (None, Some(error.to_string()))
                }
            },
            None => (None, None),
        };
        let summary = TaskSummary {
            task: self.task,
            rounds: self.records,
            started_at_us: self.started_at_us.unwrap_or(finished_at_us),
            finished_at_us,
            actions_executed: self.executor.executed_total(),
            idle_us: self.idle_us,
            failed_rounds: self.failed_rounds,
            server_record,
            end_error,
        };
        (self.on_event)(&RunnerEvent::TaskFinished(summary.clone()));
        Ok(summary)
    }
}

async fn sleep_until_some(deadline: Option<Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// The reply's actions as rows of `D` values.
fn chunk_rows(reply: &RoundReply) -> Result<Vec<Vec<f32>>, String> {
    let actions = &reply.reply.actions;
    let values = actions.to_f32().map_err(|error| error.to_string())?;
    let [rows, dim] = actions.shape[..] else {
        return Err(format!("shape {:?} is not [H, D]", actions.shape));
    };
    if dim == 0 {
        return Ok(vec![Vec::new(); rows as usize]);
    }
    Ok(values.chunks(dim as usize).map(<[f32]>::to_vec).collect())
}

/// A simulated robot: a synthetic joint state that integrates the actions it is sent and a
/// synthetic camera image, executing by counting. For tests, benchmarks and `kairos robot`.
#[derive(Clone, Debug)]
pub struct SimulatedRobot {
    state: Vec<f32>,
    cameras: Vec<(String, u32, u32)>,
    instruction: String,
    executed: u64,
    observations: u64,
}

impl SimulatedRobot {
    /// A robot with a `state_dim` joint state and `cameras` RGB cameras of `height`×`width`
    /// pixels, sent raw as `u8` (named `front`, `wrist`, then `camera2`, `camera3`, ...).
    pub fn new(state_dim: usize, cameras: usize, height: u32, width: u32) -> SimulatedRobot {
        let name = |i: usize| match i {
            0 => "front".to_owned(),
            1 => "wrist".to_owned(),
            i => format!("camera{i}"),
        };
        SimulatedRobot {
            state: (0..state_dim).map(|i| i as f32 * 0.01).collect(),
            cameras: (0..cameras).map(|i| (name(i), height, width)).collect(),
            instruction: "pick up the cube and place it in the bin".to_owned(),
            executed: 0,
            observations: 0,
        }
    }

    /// Names the cameras as `names` does, in order (the model's names from `Welcome`, for a
    /// model that matches images by name); cameras beyond `names` keep their names.
    pub fn with_camera_names(mut self, names: &[String]) -> SimulatedRobot {
        for ((camera, _, _), name) in self.cameras.iter_mut().zip(names) {
            camera.clone_from(name);
        }
        self
    }

    /// Actions executed so far.
    pub fn executed(&self) -> u64 {
        self.executed
    }

    /// Observations captured so far.
    pub fn observations(&self) -> u64 {
        self.observations
    }

    /// The joint state.
    pub fn state(&self) -> &[f32] {
        &self.state
    }

    fn image(&self, height: u32, width: u32) -> Result<Tensor, RobotError> {
        // A moving gradient, so consecutive frames differ the way a camera's do.
        let shift = (self.executed % 256) as u8;
        let data = (0..height * width * 3)
            .map(|i| (i as u8).wrapping_add(shift))
            .collect();
        Tensor::from_u8(vec![height, width, 3], data).map_err(|error| RobotError(error.to_string()))
    }
}

impl Robot for SimulatedRobot {
    fn get_obs(
        &mut self,
        now_us: u64,
    ) -> impl Future<Output = Result<Observation, RobotError>> + Send {
        self.observations += 1;
        let observation = (|| {
            let images = self
                .cameras
                .iter()
                .map(|(camera, height, width)| {
                    Ok(Image {
                        camera: camera.clone(),
                        payload: ImagePayload::Raw {
                            tensor: self.image(*height, *width)?,
                        },
                    })
                })
                .collect::<Result<Vec<_>, RobotError>>()?;
            let state = Tensor::from_f32(vec![self.state.len() as u32], &self.state)
                .map_err(|error| RobotError(error.to_string()))?;
            Ok(Observation {
                captured_at_us: now_us,
                state,
                images,
                instruction: self.instruction.clone(),
            })
        })();
        std::future::ready(observation)
    }

    fn send_act(&mut self, action: &[f32]) -> impl Future<Output = Result<(), RobotError>> + Send {
        for (joint, delta) in self.state.iter_mut().zip(action) {
            *joint += 0.01 * delta;
        }
        self.executed += 1;
        std::future::ready(Ok(()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(round: u64, len: usize) -> Vec<Vec<f32>> {
        (0..len).map(|i| vec![round as f32, i as f32]).collect()
    }

    #[test]
    fn first_request_is_immediate_and_has_no_exec_info() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        assert!(executor.wants_request());
        assert_eq!(executor.request_sent(0, 100), None);
        assert!(!executor.wants_request(), "one request in flight at a time");
    }

    #[test]
    fn trigger_fires_at_the_executed_fraction() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        let applied = executor.reply_arrived(0, chunk(0, 10));
        assert_eq!(
            applied,
            ChunkApplied {
                discarded: 0,
                executable: 10,
                replaced: None
            }
        );
        for i in 0..5 {
            assert!(!executor.wants_request(), "not yet after {i} actions");
            let step = executor.next_action(1000 + i).unwrap();
            assert_eq!(step.index as u64, i);
        }
        assert!(executor.wants_request());
        let info = executor.request_sent(1, 2000).unwrap();
        assert_eq!(info.exec_started_at_us, 1000);
        assert_eq!(info.actions_remaining, 5);
        assert_eq!(info.control_hz, 10.0);
    }

    #[test]
    fn arrival_discards_the_actions_whose_time_passed_and_replaces_the_rest() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        for t in 0..4 {
            executor.next_action(t);
        }
        executor.request_sent(1, 4);
        // Three more actions execute while round 1 is generated.
        for t in 4..7 {
            executor.next_action(t);
        }
        let applied = executor.reply_arrived(1, chunk(1, 8));
        assert_eq!(applied.discarded, 3);
        assert_eq!(applied.executable, 5);
        assert_eq!(applied.replaced, Some((0, 7, 1)));
        let step = executor.next_action(7).unwrap();
        assert_eq!((step.round, step.index), (1, 3));
        assert_eq!(step.action, &[1.0, 3.0]);
    }

    /// Last Exec Info names the chunk's round and its actual d; `ServerStart` follows the
    /// reply's start index, `Executed` the robot's own count, and a reply nobody waited for takes
    /// the server's index either way.
    #[test]
    fn alignment_follows_the_own_count_or_the_servers_start() {
        let run = |alignment: Alignment, start: Option<u32>| {
            let mut executor = ChunkExecutor::new(10.0, 0.5).with_alignment(alignment);
            executor.request_sent(0, 0);
            executor.reply_arrived(0, chunk(0, 8));
            executor.next_action(0);
            executor.request_sent(1, 1);
            // Two actions while round 1 is in flight: its actual d is 2.
            executor.next_action(1);
            executor.next_action(2);
            let applied = executor.reply_arrived_from(1, chunk(1, 8), start);
            let info = executor.last_exec(3).unwrap();
            (applied.discarded, info.round, info.delay)
        };
        assert_eq!(run(Alignment::Executed, Some(3)), (2, Some(1), Some(2)));
        assert_eq!(run(Alignment::ServerStart, Some(3)), (3, Some(1), Some(2)));
        assert_eq!(run(Alignment::ServerStart, None), (2, Some(1), Some(2)));
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        // Round 5 was never requested here (a reply to a round resent after a reconnect).
        assert_eq!(
            executor
                .reply_arrived_from(5, chunk(5, 8), Some(4))
                .discarded,
            4
        );
        let info = executor.last_exec(10).unwrap();
        assert_eq!((info.round, info.delay), (Some(5), Some(0)));
    }

    #[test]
    fn a_refetch_moves_the_alignment_point() {
        let mut executor = ChunkExecutor::new(10.0, 0.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        executor.request_sent(1, 0);
        executor.next_action(0);
        executor.next_action(1);
        executor.observation_refreshed();
        executor.next_action(2);
        assert_eq!(executor.reply_arrived(1, chunk(1, 8)).discarded, 1);
    }

    #[test]
    fn an_entirely_stale_chunk_keeps_the_old_one_and_asks_again() {
        let mut executor = ChunkExecutor::new(10.0, 0.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 10));
        executor.request_sent(1, 0);
        for t in 0..4 {
            executor.next_action(t);
        }
        let applied = executor.reply_arrived(1, chunk(1, 3));
        assert_eq!(
            applied,
            ChunkApplied {
                discarded: 3,
                executable: 0,
                replaced: None
            }
        );
        assert_eq!(executor.remaining(), 6);
        assert!(executor.wants_request());
        assert_eq!(executor.next_action(4).unwrap().round, 0);
    }

    #[test]
    fn an_idle_robot_discards_nothing() {
        let mut executor = ChunkExecutor::new(10.0, 1.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 2));
        executor.next_action(0);
        executor.next_action(1);
        assert!(executor.next_action(2).is_none());
        assert!(executor.wants_request());
        let info = executor.request_sent(1, 5).unwrap();
        assert_eq!(info.actions_remaining, 0);
        assert_eq!(info.exec_started_at_us, 0);
        let applied = executor.reply_arrived(1, chunk(1, 4));
        assert_eq!(applied.discarded, 0);
        assert_eq!(
            applied.replaced, None,
            "the old chunk ended when it ran out"
        );
    }

    #[test]
    fn trigger_one_is_synchronous_and_zero_is_immediate() {
        let mut sync = ChunkExecutor::new(10.0, 1.0);
        sync.request_sent(0, 0);
        sync.reply_arrived(0, chunk(0, 3));
        sync.next_action(0);
        sync.next_action(1);
        assert!(!sync.wants_request());
        sync.next_action(2);
        assert!(sync.wants_request());

        let mut eager = ChunkExecutor::new(10.0, 0.0);
        eager.request_sent(0, 0);
        eager.reply_arrived(0, chunk(0, 3));
        assert!(eager.wants_request());
    }
}
