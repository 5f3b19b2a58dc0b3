//! The scheduler state machine: pending requests, engine instances, running batches, and the
//! task table, driven by the event API documented on the module (`scheduler`).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::time::Duration;

use super::placement::{self, EngineSlot};
use super::policy::{PendingView, PriorityPolicy, RemainingWork, validate_order};
use super::refine::{ProfileRefiner, RefineConfig};
use super::{
    AdmitError, BatchId, Dispatch, DispatchedRequest, EngineId, EngineSpec, ExecReport, RequestId,
    RobotId, RoundOutcome, RoundSubmit, SchedulerConfig, ServerLoad, TaskEnd, TaskId, Tier,
};
use crate::lifecycle::{TaskRecord, TaskSummary, TaskTable};
use crate::time::Timestamp;

/// A request waiting for dispatch.
#[derive(Clone, Copy, Debug)]
struct PendingRequest {
    task: TaskId,
    round: u64,
    arrived_at: Timestamp,
    obs_captured_at: Timestamp,
    skipped: u32,
    remaining: Option<RemainingWork>,
}

/// A request inside a dispatched batch, with what it was while pending, so that a batch lost
/// with its engine can put it back exactly as it was.
#[derive(Clone, Copy, Debug)]
struct BatchEntry {
    request: RequestId,
    task: TaskId,
    pending: PendingRequest,
}

/// A dispatched batch, until its end is reported.
#[derive(Clone, Debug)]
struct Batch {
    engine: EngineId,
    dispatched_at: Timestamp,
    started_at: Option<Timestamp>,
    /// `G.end`, when reported by `handle_generation_ended` before the outcomes.
    generated_at: Option<Timestamp>,
    entries: Vec<BatchEntry>,
}

#[derive(Clone, Debug)]
struct EngineState {
    spec: EngineSpec,
    /// False once the instance left the pool (a remote worker gone or draining): placement no
    /// longer sees it, and its record is dropped as soon as it runs no batch.
    live: bool,
    max_batch: usize,
    busy: Option<BatchId>,
    /// Estimated end of the current batch (meaningful while `busy`).
    busy_until: Timestamp,
    /// The profile refined from the batch times this instance really takes, when
    /// [`Scheduler::refine_profiles`] turned refinement on.
    refiner: Option<ProfileRefiner>,
}

/// What `handle_cancel` did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CancelOutcome {
    /// The request was pending and is gone; its round may be sent again.
    Removed,
    /// The request is already in a batch; its end will be reported through
    /// `handle_batch_finished` as usual.
    Running,
    /// No such request (already answered, superseded, or never existed).
    NotFound,
}

/// A pending request that a newer round of the same task replaced. The driver answers it with an
/// error; the newer request inherits its skip counter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Superseded {
    /// The replaced request.
    pub request: RequestId,
    /// Its task.
    pub task: TaskId,
    /// The request that replaced it.
    pub by: RequestId,
}

/// One engine instance's state, for drivers and metrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EngineStatus<'a> {
    /// Its id.
    pub id: EngineId,
    /// Its spec, as given to `Scheduler::new`.
    pub spec: &'a EngineSpec,
    /// The batch it runs, if busy.
    pub batch: Option<BatchId>,
    /// When the scheduler expects the batch to end (profile latency plus RTT from its start).
    pub busy_until: Option<Timestamp>,
    /// Whether it is still in the pool (placement sees only live instances).
    pub live: bool,
}

/// What one scheduling decision did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecisionStats {
    /// When it was made.
    pub at: Timestamp,
    /// Requests pending when it was made.
    pub pending: usize,
    /// Requests it dispatched.
    pub dispatched: usize,
    /// Of those, requests placed on cloud instances.
    pub offloaded: usize,
    /// Of those, requests flagged for observation re-fetch.
    pub refetch: usize,
    /// Batches it formed.
    pub batches: usize,
    /// The policy failed or answered an invalid order, so arrival order was used.
    pub policy_failed: bool,
}

/// Running totals since the scheduler was created.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SchedulerCounters {
    /// Accepted submits.
    pub submitted: u64,
    /// Refused submits (any `AdmitError`).
    pub refused: u64,
    /// Decisions made.
    pub decisions: u64,
    /// Requests dispatched.
    pub dispatched: u64,
    /// Requests placed on cloud instances.
    pub offloaded: u64,
    /// Pending requests replaced by a newer round.
    pub superseded: u64,
    /// Pending requests removed by `handle_cancel`.
    pub cancelled: u64,
    /// Running requests whose task moved on (newer round or task end) before they finished.
    pub abandoned: u64,
    /// Requests answered.
    pub answered: u64,
    /// Requests whose generation failed (reported or missing from a batch's outcomes).
    pub failed: u64,
    /// Decisions where the policy failed or gave an invalid order.
    pub policy_errors: u64,
    /// Events about unknown batches or requests, ignored.
    pub ignored_events: u64,
    /// Requests put back in the queue because their batch was lost with its engine.
    pub requeued: u64,
    /// Tasks ended (any way).
    pub tasks_ended: u64,
}

/// The execution-aware scheduler. See the module documentation for the event API.
pub struct Scheduler {
    config: SchedulerConfig,
    /// The instances in the pool, and those that left while running a batch, until that batch
    /// ends (see [`Scheduler::add_engine`] for why ids are never reused).
    engines: BTreeMap<EngineId, EngineState>,
    /// The id the next instance added gets.
    next_engine: usize,
    policy: Box<dyn PriorityPolicy>,
    tasks: TaskTable,
    /// Keyed by `RequestId`, so iteration (and the views a policy sees) is in arrival order.
    pending: BTreeMap<RequestId, PendingRequest>,
    batches: HashMap<BatchId, Batch>,
    next_request: u64,
    next_batch: u64,
    finished: VecDeque<TaskSummary>,
    superseded: Vec<Superseded>,
    last_decision: Option<DecisionStats>,
    counters: SchedulerCounters,
    // Buffers reused between decisions.
    views: Vec<PendingView>,
    keys: Vec<RequestId>,
    order: Vec<usize>,
    /// Online profile refinement, for every instance present and to come (off: `None`).
    refine: Option<RefineConfig>,
}

impl Scheduler {
    /// A scheduler over `engines` (indexed by `EngineId` in this order) ordering requests with
    /// `policy`. A profile with `max_batch` 0 is treated as 1.
    pub fn new(
        config: SchedulerConfig,
        engines: Vec<EngineSpec>,
        policy: Box<dyn PriorityPolicy>,
    ) -> Self {
        let tasks = TaskTable::new(
            config.history_rounds,
            config.task_idle_timeout,
            config.ended_tasks_remembered,
        );
        let engines: BTreeMap<EngineId, EngineState> = engines
            .into_iter()
            .enumerate()
            .map(|(i, spec)| (EngineId(i), EngineState::new(spec)))
            .collect();
        Scheduler {
            config,
            next_engine: engines.len(),
            engines,
            policy,
            tasks,
            pending: BTreeMap::new(),
            batches: HashMap::new(),
            next_request: 0,
            next_batch: 0,
            finished: VecDeque::new(),
            superseded: Vec::new(),
            last_decision: None,
            counters: SchedulerCounters::default(),
            views: Vec::new(),
            keys: Vec::new(),
            order: Vec::new(),
            refine: None,
        }
    }

    /// Refine every instance's profile online from the batch times it really takes (see
    /// [`super::refine`]), from now on and for instances that join later: the batch limit and
    /// the latency estimates follow the refined profile. Off by default: the profile is then
    /// what the instance was given.
    pub fn refine_profiles(&mut self, config: RefineConfig) {
        self.refine = Some(config);
        for engine in self.engines.values_mut() {
            engine.refiner = Some(ProfileRefiner::new(&engine.spec.profile, config));
        }
    }

    /// A generation of `size` requests took `took` on `engine` (without the network round
    /// trip): the refined profile, if refinement is on, learns it.
    fn observe_generation(&mut self, engine: EngineId, size: usize, took: Duration) {
        let Some(e) = self.engines.get_mut(&engine) else {
            return;
        };
        let Some(refiner) = e.refiner.as_mut() else {
            return;
        };
        refiner.observe(
            u32::try_from(size).unwrap_or(u32::MAX),
            took.saturating_sub(e.spec.rtt),
        );
        e.spec.profile = refiner.current_profile();
        e.max_batch = usize::try_from(refiner.allowed_batch()).unwrap_or(usize::MAX);
    }

    /// Accepts a round request, or says why not.
    ///
    /// Checks, in order: the task has not ended (`TaskEnded`); the exec report is consistent
    /// (`InvalidExecInfo`); the robot owns the task (`Forbidden`); the round is not the one already
    /// in progress (`RoundInProgress`, attach to that request instead); the round id is greater
    /// than the last accepted one, or equal to it after that round failed or was withdrawn
    /// (`RoundOutOfOrder`); there is room (`Overloaded`, counting a request this one supersedes as
    /// freed). A newer round of a task whose previous round is still pending supersedes it (see
    /// [`Scheduler::take_superseded`]); one whose previous round is already in a batch abandons
    /// that request (its generation still counts as service; its answer is no round).
    pub fn handle_submit(
        &mut self,
        now: Timestamp,
        submit: RoundSubmit,
    ) -> Result<RequestId, AdmitError> {
        let plan = match self.tasks.plan_submit(&submit) {
            Ok(plan) => plan,
            Err(e) => {
                self.counters.refused += 1;
                return Err(e);
            }
        };
        let freed = usize::from(plan.supersedes_pending.is_some());
        if self.pending.len() - freed >= self.config.max_pending {
            self.counters.refused += 1;
            return Err(AdmitError::Overloaded {
                pending: self.pending.len(),
            });
        }
        let request = RequestId(self.next_request);
        self.next_request += 1;
        let mut skipped = 0;
        if let Some(old) = plan.supersedes_pending {
            if let Some(entry) = self.pending.remove(&old) {
                skipped = entry.skipped;
            }
            self.superseded.push(Superseded {
                request: old,
                task: submit.task,
                by: request,
            });
            self.counters.superseded += 1;
        }
        if plan.abandons_running.is_some() {
            self.counters.abandoned += 1;
        }
        self.tasks.apply_submit(now, &submit, &plan, request);
        self.pending.insert(
            request,
            PendingRequest {
                task: submit.task,
                round: submit.round,
                arrived_at: now,
                obs_captured_at: submit.obs_captured_at,
                skipped,
                remaining: submit.remaining,
            },
        );
        self.counters.submitted += 1;
        Ok(request)
    }

    /// Withdraws a request whose client went away. Only a pending request is removed (its round
    /// may be sent again); one already in a batch finishes normally.
    pub fn handle_cancel(&mut self, now: Timestamp, request: RequestId) -> CancelOutcome {
        if let Some(entry) = self.pending.remove(&request) {
            self.tasks.withdrawn(now, entry.task, request);
            self.counters.cancelled += 1;
            return CancelOutcome::Removed;
        }
        let running = self
            .batches
            .values()
            .any(|b| b.entries.iter().any(|e| e.request == request));
        if running {
            CancelOutcome::Running
        } else {
            CancelOutcome::NotFound
        }
    }

    /// One scheduling decision covering every idle engine instance (see the module doc for when a
    /// decision happens). Returns the batches to run, each to be confirmed with
    /// `handle_batch_started` once its re-fetches are done and its forward pass begins.
    pub fn poll_dispatch(&mut self, now: Timestamp) -> Vec<Dispatch> {
        let any_idle = self.engines.values().any(|e| e.live && e.busy.is_none());
        if !any_idle || self.pending.is_empty() {
            return Vec::new();
        }
        self.build_views(now);
        let policy_failed = self.order_pending(now);

        // Placement sees live instances only; `live_ids[i]` is the engine of slot `i`.
        let (live_ids, slots) = self.live_engine_slots();
        let placed = placement::place(now, &self.order, &slots);
        let costs: Vec<Duration> = slots
            .iter()
            .zip(&placed.batches)
            .map(|(slot, batch)| slot.cost(batch.len()))
            .collect();
        drop(slots);

        let mut dispatches = Vec::new();
        let mut dispatched = 0;
        let mut refetch = 0;
        for (slot_index, batch) in placed.batches.iter().enumerate() {
            if batch.is_empty() {
                continue;
            }
            let engine_id = live_ids[slot_index];
            let batch_id = BatchId(self.next_batch);
            self.next_batch += 1;
            let mut requests = Vec::with_capacity(batch.len());
            let mut entries = Vec::with_capacity(batch.len());
            for &index in batch {
                let request = self.keys[index];
                let Some(entry) = self.pending.remove(&request) else {
                    continue;
                };
                let stale = self.config.refetch
                    && now.saturating_since(entry.obs_captured_at) > self.config.stale_after;
                refetch += usize::from(stale);
                requests.push(DispatchedRequest {
                    request,
                    task: entry.task,
                    round: entry.round,
                    refetch: stale,
                });
                entries.push(BatchEntry {
                    request,
                    task: entry.task,
                    pending: entry,
                });
                self.tasks.dispatched(entry.task, request);
            }
            dispatched += requests.len();
            if let Some(engine) = self.engines.get_mut(&engine_id) {
                engine.busy = Some(batch_id);
                engine.busy_until = now + costs[slot_index];
            }
            self.batches.insert(
                batch_id,
                Batch {
                    engine: engine_id,
                    dispatched_at: now,
                    started_at: None,
                    generated_at: None,
                    entries,
                },
            );
            dispatches.push(Dispatch {
                batch: batch_id,
                engine: engine_id,
                requests,
            });
        }
        if dispatched > 0 {
            for entry in self.pending.values_mut() {
                entry.skipped = entry.skipped.saturating_add(1);
            }
        }
        self.counters.decisions += 1;
        self.counters.dispatched += dispatched as u64;
        self.counters.offloaded += placed.offloaded as u64;
        self.counters.policy_errors += u64::from(policy_failed);
        self.last_decision = Some(DecisionStats {
            at: now,
            pending: self.views.len(),
            dispatched,
            offloaded: placed.offloaded,
            refetch,
            batches: dispatches.len(),
            policy_failed,
        });
        dispatches
    }

    /// Fills `views`/`keys` with every pending request, in arrival (`RequestId`) order.
    fn build_views(&mut self, now: Timestamp) {
        self.views.clear();
        self.keys.clear();
        for (&request, entry) in &self.pending {
            let Some(task) = self.tasks.get(entry.task) else {
                continue;
            };
            self.views.push(PendingView {
                request,
                task: entry.task,
                round_index: u64::from(task.rounds_completed()),
                arrived_at: entry.arrived_at,
                task_started_at: task.started_at(),
                skipped: entry.skipped,
                wait: task.wait_at(now),
                attained_service: task.attained_service(),
                queued: task.queued_at(now),
                last_exec: task.last_execution(),
                exec_ends_at: task.last_execution_end(),
                last_gen: task.last_generation(),
                rounds_completed: task.rounds_completed(),
                remaining: entry.remaining,
            });
            self.keys.push(request);
        }
    }

    /// Asks the policy for an order; falls back to arrival order if it fails or answers something
    /// that is not a permutation. Returns whether it fell back.
    fn order_pending(&mut self, now: Timestamp) -> bool {
        self.order.clear();
        let ok = self
            .policy
            .order(now, &self.views, &mut self.order)
            .and_then(|()| validate_order(self.views.len(), &self.order));
        match ok {
            Ok(()) => false,
            Err(e) => {
                tracing::warn!(policy = self.policy.name(), error = %e, "priority policy failed; using arrival order");
                self.order.clear();
                self.order.extend(0..self.views.len());
                true
            }
        }
    }

    /// The batch's re-fetches are done and its forward pass begins now (`G.start` of its requests).
    pub fn handle_batch_started(&mut self, now: Timestamp, batch: BatchId) {
        let Some(b) = self.batches.get_mut(&batch) else {
            self.counters.ignored_events += 1;
            return;
        };
        if b.started_at.is_some() {
            self.counters.ignored_events += 1;
            return;
        }
        b.started_at = Some(now);
        for entry in &b.entries {
            self.tasks
                .generation_started(now, entry.task, entry.request);
        }
        if let Some(engine) = self.engines.get_mut(&b.engine) {
            let cost = engine
                .spec
                .profile
                .latency(u32::try_from(b.entries.len()).unwrap_or(u32::MAX))
                .saturating_add(engine.spec.rtt);
            engine.busy_until = now + cost;
        }
    }

    /// The batch's forward pass ended at `now` (`G.end`) and its engine instance is idle again,
    /// while the horizons of its rounds are still being chosen. Optional: a driver that reports
    /// it lets the engine take the next batch during the horizon policies; the batch's outcomes
    /// still follow through `handle_batch_finished`, which then takes `G.end` from here.
    pub fn handle_generation_ended(&mut self, now: Timestamp, batch: BatchId) {
        let Some(b) = self.batches.get_mut(&batch) else {
            self.counters.ignored_events += 1;
            return;
        };
        if b.generated_at.is_some() {
            self.counters.ignored_events += 1;
            return;
        }
        b.generated_at = Some(now);
        let engine = b.engine;
        let took = now.saturating_since(b.started_at.unwrap_or(b.dispatched_at));
        let size = b.entries.len();
        self.release_engine(engine, batch);
        self.observe_generation(engine, size, took);
    }

    /// The engine instance is idle, unless it already runs another batch than `batch`. An
    /// instance that left the pool is forgotten once idle.
    fn release_engine(&mut self, engine: EngineId, batch: BatchId) {
        if let Some(state) = self.engines.get_mut(&engine)
            && state.busy == Some(batch)
        {
            state.busy = None;
            if !state.live {
                self.engines.remove(&engine);
            }
        }
    }

    /// The batch's outcomes are known at `now`. `G.end` is the time given to
    /// `handle_generation_ended` if it was reported, else `now`; the engine instance is idle from
    /// then. A request of the batch missing from `outcomes` counts as failed; entries for
    /// requests not in the batch are ignored. A batch never reported started is taken to have
    /// started when it was dispatched.
    pub fn handle_batch_finished(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        outcomes: &[(RequestId, RoundOutcome)],
    ) {
        let Some(b) = self.batches.remove(&batch) else {
            self.counters.ignored_events += 1;
            return;
        };
        self.release_engine(b.engine, batch);
        let reported = b.generated_at.is_some();
        let now = b.generated_at.unwrap_or(now);
        let started = b.started_at.unwrap_or(b.dispatched_at);
        let generation = now.saturating_since(started);
        if !reported {
            self.observe_generation(b.engine, b.entries.len(), generation);
        }
        for entry in &b.entries {
            if b.started_at.is_none() {
                self.tasks
                    .generation_started(started, entry.task, entry.request);
            }
            let outcome = outcomes
                .iter()
                .find(|(r, _)| *r == entry.request)
                .map(|(_, o)| *o)
                .unwrap_or(RoundOutcome::Failed);
            let current = self
                .tasks
                .get(entry.task)
                .and_then(|t| t.current_request())
                .map(|(r, _)| r)
                == Some(entry.request);
            if !current {
                self.tasks.abandoned_generation(entry.task, generation);
                continue;
            }
            match outcome {
                RoundOutcome::Answered { horizon } => {
                    self.tasks.answered(now, entry.task, entry.request, horizon);
                    self.counters.answered += 1;
                }
                RoundOutcome::Failed => {
                    self.tasks.failed(now, entry.task, entry.request);
                    self.counters.failed += 1;
                }
            }
        }
    }

    /// Ends a task: `Done`/`Failed` from its robot, with the final execution report if it sent one
    /// (its `E.end` is measured from `now`). A request of the task still pending is removed and
    /// named in the summary's `open_request`; one already running finishes normally but is no
    /// longer a round. The summary is also kept for [`Scheduler::take_finished`].
    pub fn handle_task_end(
        &mut self,
        now: Timestamp,
        task: TaskId,
        robot: RobotId,
        end: TaskEnd,
        exec: Option<ExecReport>,
    ) -> Result<TaskSummary, AdmitError> {
        let exec = self.tasks.plan_end(task, robot, exec.as_ref(), now)?;
        let summary = self.end_task(now, task, end, exec);
        summary.ok_or(AdmitError::UnknownTask { task })
    }

    fn end_task(
        &mut self,
        now: Timestamp,
        task: TaskId,
        end: TaskEnd,
        exec: Option<crate::lifecycle::Interval>,
    ) -> Option<TaskSummary> {
        let current = self.tasks.get(task).and_then(|t| t.current_request());
        let summary = self.tasks.end(now, task, end, exec)?;
        if let Some((request, _)) = current
            && self.pending.remove(&request).is_none()
        {
            self.counters.abandoned += 1;
        }
        self.policy.task_finished(&summary.finished_task());
        if self.finished.len() >= self.config.ended_tasks_remembered.max(1) {
            self.finished.pop_front();
        }
        self.finished.push_back(summary);
        self.counters.tasks_ended += 1;
        Some(summary)
    }

    /// The next time `handle_timeout` has something to do: the earliest idle-expiry deadline.
    pub fn poll_timeout(&self) -> Option<Timestamp> {
        self.tasks.next_expiry()
    }

    /// The tasks `handle_timeout(now)` would end, earliest deadline first; so a driver can read
    /// their records before they go.
    pub fn expiring(&self, now: Timestamp) -> Vec<TaskId> {
        self.tasks.expired(now)
    }

    /// Ends every task idle (no request pending or running) for `task_idle_timeout` as `Expired`.
    /// Returns them, earliest deadline first; their summaries go to [`Scheduler::take_finished`].
    pub fn handle_timeout(&mut self, now: Timestamp) -> Vec<TaskId> {
        let expired = self.tasks.expired(now);
        for &task in &expired {
            self.end_task(now, task, TaskEnd::Expired, None);
        }
        expired
    }

    /// The task's lifecycle record, while it is open.
    pub fn task(&self, task: TaskId) -> Option<&TaskRecord> {
        self.tasks.get(task)
    }

    /// Open tasks.
    pub fn task_count(&self) -> usize {
        self.tasks.len()
    }

    /// The live engine instances as placement sees them, with their `EngineId` indexes, in order.
    fn live_engine_slots(&self) -> (Vec<EngineId>, Vec<EngineSlot<'_>>) {
        let live: Vec<(EngineId, &EngineState)> = self
            .engines
            .iter()
            .filter(|(_, e)| e.live)
            .map(|(&id, e)| (id, e))
            .collect();
        let live_ids = live.iter().map(|&(id, _)| id).collect();
        let slots = live
            .into_iter()
            .map(|(_, e)| EngineSlot {
                tier: e.spec.tier,
                max_batch: e.max_batch,
                busy_until: e.busy.map(|_| e.busy_until),
                profile: &e.spec.profile,
                rtt: e.spec.rtt,
            })
            .collect();
        (live_ids, slots)
    }

    /// The load at `now` (see [`ServerLoad`]): what the action manager hands load-aware horizon
    /// policies. Drivers take it right after `handle_generation_ended`, before the next dispatch
    /// decision, so a batch's horizons see the queue that built up during its forward pass.
    pub fn load(&self, now: Timestamp) -> ServerLoad {
        let (_, slots) = self.live_engine_slots();
        let running: usize = self
            .batches
            .values()
            .filter(|b| b.generated_at.is_none())
            .map(|b| b.entries.len())
            .sum();
        let count = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        ServerLoad {
            queued: count(self.pending.len()),
            running: count(running),
            open_tasks: count(self.tasks.len()),
            backlog: placement::backlog(now, self.pending.len(), &slots),
        }
    }

    /// Requests waiting for dispatch.
    pub fn pending_len(&self) -> usize {
        self.pending.len()
    }

    /// Requests in dispatched batches that have not finished.
    pub fn running_len(&self) -> usize {
        self.batches.values().map(|b| b.entries.len()).sum()
    }

    /// Whether the request is waiting for dispatch.
    pub fn is_pending(&self, request: RequestId) -> bool {
        self.pending.contains_key(&request)
    }

    /// Skip counter of a pending request (consecutive decisions that dispatched something but
    /// not it).
    pub fn skipped(&self, request: RequestId) -> Option<u32> {
        self.pending.get(&request).map(|p| p.skipped)
    }

    /// Every engine instance's state, in `EngineId` order: those in the pool, and those that
    /// left while running a batch, until it ends.
    pub fn engines(&self) -> impl ExactSizeIterator<Item = EngineStatus<'_>> {
        self.engines.iter().map(|(&id, e)| e.status(id))
    }

    /// The state of instance `engine`, while it is in the pool or runs a batch after leaving
    /// it; `None` for an id the scheduler has forgotten or never gave.
    pub fn engine(&self, engine: EngineId) -> Option<EngineStatus<'_>> {
        self.engines.get(&engine).map(|e| e.status(engine))
    }

    /// The instance's round trip changed (a remote worker's measured RTT): placement and the
    /// busy estimate use the new one from the next decision.
    pub fn set_engine_rtt(&mut self, engine: EngineId, rtt: Duration) {
        if let Some(state) = self.engines.get_mut(&engine) {
            state.spec.rtt = rtt;
        }
    }

    /// The instance's tier changed (a worker classified from its round trip); whether it did.
    pub fn set_engine_tier(&mut self, engine: EngineId, tier: Tier) -> bool {
        match self.engines.get_mut(&engine) {
            Some(state) if state.spec.tier != tier => {
                state.spec.tier = tier;
                true
            }
            _ => false,
        }
    }

    /// Instances placement may use.
    pub fn live_engines(&self) -> usize {
        self.engines.values().filter(|e| e.live).count()
    }

    /// A new engine instance joins (a remote worker registered). It gets the next
    /// [`EngineId`].
    ///
    /// Ids are never reused, so a late event about an instance that left (a batch end, a round
    /// trip measured just before it went) cannot hit a new one: the scheduler no longer knows
    /// the old id and ignores it. Storage does not grow with them: an instance's record is
    /// dropped once it has left the pool and runs no batch, so a worker that registers and
    /// leaves again and again costs nothing that stays. The ids are kept in a map rather than
    /// as indexes into a vector with a free list and generations: the pool is small (tens of
    /// instances), and a map gives the same guarantee with nothing to get wrong. A 64-bit
    /// counter does not wrap in any real lifetime (one registration per nanosecond would take
    /// 584 years).
    pub fn add_engine(&mut self, spec: EngineSpec) -> EngineId {
        let mut engine = EngineState::new(spec);
        if let Some(config) = self.refine {
            engine.refiner = Some(ProfileRefiner::new(&engine.spec.profile, config));
        }
        let id = EngineId(self.next_engine);
        self.next_engine = self.next_engine.saturating_add(1);
        self.engines.insert(id, engine);
        id
    }

    /// Engine instance records held: those in the pool, and those that left while running a
    /// batch, until it ends. What the scheduler's per-instance storage grows with.
    pub fn engine_records(&self) -> usize {
        self.engines.len()
    }

    /// The instance leaves the pool: placement no longer sees it. A batch it is running is not
    /// touched: it still ends through `handle_batch_finished` (a draining worker finishes it) or
    /// comes back through [`Scheduler::requeue_batch`] (the worker was lost). Returns that
    /// batch, if any; `None` too for an unknown or already removed instance. The instance's
    /// record is dropped now if it is idle, else when that batch ends: its id is refused from
    /// then on.
    pub fn remove_engine(&mut self, engine: EngineId) -> Option<BatchId> {
        let state = self.engines.get_mut(&engine)?;
        if !state.live {
            return None;
        }
        state.live = false;
        let busy = state.busy;
        if busy.is_none() {
            self.engines.remove(&engine);
        }
        busy
    }

    /// The batch was lost with its engine instance before it produced anything: the instance
    /// leaves the pool ([`Scheduler::remove_engine`]) and every request of the batch that is
    /// still its task's current round goes back to the queue as it was before dispatch (same
    /// `RequestId`, so the same place in arrival order, same arrival time and skip count), to be
    /// dispatched again. Returns those requests in batch order; the others (their task moved on)
    /// are dropped. An unknown batch returns nothing.
    pub fn requeue_batch(&mut self, now: Timestamp, batch: BatchId) -> Vec<RequestId> {
        let Some(b) = self.batches.remove(&batch) else {
            self.counters.ignored_events += 1;
            return Vec::new();
        };
        self.remove_engine(b.engine);
        self.release_engine(b.engine, batch);
        let mut requeued = Vec::with_capacity(b.entries.len());
        for entry in &b.entries {
            if self.tasks.requeued(now, entry.task, entry.request) {
                self.pending.insert(entry.request, entry.pending);
                requeued.push(entry.request);
            } else {
                self.counters.abandoned += 1;
            }
        }
        self.counters.requeued += requeued.len() as u64;
        requeued
    }

    /// A pending request that will not be served (a requeued round out of attempts or time)
    /// fails now: it leaves the queue and the task may send the round again. Returns whether it
    /// was pending.
    pub fn fail_pending(&mut self, now: Timestamp, request: RequestId) -> bool {
        let Some(entry) = self.pending.remove(&request) else {
            return false;
        };
        self.tasks.failed(now, entry.task, request);
        self.counters.failed += 1;
        true
    }

    /// The batch engine instance `engine` runs, if it is busy.
    pub fn engine_busy(&self, engine: EngineId) -> Option<BatchId> {
        self.engines.get(&engine).and_then(|e| e.busy)
    }

    /// What the most recent decision did.
    pub fn last_decision(&self) -> Option<&DecisionStats> {
        self.last_decision.as_ref()
    }

    /// Running totals.
    pub fn counters(&self) -> &SchedulerCounters {
        &self.counters
    }

    /// The priority policy's name.
    pub fn policy_name(&self) -> &str {
        self.policy.name()
    }

    /// The configuration it runs with.
    pub fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    /// Summaries of tasks that ended since the last call, oldest first. At most
    /// `ended_tasks_remembered` are kept between calls (oldest dropped first).
    pub fn take_finished(&mut self) -> Vec<TaskSummary> {
        self.finished.drain(..).collect()
    }

    /// Pending requests replaced by a newer round of their task since the last call. The driver
    /// answers each with an error.
    pub fn take_superseded(&mut self) -> Vec<Superseded> {
        std::mem::take(&mut self.superseded)
    }
}

impl EngineState {
    /// A live, idle instance. A profile with `max_batch` 0 is treated as 1.
    fn new(spec: EngineSpec) -> EngineState {
        EngineState {
            max_batch: usize::try_from(spec.profile.max_batch.max(1)).unwrap_or(usize::MAX),
            spec,
            live: true,
            busy: None,
            busy_until: Timestamp::ZERO,
            refiner: None,
        }
    }

    fn status(&self, id: EngineId) -> EngineStatus<'_> {
        EngineStatus {
            id,
            spec: &self.spec,
            batch: self.busy,
            busy_until: self.busy.map(|_| self.busy_until),
            live: self.live,
        }
    }
}

impl std::fmt::Debug for Scheduler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scheduler")
            .field("policy", &self.policy.name())
            .field("engines", &self.engines.len())
            .field("pending", &self.pending.len())
            .field("batches", &self.batches.len())
            .field("tasks", &self.tasks.len())
            .finish()
    }
}
