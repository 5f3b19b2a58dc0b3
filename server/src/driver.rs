//! The driver: the one task that owns the [`Scheduler`].
//!
//! Connection tasks talk to it through a [`DriverHandle`] (an mpsc of [`Command`]s, each with a
//! oneshot for its answer); nothing else touches the scheduler, so there is no lock around it.
//! After every event the driver asks the scheduler for dispatches and carries them out:
//!
//! 1. for each request flagged stale, it asks the round's connection task to send
//!    `FetchObservation` and waits (off the driver task) up to the re-fetch deadline; a fresh
//!    observation replaces the queued one, a late or failed one leaves it;
//! 2. when a batch's re-fetches are settled it reports `handle_batch_started` (`G.start`) and
//!    hands the batch to its engine instance in a spawned task, which also runs the action
//!    manager (horizon policy, trim) on the chunks;
//! 3. when that task reports back, it reports `handle_batch_finished` (`G.end`) with the
//!    horizons, stamps each reply's timing and sends it to every stream waiting for the round.
//!
//! The driver keeps what the scheduler does not: observations and policies of pending rounds,
//! the streams waiting for each round, each task's last reply (so a round re-sent after a
//! reconnect gets the same answer instead of a second generation), and the clock mapping of each
//! task's latest request (to show G/E records on the robot's clock).
//!
//! Shutdown: once the shutdown future resolves (or every handle is dropped) new rounds are
//! refused with `shutting_down`; rounds already accepted are still run and answered, and
//! [`run`] returns when none is left.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use kairos_sdk::protocol::{ErrorReply, IntervalUs, Reply, RoundRecordWire, TaskEnded, Timing};
use tokio::sync::{mpsc, oneshot};

use crate::action::{ActionManager, RoundContext, RoundPolicy, build_reply};
use crate::lifecycle::{RoundRecord, exec_interval};
use crate::pool::EnginePool;
use crate::scheduler::{
    AdmitError, BatchId, CancelOutcome, Dispatch, RequestId, RobotId, RoundOutcome, Scheduler,
    TaskId,
};
use crate::time::{Timestamp, duration_micros};
use crate::validation::{ClockMap, RequestError, ValidEndTask, ValidObservation, ValidSubmit};

/// The server clock: [`Timestamp`]s are microseconds since the driver's epoch.
#[derive(Clone, Copy, Debug)]
pub struct Clock {
    epoch: Instant,
}

impl Clock {
    /// A clock whose epoch is now.
    pub fn start() -> Clock {
        Clock {
            epoch: Instant::now(),
        }
    }

    /// Now on the server clock.
    pub fn now(&self) -> Timestamp {
        self.at(Instant::now())
    }

    /// `instant` on the server clock.
    pub fn at(&self, instant: Instant) -> Timestamp {
        Timestamp::from_micros(duration_micros(
            instant.saturating_duration_since(self.epoch),
        ))
    }

    /// The instant of a server timestamp.
    pub fn instant(&self, t: Timestamp) -> Instant {
        self.epoch + Duration::from_micros(t.as_micros())
    }
}

/// Identifies one stream waiting for a round (a round may have several after reconnects).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct WaiterId(u64);

/// A request from the driver to a round's connection task: send `FetchObservation` and return
/// the validated `FreshObservation`. Dropping `reply` means "no fresh observation".
#[derive(Debug)]
pub struct RefetchAsk {
    /// How old the queued observation is.
    pub age: Duration,
    /// Where the fresh observation goes.
    pub reply: oneshot::Sender<ValidObservation>,
}

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

/// Running totals of the driver.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DriverStats {
    /// Rounds accepted by the scheduler.
    pub accepted: u64,
    /// Rounds refused (any reason).
    pub refused: u64,
    /// Re-sent rounds attached to the request already carrying them.
    pub attached: u64,
    /// Re-sent rounds answered from the reply cache.
    pub cached_replies: u64,
    /// Replies generated and sent.
    pub replies: u64,
    /// Rounds whose generation failed.
    pub failed: u64,
    /// Pending requests removed because every stream waiting for them went away.
    pub cancelled: u64,
    /// Pending requests replaced by a newer round of their task.
    pub superseded: u64,
    /// `FetchObservation`s sent.
    pub refetch_asked: u64,
    /// Fresh observations received in time and used.
    pub refetch_used: u64,
    /// Batches run.
    pub batches: u64,
    /// Tasks ended (explicitly or by expiry).
    pub tasks_ended: u64,
    /// Server-added latency of recent replies: `timing.total − timing.inference` (queueing
    /// behind other batches included).
    pub overhead: LatencySummary,
    /// The part of `overhead` that is the server's own work, without waiting for an engine or a
    /// re-fetched observation: from the `Submit` frame read to the scheduler accepting it
    /// (validation, the driver's queue), plus from dispatch to the reply handed to the stream
    /// (batch start, engine hand-off, horizon policy, trim, driver), less the forward pass.
    pub processing: LatencySummary,
}

/// Percentiles of a latency over the most recent [`RECENT_LATENCIES`] replies, µs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LatencySummary {
    /// Replies summarised.
    pub count: u64,
    /// Median.
    pub p50_us: u64,
    /// 99th percentile (nearest rank).
    pub p99_us: u64,
    /// Largest.
    pub max_us: u64,
}

/// Replies the latency summaries cover.
pub const RECENT_LATENCIES: usize = 1 << 16;

impl LatencySummary {
    /// Nearest-rank percentiles of `values`.
    pub fn of(values: impl Iterator<Item = u64>) -> LatencySummary {
        let mut sorted: Vec<u64> = values.collect();
        if sorted.is_empty() {
            return LatencySummary::default();
        }
        sorted.sort_unstable();
        let rank = |p: f64| {
            let index = ((p * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1;
            sorted[index]
        };
        LatencySummary {
            count: sorted.len() as u64,
            p50_us: rank(0.50),
            p99_us: rank(0.99),
            max_us: sorted[sorted.len() - 1],
        }
    }
}

/// The latest [`RECENT_LATENCIES`] values of server-added latency.
#[derive(Default)]
struct RecentLatencies {
    /// `(overhead, processing)` per reply, µs.
    values: VecDeque<(u64, u64)>,
}

impl RecentLatencies {
    fn record(&mut self, timing: &Timing, processing_us: u64) {
        if self.values.len() >= RECENT_LATENCIES {
            self.values.pop_front();
        }
        let overhead = timing.total_us.saturating_sub(timing.inference_us);
        self.values.push_back((overhead, processing_us));
    }

    fn summaries(&self) -> (LatencySummary, LatencySummary) {
        (
            LatencySummary::of(self.values.iter().map(|v| v.0)),
            LatencySummary::of(self.values.iter().map(|v| v.1)),
        )
    }
}

/// Messages to the driver.
#[derive(Debug)]
enum Command {
    Submit {
        submit: Box<ValidSubmit>,
        received: Instant,
        waiter: WaiterId,
        link: mpsc::Sender<RefetchAsk>,
        answer: oneshot::Sender<RoundAnswer>,
    },
    Detach {
        task: TaskId,
        round: u64,
        waiter: WaiterId,
    },
    EndTask {
        robot: RobotId,
        end: ValidEndTask,
        answer: oneshot::Sender<Result<TaskEnded, ErrorReply>>,
    },
    Snapshot {
        task: TaskId,
        answer: oneshot::Sender<Option<TaskSnapshot>>,
    },
    Stats {
        answer: oneshot::Sender<DriverStats>,
    },
    Refetched {
        batch: BatchId,
        request: RequestId,
        observation: Option<ValidObservation>,
    },
    BatchDone {
        batch: BatchId,
        results: Vec<(RequestId, Result<Reply, ErrorReply>)>,
        inference: Duration,
    },
}

/// A cloneable handle to the driver.
#[derive(Clone, Debug)]
pub struct DriverHandle {
    commands: mpsc::Sender<Command>,
    waiters: Arc<AtomicU64>,
    clock: Clock,
}

/// The driver has stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the driver has stopped")]
pub struct DriverGone;

/// A round accepted by the driver: await its answer, and detach if the stream goes away first.
#[derive(Debug)]
pub struct PendingRound {
    /// The task.
    pub task: TaskId,
    /// The round.
    pub round: u64,
    /// This stream's waiter id.
    pub waiter: WaiterId,
    /// The answer.
    pub answer: oneshot::Receiver<RoundAnswer>,
}

impl DriverHandle {
    /// The server clock the driver runs on.
    pub fn clock(&self) -> Clock {
        self.clock
    }

    /// Hands a validated round to the driver. `received` is when its `Submit` frame was read
    /// (replies' timing counts from there); `link` receives re-fetch asks for it.
    pub async fn submit(
        &self,
        submit: ValidSubmit,
        received: Instant,
        link: mpsc::Sender<RefetchAsk>,
    ) -> Result<PendingRound, DriverGone> {
        let (answer_tx, answer) = oneshot::channel();
        let waiter = WaiterId(self.waiters.fetch_add(1, Ordering::Relaxed));
        let (task, round) = (submit.round.task, submit.round.round);
        self.commands
            .send(Command::Submit {
                submit: Box::new(submit),
                received,
                waiter,
                link,
                answer: answer_tx,
            })
            .await
            .map_err(|_| DriverGone)?;
        Ok(PendingRound {
            task,
            round,
            waiter,
            answer,
        })
    }

    /// The stream waiting for `pending` is gone. If no other stream waits for the round and it is
    /// still queued, it is withdrawn (the robot may send it again).
    pub async fn detach(&self, pending: &PendingRound) {
        let _ = self
            .commands
            .send(Command::Detach {
                task: pending.task,
                round: pending.round,
                waiter: pending.waiter,
            })
            .await;
    }

    /// Ends a task on behalf of `robot`.
    pub async fn end_task(
        &self,
        robot: RobotId,
        end: ValidEndTask,
    ) -> Result<Result<TaskEnded, ErrorReply>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::EndTask { robot, end, answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// The task's record: open tasks, or recently ended ones.
    pub async fn snapshot(&self, task: TaskId) -> Result<Option<TaskSnapshot>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::Snapshot { task, answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// The driver's running totals.
    pub async fn stats(&self) -> Result<DriverStats, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::Stats { answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }
}

/// Tunables of the driver.
#[derive(Clone, Debug)]
pub struct DriverConfig {
    /// How long to wait for a re-fetched observation.
    pub refetch_timeout: Duration,
    /// Ended tasks whose snapshot is kept (for `snapshot` after the end).
    pub ended_snapshots: usize,
    /// Capacity of the command channel.
    pub queue: usize,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig {
            refetch_timeout: Duration::from_millis(50),
            ended_snapshots: 4096,
            queue: 8192,
        }
    }
}

struct Waiter {
    id: WaiterId,
    answer: oneshot::Sender<RoundAnswer>,
}

struct RequestState {
    task: TaskId,
    round: u64,
    /// When its `Submit` frame was read off the stream.
    received: Instant,
    /// When the scheduler accepted it.
    accepted: Instant,
    observation: Option<ValidObservation>,
    policy: Option<RoundPolicy>,
    control_hz: f32,
    waiters: Vec<Waiter>,
    link: mpsc::Sender<RefetchAsk>,
    dispatched: Option<Instant>,
    refetch: Duration,
    batch_size: u32,
}

struct TaskState {
    owner: RobotId,
    clock: ClockMap,
    control_hz: Option<f32>,
    last_reply: Option<Reply>,
    generated: BTreeMap<u64, u32>,
}

struct BatchState {
    dispatch: Dispatch,
    outstanding: usize,
    refetch_started: Instant,
}

struct Driver {
    scheduler: Scheduler,
    pool: EnginePool,
    actions: Arc<ActionManager>,
    clock: Clock,
    config: DriverConfig,
    requests: HashMap<RequestId, RequestState>,
    by_round: HashMap<(TaskId, u64), RequestId>,
    tasks: HashMap<TaskId, TaskState>,
    batches: HashMap<BatchId, BatchState>,
    ended: VecDeque<TaskSnapshot>,
    stats: DriverStats,
    latencies: RecentLatencies,
    draining: bool,
    reports: mpsc::WeakSender<Command>,
}

/// Starts the driver on the current tokio runtime. It runs until `shutdown` resolves (or every
/// handle is dropped) and every accepted round has been answered.
pub fn spawn(
    scheduler: Scheduler,
    pool: EnginePool,
    actions: Arc<ActionManager>,
    config: DriverConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> (DriverHandle, tokio::task::JoinHandle<DriverStats>) {
    let (tx, rx) = mpsc::channel(config.queue.max(1));
    let clock = Clock::start();
    let handle = DriverHandle {
        commands: tx.clone(),
        waiters: Arc::new(AtomicU64::new(0)),
        clock,
    };
    let driver = Driver {
        scheduler,
        pool,
        actions,
        clock,
        config,
        requests: HashMap::new(),
        by_round: HashMap::new(),
        tasks: HashMap::new(),
        batches: HashMap::new(),
        ended: VecDeque::new(),
        stats: DriverStats::default(),
        latencies: RecentLatencies::default(),
        draining: false,
        reports: tx.downgrade(),
    };
    drop(tx);
    let join = tokio::spawn(driver.run(rx, shutdown));
    (handle, join)
}

impl Driver {
    async fn run(
        mut self,
        mut commands: mpsc::Receiver<Command>,
        shutdown: impl Future<Output = ()> + Send,
    ) -> DriverStats {
        let mut shutdown = std::pin::pin!(shutdown);
        loop {
            let deadline = self.scheduler.poll_timeout().map(|t| self.clock.instant(t));
            // Biased: a shutdown signalled before a command was sent is seen first, so that
            // command is refused rather than accepted (with random order it could be either);
            // and due timeouts are not starved by a steady stream of commands.
            tokio::select! {
                biased;
                () = &mut shutdown, if !self.draining => {
                    tracing::info!(pending = self.requests.len(), "driver draining");
                    self.draining = true;
                }
                () = sleep_until(deadline), if deadline.is_some() => {
                    let now = self.clock.now();
                    for task in self.scheduler.handle_timeout(now) {
                        self.forget_task(task);
                    }
                }
                command = commands.recv() => match command {
                    Some(command) => self.handle(command),
                    None => self.draining = true,
                },
            }
            self.account_finished();
            self.dispatch();
            if self.draining && self.requests.is_empty() && self.batches.is_empty() {
                break;
            }
        }
        // Commands that were already queued get their answer (a submit: `shutting_down`).
        commands.close();
        while let Ok(command) = commands.try_recv() {
            self.handle(command);
        }
        self.stats()
    }

    fn stats(&self) -> DriverStats {
        let (overhead, processing) = self.latencies.summaries();
        DriverStats {
            overhead,
            processing,
            ..self.stats
        }
    }

    fn handle(&mut self, command: Command) {
        match command {
            Command::Submit {
                submit,
                received,
                waiter,
                link,
                answer,
            } => self.on_submit(*submit, received, waiter, link, answer),
            Command::Detach {
                task,
                round,
                waiter,
            } => self.on_detach(task, round, waiter),
            Command::EndTask { robot, end, answer } => {
                let _ = answer.send(self.on_end_task(robot, end));
            }
            Command::Snapshot { task, answer } => {
                let _ = answer.send(self.snapshot(task));
            }
            Command::Stats { answer } => {
                let _ = answer.send(self.stats());
            }
            Command::Refetched {
                batch,
                request,
                observation,
            } => self.on_refetched(batch, request, observation),
            Command::BatchDone {
                batch,
                results,
                inference,
            } => self.on_batch_done(batch, results, inference),
        }
    }

    fn on_submit(
        &mut self,
        submit: ValidSubmit,
        received: Instant,
        waiter: WaiterId,
        link: mpsc::Sender<RefetchAsk>,
        answer: oneshot::Sender<RoundAnswer>,
    ) {
        let refuse = |answer: oneshot::Sender<RoundAnswer>, error: RequestError| {
            let _ = answer.send(Err(ErrorReply::from(&error)));
        };
        if self.draining {
            self.stats.refused += 1;
            return refuse(answer, RequestError::ShuttingDown);
        }
        let (task, round, robot) = (submit.round.task, submit.round.round, submit.round.robot);
        if let Some(state) = self.tasks.get(&task)
            && state.owner == robot
            && let Some(reply) = state.last_reply.as_ref().filter(|r| r.round == round)
        {
            self.stats.cached_replies += 1;
            let _ = answer.send(Ok(reply.clone()));
            return;
        }
        let now = self.clock.now();
        match self.scheduler.handle_submit(now, submit.round) {
            Ok(request) => {
                self.stats.accepted += 1;
                let state = self.tasks.entry(task).or_insert_with(|| TaskState {
                    owner: robot,
                    clock: submit.clock,
                    control_hz: None,
                    last_reply: None,
                    generated: BTreeMap::new(),
                });
                state.clock = submit.clock;
                if submit.control_hz.is_some() {
                    state.control_hz = submit.control_hz;
                }
                let control_hz = state.control_hz.unwrap_or(0.0);
                self.by_round.insert((task, round), request);
                self.requests.insert(
                    request,
                    RequestState {
                        task,
                        round,
                        received,
                        accepted: self.clock.instant(now),
                        observation: Some(submit.observation),
                        policy: Some(submit.policy),
                        control_hz,
                        waiters: vec![Waiter { id: waiter, answer }],
                        link,
                        dispatched: None,
                        refetch: Duration::ZERO,
                        batch_size: 0,
                    },
                );
            }
            Err(AdmitError::RoundInProgress { request, .. }) => {
                match self.requests.get_mut(&request) {
                    Some(state) => {
                        self.stats.attached += 1;
                        state.waiters.push(Waiter { id: waiter, answer });
                        // The newest stream is the live one; a re-sent observation is fresher.
                        state.link = link;
                        if state.dispatched.is_none() {
                            state.observation = Some(submit.observation);
                        }
                    }
                    None => refuse(
                        answer,
                        RequestError::Internal(format!(
                            "round {round} is in progress but has no state"
                        )),
                    ),
                }
            }
            Err(error) => {
                self.stats.refused += 1;
                refuse(answer, RequestError::Admit(error));
            }
        }
        for superseded in self.scheduler.take_superseded() {
            self.stats.superseded += 1;
            if let Some(old) = self.remove_request(superseded.request) {
                let error = RequestError::Superseded {
                    round: old.round,
                    by: round,
                };
                answer_all(old.waiters, &Err(ErrorReply::from(&error)));
            }
        }
    }

    fn on_detach(&mut self, task: TaskId, round: u64, waiter: WaiterId) {
        let Some(&request) = self.by_round.get(&(task, round)) else {
            return;
        };
        let Some(state) = self.requests.get_mut(&request) else {
            return;
        };
        state.waiters.retain(|w| w.id != waiter);
        if !state.waiters.is_empty() || state.dispatched.is_some() {
            return;
        }
        let now = self.clock.now();
        if self.scheduler.handle_cancel(now, request) == CancelOutcome::Removed {
            self.stats.cancelled += 1;
            self.remove_request(request);
        }
    }

    fn on_end_task(&mut self, robot: RobotId, end: ValidEndTask) -> Result<TaskEnded, ErrorReply> {
        let now = self.clock.now();
        let mut snapshot = self
            .snapshot(end.task)
            .filter(|s| !s.ended && s.owner == robot);
        let summary = self
            .scheduler
            .handle_task_end(now, end.task, robot, end.end, end.exec)
            .map_err(|e| ErrorReply::from(&RequestError::Admit(e)))?;
        if let Some(request) = summary.open_request
            && self.scheduler.is_pending(request)
        {
            // The scheduler dropped it; nothing will run it.
            if let Some(old) = self.remove_request(request) {
                let error = RequestError::Admit(AdmitError::TaskEnded { task: end.task });
                answer_all(old.waiters, &Err(ErrorReply::from(&error)));
            }
        }
        if let Some(snapshot) = snapshot.as_mut() {
            // The end report closes the last round's execution phase, exactly as the lifecycle
            // computes it.
            if let (Some(exec), Some(last)) = (end.exec, snapshot.history.last_mut())
                && last.execution.is_none()
                && let Ok(interval) = exec_interval(&exec, now)
            {
                last.execution = Some(interval);
            }
            snapshot.clock = end.clock;
        }
        let history = snapshot
            .as_ref()
            .map(TaskSnapshot::wire_history)
            .unwrap_or_default();
        self.forget_task_with(end.task, snapshot);
        Ok(TaskEnded {
            task: end.task.0,
            rounds: summary.rounds,
            wait_us: duration_micros(summary.wait),
            attained_service_us: duration_micros(summary.attained_service),
            history,
        })
    }

    fn snapshot(&self, task: TaskId) -> Option<TaskSnapshot> {
        if let (Some(record), Some(state)) = (self.scheduler.task(task), self.tasks.get(&task)) {
            return Some(TaskSnapshot {
                task,
                owner: record.owner(),
                rounds_completed: record.rounds_completed(),
                history: record.history().copied().collect(),
                clock: state.clock,
                generated: state.generated.clone(),
                ended: false,
            });
        }
        self.ended.iter().rev().find(|s| s.task == task).cloned()
    }

    /// Drops the driver's state of a task the scheduler ended, keeping its last snapshot.
    fn forget_task(&mut self, task: TaskId) {
        let snapshot = self.snapshot(task);
        self.forget_task_with(task, snapshot);
    }

    fn forget_task_with(&mut self, task: TaskId, snapshot: Option<TaskSnapshot>) {
        self.tasks.remove(&task);
        if let Some(mut snapshot) = snapshot {
            snapshot.ended = true;
            if self.ended.len() >= self.config.ended_snapshots.max(1) {
                self.ended.pop_front();
            }
            self.ended.push_back(snapshot);
        }
    }

    /// Counts tasks the scheduler ended and drops their driver state (expired tasks were already
    /// handled; explicit ends too; this catches both without double counting).
    fn account_finished(&mut self) {
        for summary in self.scheduler.take_finished() {
            self.stats.tasks_ended += 1;
            if self.tasks.contains_key(&summary.task) {
                self.forget_task(summary.task);
            }
        }
    }

    fn remove_request(&mut self, request: RequestId) -> Option<RequestState> {
        let state = self.requests.remove(&request)?;
        if self.by_round.get(&(state.task, state.round)) == Some(&request) {
            self.by_round.remove(&(state.task, state.round));
        }
        Some(state)
    }

    fn dispatch(&mut self) {
        let now = self.clock.now();
        let instant = self.clock.instant(now);
        for dispatch in self.scheduler.poll_dispatch(now) {
            let batch = dispatch.batch;
            let mut outstanding = 0;
            for entry in &dispatch.requests {
                let Some(state) = self.requests.get_mut(&entry.request) else {
                    continue;
                };
                state.dispatched = Some(instant);
                state.batch_size = u32::try_from(dispatch.requests.len()).unwrap_or(u32::MAX);
                if !entry.refetch {
                    continue;
                }
                let age = state
                    .observation
                    .as_ref()
                    .map(|o| now.saturating_since(o.captured_at))
                    .unwrap_or_default();
                let (reply, fresh) = oneshot::channel();
                if state.link.try_send(RefetchAsk { age, reply }).is_err() {
                    continue;
                }
                self.stats.refetch_asked += 1;
                outstanding += 1;
                let Some(reports) = self.reports.upgrade() else {
                    continue;
                };
                let request = entry.request;
                let timeout = self.config.refetch_timeout;
                tokio::spawn(async move {
                    let observation = tokio::time::timeout(timeout, fresh)
                        .await
                        .ok()
                        .and_then(Result::ok);
                    let _ = reports
                        .send(Command::Refetched {
                            batch,
                            request,
                            observation,
                        })
                        .await;
                });
            }
            self.batches.insert(
                batch,
                BatchState {
                    dispatch,
                    outstanding,
                    refetch_started: instant,
                },
            );
            if outstanding == 0 {
                self.start_batch(batch);
            }
        }
    }

    fn on_refetched(
        &mut self,
        batch: BatchId,
        request: RequestId,
        observation: Option<ValidObservation>,
    ) {
        let Some(state) = self.batches.get_mut(&batch) else {
            return;
        };
        let waited = state.refetch_started.elapsed();
        state.outstanding = state.outstanding.saturating_sub(1);
        let ready = state.outstanding == 0;
        if let Some(req) = self.requests.get_mut(&request) {
            req.refetch = waited;
            if let (Some(fresh), Some(queued)) = (observation, req.observation.as_mut()) {
                self.stats.refetch_used += 1;
                let (samples, seed) = (queued.request.samples, queued.request.seed);
                *queued = fresh;
                queued.request.samples = samples;
                queued.request.seed = seed;
            }
        }
        if ready {
            self.start_batch(batch);
        }
    }

    fn start_batch(&mut self, batch: BatchId) {
        let Some(state) = self.batches.get(&batch) else {
            return;
        };
        let now = self.clock.now();
        self.scheduler.handle_batch_started(now, batch);
        self.stats.batches += 1;
        let mut inputs = Vec::with_capacity(state.dispatch.requests.len());
        let mut rounds = Vec::with_capacity(state.dispatch.requests.len());
        let mut missing = Vec::new();
        for entry in &state.dispatch.requests {
            let record = self.scheduler.task(entry.task);
            let round_index = record.map(|r| u64::from(r.rounds_completed())).unwrap_or(0);
            let recent: Vec<u32> = record
                .map(|r| r.recent_horizons().to_vec())
                .unwrap_or_default();
            let Some(req) = self.requests.get_mut(&entry.request) else {
                missing.push(entry.request);
                continue;
            };
            let (Some(observation), Some(policy)) = (req.observation.take(), req.policy.take())
            else {
                missing.push(entry.request);
                continue;
            };
            inputs.push(observation.request);
            rounds.push(BatchRound {
                request: entry.request,
                task: req.task.0,
                round: req.round,
                policy,
                control_hz: req.control_hz,
                round_index,
                recent,
            });
        }
        let engine = self.pool.get(state.dispatch.engine).cloned();
        let (Some(engine), Some(reports)) = (engine, self.reports.upgrade()) else {
            let results = rounds
                .iter()
                .map(|r| r.request)
                .chain(missing)
                .map(|r| {
                    let error = RequestError::Internal("no engine instance for the batch".into());
                    (r, Err(ErrorReply::from(&error)))
                })
                .collect();
            self.on_batch_done(batch, results, Duration::ZERO);
            return;
        };
        let actions = self.actions.clone();
        tokio::spawn(async move {
            let started = Instant::now();
            let outcome = engine.run(inputs).await;
            let inference = started.elapsed();
            let mut results: Vec<(RequestId, Result<Reply, ErrorReply>)> = match outcome {
                Ok(chunks) => rounds
                    .into_iter()
                    .zip(chunks)
                    .map(|(mut round, chunk)| {
                        let context = RoundContext {
                            control_hz: round.control_hz,
                            round_index: round.round_index,
                            recent_horizons: &round.recent,
                        };
                        let result = match chunk {
                            Ok(chunk) => actions
                                .choose(&mut round.policy, &chunk, context)
                                .map(|choice| build_reply(round.task, round.round, &chunk, &choice))
                                .map_err(|e| {
                                    ErrorReply::from(&RequestError::Internal(e.to_string()))
                                }),
                            // The engine failed this request alone; the batch's others go on.
                            Err(error) => Err(ErrorReply::from(&RequestError::Engine(error))),
                        };
                        (round.request, result)
                    })
                    .collect(),
                Err(error) => {
                    tracing::error!(%error, "batch failed");
                    let reply = ErrorReply::from(&RequestError::Engine(error));
                    rounds
                        .into_iter()
                        .map(|r| (r.request, Err(reply.clone())))
                        .collect()
                }
            };
            results.extend(missing.into_iter().map(|r| {
                let error = RequestError::Internal("the round's observation was lost".into());
                (r, Err(ErrorReply::from(&error)))
            }));
            let _ = reports
                .send(Command::BatchDone {
                    batch,
                    results,
                    inference,
                })
                .await;
        });
    }

    fn on_batch_done(
        &mut self,
        batch: BatchId,
        results: Vec<(RequestId, Result<Reply, ErrorReply>)>,
        inference: Duration,
    ) {
        self.batches.remove(&batch);
        let now = self.clock.now();
        let outcomes: Vec<(RequestId, RoundOutcome)> = results
            .iter()
            .map(|(request, result)| {
                let outcome = match result {
                    Ok(reply) => RoundOutcome::Answered {
                        horizon: reply.horizon,
                    },
                    Err(_) => RoundOutcome::Failed,
                };
                (*request, outcome)
            })
            .collect();
        self.scheduler.handle_batch_finished(now, batch, &outcomes);
        let sent_at = self.clock.instant(now);
        for (request, result) in results {
            let Some(state) = self.remove_request(request) else {
                continue;
            };
            let dispatched = state.dispatched.unwrap_or(state.accepted);
            let answer = result.map(|mut reply| {
                reply.timing = Timing {
                    queue_us: micros(dispatched.saturating_duration_since(state.received)),
                    refetch_us: micros(state.refetch),
                    inference_us: micros(inference),
                    total_us: micros(sent_at.saturating_duration_since(state.received)),
                    batch_size: state.batch_size,
                };
                reply
            });
            match &answer {
                Ok(reply) => {
                    self.stats.replies += 1;
                    // The server's own work: reading to acceptance, and dispatch to reply, less
                    // the re-fetch wait and the forward pass.
                    let own = state.accepted.saturating_duration_since(state.received)
                        + sent_at
                            .saturating_duration_since(dispatched)
                            .saturating_sub(state.refetch)
                            .saturating_sub(inference);
                    self.latencies.record(&reply.timing, micros(own));
                    if let Some(task) = self.tasks.get_mut(&state.task) {
                        *task.generated.entry(state.round).or_insert(0) += 1;
                        let keep = self.scheduler.config().history_rounds.max(1);
                        while task.generated.len() > keep {
                            task.generated.pop_first();
                        }
                        let newer = task
                            .last_reply
                            .as_ref()
                            .is_some_and(|r| r.round > state.round);
                        if !newer {
                            task.last_reply = Some(reply.clone());
                        }
                    }
                }
                Err(_) => self.stats.failed += 1,
            }
            answer_all(state.waiters, &answer);
        }
    }
}

/// What the batch task needs of each round to run the action manager.
struct BatchRound {
    request: RequestId,
    task: u64,
    round: u64,
    policy: RoundPolicy,
    control_hz: f32,
    round_index: u64,
    recent: Vec<u32>,
}

fn answer_all(waiters: Vec<Waiter>, answer: &RoundAnswer) {
    for waiter in waiters {
        let _ = waiter.answer.send(answer.clone());
    }
}

fn micros(d: Duration) -> u64 {
    duration_micros(d)
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline.into()).await,
        None => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineError, ModelSpec};
    use kairos_sdk::protocol::{
        EndTask, ErrorCode, LastExecInfo, Limits, Observation, Submit, TaskOutcome, Tensor,
    };

    use super::*;
    use crate::pool::test_model::LinearFlow;
    use crate::pool::{EngineInstance, LocalEngine};
    use crate::registry::native_horizon_policies;
    use crate::scheduler::SchedulerConfig;
    use crate::scheduler::fifo::Fifo;
    use crate::validation::Validator;

    /// LinearFlow that blocks each batch until the test lets it through.
    struct Gated {
        inner: LinearFlow,
        gate: Mutex<std::sync::mpsc::Receiver<()>>,
    }

    impl ActionModel for Gated {
        fn spec(&self) -> &ModelSpec {
            &self.inner.spec
        }
        fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
            if let Ok(gate) = self.gate.lock() {
                let _ = gate.recv();
            }
            self.inner.generate(batch)
        }
    }

    struct Fixture {
        driver: DriverHandle,
        join: tokio::task::JoinHandle<DriverStats>,
        stop: Option<oneshot::Sender<()>>,
        gate: std::sync::mpsc::Sender<()>,
        validator: Validator,
        actions: Arc<ActionManager>,
        /// The simulated robot's clock: 1 s ahead of the driver's, so the mapping is exercised.
        client_clock: ClockMap,
    }

    fn fixture(stale_after: Duration) -> Fixture {
        let (gate, gate_rx) = std::sync::mpsc::channel();
        let model = Gated {
            inner: LinearFlow::new(),
            gate: Mutex::new(gate_rx),
        };
        let spec = model.inner.spec.clone();
        let profile = kairos_engine::EngineProfile {
            model: spec.name.clone(),
            device: "cpu".into(),
            points: vec![kairos_engine::ProfilePoint {
                batch: 1,
                latency_ms: 1.0,
            }],
            max_batch: 1,
        };
        let engine: Arc<dyn EngineInstance> =
            Arc::new(LocalEngine::start("gated", Arc::new(model), profile));
        let pool = EnginePool::new(vec![engine]).unwrap();
        let config = SchedulerConfig {
            stale_after,
            ..SchedulerConfig::default()
        };
        let scheduler = Scheduler::new(config, pool.specs(), Box::new(Fifo::default()));
        let natives = native_horizon_policies();
        let actions = Arc::new(
            ActionManager::new(
                natives.clone(),
                &natives,
                "static",
                [("h".to_string(), 3.0)].into(),
            )
            .unwrap(),
        );
        let (stop, stop_rx) = oneshot::channel::<()>();
        let (driver, join) = spawn(
            scheduler,
            pool,
            actions.clone(),
            DriverConfig {
                refetch_timeout: Duration::from_millis(200),
                ..DriverConfig::default()
            },
            async move {
                let _ = stop_rx.await;
            },
        );
        let client_clock = ClockMap::new(driver.clock().now(), 1_000_000, Duration::ZERO);
        Fixture {
            client_clock,
            driver,
            join,
            stop: Some(stop),
            gate,
            validator: Validator {
                spec,
                limits: Limits::default(),
            },
            actions,
        }
    }

    fn wire_submit(
        f: &Fixture,
        task: u64,
        round: u64,
        state0: f32,
        last_exec: Option<LastExecInfo>,
    ) -> Submit {
        let now = f.client_now();
        Submit {
            task,
            round,
            sent_at_us: now,
            observation: Observation {
                captured_at_us: now,
                state: Tensor::from_f32(vec![3], &[state0, 0.0, 0.0]).unwrap(),
                images: Vec::new(),
                instruction: String::new(),
            },
            last_exec,
            horizon: None,
            remaining: None,
            attempt: 0,
        }
    }

    impl Fixture {
        fn client_now(&self) -> u64 {
            self.client_clock.to_client(self.driver.clock().now())
        }

        async fn submit(
            &self,
            robot: u32,
            submit: Submit,
        ) -> (PendingRound, mpsc::Receiver<RefetchAsk>) {
            let valid = self
                .validator
                .submit(submit, RobotId(robot), &self.actions, self.client_clock)
                .unwrap();
            let (link, asks) = mpsc::channel(1);
            (
                self.driver
                    .submit(valid, Instant::now(), link)
                    .await
                    .unwrap(),
                asks,
            )
        }

        fn open(&self, n: usize) {
            for _ in 0..n {
                self.gate.send(()).unwrap();
            }
        }

        async fn end(&self, robot: u32, task: u64) -> Result<TaskEnded, ErrorReply> {
            let now = self.client_now();
            let end = EndTask {
                task,
                outcome: TaskOutcome::Done,
                sent_at_us: now,
                last_exec: Some(LastExecInfo {
                    exec_started_at_us: now,
                    actions_remaining: 0,
                    control_hz: 10.0,
                }),
            };
            let valid = self.validator.end_task(end, self.client_clock).unwrap();
            self.driver.end_task(RobotId(robot), valid).await.unwrap()
        }
    }

    #[test]
    fn latency_summary_uses_nearest_rank() {
        let s = LatencySummary::of((1..=200).rev());
        assert_eq!(
            (s.count, s.p50_us, s.p99_us, s.max_us),
            (200, 100, 198, 200)
        );
        assert_eq!(
            LatencySummary::of(std::iter::empty()),
            LatencySummary::default()
        );
    }

    #[tokio::test]
    async fn rounds_are_answered_and_a_resent_finished_round_gets_the_cached_reply() {
        let f = fixture(Duration::from_secs(10));
        f.open(1);
        let (round, _asks) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        let reply = round.answer.await.unwrap().unwrap();
        assert_eq!((reply.task, reply.round, reply.horizon), (1, 0, 3));
        assert_eq!(reply.policy, "static");
        assert_eq!(reply.actions.shape, vec![3, 2]);
        assert_eq!(reply.timing.batch_size, 1);
        assert!(reply.timing.total_us >= reply.timing.inference_us);

        let (again, _asks) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        assert_eq!(again.answer.await.unwrap().unwrap(), reply);
        let stats = f.driver.stats().await.unwrap();
        assert_eq!((stats.replies, stats.cached_replies), (1, 1));
        let snapshot = f.driver.snapshot(TaskId(1)).await.unwrap().unwrap();
        assert_eq!(snapshot.generated.get(&0), Some(&1));
        assert_eq!(snapshot.rounds_completed, 1);
    }

    #[tokio::test]
    async fn a_round_resent_while_queued_attaches_and_is_generated_once() {
        let f = fixture(Duration::from_secs(10));
        // Task 1 occupies the only engine; task 2's round waits.
        let (busy, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        let (first, _b) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
        let (second, _c) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
        f.open(2);
        busy.answer.await.unwrap().unwrap();
        let a = first.answer.await.unwrap().unwrap();
        let b = second.answer.await.unwrap().unwrap();
        assert_eq!(a, b);
        let stats = f.driver.stats().await.unwrap();
        assert_eq!(stats.attached, 1);
        assert_eq!(stats.replies, 2, "one generation per round");
    }

    #[tokio::test]
    async fn detaching_the_last_waiter_withdraws_a_queued_round() {
        let f = fixture(Duration::from_secs(10));
        let (busy, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        let (queued, _b) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
        f.driver.detach(&queued).await;
        assert_eq!(f.driver.stats().await.unwrap().cancelled, 1);
        // The robot may send the same round again after a withdrawal.
        let (again, _c) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
        f.open(2);
        busy.answer.await.unwrap().unwrap();
        assert_eq!(again.answer.await.unwrap().unwrap().round, 0);
    }

    #[tokio::test]
    async fn another_robot_can_neither_advance_nor_read_a_task() {
        let f = fixture(Duration::from_secs(10));
        f.open(1);
        let (own, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        own.answer.await.unwrap().unwrap();
        // Robot 1 re-sends robot 0's finished round: no cached reply for it.
        // Another robot's task is answered like an unknown one (validation.rs).
        let (read, _b) = f.submit(1, wire_submit(&f, 1, 0, 1.0, None)).await;
        assert_eq!(
            read.answer.await.unwrap().unwrap_err().code,
            ErrorCode::UnknownTask
        );
        let (advance, _c) = f.submit(1, wire_submit(&f, 1, 1, 1.0, None)).await;
        assert_eq!(
            advance.answer.await.unwrap().unwrap_err().code,
            ErrorCode::UnknownTask
        );
        assert_eq!(f.end(1, 1).await.unwrap_err().code, ErrorCode::UnknownTask);
        assert_eq!(f.end(0, 1).await.unwrap().rounds, 1);
    }

    #[tokio::test]
    async fn task_end_returns_the_history_and_later_rounds_are_refused() {
        let f = fixture(Duration::from_secs(10));
        f.open(2);
        let (r0, _a) = f.submit(0, wire_submit(&f, 7, 0, 1.0, None)).await;
        r0.answer.await.unwrap().unwrap();
        let exec_start = f.client_now();
        let exec = LastExecInfo {
            exec_started_at_us: exec_start,
            actions_remaining: 1,
            control_hz: 10.0,
        };
        let submit1 = wire_submit(&f, 7, 1, 1.0, Some(exec));
        let sent1 = submit1.sent_at_us;
        let (r1, _b) = f.submit(0, submit1).await;
        r1.answer.await.unwrap().unwrap();
        let ended = f.end(0, 7).await.unwrap();
        assert_eq!(ended.rounds, 2);
        assert_eq!(ended.history.len(), 2);
        assert!(ended.history.iter().all(|r| r.generation.is_some()));
        let first_exec = ended.history[0].execution.unwrap();
        assert_eq!(
            first_exec.start_us, exec_start,
            "E_0 maps back to the robot's clock"
        );
        assert_eq!(
            first_exec.end_us - sent1,
            100_000,
            "E_0 ends one action (100 ms at 10 Hz) after round 1 was sent"
        );
        assert!(
            ended.history[1].execution.is_some(),
            "the end report closes E_1"
        );
        let (late, _c) = f.submit(0, wire_submit(&f, 7, 2, 1.0, None)).await;
        assert_eq!(
            late.answer.await.unwrap().unwrap_err().code,
            ErrorCode::UnknownTask
        );
        let snapshot = f.driver.snapshot(TaskId(7)).await.unwrap().unwrap();
        assert!(snapshot.ended);
        assert_eq!(snapshot.history.len(), 2);
    }

    #[tokio::test]
    async fn stale_observations_are_refetched_through_the_round_link() {
        let f = fixture(Duration::ZERO);
        f.open(2);
        let (round, mut asks) = f.submit(0, wire_submit(&f, 3, 0, 1.0, None)).await;
        let ask = asks.recv().await.unwrap();
        let now = f.client_now();
        let fresh = kairos_sdk::protocol::FreshObservation {
            sent_at_us: now,
            observation: Observation {
                captured_at_us: now,
                state: Tensor::from_f32(vec![3], &[50.0, 0.0, 0.0]).unwrap(),
                images: Vec::new(),
                instruction: String::new(),
            },
        };
        let valid = f.validator.fresh(fresh, f.client_clock).unwrap();
        ask.reply.send(valid).unwrap();
        let reply = round.answer.await.unwrap().unwrap();
        // LinearFlow pulls actions towards state[0]: 50 now, not 1.
        let actions = reply.actions.to_f32().unwrap();
        assert!(actions[0] > 10.0, "{actions:?}");
        assert!(reply.timing.refetch_us > 0);

        // A client that never answers: the queued observation is used after the deadline.
        let (round, mut asks) = f.submit(0, wire_submit(&f, 3, 1, 1.0, None)).await;
        let _ignored = asks.recv().await.unwrap();
        let reply = round.answer.await.unwrap().unwrap();
        assert!(reply.timing.refetch_us >= 200_000);
        let stats = f.driver.stats().await.unwrap();
        assert_eq!((stats.refetch_asked, stats.refetch_used), (2, 1));
    }

    #[tokio::test]
    async fn shutdown_answers_accepted_rounds_and_refuses_new_ones() {
        let mut f = fixture(Duration::from_secs(10));
        let (running, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
        let (queued, _b) = f.submit(0, wire_submit(&f, 2, 0, 1.0, None)).await;
        // A round trip through the driver: both rounds are accepted before the shutdown.
        assert_eq!(f.driver.stats().await.unwrap().accepted, 2);
        f.stop.take().unwrap().send(()).unwrap();
        let (late, _c) = f.submit(0, wire_submit(&f, 3, 0, 1.0, None)).await;
        assert_eq!(
            late.answer.await.unwrap().unwrap_err().code,
            ErrorCode::ShuttingDown
        );
        f.open(2);
        assert!(running.answer.await.unwrap().is_ok());
        assert!(queued.answer.await.unwrap().is_ok());
        let stats = f.join.await.unwrap();
        assert_eq!(stats.replies, 2);
        assert_eq!(stats.overhead.count, 2);
        assert!(stats.overhead.p50_us <= stats.overhead.p99_us);
        assert!(stats.processing.max_us <= stats.overhead.max_us);
    }
}
