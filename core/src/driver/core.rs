//! The driver's state machine: the [`Scheduler`] plus what the server must remember around it,
//! driven by events that carry `now` and answered with [`Effect`]s. No I/O, no clock, no async,
//! no policy call of its own beyond the scheduler's priority policy (quinn-proto style).
//!
//! Each fact has one owner. A task's owner, its G/E history and whether it has ended belong to
//! the scheduler's lifecycle record ([`crate::lifecycle::TaskRecord`]); the core only reads them.
//! The core owns what the scheduler does not know: the observation, horizon policy and waiting
//! streams of each request, each open task's clock mapping, last reply and generation counts,
//! the snapshots of ended tasks, and the statistics.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::time::Duration;

use kairos_engine_types::ActionRequest;
use kairos_protocol::{ErrorReply, Reply, TaskEnded, Timing};

use super::stats::{
    DriverReport, DriverStats, EngineReport, EngineState, Histogram, RecentLatencies,
};
use super::{RoundAnswer, TaskSnapshot, WaiterId};
use crate::action::{HorizonJob, RoundPolicy};
use crate::chunking::{
    DelayErrorStats, DelayInputs, DurationAverage, NetworkEstimate, PreviousChunk, RoundChunking,
    RoundPlan, actual_delay_from_times, plan_round, predict_delay,
};
use crate::clock_map::ClockMap;
use crate::error::{LossReason, RoundError};
use crate::lifecycle::exec_interval;
use crate::round::{ValidEndTask, ValidObservation, ValidSubmit};
use crate::scheduler::{
    AdmitError, BatchId, CancelOutcome, Dispatch, EngineId, EngineSpec, ExecReport, RequestId,
    RobotId, RoundOutcome, Scheduler, ServerLoad, TaskId,
};
use crate::time::{Timestamp, duration_micros};

/// What the shell carries out for the core.
#[derive(Debug)]
pub enum Effect {
    /// Send `answer` to every stream in `waiters`; they wait for nothing else.
    Answer {
        /// The streams waiting for the round.
        waiters: Vec<WaiterId>,
        /// The reply or the error.
        answer: RoundAnswer,
    },
    /// Ask the stream of `waiter` for a fresh observation of `request` (a `FetchObservation`) and
    /// report what came back, or `None`, with [`DriverCore::refetched`].
    Refetch {
        /// The batch waiting for it.
        batch: BatchId,
        /// The request whose observation is stale.
        request: RequestId,
        /// The stream to ask (the newest one waiting for the round).
        waiter: WaiterId,
        /// How old the queued observation is.
        age: Duration,
    },
    /// Run a batch: its forward pass on the engine instance, then
    /// [`DriverCore::generation_ended`], then the horizon policies (blocking: off the async
    /// runtime), then [`DriverCore::batch_done`] with one answer per round.
    RunBatch(BatchJob),
    /// Call [`DriverCore::timeout`] at this time; `None`: no timer. Replaces the previous one.
    SetTimer(Option<Timestamp>),
}

/// What happens to a round whose batch was lost with its engine (pure: time is an argument).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RedispatchRule {
    /// Dispatches a round may get in all, the first included.
    pub max_attempts: u32,
    /// A round that arrived longer ago than this is not run again.
    pub within: Duration,
}

/// The verdict of [`RedispatchRule::decide`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Redispatch {
    /// Back to the front of the queue (its original arrival time), to run again.
    Again,
    /// Failed now with a retryable error: it ran `attempts` times already.
    OutOfAttempts,
    /// Failed now with a retryable error: it can no longer be served in time.
    TooLate,
}

impl Default for RedispatchRule {
    fn default() -> Self {
        RedispatchRule {
            max_attempts: 3,
            within: Duration::from_secs(10),
        }
    }
}

impl RedispatchRule {
    /// The verdict for a round received at `received` and dispatched `attempts` times, lost at
    /// `now`.
    pub fn decide(&self, now: Timestamp, received: Timestamp, attempts: u32) -> Redispatch {
        if attempts >= self.max_attempts {
            Redispatch::OutOfAttempts
        } else if now.saturating_since(received) > self.within {
            Redispatch::TooLate
        } else {
            Redispatch::Again
        }
    }
}

/// A batch to run.
#[derive(Debug)]
pub struct BatchJob {
    /// The batch.
    pub batch: BatchId,
    /// The engine instance the scheduler placed it on.
    pub engine: EngineId,
    /// Earlier dispatches of its rounds (the most of any): 0 unless some ran in a lost batch.
    pub attempt: u32,
    /// The model inputs, in the order of `rounds`.
    pub inputs: Vec<ActionRequest>,
    /// Each round's horizon policy and context.
    pub rounds: Vec<HorizonJob>,
}

/// What the chunking strategies need to know about the served model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChunkingModel {
    /// Values per action the robot receives.
    pub action_dim: usize,
    /// What the model's actions are (whether a state can be rolled forward through them).
    pub action_space: kairos_engine_types::ActionSpace,
}

/// What the core counts per engine instance beside the scheduler's own state.
#[derive(Clone, Copy, Debug, Default)]
struct EngineFacts {
    busy_time: Duration,
    rtt: Option<Duration>,
}

/// A request the scheduler accepted and has not answered.
struct RequestState {
    task: TaskId,
    round: u64,
    /// When its `Submit` frame was read off the stream.
    received: Timestamp,
    /// When the scheduler accepted it.
    accepted: Timestamp,
    /// Until the batch starts.
    observation: Option<ValidObservation>,
    /// Until the batch starts.
    policy: Option<RoundPolicy>,
    control_hz: f32,
    /// Streams waiting for the round, oldest first (more than one after reconnects).
    waiters: Vec<WaiterId>,
    dispatched: Option<Timestamp>,
    refetch: Duration,
    batch_size: u32,
    /// Times the round was placed in a batch.
    attempts: u32,
    /// When the observation handed to the engine was captured (kept to put it back if the
    /// batch is lost).
    captured_at: Timestamp,
    /// When its `Submit` was sent (server clock): the instant `exec` describes.
    sent_at: Timestamp,
    /// The robot's execution phase when it sent the round.
    exec: Option<ExecReport>,
    /// The round whose chunk the robot executes (`None`: not said).
    exec_round: Option<u64>,
    /// The round's chunking strategy.
    chunking: RoundChunking,
    /// Its plan, made when its batch starts.
    plan: Option<RoundPlan>,
    /// The observed state, kept while the engine plans from another one (to put it back if
    /// the batch is lost).
    observed_state: Option<Vec<f32>>,
}

/// What the core keeps of an open task beyond the scheduler's record.
struct TaskFacts {
    clock: ClockMap,
    control_hz: Option<f32>,
    last_reply: Option<Reply>,
    generated: BTreeMap<u64, u32>,
    /// The one-way network time to the robot.
    network: NetworkEstimate,
    /// The last answered round's predicted `d`, until the robot's next Last Exec Info says
    /// what it was: (round, predicted `d`, capture time).
    predicted: Option<(u64, u32, Timestamp)>,
    /// Predicted against actual `d`.
    delay_errors: DelayErrorStats,
}

struct BatchState {
    dispatch: Dispatch,
    /// Re-fetches not yet reported.
    outstanding: usize,
    refetch_started: Timestamp,
    inference: Duration,
    /// Requests of the batch that could not be given to the engine.
    missing: Vec<RequestId>,
    /// When its forward pass ended.
    generation_end: Option<Timestamp>,
}

/// The driver's state machine.
pub struct DriverCore {
    scheduler: Scheduler,
    ended_snapshots: usize,
    requests: HashMap<RequestId, RequestState>,
    tasks: HashMap<TaskId, TaskFacts>,
    batches: HashMap<BatchId, BatchState>,
    ended: VecDeque<TaskSnapshot>,
    stats: DriverStats,
    latencies: RecentLatencies,
    /// Per engine instance the scheduler still knows (ids are never reused): time spent in
    /// forward passes, and a remote worker's measured round trip. Pruned with the scheduler's
    /// records ([`DriverCore::forget_departed_engines`]), so registrations do not pile up here.
    engine_facts: BTreeMap<EngineId, EngineFacts>,
    draining: bool,
    redispatch: RedispatchRule,
    /// The timer last asked of the shell.
    timer: Option<Timestamp>,
    /// The latest `now` seen: events' times never go backwards inside the core.
    now: Timestamp,
    effects: VecDeque<Effect>,
    /// The served model, as the chunking strategies see it.
    chunking_model: ChunkingModel,
    /// The server's own time from the end of a batch's generation to its answers.
    reply_overhead: DurationAverage,
}

impl std::fmt::Debug for DriverCore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DriverCore")
            .field("scheduler", &self.scheduler)
            .field("requests", &self.requests.len())
            .field("batches", &self.batches.len())
            .field("draining", &self.draining)
            .finish()
    }
}

impl DriverCore {
    /// A core around `scheduler`, keeping the snapshots of the last `ended_snapshots` ended tasks.
    pub fn new(scheduler: Scheduler, ended_snapshots: usize) -> DriverCore {
        DriverCore {
            scheduler,
            ended_snapshots: ended_snapshots.max(1),
            requests: HashMap::new(),
            tasks: HashMap::new(),
            batches: HashMap::new(),
            ended: VecDeque::new(),
            stats: DriverStats {
                round_latency: Histogram::round_latency(),
                batch_size: Histogram::batch_size(),
                horizon: Histogram::horizon(),
                delay_predicted: Histogram::delay_steps(),
                delay_error: Histogram::delay_error(),
                ..DriverStats::default()
            },
            latencies: RecentLatencies::default(),
            engine_facts: BTreeMap::new(),
            draining: false,
            redispatch: RedispatchRule::default(),
            timer: None,
            now: Timestamp::ZERO,
            effects: VecDeque::new(),
            chunking_model: ChunkingModel::default(),
            reply_overhead: DurationAverage::default(),
        }
    }

    /// Sets what the chunking strategies know of the served model (its action width and
    /// action space); without it no state is rolled forward.
    pub fn set_chunking_model(&mut self, model: ChunkingModel) {
        self.chunking_model = model;
    }

    /// Sets what happens to rounds lost with a remote engine.
    pub fn set_redispatch_rule(&mut self, rule: RedispatchRule) {
        self.redispatch = rule;
    }

    /// A new engine instance (a remote worker that registered) joins; pending rounds may be
    /// placed on it at once. Returns its id, the next one (the shell adds the instance to its
    /// pool under the same id).
    pub fn add_engine(&mut self, now: Timestamp, spec: EngineSpec) -> EngineId {
        let now = self.advance(now);
        let id = self.scheduler.add_engine(spec);
        self.after_event(now);
        id
    }

    /// The instance leaves the pool (draining, or gone): no new batch is placed on it. A batch it
    /// runs ends through [`DriverCore::batch_done`] or [`DriverCore::batch_lost`].
    pub fn remove_engine(&mut self, now: Timestamp, engine: EngineId) {
        let now = self.advance(now);
        self.scheduler.remove_engine(engine);
        self.after_event(now);
    }

    /// A remote instance's measured round trip changed, and with it perhaps its tier (a worker
    /// registered as `auto`): the scheduler plans with them from now.
    pub fn engine_link(&mut self, engine: EngineId, rtt: Duration, tier: crate::scheduler::Tier) {
        self.scheduler.set_engine_rtt(engine, rtt);
        let retiered = self.scheduler.set_engine_tier(engine, tier);
        if let Some(facts) = self.engine_facts_mut(engine) {
            facts.rtt = Some(rtt);
        }
        if let Some(state) = self.scheduler.engine(engine)
            && retiered
        {
            tracing::info!(engine = %state.spec.name, ?tier, ?rtt, "worker re-classified");
        }
    }

    /// The batch was lost with its engine (connection lost, stream reset, deadline passed)
    /// before it answered; `inputs` and `rounds` are its [`BatchJob`]'s, given back. The engine
    /// leaves the pool; each round of the batch still wanted goes back to the front of the queue
    /// with its original arrival time ([`RedispatchRule::decide`]: unless it ran out of attempts
    /// or time, then it fails with a retryable error). A result of the lost batch that arrives
    /// later is dropped: the batch is no longer known. Every round still gets exactly one answer.
    pub fn batch_lost(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        reason: LossReason,
        inputs: Vec<ActionRequest>,
        rounds: Vec<HorizonJob>,
    ) {
        let now = self.advance(now);
        if let Some(state) = self.batches.remove(&batch) {
            let engine = self
                .scheduler
                .engine(state.dispatch.engine)
                .map(|e| e.spec.name.clone())
                .unwrap_or_default();
            for (mut input, job) in inputs.into_iter().zip(rounds) {
                if let Some(req) = self.requests.get_mut(&job.request) {
                    // The round is planned again when it runs again.
                    if let Some(state) = req.observed_state.take() {
                        input.state = state;
                    }
                    input.guidance = None;
                    req.plan = None;
                    req.observation = Some(ValidObservation {
                        captured_at: req.captured_at,
                        request: input,
                    });
                    req.policy = Some(job.policy);
                }
            }
            let requeued = self.scheduler.requeue_batch(now, batch);
            for entry in &state.dispatch.requests {
                let Some(req) = self.requests.get_mut(&entry.request) else {
                    continue;
                };
                req.dispatched = None;
                req.refetch = Duration::ZERO;
                let verdict = if requeued.contains(&entry.request) {
                    self.redispatch.decide(now, req.received, req.attempts)
                } else {
                    // Its task moved on while it ran: nothing to run again.
                    Redispatch::TooLate
                };
                if verdict == Redispatch::Again && req.observation.is_some() {
                    self.stats.redispatched.count(reason);
                    continue;
                }
                self.scheduler.fail_pending(now, entry.request);
                self.stats.redispatch_given_up += 1;
                self.stats.failed += 1;
                if let Some(old) = self.requests.remove(&entry.request) {
                    let error = RoundError::Lost {
                        engine: engine.clone(),
                        reason,
                        detail: format!(
                            "the round was not run again ({verdict:?} after {} attempts)",
                            old.attempts
                        ),
                    };
                    self.answer(old.waiters, Err(ErrorReply::from(&error)));
                }
            }
        }
        self.after_event(now);
    }

    /// The next effect to carry out, oldest first.
    pub fn poll_effect(&mut self) -> Option<Effect> {
        self.effects.pop_front()
    }

    /// The scheduler, read-only.
    pub fn scheduler(&self) -> &Scheduler {
        &self.scheduler
    }

    /// Whether the core is draining and has nothing left to answer: the shell may stop.
    pub fn is_done(&self) -> bool {
        self.draining && self.requests.is_empty() && self.batches.is_empty()
    }

    /// A validated round from the stream `waiter`, whose `Submit` frame was read at `received`.
    /// Accepted, attached to the request already carrying the round, answered from the reply
    /// cache, or refused.
    pub fn submit(
        &mut self,
        now: Timestamp,
        submit: ValidSubmit,
        received: Timestamp,
        waiter: WaiterId,
    ) {
        let now = self.advance(now);
        self.on_submit(now, submit, received, waiter);
        self.after_event(now);
    }

    /// The stream `waiter` no longer waits for round `round` of `task`. If no stream is left and
    /// the round is still queued, it is withdrawn (the robot may send it again).
    pub fn detach(&mut self, now: Timestamp, task: TaskId, round: u64, waiter: WaiterId) {
        let now = self.advance(now);
        let current = self
            .scheduler
            .task(task)
            .and_then(|record| record.current_request())
            .filter(|&(_, current_round)| current_round == round);
        if let Some((request, _)) = current
            && let Some(state) = self.requests.get_mut(&request)
        {
            state.waiters.retain(|w| *w != waiter);
            if state.waiters.is_empty()
                && state.dispatched.is_none()
                && self.scheduler.handle_cancel(now, request) == CancelOutcome::Removed
            {
                self.stats.cancelled += 1;
                self.requests.remove(&request);
            }
        }
        self.after_event(now);
    }

    /// Ends a task on behalf of `robot`.
    pub fn end_task(
        &mut self,
        now: Timestamp,
        robot: RobotId,
        end: ValidEndTask,
    ) -> Result<TaskEnded, ErrorReply> {
        let now = self.advance(now);
        let ended = self.on_end_task(now, robot, end);
        self.after_event(now);
        ended
    }

    /// The answer to an [`Effect::Refetch`]: the fresh observation, or `None` (no answer in time,
    /// a refused one, or no stream to ask).
    pub fn refetched(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        request: RequestId,
        observation: Option<ValidObservation>,
    ) {
        let now = self.advance(now);
        if let Some(state) = self.batches.get_mut(&batch) {
            let waited = now.saturating_since(state.refetch_started);
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
                self.start_batch(now, batch);
            }
        }
        self.after_event(now);
    }

    /// The batch's forward pass ended (`G.end`) after `inference`: its engine instance may take
    /// the next batch while the horizon policies run. Returns the server's load at that instant,
    /// before the next dispatch decision: what the batch's horizon policies see.
    pub fn generation_ended(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        inference: Duration,
    ) -> ServerLoad {
        let now = self.advance(now);
        if let Some(state) = self.batches.get_mut(&batch) {
            state.inference = inference;
            state.generation_end = Some(now);
            let engine = state.dispatch.engine;
            if let Some(facts) = self.engine_facts_mut(engine) {
                facts.busy_time += inference;
            }
            self.scheduler.handle_generation_ended(now, batch);
        }
        let load = self.scheduler.load(now);
        self.after_event(now);
        load
    }

    /// The batch's answers, one per round given in its [`BatchJob`]: each goes to every stream
    /// waiting for its round, with its timing.
    pub fn batch_done(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        results: Vec<(RequestId, RoundAnswer)>,
    ) {
        let now = self.advance(now);
        if let Some(state) = self.batches.remove(&batch) {
            if let Some(end) = state.generation_end {
                self.reply_overhead.observe(now.saturating_since(end));
            }
            self.finish_batch(now, batch, state, results);
        }
        self.after_event(now);
    }

    /// The timer asked for with [`Effect::SetTimer`] fired: tasks idle too long end as expired.
    pub fn timeout(&mut self, now: Timestamp) {
        let now = self.advance(now);
        for task in self.scheduler.expiring(now) {
            if let Some(snapshot) = self.open_snapshot(task) {
                self.keep_ended(snapshot);
            }
        }
        self.scheduler.handle_timeout(now);
        // The shell's timer has fired: ask for the next one even if its time is unchanged.
        self.timer = None;
        self.after_event(now);
    }

    /// From now on new rounds are refused with `shutting_down`; accepted ones are still run and
    /// answered.
    pub fn shut_down(&mut self) {
        if !self.draining {
            tracing::info!(pending = self.requests.len(), "driver draining");
            self.draining = true;
        }
    }

    /// The task's record: open tasks, or recently ended ones.
    pub fn snapshot(&self, task: TaskId) -> Option<TaskSnapshot> {
        self.open_snapshot(task)
            .or_else(|| self.ended.iter().rev().find(|s| s.task == task).cloned())
    }

    /// The running totals.
    pub fn stats(&self) -> DriverStats {
        let (overhead, processing) = self.latencies.summaries();
        DriverStats {
            overhead,
            processing,
            ..self.stats.clone()
        }
    }

    /// What the core reports about itself: totals, the queue, the engine instances. Cheap
    /// (no sorting): the shell publishes one after every event.
    pub fn report(&self) -> DriverReport {
        let engines = self
            .scheduler
            .engines()
            .filter_map(|e| {
                let state = if e.live {
                    EngineState::Ready
                } else if e.batch.is_some() {
                    EngineState::Draining
                } else {
                    return None;
                };
                let facts = self.engine_facts.get(&e.id).copied().unwrap_or_default();
                Some(EngineReport {
                    name: e.spec.name.clone(),
                    tier: e.spec.tier,
                    state,
                    busy: e.batch.is_some(),
                    busy_time: facts.busy_time,
                    rtt: facts.rtt,
                })
            })
            .collect();
        DriverReport {
            stats: self.stats.clone(),
            queue_depth: self.scheduler.pending_len(),
            running: self.scheduler.running_len(),
            open_tasks: self.tasks.len(),
            engines,
        }
    }

    /// The facts of an instance the scheduler knows; `None` for one it has forgotten (a late
    /// event about an instance that left), which must not bring its facts back.
    fn engine_facts_mut(&mut self, engine: EngineId) -> Option<&mut EngineFacts> {
        self.scheduler.engine(engine)?;
        Some(self.engine_facts.entry(engine).or_default())
    }

    /// Drops the facts of instances the scheduler has forgotten (left the pool, no batch left).
    fn forget_departed_engines(&mut self) {
        if self.engine_facts.len() > self.scheduler.engine_records() {
            let scheduler = &self.scheduler;
            self.engine_facts
                .retain(|&id, _| scheduler.engine(id).is_some());
        }
    }

    /// Engine instances the core keeps facts about (at most those the scheduler knows).
    pub fn engine_facts_held(&self) -> usize {
        self.engine_facts.len()
    }

    fn advance(&mut self, now: Timestamp) -> Timestamp {
        self.now = self.now.max(now);
        self.now
    }

    fn answer(&mut self, waiters: Vec<WaiterId>, answer: RoundAnswer) {
        if !waiters.is_empty() {
            self.effects.push_back(Effect::Answer { waiters, answer });
        }
    }

    fn refuse(&mut self, waiter: WaiterId, error: RoundError) {
        self.answer(vec![waiter], Err(ErrorReply::from(&error)));
    }

    fn on_submit(
        &mut self,
        now: Timestamp,
        submit: ValidSubmit,
        received: Timestamp,
        waiter: WaiterId,
    ) {
        if self.draining {
            self.stats.refused += 1;
            return self.refuse(waiter, RoundError::ShuttingDown);
        }
        let (task, round, robot) = (submit.round.task, submit.round.round, submit.round.robot);
        if let Some(reply) = self.cached_reply(task, round, robot) {
            self.stats.cached_replies += 1;
            return self.answer(vec![waiter], Ok(reply));
        }
        match self.scheduler.handle_submit(now, submit.round) {
            Ok(request) => {
                self.stats.accepted += 1;
                let facts = self.tasks.entry(task).or_insert_with(|| TaskFacts {
                    clock: submit.clock,
                    control_hz: None,
                    last_reply: None,
                    generated: BTreeMap::new(),
                    network: NetworkEstimate::default(),
                    predicted: None,
                    delay_errors: DelayErrorStats::default(),
                });
                facts.clock = submit.clock;
                facts.network.observe(submit.round.sent_at, received);
                // The robot's Last Exec Info says what the previous round's `d` was.
                if let (Some(exec), Some((predicted_round, predicted, captured))) =
                    (submit.round.last_exec, facts.predicted)
                    && submit.exec_round.is_none_or(|r| r == predicted_round)
                {
                    let actual = submit
                        .exec_delay
                        .unwrap_or_else(|| actual_delay_from_times(captured, &exec));
                    facts.delay_errors.record(predicted, actual);
                    let error = i64::from(predicted) - i64::from(actual);
                    self.stats.delay_error.observe(error.unsigned_abs() as f64);
                    self.stats.delay_error_signed =
                        self.stats.delay_error_signed.saturating_add(error);
                    facts.predicted = None;
                }
                if submit.control_hz.is_some() {
                    facts.control_hz = submit.control_hz;
                }
                let control_hz = facts.control_hz.unwrap_or(0.0);
                self.requests.insert(
                    request,
                    RequestState {
                        task,
                        round,
                        received,
                        accepted: now,
                        observation: Some(submit.observation),
                        policy: Some(submit.policy),
                        control_hz,
                        waiters: vec![waiter],
                        dispatched: None,
                        refetch: Duration::ZERO,
                        batch_size: 0,
                        attempts: 0,
                        captured_at: now,
                        sent_at: submit.round.sent_at,
                        exec: submit.round.last_exec,
                        exec_round: submit.exec_round,
                        chunking: submit.chunking,
                        plan: None,
                        observed_state: None,
                    },
                );
            }
            Err(AdmitError::RoundInProgress { request, .. }) => {
                match self.requests.get_mut(&request) {
                    Some(state) => {
                        self.stats.attached += 1;
                        // The newest stream is the live one (re-fetches ask it); a re-sent
                        // observation is fresher.
                        state.waiters.push(waiter);
                        if state.dispatched.is_none() {
                            state.observation = Some(submit.observation);
                            state.chunking = submit.chunking;
                        }
                    }
                    None => self.refuse(
                        waiter,
                        RoundError::Internal(format!(
                            "round {round} is in progress but has no state"
                        )),
                    ),
                }
            }
            Err(error) => {
                self.stats.refused += 1;
                self.refuse(waiter, RoundError::Admit(error));
            }
        }
        for superseded in self.scheduler.take_superseded() {
            self.stats.superseded += 1;
            if let Some(old) = self.requests.remove(&superseded.request) {
                let error = RoundError::Superseded {
                    round: old.round,
                    by: round,
                };
                self.answer(old.waiters, Err(ErrorReply::from(&error)));
            }
        }
    }

    /// The task's last reply, if it answers `round` and `robot` owns the open task.
    fn cached_reply(&self, task: TaskId, round: u64, robot: RobotId) -> Option<Reply> {
        let owner = self.scheduler.task(task)?.owner();
        if owner != robot {
            return None;
        }
        self.tasks
            .get(&task)?
            .last_reply
            .as_ref()
            .filter(|reply| reply.round == round)
            .cloned()
    }

    fn on_end_task(
        &mut self,
        now: Timestamp,
        robot: RobotId,
        end: ValidEndTask,
    ) -> Result<TaskEnded, ErrorReply> {
        let snapshot = self
            .open_snapshot(end.task)
            .filter(|snapshot| snapshot.owner == robot);
        let summary = self
            .scheduler
            .handle_task_end(now, end.task, robot, end.end, end.exec)
            .map_err(|e| ErrorReply::from(&RoundError::Admit(e)))?;
        // A request still queued was dropped by the scheduler: nothing will run it. One already
        // in a batch is answered when the batch is done.
        let queued = summary
            .open_request
            .filter(|r| self.requests.get(r).is_some_and(|s| s.dispatched.is_none()));
        if let Some(old) = queued.and_then(|request| self.requests.remove(&request)) {
            let error = RoundError::Admit(AdmitError::TaskEnded { task: end.task });
            self.answer(old.waiters, Err(ErrorReply::from(&error)));
        }
        let mut history = Vec::new();
        if let Some(mut snapshot) = snapshot {
            // The end report closes the last round's execution phase, exactly as the lifecycle
            // computes it.
            if let (Some(exec), Some(last)) = (end.exec, snapshot.history.last_mut())
                && last.execution.is_none()
                && let Ok(interval) = exec_interval(&exec, now)
            {
                last.execution = Some(interval);
            }
            snapshot.clock = end.clock;
            history = snapshot.wire_history();
            self.keep_ended(snapshot);
        }
        Ok(TaskEnded {
            task: end.task.0,
            rounds: summary.rounds,
            wait_us: duration_micros(summary.wait),
            attained_service_us: duration_micros(summary.attained_service),
            history,
        })
    }

    /// The snapshot of an open task.
    fn open_snapshot(&self, task: TaskId) -> Option<TaskSnapshot> {
        let record = self.scheduler.task(task)?;
        let facts = self.tasks.get(&task)?;
        Some(TaskSnapshot {
            task,
            owner: record.owner(),
            rounds_completed: record.rounds_completed(),
            history: record.history().copied().collect(),
            clock: facts.clock,
            generated: facts.generated.clone(),
            delay_errors: facts.delay_errors,
            ended: false,
        })
    }

    fn keep_ended(&mut self, mut snapshot: TaskSnapshot) {
        snapshot.ended = true;
        if self.ended.len() >= self.ended_snapshots {
            self.ended.pop_front();
        }
        self.ended.push_back(snapshot);
    }

    /// After every event: count ended tasks and drop their facts, dispatch what became
    /// runnable, and keep the shell's timer on the scheduler's next deadline.
    fn after_event(&mut self, now: Timestamp) {
        for summary in self.scheduler.take_finished() {
            self.stats.tasks_ended += 1;
            self.tasks.remove(&summary.task);
        }
        self.answer_stranded(now);
        self.dispatch(now);
        self.forget_departed_engines();
        let next = self.scheduler.poll_timeout();
        if next != self.timer {
            self.timer = next;
            self.effects.push_back(Effect::SetTimer(next));
        }
    }

    /// Draining with no engine left (every remote worker gone) and nothing running: the queued
    /// rounds can never run, so they are answered `shutting_down` (retryable) and the driver can
    /// stop. Rounds wait for a worker only while the server runs.
    fn answer_stranded(&mut self, now: Timestamp) {
        if !self.draining || self.scheduler.live_engines() > 0 || !self.batches.is_empty() {
            return;
        }
        let stranded: Vec<RequestId> = self
            .requests
            .iter()
            .filter(|(_, r)| r.dispatched.is_none())
            .map(|(&id, _)| id)
            .collect();
        for request in stranded {
            self.scheduler.fail_pending(now, request);
            if let Some(old) = self.requests.remove(&request) {
                self.stats.failed += 1;
                self.answer(
                    old.waiters,
                    Err(ErrorReply::from(&RoundError::ShuttingDown)),
                );
            }
        }
    }

    fn dispatch(&mut self, now: Timestamp) {
        for dispatch in self.scheduler.poll_dispatch(now) {
            let batch = dispatch.batch;
            let batch_size = u32::try_from(dispatch.requests.len()).unwrap_or(u32::MAX);
            let mut outstanding = 0;
            for entry in &dispatch.requests {
                let Some(state) = self.requests.get_mut(&entry.request) else {
                    continue;
                };
                state.dispatched = Some(now);
                state.batch_size = batch_size;
                state.attempts = state.attempts.saturating_add(1);
                if !entry.refetch {
                    continue;
                }
                let Some(&waiter) = state.waiters.last() else {
                    continue;
                };
                let age = state
                    .observation
                    .as_ref()
                    .map(|o| now.saturating_since(o.captured_at))
                    .unwrap_or_default();
                self.stats.refetch_asked += 1;
                outstanding += 1;
                self.effects.push_back(Effect::Refetch {
                    batch,
                    request: entry.request,
                    waiter,
                    age,
                });
            }
            self.batches.insert(
                batch,
                BatchState {
                    dispatch,
                    outstanding,
                    refetch_started: now,
                    inference: Duration::ZERO,
                    missing: Vec::new(),
                    generation_end: None,
                },
            );
            if outstanding == 0 {
                self.start_batch(now, batch);
            }
        }
    }

    /// The batch's re-fetches are settled: its forward pass begins (`G.start`).
    fn start_batch(&mut self, now: Timestamp, batch: BatchId) {
        let Some(state) = self.batches.get_mut(&batch) else {
            return;
        };
        self.scheduler.handle_batch_started(now, batch);
        self.stats.batches += 1;
        let engine = state.dispatch.engine;
        // What is ahead of every round of the batch once it starts: its generation on this
        // instance (the profile's latency at the batch's size, and a remote instance's round
        // trip) and the server's own time before the answers go out.
        let batch_size = u32::try_from(state.dispatch.requests.len()).unwrap_or(u32::MAX);
        let generation = self
            .scheduler
            .engine(engine)
            .map(|e| e.spec.profile.latency(batch_size) + e.spec.rtt)
            .unwrap_or_default();
        let reply_overhead = self.reply_overhead.get();
        let mut inputs = Vec::with_capacity(state.dispatch.requests.len());
        let mut attempt = 0;
        let mut rounds = Vec::with_capacity(state.dispatch.requests.len());
        for entry in &state.dispatch.requests {
            let record = self.scheduler.task(entry.task);
            let round_index = record.map(|r| u64::from(r.rounds_completed())).unwrap_or(0);
            let recent_horizons = record
                .map(|r| r.recent_horizons().to_vec())
                .unwrap_or_default();
            let facts = self.tasks.get(&entry.task);
            let network = facts.map(|f| f.network.get()).unwrap_or_default();
            let taken = self
                .requests
                .get_mut(&entry.request)
                .and_then(|req| Some((req.observation.take()?, req.policy.take()?, req)));
            let Some((mut observation, policy, req)) = taken else {
                state.missing.push(entry.request);
                continue;
            };
            let captured_at = observation.captured_at;
            let prediction = predict_delay(&DelayInputs {
                captured_at,
                now,
                queue_wait: Duration::ZERO,
                generation,
                reply_overhead,
                network,
                exec: req.exec,
                sent_at: req.sent_at,
            });
            // The chunk the robot executes is the task's last reply, unless its Last Exec Info
            // names another round.
            let previous = facts
                .and_then(|f| f.last_reply.as_ref())
                .filter(|r| req.exec_round.is_none_or(|round| round == r.round))
                .and_then(|r| Some((r.actions.to_f32().ok()?, r.actions.shape.get(1).copied()?)));
            let (plan, planned) = plan_round(
                &req.chunking,
                prediction,
                previous.as_ref().map(|(actions, width)| PreviousChunk {
                    actions,
                    action_dim: *width as usize,
                }),
                &observation.request.state,
                &self.chunking_model.action_space,
                self.chunking_model.action_dim,
            );
            if let Some(state) = planned.state {
                req.observed_state = Some(std::mem::replace(&mut observation.request.state, state));
            }
            observation.request.guidance = planned.guidance;
            req.plan = Some(plan);
            let req = &*req;
            attempt = attempt.max(req.attempts.saturating_sub(1));
            inputs.push(observation.request);
            rounds.push(HorizonJob {
                request: entry.request,
                task: req.task.0,
                round: req.round,
                policy,
                control_hz: req.control_hz,
                round_index,
                recent_horizons,
            });
            if let Some(req) = self.requests.get_mut(&entry.request) {
                req.captured_at = captured_at;
            }
        }
        if rounds.is_empty() {
            // Nothing to run: the batch ends here, its requests answered as failed.
            if let Some(state) = self.batches.remove(&batch) {
                self.scheduler.handle_generation_ended(now, batch);
                self.finish_batch(now, batch, state, Vec::new());
            }
            return;
        }
        self.stats.batch_size.observe(inputs.len() as f64);
        self.effects.push_back(Effect::RunBatch(BatchJob {
            batch,
            engine,
            attempt,
            inputs,
            rounds,
        }));
    }

    fn finish_batch(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        state: BatchState,
        mut results: Vec<(RequestId, RoundAnswer)>,
    ) {
        results.extend(state.missing.iter().map(|&request| {
            let error = RoundError::Internal("the round's observation was lost".into());
            (request, Err(ErrorReply::from(&error)))
        }));
        // Each chunk goes into its reply as the round's strategy says, before its horizon is
        // recorded.
        for (request, result) in &mut results {
            if let (Ok(reply), Some(plan)) = (
                result,
                self.requests.get(request).and_then(|r| r.plan.as_ref()),
            ) {
                plan.finish(reply);
                self.stats.chunking.count(plan.applied);
                if plan.applied != plan.requested {
                    self.stats.chunking.fallbacks += 1;
                }
                self.stats
                    .delay_predicted
                    .observe(f64::from(plan.prediction.delay));
            }
        }
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
        // A deadline miss: the round is answered after its robot ran out of actions, i.e. after
        // `E.end` of the task's previous round (read before the scheduler records this one).
        for (request, result) in &results {
            let late = result.is_ok()
                && self
                    .requests
                    .get(request)
                    .and_then(|req| self.scheduler.task(req.task))
                    .and_then(|task| task.last_execution_end())
                    .is_some_and(|deadline| now > deadline);
            if late {
                self.stats.deadline_misses += 1;
            }
        }
        self.scheduler.handle_batch_finished(now, batch, &outcomes);
        let keep = self.scheduler.config().history_rounds.max(1);
        for (request, result) in results {
            let Some(req) = self.requests.remove(&request) else {
                continue;
            };
            let dispatched = req.dispatched.unwrap_or(req.accepted);
            let answer = result.map(|mut reply| {
                reply.timing = Timing {
                    queue_us: micros(dispatched.saturating_since(req.received)),
                    refetch_us: micros(req.refetch),
                    inference_us: micros(state.inference),
                    total_us: micros(now.saturating_since(req.received)),
                    batch_size: req.batch_size,
                };
                reply
            });
            match &answer {
                Ok(reply) => {
                    self.stats.replies += 1;
                    self.stats
                        .round_latency
                        .observe(now.saturating_since(req.received).as_secs_f64());
                    self.stats.horizon.observe(f64::from(reply.horizon));
                    // The server's own work: reading to acceptance, and dispatch to reply, less
                    // the re-fetch wait and the forward pass.
                    let own = req.accepted.saturating_since(req.received)
                        + now
                            .saturating_since(dispatched)
                            .saturating_sub(req.refetch)
                            .saturating_sub(state.inference);
                    self.latencies.record(&reply.timing, micros(own));
                    if let Some(facts) = self.tasks.get_mut(&req.task) {
                        *facts.generated.entry(req.round).or_insert(0) += 1;
                        while facts.generated.len() > keep {
                            facts.generated.pop_first();
                        }
                        let newer = facts
                            .last_reply
                            .as_ref()
                            .is_some_and(|r| r.round > req.round);
                        if !newer {
                            facts.last_reply = Some(reply.clone());
                            facts.predicted = req
                                .plan
                                .as_ref()
                                .map(|plan| (req.round, plan.prediction.delay, req.captured_at));
                        }
                    }
                }
                Err(_) => self.stats.failed += 1,
            }
            self.answer(req.waiters, answer);
        }
    }
}

fn micros(d: Duration) -> u64 {
    duration_micros(d)
}
