//! Task lifecycle state: per task, the generation intervals `G_i` and execution intervals `E_i`
//! and the wait accounting of paper §3.2 (Fig. "wait_time").
//!
//! # The model
//!
//! A task is a sequence of *answered* rounds `0, 1, …, m`. Round `j` has a generation phase
//! `G_j = [dispatch start, generation end]` measured on the server, and an execution phase `E_j`
//! that the robot reports on its next request (Last Exec Info): `E_j.start` is the reported start
//! and `E_j.end = request.sent_at + actions_remaining / control_hz`. A request that never produces
//! an answered round (it failed, was superseded by a newer round, was cancelled, or its task ended)
//! leaves no round behind; the generation time it consumed still counts as attained service and the
//! wait of its task keeps accruing until a later attempt succeeds.
//!
//! The Last Exec Info carried by a request always describes the chunk of the most recent answered
//! round `m`; a later report about the same round (a retry) replaces the earlier one.
//!
//! # The wait rule
//!
//! For consecutive answered rounds `j, j+1`, round `j` is generation-dominated iff
//! `|G_j| ≥ |E_j|` (a round whose execution was never reported has `|E_j| = 0`). `|E_j|` counts
//! only what chunk `j` can execute: the report's `E_j.end` assumes the chunk runs to its end, but
//! chunk `j+1` replaces it when it arrives and drops its unexecuted tail, so `E_j` is cut at
//! `G_{j+1}.end` when the dominance is decided, and at `E_{j+1}.start` once that is reported (the
//! history then keeps the executed interval). Then
//! `W_j = G_{j+1}.start − G_j.end`; otherwise `W_j = E_{j+1}.start − E_j.end`. Both are clamped at
//! zero. Two interpretations the paper leaves open (docs/ARCHITECTURE.md, "The wait-time rule"):
//!
//! - **The open round counts.** While the request for round `m+1` waits, `W_m` accrues up to `now`:
//!   `now − G_m.end` if round `m` was generation-dominated, `max(0, now − E_m.end)` otherwise.
//!   Without this a waiting request's wait ratio would fall as it waits.
//! - **The first round's queueing counts.** Before `G_0` the robot has nothing to execute, so
//!   `G_0.start − t_start` is wait (`now − t_start` while round 0 is still pending).
//!
//! An execution-dominated `W_m` needs `E_{m+1}.start`, which only the request after round `m+1` (or
//! the task's end report) brings. Between the answer of round `m+1` and that report, `W_m` is
//! estimated as `max(0, G_{m+1}.end − E_m.end)`: the chunk became available at `G_{m+1}.end`, the
//! earliest the robot can start it. The report then replaces the estimate with the exact value.
//!
//! Every `W_j` is added to a running sum the moment it becomes final, and the open one is computed
//! from the last answered round alone. So the G/E history kept for inspection can be bounded
//! (`SchedulerConfig::history_rounds`) while the wait ratio stays exact.
//!
//! # Time
//!
//! All arithmetic is on whole microseconds ([`Timestamp`]); durations saturate at zero instead of
//! going negative, so a client clock mapped slightly off cannot produce a negative wait.

use std::collections::{BTreeSet, HashMap, HashSet, VecDeque};
use std::time::Duration;

use crate::scheduler::{AdmitError, ExecReport, RequestId, RobotId, RoundSubmit, TaskEnd, TaskId};
use crate::time::Timestamp;

/// Horizons of a task's most recent rounds kept for horizon policies
/// ([`crate::horizon::HorizonInput::recent_horizons`]).
pub const RECENT_HORIZONS: usize = 16;

/// A closed interval on the server clock.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Interval {
    /// Start.
    pub start: Timestamp,
    /// End (never before `start` for intervals built here, except exec reports whose robot clock
    /// mapped the start after the computed end: their length is then zero).
    pub end: Timestamp,
}

impl Interval {
    /// `end − start`, zero when `end` is earlier.
    pub fn len(&self) -> Duration {
        self.end.saturating_since(self.start)
    }

    /// Whether the interval has zero length.
    pub fn is_empty(&self) -> bool {
        self.len().is_zero()
    }
}

/// The execution phase a Last Exec Info report describes.
///
/// `reference` is the time the report refers to: the request's `sent_at`, or the time of the task
/// end event. `E.end = reference + round(actions_remaining · 10⁶ / control_hz)` µs, computed in
/// `f64`. Fails on a non-finite or non-positive control frequency and on a start after `reference`.
pub fn exec_interval(report: &ExecReport, reference: Timestamp) -> Result<Interval, AdmitError> {
    let hz = f64::from(report.control_hz);
    if !hz.is_finite() || hz <= 0.0 {
        return Err(AdmitError::InvalidExecInfo(format!(
            "control frequency {} Hz is not positive",
            report.control_hz
        )));
    }
    if report.started_at > reference {
        return Err(AdmitError::InvalidExecInfo(format!(
            "execution started at {} after the report was made at {}",
            report.started_at, reference
        )));
    }
    Ok(Interval {
        start: report.started_at,
        end: reference + actions_duration(report.actions_remaining, report.control_hz),
    })
}

/// How long `actions` actions take at `control_hz` (> 0), to the microsecond.
pub fn actions_duration(actions: u32, control_hz: f32) -> Duration {
    let micros = (f64::from(actions) * 1e6 / f64::from(control_hz)).round();
    // Anything beyond ~10^12 s is nonsense from the client; saturate rather than wrap.
    if micros >= 1.8e19 {
        Duration::from_micros(u64::MAX)
    } else {
        Duration::from_micros(micros as u64)
    }
}

/// The part of a reported execution `exec` that can have run by `cut`: a newer chunk that reaches
/// the robot replaces the one executing and drops its actions not yet started, so a chunk's
/// execution ends at the newer chunk's start if that comes before the reported end.
fn executed_until(exec: Interval, cut: Timestamp) -> Interval {
    Interval {
        start: exec.start,
        end: exec.end.min(cut).max(exec.start),
    }
}

/// The longest execution of one granted chunk the idle clock waits for (see
/// [`TaskTable::new`]): a robot reporting an absurdly low control rate cannot keep a task it
/// abandoned open for longer than this past the idle timeout.
pub const MAX_GRANTED_EXECUTION: Duration = Duration::from_secs(3600);

/// Which phase of a round dominated it, and so on which side its wait is measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dominance {
    /// `|G| ≥ |E|`: the wait is measured between generations.
    Generation,
    /// `|G| < |E|`: the wait is measured between executions.
    Execution,
}

impl Dominance {
    fn of(generation: Duration, execution: Duration) -> Dominance {
        if generation >= execution {
            Dominance::Generation
        } else {
            Dominance::Execution
        }
    }
}

/// One answered round as kept in a task's (bounded) history.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundRecord {
    /// The client's round id.
    pub round: u64,
    /// Position among the task's answered rounds (0 = first).
    pub index: u64,
    /// When the request that produced it reached the scheduler.
    pub arrived_at: Timestamp,
    /// `G`: from the start of the forward pass to the end of generation.
    pub generation: Interval,
    /// `E`, once the robot reported it.
    pub execution: Option<Interval>,
    /// Actions the robot was allowed to execute.
    pub horizon: u32,
    /// `W` between this round and the next, once final.
    pub wait: Option<Duration>,
}

/// The current request of a task (pending, dispatched or generating).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Attempt {
    request: RequestId,
    round: u64,
    arrived_at: Timestamp,
    /// Handed to an engine (possibly still re-fetching its observation).
    dispatched: bool,
    gen_start: Option<Timestamp>,
}

/// What a task looked like when it ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TaskSummary {
    /// The task.
    pub task: TaskId,
    /// Its owner.
    pub robot: RobotId,
    /// How it ended.
    pub end: TaskEnd,
    /// Arrival of its first request (`t_start`).
    pub started_at: Timestamp,
    /// End of its last reported execution if the end carried one; otherwise the end event's time
    /// (for `Expired`: its last activity).
    pub ended_at: Timestamp,
    /// Answered rounds.
    pub rounds: u32,
    /// Σ |G| over every generation it received, answered or not.
    pub attained_service: Duration,
    /// Σ W_j by the dominant-phase rule.
    pub wait: Duration,
    /// Σ time its requests spent queued before their forward pass started.
    pub queued: Duration,
    /// Σ of the horizons it was answered with (actions granted).
    pub actions: u64,
    /// Requests whose generation failed.
    pub failed_attempts: u32,
    /// The request that was still pending or running when the task ended; the driver answers it
    /// with an error (a running one still reports its batch's end normally).
    pub open_request: Option<RequestId>,
}

impl TaskSummary {
    /// `ended_at − started_at`: the end-to-end latency the paper reports.
    pub fn latency(&self) -> Duration {
        self.ended_at.saturating_since(self.started_at)
    }

    /// What a priority policy may learn from it.
    pub fn finished_task(&self) -> crate::scheduler::FinishedTask {
        crate::scheduler::FinishedTask {
            task: self.task,
            rounds: self.rounds,
            latency: self.latency(),
            attained_service: self.attained_service,
            wait: self.wait,
        }
    }
}

/// One task's lifecycle: ownership, round bookkeeping and the G/E history with its wait sums.
#[derive(Clone, Debug)]
pub struct TaskRecord {
    task: TaskId,
    owner: RobotId,
    started_at: Timestamp,
    last_activity: Timestamp,
    last_round: u64,
    retry_allowed: bool,
    answered: u32,
    attempt: Option<Attempt>,
    /// The last answered round `m`: its `G`, and its `E` once reported.
    last_gen: Option<Interval>,
    last_exec: Option<Interval>,
    /// `E_{m-1}.end` while `W_{m-1}` (execution-dominated) waits for `E_m.start`.
    open_exec_wait: Option<Timestamp>,
    closed_wait: Duration,
    closed_queued: Duration,
    attained_service: Duration,
    history: VecDeque<RoundRecord>,
    history_limit: usize,
    recent_horizons: Vec<u32>,
    actions: u64,
    failed_attempts: u32,
    /// The robot's control rate, from its latest Last Exec Info.
    control_hz: Option<f32>,
    /// When the robot finishes executing the last answered chunk's `H` actions, if they were
    /// answered at a known control rate: until then the task is busy on the robot, not idle.
    granted_until: Option<Timestamp>,
    idle_deadline: Option<Timestamp>,
}

impl TaskRecord {
    fn new(task: TaskId, owner: RobotId, now: Timestamp, history_limit: usize) -> Self {
        TaskRecord {
            task,
            owner,
            started_at: now,
            last_activity: now,
            last_round: 0,
            retry_allowed: true,
            answered: 0,
            attempt: None,
            last_gen: None,
            last_exec: None,
            open_exec_wait: None,
            closed_wait: Duration::ZERO,
            closed_queued: Duration::ZERO,
            attained_service: Duration::ZERO,
            history: VecDeque::with_capacity(history_limit.min(64)),
            history_limit: history_limit.max(1),
            recent_horizons: Vec::with_capacity(RECENT_HORIZONS),
            actions: 0,
            failed_attempts: 0,
            control_hz: None,
            granted_until: None,
            idle_deadline: None,
        }
    }

    /// The task.
    pub fn id(&self) -> TaskId {
        self.task
    }

    /// The robot that owns it (the first to use its id).
    pub fn owner(&self) -> RobotId {
        self.owner
    }

    /// Arrival of its first request (`t_start` in Eq. 1).
    pub fn started_at(&self) -> Timestamp {
        self.started_at
    }

    /// Its most recent event (request, dispatch, answer).
    pub fn last_activity(&self) -> Timestamp {
        self.last_activity
    }

    /// Answered rounds.
    pub fn rounds_completed(&self) -> u32 {
        self.answered
    }

    /// The last round id accepted for this task (0 before any).
    pub fn last_round(&self) -> u64 {
        self.last_round
    }

    /// The request currently pending or running for it, with its round id.
    pub fn current_request(&self) -> Option<(RequestId, u64)> {
        self.attempt.map(|a| (a.request, a.round))
    }

    /// The most recent answered rounds, oldest first (at most `history_rounds`).
    pub fn history(&self) -> impl ExactSizeIterator<Item = &RoundRecord> {
        self.history.iter()
    }

    /// Σ |G| over every generation the task received (answered, failed or abandoned).
    pub fn attained_service(&self) -> Duration {
        self.attained_service
    }

    /// |G| of the last answered round.
    pub fn last_generation(&self) -> Option<Duration> {
        self.last_gen.map(|g| g.len())
    }

    /// |E| of the last answered round, once the robot reported it.
    pub fn last_execution(&self) -> Option<Duration> {
        self.last_exec.map(|e| e.len())
    }

    /// `E.end` of the last answered round, once the robot reported it: while the next request is
    /// pending, when the robot runs out of actions unless that request is answered.
    pub fn last_execution_end(&self) -> Option<Timestamp> {
        self.last_exec.map(|e| e.end)
    }

    /// Horizons of the most recent answered rounds, oldest first (at most [`RECENT_HORIZONS`]).
    pub fn recent_horizons(&self) -> &[u32] {
        &self.recent_horizons
    }

    /// Σ W_j at `now`, including the open round (see the module doc).
    pub fn wait_at(&self, now: Timestamp) -> Duration {
        self.closed_wait + self.provisional_exec_wait() + self.open_wait(now)
    }

    /// Σ time the task's requests spent queued before their forward pass, including the current
    /// request's wait so far.
    pub fn queued_at(&self, now: Timestamp) -> Duration {
        let open = match self.attempt {
            Some(a) if a.gen_start.is_none() => now.saturating_since(a.arrived_at),
            _ => Duration::ZERO,
        };
        self.closed_queued + open
    }

    /// Eq. 1 at `now`: `wait / (now − t_start)` in `[0, 1]`, computed as `f64` over whole
    /// microseconds (0 for a task that started at `now`).
    pub fn wait_ratio(&self, now: Timestamp) -> f64 {
        wait_ratio_micros(self.wait_at(now), now.saturating_since(self.started_at))
    }

    /// `W_{m-1}` while it waits for `E_m.start`: estimated from `G_m.end`.
    fn provisional_exec_wait(&self) -> Duration {
        match (self.open_exec_wait, self.last_gen) {
            (Some(prev_exec_end), Some(g)) => g.end.saturating_since(prev_exec_end),
            _ => Duration::ZERO,
        }
    }

    /// The wait of the pair (last answered round, current request), accrued up to `now`.
    fn open_wait(&self, now: Timestamp) -> Duration {
        let Some(g) = self.last_gen else {
            // First round: from the task's first request to G_0.start.
            let until = self.attempt.and_then(|a| a.gen_start).unwrap_or(now);
            return until.saturating_since(self.started_at);
        };
        let Some(attempt) = self.attempt else {
            // Between an answer and the next request nothing is owed yet: the next request
            // accrues retroactively from G_m.end / E_m.end.
            return Duration::ZERO;
        };
        let exec_len = self.last_exec.map(|e| e.len()).unwrap_or(Duration::ZERO);
        match Dominance::of(g.len(), exec_len) {
            Dominance::Generation => attempt.gen_start.unwrap_or(now).saturating_since(g.end),
            Dominance::Execution => {
                let exec_end = self.last_exec.map(|e| e.end).unwrap_or(g.end);
                now.saturating_since(exec_end)
            }
        }
    }

    fn push_history(&mut self, record: RoundRecord) {
        if self.history.len() == self.history_limit {
            self.history.pop_front();
        }
        self.history.push_back(record);
    }

    /// Applies `E_m` (the execution of the last answered round) reported at `reference`.
    fn apply_exec_report(&mut self, exec: Interval) {
        if self.last_gen.is_none() {
            // Nothing answered yet: there is no chunk this report can describe.
            return;
        }
        let wait = self
            .open_exec_wait
            .take()
            .map(|prev_exec_end| exec.start.saturating_since(prev_exec_end));
        if let Some(w) = wait {
            self.closed_wait += w;
        }
        let len = self.history.len();
        if len >= 2
            && let Some(prev) = self.history.get_mut(len - 2)
        {
            if let Some(w) = wait {
                prev.wait = Some(w);
            }
            // This chunk's first action ended the previous chunk's execution.
            prev.execution = prev.execution.map(|e| executed_until(e, exec.start));
        }
        self.last_exec = Some(exec);
        if let Some(last) = self.history.back_mut() {
            last.execution = Some(exec);
        }
    }

    /// The current request's generation ended with a chunk the robot executes up to `horizon`.
    fn answer(&mut self, now: Timestamp, horizon: u32) {
        let Some(attempt) = self.attempt.take() else {
            return;
        };
        let g = Interval {
            start: attempt.gen_start.unwrap_or(now),
            end: now,
        };
        self.attained_service += g.len();
        if attempt.gen_start.is_none() {
            self.closed_queued += now.saturating_since(attempt.arrived_at);
        }
        // Close W between the previous round (or the task start) and this one.
        match self.last_gen {
            None => self.closed_wait += g.start.saturating_since(self.started_at),
            Some(prev_gen) => {
                // A still-open W_{m-1} is finalised with its estimate: the round it waited for is
                // now followed by another answered round, so no report about E_m will come.
                self.closed_wait += self.provisional_exec_wait();
                self.open_exec_wait = None;
                // The chunk just generated replaces the one executing: only what that one ran
                // until now counts as its execution.
                let exec_len = self
                    .last_exec
                    .map(|e| executed_until(e, now).len())
                    .unwrap_or(Duration::ZERO);
                match Dominance::of(prev_gen.len(), exec_len) {
                    Dominance::Generation => {
                        let w = g.start.saturating_since(prev_gen.end);
                        self.closed_wait += w;
                        if let Some(prev) = self.history.back_mut() {
                            prev.wait = Some(w);
                        }
                    }
                    Dominance::Execution => {
                        self.open_exec_wait =
                            Some(self.last_exec.map(|e| e.end).unwrap_or(prev_gen.end));
                    }
                }
            }
        }
        let record = RoundRecord {
            round: attempt.round,
            index: u64::from(self.answered),
            arrived_at: attempt.arrived_at,
            generation: g,
            execution: None,
            horizon,
            wait: None,
        };
        self.push_history(record);
        self.answered = self.answered.saturating_add(1);
        self.last_gen = Some(g);
        self.last_exec = None;
        self.retry_allowed = false;
        self.actions = self.actions.saturating_add(u64::from(horizon));
        if self.recent_horizons.len() == RECENT_HORIZONS {
            self.recent_horizons.remove(0);
        }
        self.recent_horizons.push(horizon);
        self.last_activity = now;
        self.granted_until = self
            .control_hz
            .map(|hz| now + actions_duration(horizon, hz).min(MAX_GRANTED_EXECUTION));
    }

    /// The current request's generation failed: the round may be sent again.
    fn fail(&mut self, now: Timestamp) {
        let Some(attempt) = self.attempt.take() else {
            return;
        };
        if let Some(start) = attempt.gen_start {
            self.attained_service += now.saturating_since(start);
        } else {
            self.closed_queued += now.saturating_since(attempt.arrived_at);
        }
        self.failed_attempts = self.failed_attempts.saturating_add(1);
        self.retry_allowed = true;
        self.last_activity = now;
    }

    /// Drops the current request without an answer (superseded, cancelled or the task ended).
    /// Returns it. A running request's later generation time is added by
    /// [`TaskTable::abandoned_generation`].
    fn drop_attempt(&mut self, now: Timestamp) -> Option<RequestId> {
        let attempt = self.attempt.take()?;
        if attempt.gen_start.is_none() {
            self.closed_queued += now.saturating_since(attempt.arrived_at);
        }
        Some(attempt.request)
    }

    fn summary(
        &self,
        end: TaskEnd,
        ended_at: Timestamp,
        open_request: Option<RequestId>,
    ) -> TaskSummary {
        TaskSummary {
            task: self.task,
            robot: self.owner,
            end,
            started_at: self.started_at,
            ended_at,
            rounds: self.answered,
            attained_service: self.attained_service,
            wait: self.closed_wait,
            queued: self.closed_queued,
            actions: self.actions,
            failed_attempts: self.failed_attempts,
            open_request,
        }
    }
}

/// `wait / life` over whole microseconds, clamped to `[0, 1]`; 0 when `life` is zero.
///
/// This is the one definition of Eq. 1 used everywhere (policies, plugins' C twins): both operands
/// are converted from integer microseconds to `f64` (exact below 2⁵³ µs) and divided once.
pub fn wait_ratio_micros(wait: Duration, life: Duration) -> f64 {
    let life_us = crate::time::duration_micros(life);
    if life_us == 0 {
        return 0.0;
    }
    let w = crate::time::duration_micros(wait) as f64 / life_us as f64;
    w.clamp(0.0, 1.0)
}

/// What accepting a submit will do, decided before anything changes (so an `Overloaded` refusal
/// can still be returned without side effects).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SubmitPlan {
    /// The task is new.
    pub new_task: bool,
    /// An older round of the task is still pending (not yet dispatched): it will be superseded,
    /// i.e. removed from the pending set; the driver answers it with an error.
    pub supersedes_pending: Option<RequestId>,
    /// An older round of the task is dispatched or generating: it will be abandoned (its
    /// generation still counts as attained service; its answer is not a round).
    pub abandons_running: Option<RequestId>,
    exec: Option<Interval>,
}

/// Every task's lifecycle, keyed by task id, plus the ids of ended tasks (bounded) and the idle
/// deadlines for expiry.
#[derive(Clone, Debug)]
pub struct TaskTable {
    tasks: HashMap<TaskId, TaskRecord>,
    ended: HashSet<TaskId>,
    ended_order: VecDeque<TaskId>,
    ended_limit: usize,
    idle: BTreeSet<(Timestamp, TaskId)>,
    history_rounds: usize,
    idle_timeout: Duration,
}

impl TaskTable {
    /// An empty table keeping `history_rounds` rounds per task, expiring tasks idle for
    /// `idle_timeout` (counted from the end of the execution the server last granted, see
    /// `refresh_idle`, at most [`MAX_GRANTED_EXECUTION`] after the answer), and remembering the last `ended_limit` ended task ids (so late rounds of an
    /// ended task get `TaskEnded` rather than opening a new task).
    pub fn new(history_rounds: usize, idle_timeout: Duration, ended_limit: usize) -> Self {
        TaskTable {
            tasks: HashMap::new(),
            ended: HashSet::new(),
            ended_order: VecDeque::new(),
            ended_limit: ended_limit.max(1),
            idle: BTreeSet::new(),
            history_rounds: history_rounds.max(1),
            idle_timeout,
        }
    }

    /// The task's record, if it is open.
    pub fn get(&self, task: TaskId) -> Option<&TaskRecord> {
        self.tasks.get(&task)
    }

    /// Open tasks.
    pub fn len(&self) -> usize {
        self.tasks.len()
    }

    /// Whether no task is open.
    pub fn is_empty(&self) -> bool {
        self.tasks.is_empty()
    }

    /// Whether the task ended recently enough to be remembered.
    pub fn has_ended(&self, task: TaskId) -> bool {
        self.ended.contains(&task)
    }

    /// Checks a submit against ownership, round order and task state without changing anything.
    pub fn plan_submit(&self, submit: &RoundSubmit) -> Result<SubmitPlan, AdmitError> {
        if self.ended.contains(&submit.task) {
            return Err(AdmitError::TaskEnded { task: submit.task });
        }
        let exec = match &submit.last_exec {
            Some(report) => Some(exec_interval(report, submit.sent_at)?),
            None => None,
        };
        let Some(record) = self.tasks.get(&submit.task) else {
            return Ok(SubmitPlan {
                new_task: true,
                supersedes_pending: None,
                abandons_running: None,
                exec,
            });
        };
        if record.owner != submit.robot {
            return Err(AdmitError::Forbidden { task: submit.task });
        }
        if let Some(attempt) = record.attempt
            && attempt.round == submit.round
        {
            return Err(AdmitError::RoundInProgress {
                round: submit.round,
                request: attempt.request,
            });
        }
        let in_order = submit.round > record.last_round
            || (submit.round == record.last_round
                && record.retry_allowed
                && record.attempt.is_none());
        if !in_order {
            return Err(AdmitError::RoundOutOfOrder {
                last: record.last_round,
                got: submit.round,
            });
        }
        let (supersedes_pending, abandons_running) = match record.attempt {
            Some(a) if !a.dispatched => (Some(a.request), None),
            Some(a) => (None, Some(a.request)),
            None => (None, None),
        };
        Ok(SubmitPlan {
            new_task: false,
            supersedes_pending,
            abandons_running,
            exec,
        })
    }

    /// Applies a planned submit: the request `request` now carries round `submit.round`.
    ///
    /// `plan` must come from [`TaskTable::plan_submit`] on the same table state. A superseded
    /// request counts as dispatched-for-nothing only if it had started; otherwise its queueing
    /// time is kept and it simply disappears.
    pub fn apply_submit(
        &mut self,
        now: Timestamp,
        submit: &RoundSubmit,
        plan: &SubmitPlan,
        request: RequestId,
    ) {
        let history_rounds = self.history_rounds;
        let record = self
            .tasks
            .entry(submit.task)
            .or_insert_with(|| TaskRecord::new(submit.task, submit.robot, now, history_rounds));
        if plan.supersedes_pending.is_some() || plan.abandons_running.is_some() {
            record.drop_attempt(now);
        }
        if let Some(exec) = plan.exec {
            record.apply_exec_report(exec);
        }
        if let Some(hz) = submit
            .last_exec
            .as_ref()
            .map(|report| report.control_hz)
            .or(submit.control_hz)
        {
            record.control_hz = Some(hz);
        }
        record.last_round = submit.round;
        record.retry_allowed = false;
        record.attempt = Some(Attempt {
            request,
            round: submit.round,
            arrived_at: now,
            dispatched: false,
            gen_start: None,
        });
        record.last_activity = now;
        self.refresh_idle(submit.task);
    }

    /// The task's current request was placed in a batch (its observation may still be
    /// re-fetched). From now on a newer round abandons it instead of superseding it.
    pub fn dispatched(&mut self, task: TaskId, request: RequestId) {
        if let Some(attempt) = self
            .tasks
            .get_mut(&task)
            .and_then(|r| r.attempt.as_mut())
            .filter(|a| a.request == request)
        {
            attempt.dispatched = true;
        }
    }

    /// The task's current request was handed to an engine; the forward pass (`G.start`) began at
    /// `now`. Ignored unless `request` is the task's current request.
    pub fn generation_started(&mut self, now: Timestamp, task: TaskId, request: RequestId) {
        if let Some(record) = self.tasks.get_mut(&task)
            && let Some(attempt) = record.attempt.as_mut()
            && attempt.request == request
            && attempt.gen_start.is_none()
        {
            attempt.dispatched = true;
            attempt.gen_start = Some(now);
            record.closed_queued += now.saturating_since(attempt.arrived_at);
            record.last_activity = now;
        }
    }

    /// The task's current request `request` was in a batch lost with its engine before it
    /// answered: it waits in the queue again, as before dispatch. The lost forward pass counts as
    /// queueing, not as service: the robot got nothing from it. Returns false (and changes
    /// nothing) if `request` is not the task's current request.
    pub fn requeued(&mut self, now: Timestamp, task: TaskId, request: RequestId) -> bool {
        let Some(record) = self.tasks.get_mut(&task) else {
            return false;
        };
        let Some(attempt) = record.attempt.as_mut().filter(|a| a.request == request) else {
            return false;
        };
        let started = attempt.gen_start.take();
        let arrived = attempt.arrived_at;
        attempt.dispatched = false;
        if let Some(started) = started {
            // `generation_started` closed the queueing up to `started`; it is open again.
            record.closed_queued = record
                .closed_queued
                .saturating_sub(started.saturating_since(arrived));
        }
        record.last_activity = now;
        self.refresh_idle(task);
        true
    }

    /// The task's current request `request` was answered at `now` (`G.end`) with `horizon`.
    /// Returns false (and changes nothing) if `request` is not the task's current request.
    pub fn answered(
        &mut self,
        now: Timestamp,
        task: TaskId,
        request: RequestId,
        horizon: u32,
    ) -> bool {
        let Some(record) = self.tasks.get_mut(&task) else {
            return false;
        };
        if record.attempt.map(|a| a.request) != Some(request) {
            return false;
        }
        record.answer(now, horizon);
        self.refresh_idle(task);
        true
    }

    /// The task's current request `request` failed at `now`; the same round id may be sent again.
    /// Returns false if `request` is not the task's current request.
    pub fn failed(&mut self, now: Timestamp, task: TaskId, request: RequestId) -> bool {
        let Some(record) = self.tasks.get_mut(&task) else {
            return false;
        };
        if record.attempt.map(|a| a.request) != Some(request) {
            return false;
        }
        record.fail(now);
        self.refresh_idle(task);
        true
    }

    /// A generation that no longer belongs to the task's current request (it was superseded or
    /// cancelled while running) finished: its time still counts as attained service.
    pub fn abandoned_generation(&mut self, task: TaskId, generation: Duration) {
        if let Some(record) = self.tasks.get_mut(&task) {
            record.attained_service += generation;
        }
    }

    /// The pending request `request` was withdrawn (the client went away). The round may be sent
    /// again. Returns false if it is not the task's current request.
    pub fn withdrawn(&mut self, now: Timestamp, task: TaskId, request: RequestId) -> bool {
        let Some(record) = self.tasks.get_mut(&task) else {
            return false;
        };
        if record.attempt.map(|a| a.request) != Some(request) {
            return false;
        }
        record.drop_attempt(now);
        record.retry_allowed = true;
        record.last_activity = now;
        self.refresh_idle(task);
        true
    }

    /// Checks a task end without changing anything: the task must be open and owned by `robot`.
    pub fn plan_end(
        &self,
        task: TaskId,
        robot: RobotId,
        exec: Option<&ExecReport>,
        now: Timestamp,
    ) -> Result<Option<Interval>, AdmitError> {
        if self.ended.contains(&task) {
            return Err(AdmitError::TaskEnded { task });
        }
        let record = self
            .tasks
            .get(&task)
            .ok_or(AdmitError::UnknownTask { task })?;
        if record.owner != robot {
            return Err(AdmitError::Forbidden { task });
        }
        exec.map(|report| exec_interval(report, now)).transpose()
    }

    /// Ends a task at `now` (after [`TaskTable::plan_end`] accepted it). The final execution
    /// report, if any, closes the last open wait exactly; a request still open counts the wait it
    /// accrued until `now`. Returns the summary.
    pub fn end(
        &mut self,
        now: Timestamp,
        task: TaskId,
        end: TaskEnd,
        exec: Option<Interval>,
    ) -> Option<TaskSummary> {
        let mut record = self.tasks.remove(&task)?;
        if let Some(deadline) = record.idle_deadline.take() {
            self.idle.remove(&(deadline, task));
        }
        if let Some(exec) = exec {
            record.apply_exec_report(exec);
        }
        // Whatever is still open is final now.
        let open = record.provisional_exec_wait() + record.open_wait(now);
        record.closed_wait += open;
        record.open_exec_wait = None;
        let open_request = record.drop_attempt(now);
        let ended_at = match (exec, end) {
            (Some(e), _) => e.end,
            (None, TaskEnd::Expired) => record.last_activity,
            (None, _) => now,
        };
        let summary = record.summary(end, ended_at, open_request);
        self.remember_ended(task);
        Some(summary)
    }

    fn remember_ended(&mut self, task: TaskId) {
        if self.ended.insert(task) {
            self.ended_order.push_back(task);
        }
        while self.ended_order.len() > self.ended_limit {
            if let Some(old) = self.ended_order.pop_front() {
                self.ended.remove(&old);
            }
        }
    }

    /// The earliest idle-expiry deadline, if any task is idle.
    pub fn next_expiry(&self) -> Option<Timestamp> {
        self.idle.first().map(|(t, _)| *t)
    }

    /// Tasks whose idle deadline is at or before `now`, earliest first (not yet removed).
    pub fn expired(&self, now: Timestamp) -> Vec<TaskId> {
        self.idle
            .range(..=(now, TaskId(u64::MAX)))
            .map(|(_, task)| *task)
            .collect()
    }

    /// Keeps the idle index in step with the task: a task with no current request expires
    /// `idle_timeout` after its last activity, or after the robot finishes executing the chunk
    /// the server last granted it, whichever is later. A robot executing the server's own chunk
    /// is not idle, however slow its control rate: the last answer's `H` actions at the rate of
    /// its latest Last Exec Info (a task's first chunk, answered before any report, counts from
    /// its answer alone, the rate being unknown).
    fn refresh_idle(&mut self, task: TaskId) {
        let Some(record) = self.tasks.get_mut(&task) else {
            return;
        };
        let busy_until = record
            .granted_until
            .map_or(record.last_activity, |granted| {
                granted.max(record.last_activity)
            });
        let wanted = match record.attempt {
            None => Some(busy_until + self.idle_timeout),
            Some(_) => None,
        };
        if record.idle_deadline != wanted {
            if let Some(old) = record.idle_deadline.take() {
                self.idle.remove(&(old, task));
            }
            if let Some(new) = wanted {
                self.idle.insert((new, task));
            }
            record.idle_deadline = wanted;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000;

    fn t(ms: u64) -> Timestamp {
        Timestamp::from_micros(ms * MS)
    }

    fn ms(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    /// A report saying execution started at `start_ms` and had `remaining` actions left at
    /// 10 Hz (100 ms each) when sent.
    fn report(start_ms: u64, remaining: u32) -> ExecReport {
        ExecReport {
            started_at: t(start_ms),
            actions_remaining: remaining,
            control_hz: 10.0,
        }
    }

    fn submit(task: u64, round: u64, sent_ms: u64, exec: Option<ExecReport>) -> RoundSubmit {
        RoundSubmit {
            task: TaskId(task),
            robot: RobotId(1),
            round,
            sent_at: t(sent_ms),
            obs_captured_at: t(sent_ms),
            last_exec: exec,
            remaining: None,
            control_hz: None,
        }
    }

    /// Drives one task through the table like the scheduler does.
    struct Driver {
        table: TaskTable,
        next: u64,
    }

    impl Driver {
        fn new(history: usize) -> Self {
            Driver {
                table: TaskTable::new(history, Duration::from_secs(60), 1024),
                next: 0,
            }
        }

        fn submit(&mut self, at: u64, round: u64, exec: Option<ExecReport>) -> RequestId {
            let s = submit(7, round, at, exec);
            let plan = self.table.plan_submit(&s).unwrap();
            let id = RequestId(self.next);
            self.next += 1;
            self.table.apply_submit(t(at), &s, &plan, id);
            id
        }

        /// Generation of `id` from `start` to `end`, answered with horizon 5.
        fn generate(&mut self, id: RequestId, start: u64, end: u64) {
            self.table.generation_started(t(start), TaskId(7), id);
            assert!(self.table.answered(t(end), TaskId(7), id, 5));
        }

        fn record(&self) -> &TaskRecord {
            self.table.get(TaskId(7)).unwrap()
        }
    }

    #[test]
    fn a_first_round_that_reports_its_control_rate_is_not_idle_while_its_chunk_executes() {
        // A 0.4 Hz robot: H = 5 actions take 12.5 s; with a 10 s idle timeout the first chunk
        // alone outlasts it. `Submit.control_hz` tells the server the rate before any Last
        // Exec Info exists.
        let mut table = TaskTable::new(8, Duration::from_secs(10), 1024);
        let first = RoundSubmit {
            control_hz: Some(0.4),
            ..submit(7, 0, 0, None)
        };
        let plan = table.plan_submit(&first).unwrap();
        table.apply_submit(t(0), &first, &plan, RequestId(0));
        table.generation_started(t(0), TaskId(7), RequestId(0));
        assert!(table.answered(t(100), TaskId(7), RequestId(0), 5));
        // Idle only from the end of the chunk's execution: 0.1 s + 12.5 s, then 10 s.
        assert_eq!(table.next_expiry(), Some(t(100 + 12_500 + 10_000)));
        assert!(
            table.expired(t(10_100)).is_empty(),
            "10 s after the answer the robot is still executing its first chunk"
        );
        assert!(table.expired(t(22_599)).is_empty());
        assert_eq!(table.expired(t(22_600)), vec![TaskId(7)]);
    }

    #[test]
    fn a_robot_executing_the_chunk_it_was_granted_is_not_idle() {
        // A slow robot: 0.0625 Hz, 16 s per action. Each answer grants H = 5 actions = 80 s,
        // longer than the 60 s idle timeout.
        let slow = |start_ms: u64, remaining: u32| ExecReport {
            control_hz: 0.0625,
            ..report(start_ms, remaining)
        };
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 0, None);
        d.generate(r0, 0, 100);
        // Before any Last Exec Info the rate is unknown: the clock runs from the answer.
        assert_eq!(d.table.next_expiry(), Some(t(60_100)));
        let r1 = d.submit(50_000, 1, Some(slow(200, 3)));
        assert_eq!(
            d.table.next_expiry(),
            None,
            "a task with a request is never idle"
        );
        d.generate(r1, 50_000, 50_100);
        // Round 1's chunk runs until 50.1 s + 80 s; idle only after that.
        assert_eq!(d.table.next_expiry(), Some(t(130_100 + 60_000)));
        assert!(
            d.table.expired(t(110_100)).is_empty(),
            "60 s after the answer the robot is still executing the chunk"
        );
        assert!(d.table.expired(t(190_099)).is_empty());
        assert_eq!(d.table.expired(t(190_100)), vec![TaskId(7)]);

        // An absurd rate cannot keep an abandoned task open for more than an hour.
        let r2 = d.submit(60_000, 2, Some(slow(50_200, 2)));
        let crawl = ExecReport {
            control_hz: 1e-9,
            ..report(60_000, 1)
        };
        let r3 = d.submit(61_000, 3, Some(crawl));
        assert_ne!(r2, r3);
        d.generate(r3, 61_000, 61_100);
        assert_eq!(
            d.table.next_expiry(),
            Some(t(61_100) + MAX_GRANTED_EXECUTION + Duration::from_secs(60))
        );
    }

    #[test]
    fn exec_interval_uses_remaining_actions_at_control_rate() {
        let e = exec_interval(&report(1_000, 3), t(1_500)).unwrap();
        assert_eq!(e.start, t(1_000));
        assert_eq!(e.end, t(1_800), "3 actions at 10 Hz after the send time");
        assert_eq!(e.len(), ms(800));
        let bad_hz = ExecReport {
            control_hz: 0.0,
            ..report(0, 1)
        };
        assert!(matches!(
            exec_interval(&bad_hz, t(1)),
            Err(AdmitError::InvalidExecInfo(_))
        ));
        let nan_hz = ExecReport {
            control_hz: f32::NAN,
            ..report(0, 1)
        };
        assert!(exec_interval(&nan_hz, t(1)).is_err());
        assert!(
            exec_interval(&report(2_000, 1), t(1_000)).is_err(),
            "a start after the report is refused"
        );
    }

    #[test]
    fn first_round_queueing_is_wait_while_pending_and_after_dispatch() {
        let mut d = Driver::new(8);
        let r0 = d.submit(1_000, 1, None);
        // Pending: wait = now - t_start, so the ratio is 1.
        assert_eq!(d.record().wait_at(t(1_300)), ms(300));
        assert_eq!(d.record().wait_ratio(t(1_300)), 1.0);
        assert_eq!(d.record().queued_at(t(1_300)), ms(300));
        d.table.generation_started(t(1_400), TaskId(7), r0);
        // Generating: the wait stopped at G_0.start.
        assert_eq!(d.record().wait_at(t(1_900)), ms(400));
        assert_eq!(d.record().queued_at(t(1_900)), ms(400));
        assert!(d.table.answered(t(2_000), TaskId(7), r0, 5));
        assert_eq!(d.record().wait_at(t(5_000)), ms(400));
        assert_eq!(d.record().attained_service(), ms(600));
        assert_eq!(d.record().rounds_completed(), 1);
    }

    #[test]
    fn generation_dominated_round_measures_wait_between_generations() {
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 1, None);
        d.generate(r0, 0, 500); // G_0 = [0, 500], |G_0| = 500 ms
        // E_0 = [550, 550 + ...]: sent at 700 with 1 action left -> E_0.end = 800, |E_0| = 250 ms.
        let r1 = d.submit(700, 2, Some(report(550, 1)));
        assert_eq!(d.record().last_execution(), Some(ms(250)));
        // Generation-dominated: W_0 accrues from G_0.end = 500.
        assert_eq!(d.record().wait_at(t(900)), ms(400));
        d.generate(r1, 1_000, 1_500);
        // W_0 = G_1.start - G_0.end = 500, final.
        assert_eq!(d.record().wait_at(t(9_000)), ms(500));
        let h: Vec<_> = d.record().history().copied().collect();
        assert_eq!(h[0].wait, Some(ms(500)));
        assert_eq!(h[0].execution.map(|e| e.len()), Some(ms(250)));
        assert_eq!(h[1].generation.len(), ms(500));
    }

    #[test]
    fn execution_dominated_round_measures_wait_between_executions() {
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 1, None);
        d.generate(r0, 0, 100); // |G_0| = 100
        // E_0 = [150, 1_150]: sent at 650 with 5 actions left (500 ms). |E_0| = 1 s.
        let r1 = d.submit(650, 2, Some(report(150, 5)));
        // While E_0 runs, queueing is not wait.
        assert_eq!(d.record().wait_at(t(1_000)), Duration::ZERO);
        // After E_0.end the robot idles: wait accrues.
        assert_eq!(d.record().wait_at(t(1_250)), ms(100));
        d.generate(r1, 1_300, 1_400);
        // Until E_1.start is reported, W_0 is estimated from G_1.end: 1_400 - 1_150.
        assert_eq!(d.record().wait_at(t(2_000)), ms(250));
        // The robot reports it started E_1 at 1_420: W_0 = 1_420 - 1_150 = 270.
        let _r2 = d.submit(1_600, 3, Some(report(1_420, 10)));
        let h: Vec<_> = d.record().history().copied().collect();
        assert_eq!(h[0].wait, Some(ms(270)));
        // E_1 = [1_420, 2_600] is execution-dominated over |G_1| = 100: nothing accrues yet.
        assert_eq!(d.record().wait_at(t(2_500)), ms(270));
        assert_eq!(d.record().wait_at(t(2_700)), ms(370));
    }

    #[test]
    fn a_replaced_chunk_counts_only_its_executed_actions() {
        // 20 Hz (50 ms per action), chunks of 10. G_0 = [0, 300]; chunk 0's first action starts
        // at 300 and round 1 goes out at once with 9 actions left: E_0 as reported is
        // [300, 300 + 9 × 50] = [300, 750], 450 ms. Round 1 is generated 400..550 and its chunk
        // takes over at the tick of 550, dropping chunk 0's last 4 actions: chunk 0 executed
        // 300..550, 250 ms. So |G_0| = 300 ≥ |E_0| = 250: round 0 is generation-dominated and
        // W_0 = G_1.start − G_0.end = 100 ms (counting the tail, 300 < 450, would have made it
        // execution-dominated with W_0 = max(0, E_1.start − 750) = 0).
        let at_20hz = |start_ms: u64, remaining: u32| ExecReport {
            started_at: t(start_ms),
            actions_remaining: remaining,
            control_hz: 20.0,
        };
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 1, None);
        d.generate(r0, 0, 300);
        let r1 = d.submit(300, 2, Some(at_20hz(300, 9)));
        assert_eq!(d.record().last_execution(), Some(ms(450)), "as reported");
        d.generate(r1, 400, 550);
        assert_eq!(d.record().wait_at(t(600)), ms(100));
        // Round 2 reports chunk 1 starting at 550: the history keeps what chunk 0 executed.
        let _r2 = d.submit(700, 3, Some(at_20hz(550, 7)));
        let h: Vec<_> = d.record().history().copied().collect();
        assert_eq!(h[0].execution.map(|e| e.len()), Some(ms(250)));
        assert_eq!(h[0].wait, Some(ms(100)));
        assert_eq!(d.record().wait_at(t(700)), ms(100));
    }

    #[test]
    fn unreported_execution_counts_as_generation_dominated() {
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 1, None);
        d.generate(r0, 0, 100);
        let _r1 = d.submit(2_000, 2, None);
        assert_eq!(d.record().last_execution(), None);
        assert_eq!(d.record().wait_at(t(2_500)), ms(2_400));
    }

    #[test]
    fn task_end_report_closes_the_last_execution_wait_exactly() {
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 1, None);
        d.generate(r0, 0, 100);
        let r1 = d.submit(650, 2, Some(report(150, 5))); // E_0.end = 1_150, exec-dominated
        d.generate(r1, 1_300, 1_400);
        let exec = d
            .table
            .plan_end(TaskId(7), RobotId(1), Some(&report(1_500, 2)), t(3_000))
            .unwrap();
        let s = d
            .table
            .end(t(3_000), TaskId(7), TaskEnd::Done, exec)
            .unwrap();
        // W_0 = E_1.start - E_0.end = 1_500 - 1_150; no W after the last round.
        assert_eq!(s.wait, ms(350));
        assert_eq!(s.ended_at, t(3_200), "E_1.end = end time + 2 actions");
        assert_eq!(s.latency(), ms(3_200));
        assert_eq!(s.rounds, 2);
        assert_eq!(s.actions, 10);
        assert_eq!(s.attained_service, ms(200));
        assert_eq!(s.queued, ms(650), "0 ms for round 0, 650 ms for round 1");
        assert!(d.table.has_ended(TaskId(7)));
        assert_eq!(
            d.table.plan_submit(&submit(7, 9, 4_000, None)),
            Err(AdmitError::TaskEnded { task: TaskId(7) })
        );
    }

    #[test]
    fn round_ownership_order_retry_and_supersede() {
        let mut d = Driver::new(8);
        let r0 = d.submit(0, 5, None);
        let other = RoundSubmit {
            robot: RobotId(2),
            ..submit(7, 6, 10, None)
        };
        assert_eq!(
            d.table.plan_submit(&other),
            Err(AdmitError::Forbidden { task: TaskId(7) })
        );
        assert_eq!(
            d.table.plan_submit(&submit(7, 5, 10, None)),
            Err(AdmitError::RoundInProgress {
                round: 5,
                request: r0
            })
        );
        assert_eq!(
            d.table.plan_submit(&submit(7, 4, 10, None)),
            Err(AdmitError::RoundOutOfOrder { last: 5, got: 4 })
        );
        // A newer round while round 5 is still pending supersedes it.
        let plan = d.table.plan_submit(&submit(7, 6, 10, None)).unwrap();
        assert_eq!(plan.supersedes_pending, Some(r0));
        assert_eq!(plan.abandons_running, None);
        let r1 = d.submit(10, 6, None);
        assert_eq!(d.record().current_request(), Some((r1, 6)));
        // Once running, a newer round abandons it instead.
        d.table.generation_started(t(20), TaskId(7), r1);
        let plan = d.table.plan_submit(&submit(7, 7, 30, None)).unwrap();
        assert_eq!(plan.abandons_running, Some(r1));
        // A failed round may be sent again with the same id, but an answered one may not.
        let r2 = d.submit(30, 7, None);
        assert!(d.table.failed(t(40), TaskId(7), r2));
        assert!(d.table.plan_submit(&submit(7, 7, 50, None)).is_ok());
        let r3 = d.submit(50, 7, None);
        d.generate(r3, 60, 70);
        assert_eq!(
            d.table.plan_submit(&submit(7, 7, 80, None)),
            Err(AdmitError::RoundOutOfOrder { last: 7, got: 7 })
        );
        // The superseded and failed attempts left no rounds; the first-round wait ran until
        // the successful G_0.start.
        assert_eq!(d.record().rounds_completed(), 1);
        assert_eq!(d.record().wait_at(t(80)), ms(60));
        assert_eq!(d.record().history().next().map(|r| r.round), Some(7));
    }

    #[test]
    fn idle_tasks_expire_after_the_timeout_and_busy_ones_do_not() {
        let mut table = TaskTable::new(8, Duration::from_secs(10), 4);
        let s = submit(1, 1, 0, None);
        let plan = table.plan_submit(&s).unwrap();
        table.apply_submit(t(0), &s, &plan, RequestId(0));
        assert_eq!(
            table.next_expiry(),
            None,
            "a pending request keeps the task alive"
        );
        table.generation_started(t(100), TaskId(1), RequestId(0));
        table.answered(t(200), TaskId(1), RequestId(0), 3);
        assert_eq!(table.next_expiry(), Some(t(10_200)));
        assert!(table.expired(t(10_199)).is_empty());
        assert_eq!(table.expired(t(10_200)), vec![TaskId(1)]);
        let s = table
            .end(t(10_200), TaskId(1), TaskEnd::Expired, None)
            .unwrap();
        assert_eq!(
            s.ended_at,
            t(200),
            "an expired task ended at its last activity"
        );
        assert_eq!(table.next_expiry(), None);
    }

    #[test]
    fn ended_task_memory_is_bounded() {
        let mut table = TaskTable::new(8, Duration::from_secs(10), 2);
        for task in 0..3 {
            let s = submit(task, 1, 0, None);
            let plan = table.plan_submit(&s).unwrap();
            table.apply_submit(t(0), &s, &plan, RequestId(task));
            table.end(t(1), TaskId(task), TaskEnd::Done, None);
        }
        assert!(
            !table.has_ended(TaskId(0)),
            "the oldest ended id was forgotten"
        );
        assert!(table.has_ended(TaskId(1)) && table.has_ended(TaskId(2)));
    }

    /// Recomputes Σ W_j from a full history with the rule written out directly.
    fn naive_wait(rounds: &[(Interval, Option<Interval>)], t_start: Timestamp) -> Duration {
        let mut w = rounds[0].0.start.saturating_since(t_start);
        for pair in rounds.windows(2) {
            let (g, e) = pair[0];
            let (g_next, e_next) = pair[1];
            // A chunk executes at most until the next one is generated.
            let e_len = e
                .map(|e| executed_until(e, g_next.end).len())
                .unwrap_or_default();
            w += if g.len() >= e_len {
                g_next.start.saturating_since(g.end)
            } else {
                let next_start = e_next.map(|e| e.start).unwrap_or(g_next.end);
                next_start.saturating_since(e.map(|e| e.end).unwrap_or(g.end))
            };
        }
        w
    }

    #[test]
    fn folding_beyond_the_history_bound_keeps_the_sums_exact() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut small = Driver::new(2);
        let mut large = Driver::new(10_000);
        let mut clock = 0u64;
        for round in 1..=200u64 {
            let exec = if round == 1 {
                None
            } else {
                let started = clock + rng.random_range(0..50);
                Some(report(started, rng.random_range(0..20)))
            };
            clock += rng.random_range(50..400);
            let a = small.submit(clock, round, exec);
            let b = large.submit(clock, round, exec);
            let start = clock + rng.random_range(0..300);
            clock = start + rng.random_range(50..400);
            small.generate(a, start, clock);
            large.generate(b, start, clock);
            if round % 37 == 0 {
                assert_eq!(
                    small.record().wait_at(t(clock)),
                    large.record().wait_at(t(clock))
                );
            }
        }
        assert_eq!(small.record().history().len(), 2);
        assert_eq!(large.record().history().len(), 200);
        let end_report = report(clock + 20, 4);
        let exec = small
            .table
            .plan_end(TaskId(7), RobotId(1), Some(&end_report), t(clock + 30))
            .unwrap();
        // The unbounded history, with the end report as the last round's execution.
        let mut rounds: Vec<_> = large
            .record()
            .history()
            .map(|r| (r.generation, r.execution))
            .collect();
        if let Some(last) = rounds.last_mut() {
            last.1 = exec;
        }
        let t_start = large.record().started_at();
        let a = small
            .table
            .end(t(clock + 30), TaskId(7), TaskEnd::Done, exec)
            .unwrap();
        let b = large
            .table
            .end(t(clock + 30), TaskId(7), TaskEnd::Done, exec)
            .unwrap();
        assert_eq!(
            a, b,
            "bounded and unbounded histories give identical summaries"
        );
        assert_eq!(a.wait, naive_wait(&rounds, t_start));
        assert!(a.wait > Duration::ZERO);
    }
}
