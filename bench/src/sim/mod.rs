//! The virtual-time simulator: trace replay against the real scheduler.
//!
//! A discrete-event simulation in the style of quinn-proto's test `Pair`: events sit on a binary
//! heap in virtual time, and the loop jumps from one to the next. It drives the *same*
//! [`Scheduler`] (policy, batching, placement, re-fetch, skip counters) and the same horizon
//! policies as the live server, through the same event API; only the robots, the network and
//! the engines are modelled:
//!
//! - **Robots** replay traces (`kairos_sdk::trace`): a robot issues round `i` when it has
//!   executed `issued_at_action` actions and holds the reply to round `i − 1` (paper §5.1,
//!   "at the recorded action index"), and executes chunks by the shared execution rule
//!   ([`robot`]).
//! - **The work is the recording's.** Round `i`'s chunk covers the steps its recording says
//!   (`aligned_at_action`, `horizon`), whatever the load and whether the scheduler re-fetched its
//!   observation: a replay has only the recorded chunk, meant for the recorded steps. A late
//!   reply therefore stalls the robot (it runs out of actions and idles) and never lets it skip
//!   recorded rounds, so every system is asked for exactly the recorded rounds of each task
//!   (paper §5.1: "faithfully preserving the original execution horizon"). A re-fetch costs its
//!   fetch (half a round trip out, the observation back) before the forward pass; what a fresher
//!   observation buys — accuracy — is not something a latency replay can measure.
//! - **Network**: robot ↔ edge is a fixed round trip plus the observation's transfer time on the
//!   uplink; edge ↔ cloud is each cloud engine's `rtt` plus the batch's observations on the WAN.
//! - **Engines** take `profile.latency(batch)` per batch.
//!
//! Everything is a function of the trace set, the configuration and the seed: same inputs,
//! same numbers. No I/O, and no clock except in [`simulate_timed`], which reads a real clock
//! around each call into the scheduler to measure what its decisions cost (the scale
//! experiment); the simulation itself is the same.

pub mod experiment;
pub mod horizon;
pub mod plugins;
pub mod robot;
pub mod scale;
pub mod stats;
#[cfg(test)]
mod tests;

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::time::{Duration, Instant};

use kairos_engine::profile::thread_cpu_time;
use kairos_sdk::trace::{
    HorizonSetting, RoundEvent, RoundTrace, TaskMeta, TaskRecording, TaskTrace, TraceSet,
};
use rand::{Rng, SeedableRng, rngs::StdRng};

use horizon::{ReplayHorizon, ReplayHorizonError};
use kairos_core::registry::{HorizonRegistry, Policies};
use kairos_core::scheduler::{
    AdmitError, BatchId, Dispatch, EngineSpec, ExecReport, PolicySpec, RemainingWork, RequestId,
    RobotId, RoundOutcome, RoundSubmit, Scheduler, SchedulerConfig, SchedulerCounters, TaskEnd,
    TaskId, Tier,
};
use kairos_core::time::Timestamp;
use robot::{Accepted, Execution};

/// How tasks arrive.
#[derive(Clone, Debug, PartialEq)]
pub enum Load {
    /// Online serving: `tasks` tasks sampled from the trace set arrive as a Poisson process.
    Poisson {
        /// Mean arrivals per second.
        rate: f64,
        /// Tasks in the run.
        tasks: usize,
    },
    /// Offline: `robots` robots work through a fixed list of `tasks` tasks, each robot taking the
    /// next task the moment it finishes one.
    Fleet {
        /// Robots.
        robots: usize,
        /// Tasks in the list.
        tasks: usize,
    },
    /// Exactly these tasks (trace task ids) starting at exactly these times, one robot each: for
    /// hand-computed scenarios and replaying a single recording.
    Explicit(Vec<(Timestamp, u64)>),
}

/// The modelled network.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimNetwork {
    /// Robot ↔ edge server round trip.
    pub robot_rtt: Duration,
    /// Robot → edge uplink, Mbit/s.
    pub robot_uplink_mbps: f64,
    /// Edge → cloud bandwidth, Mbit/s (the round trip is each cloud engine's `rtt`).
    pub wan_mbps: f64,
}

/// One simulation run.
#[derive(Clone, Debug)]
pub struct SimConfig {
    /// Engine instances, as the scheduler sees them.
    pub engines: Vec<EngineSpec>,
    /// Scheduler tunables.
    pub scheduler: SchedulerConfig,
    /// The priority policy.
    pub policy: PolicySpec,
    /// Which recorded variant of each task to replay (`static`, `dynamic`).
    pub setting: String,
    /// The network.
    pub network: SimNetwork,
    /// Whether robots send the remaining-work hint (rounds and seconds left in their trace).
    pub hints: bool,
    /// Arrivals.
    pub load: Load,
    /// Seed for task sampling and arrival times.
    pub seed: u64,
    /// Record what every replayed robot experienced as traces (`SimResult::recorded`), with the
    /// same recorder a live robot uses.
    pub record: bool,
    /// Policies beyond the natives (users' plugins), resolved by name like the natives:
    /// `policy` and each trace's horizon setting may name one.
    pub policies: Policies,
    /// Replay every task's chunks with this horizon policy instead of the one its recording
    /// names (`None`: the recording's). The rounds stay the recording's; only how much of each
    /// chunk runs changes. How a policy that reads the server's load, which no recording can
    /// know, is measured (`load-horizon` experiment).
    pub replay_horizon: Option<HorizonSetting>,
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The trace set has no task under the requested setting.
    #[error("the trace set has no task recorded under setting `{0}`")]
    NoTasks(String),
    /// The policy name is not registered, or its parameters are wrong.
    #[error("policy: {0}")]
    Policy(String),
    /// A horizon policy failed.
    #[error(transparent)]
    Horizon(#[from] ReplayHorizonError),
    /// The scheduler refused something the robots did. A simulated robot follows the protocol,
    /// so this is a bug in the simulator or the scheduler, never load.
    #[error("scheduler refused a {what} at {at}")]
    Admit {
        /// What was refused.
        what: &'static str,
        /// When.
        at: Timestamp,
        /// Why.
        source: AdmitError,
    },
    /// The configuration is unusable.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// Recording a replayed task failed (the replay broke a trace invariant).
    #[error("recording a replayed task failed")]
    Record(#[from] kairos_sdk::trace::TraceError),
}

fn record(recording: &mut Option<TaskRecording>, event: RoundEvent) -> Result<(), SimError> {
    if let Some(r) = recording {
        r.record(event)?;
    }
    Ok(())
}

/// One task's outcome.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TaskResult {
    /// Trace task id.
    pub trace_task: u64,
    /// When its first request was sent.
    pub started_at: Timestamp,
    /// First request to last action executed, seconds (the paper's end-to-end latency).
    pub latency_s: f64,
    /// Its actions at the control frequency, seconds: the latency with no waiting at all.
    pub execution_s: f64,
    /// Rounds requested.
    pub rounds: u32,
}

/// What one run produced.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SimResult {
    /// Every task, in completion order.
    pub tasks: Vec<TaskResult>,
    /// Round requests submitted.
    pub requests: u64,
    /// Batches run.
    pub batches: u64,
    /// Requests whose observation was re-fetched before dispatch.
    pub refetches: u64,
    /// Requests served by cloud engines.
    pub cloud_requests: u64,
    /// Σ over requests of (dispatch − arrival at the server), seconds.
    pub queue_s: f64,
    /// Virtual time when the last task finished, seconds.
    pub makespan_s: f64,
    /// Events processed.
    pub events: u64,
    /// With `SimConfig::record`: every task as its robot experienced it, in completion order.
    pub recorded: Vec<TaskTrace>,
    /// The scheduler's running totals at the end of the run.
    pub scheduler: SchedulerCounters,
    /// Σ over answered requests of the horizon chosen.
    pub horizon_sum: u64,
    /// Actions executed past their chunk's recorded horizon (the recording's policy's cut, e.g.
    /// the threshold rule's): open-loop actions a longer replayed horizon added.
    pub beyond_cut_actions: u64,
}

/// What the scheduler's calls cost in wall-clock time during one run ([`simulate_timed`]).
///
/// Measured with a real clock around each call into the scheduler and nothing else, so it is
/// the scheduler's own cost, whatever the simulator spends on robots, network and engines.
/// Unlike everything else the simulator reports, these numbers depend on the machine and its
/// load. Wall time also counts the time the thread waited for a core on a shared machine; the
/// thread's CPU time does not, so the decisions and the whole run are measured both ways.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SchedulerTiming {
    /// Wall time of each `poll_dispatch` call that made a decision, seconds, in order.
    pub decisions: Vec<f64>,
    /// The thread's CPU time in each of those calls, seconds, same order (empty where the
    /// platform has no thread CPU clock).
    pub decisions_cpu: Vec<f64>,
    /// Σ over decisions of the requests pending when it was made.
    pub decision_pending: u64,
    /// Most requests pending at one decision.
    pub max_pending: usize,
    /// Batches the decisions formed.
    pub decision_batches: u64,
    /// `poll_dispatch` calls that made no decision (every engine busy, or nothing pending).
    pub idle_polls: u64,
    /// Their wall time, seconds.
    pub idle_polls_s: f64,
    /// Every other call into the scheduler (submit, batch started / generation ended / batch
    /// finished, cancel, task end, timeouts).
    pub events: u64,
    /// Their wall time, seconds.
    pub events_s: f64,
    /// Wall time of the whole event loop (simulator and scheduler), seconds.
    pub run_s: f64,
    /// The thread's CPU time in the whole event loop, seconds (0 without a thread CPU clock).
    pub run_cpu_s: f64,
}

impl SchedulerTiming {
    /// Wall time in all calls into the scheduler, seconds.
    pub fn scheduler_s(&self) -> f64 {
        self.decisions.iter().sum::<f64>() + self.idle_polls_s + self.events_s
    }

    /// Times one call that is not a decision; a no-op wrapper when not timing.
    fn event<R>(timing: &mut Option<Self>, call: impl FnOnce() -> R) -> R {
        let Some(t) = timing else {
            return call();
        };
        let start = Instant::now();
        let out = call();
        t.events_s += start.elapsed().as_secs_f64();
        t.events += 1;
        out
    }
}

impl SimResult {
    /// Mean horizon over answered requests.
    pub fn mean_horizon(&self) -> f64 {
        if self.requests == 0 {
            0.0
        } else {
            self.horizon_sum as f64 / self.requests as f64
        }
    }

    /// Mean requests per batch.
    pub fn mean_batch(&self) -> f64 {
        if self.batches == 0 {
            0.0
        } else {
            self.requests as f64 / self.batches as f64
        }
    }

    /// End-to-end latencies, seconds, in completion order.
    pub fn latencies(&self) -> Vec<f64> {
        self.tasks.iter().map(|t| t.latency_s).collect()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Event {
    /// A task instance begins: its robot sends round 0.
    Start { inst: usize },
    /// A robot timer: trigger the next request or finish the task (ignored if `timer` is old).
    Wake { inst: usize, timer: u64 },
    /// A round request reaches the server.
    Submit { inst: usize },
    /// A batch's re-fetches are done: the forward pass begins.
    BatchStart { batch: u64 },
    /// A batch's forward pass is done.
    BatchDone { batch: u64 },
    /// A reply reaches its robot.
    Reply { inst: usize, horizon: u32 },
}

struct Outstanding {
    round: usize,
    sent_at: Timestamp,
    /// Actions started when the request went out (its observation's step).
    obs_step: u32,
    /// The step the chunk's action 0 is meant for: the recording's alignment of this round.
    aligned: u32,
    obs_bytes: u32,
    request: Option<RequestId>,
    /// Generation time of its batch, once finished.
    inference: Duration,
}

struct Instance<'a> {
    trace: &'a TaskTrace,
    robot: RobotId,
    task: TaskId,
    exec: Execution,
    horizon: ReplayHorizon,
    sent: usize,
    outstanding: Option<Outstanding>,
    started_at: Timestamp,
    timer: u64,
    done: bool,
    /// The round whose chunk is executing, the step it took over at, and the end of its
    /// recorded horizon (`aligned + recorded H`).
    running: Option<(usize, u32, u32)>,
    recording: Option<TaskRecording>,
}

impl Instance<'_> {
    /// Round `i` of the trace; past the end (only possible if replay drifted from the
    /// recording) the last round is repeated, issued when the robot runs dry.
    fn round(&self, i: usize) -> (&RoundTrace, u32) {
        let rounds = &self.trace.rounds;
        match rounds.get(i) {
            Some(r) => (r, r.issued_at_action),
            None => (&rounds[rounds.len() - 1], self.exec.until()),
        }
    }
}

struct InFlight {
    requests: Vec<(RequestId, usize)>,
    generation: Duration,
}

/// The simulation state: the real scheduler plus modelled robots, network and engines.
struct Sim<'a> {
    cfg: &'a SimConfig,
    /// Natives and `cfg.policies`: what each task's horizon setting is resolved in.
    horizons: HorizonRegistry,
    sched: Scheduler,
    queue: BinaryHeap<Reverse<(Timestamp, u64, Event)>>,
    seq: u64,
    insts: Vec<Instance<'a>>,
    requests: HashMap<RequestId, usize>,
    batches: HashMap<u64, InFlight>,
    /// Fleet mode: the task list and the next entry to hand out.
    backlog: Vec<&'a TaskTrace>,
    next_backlog: usize,
    arrived_at_server: HashMap<RequestId, Timestamp>,
    out: SimResult,
    /// With [`simulate_timed`]: the wall-clock cost of the scheduler calls.
    timing: Option<SchedulerTiming>,
}

fn transfer(bytes: u32, mbps: f64) -> Duration {
    crate::workload::generate::transfer_time(bytes, mbps)
}

impl<'a> Sim<'a> {
    fn push(&mut self, at: Timestamp, ev: Event) {
        self.seq += 1;
        self.queue.push(Reverse((at, self.seq, ev)));
    }

    fn one_way(&self) -> Duration {
        self.cfg.network.robot_rtt / 2
    }

    fn spawn(
        &mut self,
        trace: &'a TaskTrace,
        robot: RobotId,
        at: Timestamp,
    ) -> Result<(), SimError> {
        let inst = self.insts.len();
        let recording = self.cfg.record.then(|| {
            TaskRecording::new(TaskMeta {
                task: trace.task,
                label: trace.label.clone(),
                setting: trace.setting.clone(),
                horizon: trace.horizon.clone(),
                control_hz: trace.control_hz,
                chunk_len: trace.chunk_len,
            })
        });
        self.insts.push(Instance {
            trace,
            robot,
            task: TaskId(inst as u64),
            exec: Execution::new(trace.control_hz),
            horizon: ReplayHorizon::with_registry(
                self.cfg.replay_horizon.as_ref().unwrap_or(&trace.horizon),
                &self.horizons,
            )?,
            sent: 0,
            outstanding: None,
            started_at: at,
            timer: 0,
            done: false,
            running: None,
            recording,
        });
        self.push(at, Event::Start { inst });
        Ok(())
    }

    /// Plans the robot's next timer: finishing the task, or sending the next request.
    fn plan(&mut self, inst: usize, now: Timestamp) {
        let i = &mut self.insts[inst];
        i.timer += 1;
        let timer = i.timer;
        if i.done {
            return;
        }
        let total = i.trace.total_actions;
        let at = if i.exec.until() >= total {
            i.exec.reaches(total)
        } else if i.outstanding.is_none() {
            let (_, step) = i.round(i.sent);
            i.exec.reaches(step.min(i.exec.until()))
        } else {
            None
        };
        if let Some(at) = at {
            self.push(at.max(now), Event::Wake { inst, timer });
        }
    }

    fn send(&mut self, inst: usize, now: Timestamp) -> Result<(), SimError> {
        let obs_step = self.insts[inst].exec.started_at(now);
        self.send_observed(inst, now, obs_step)
    }

    /// Sends the next round at `now` with an observation taken after `obs_step` started actions.
    fn send_observed(
        &mut self,
        inst: usize,
        now: Timestamp,
        obs_step: u32,
    ) -> Result<(), SimError> {
        let one_way = self.one_way();
        let i = &mut self.insts[inst];
        let round = i.sent;
        i.sent += 1;
        let obs_bytes = i.round(round).0.obs_bytes;
        // A round past the recording (only after the replay drifted from it) is aligned where it
        // was sent.
        let aligned = i
            .trace
            .rounds
            .get(round)
            .map_or(obs_step, RoundTrace::aligned_at_action);
        i.outstanding = Some(Outstanding {
            round,
            sent_at: now,
            obs_step,
            aligned,
            obs_bytes,
            request: None,
            inference: Duration::ZERO,
        });
        record(
            &mut i.recording,
            RoundEvent::Requested {
                round: round as u64,
                at_action: obs_step,
                sent_at_us: now.as_micros(),
                obs_bytes,
            },
        )?;
        let arrive = now + one_way + transfer(obs_bytes, self.cfg.network.robot_uplink_mbps);
        self.out.requests += 1;
        self.push(arrive, Event::Submit { inst });
        Ok(())
    }

    fn submit(&mut self, inst: usize, now: Timestamp) -> Result<(), SimError> {
        let i = &self.insts[inst];
        let Some(o) = &i.outstanding else {
            return Ok(());
        };
        // As the SDK reports it: a chunk that arrived but whose first action has not started yet
        // counts as starting at the send time.
        let last_exec = i.exec.chunk_started_at().map(|started_at| ExecReport {
            started_at: started_at.min(o.sent_at),
            actions_remaining: i.exec.until().saturating_sub(o.obs_step),
            control_hz: i.trace.control_hz,
        });
        // What the SDK runner sends: rounds left, this one included.
        let remaining = self.cfg.hints.then(|| RemainingWork {
            rounds: Some(i.trace.rounds.len().saturating_sub(o.round).max(1) as u32),
            seconds: None,
        });
        let submit = RoundSubmit {
            task: i.task,
            robot: i.robot,
            round: o.round as u64,
            sent_at: o.sent_at,
            obs_captured_at: o.sent_at,
            last_exec: if o.round == 0 { None } else { last_exec },
            remaining,
            control_hz: None,
        };
        let id = SchedulerTiming::event(&mut self.timing, || self.sched.handle_submit(now, submit))
            .map_err(|source| SimError::Admit {
                what: "submit",
                at: now,
                source,
            })?;
        if let Some(o) = &mut self.insts[inst].outstanding {
            o.request = Some(id);
        }
        self.requests.insert(id, inst);
        self.arrived_at_server.insert(id, now);
        self.dispatch(now);
        Ok(())
    }

    fn dispatch(&mut self, now: Timestamp) {
        let decisions = self.sched.counters().decisions;
        // The CPU clock is a system call: read only when a decision is due (an idle engine and a
        // pending request, as `poll_dispatch` decides), outside the wall-clock window.
        let due = self.timing.is_some()
            && self.sched.pending_len() > 0
            && self.sched.engines().any(|e| e.batch.is_none());
        let cpu = if due { thread_cpu_time() } else { None };
        let start = self.timing.is_some().then(Instant::now);
        let dispatches = self.sched.poll_dispatch(now);
        if let (Some(t), Some(start)) = (&mut self.timing, start) {
            let wall = start.elapsed().as_secs_f64();
            let cpu = cpu
                .zip(thread_cpu_time())
                .map(|(a, b)| b.saturating_sub(a).as_secs_f64());
            if self.sched.counters().decisions > decisions {
                t.decisions.push(wall);
                t.decisions_cpu.extend(cpu);
                let pending = self.sched.last_decision().map_or(0, |d| d.pending);
                t.decision_pending += pending as u64;
                t.max_pending = t.max_pending.max(pending);
                t.decision_batches += dispatches.len() as u64;
            } else {
                t.idle_polls += 1;
                t.idle_polls_s += wall;
            }
        }
        for d in dispatches {
            self.start_batch(d, now);
        }
    }

    fn start_batch(&mut self, d: Dispatch, now: Timestamp) {
        let one_way = self.one_way();
        let engine = &self.cfg.engines[d.engine.0];
        let mut ready = now;
        let mut wan_bytes = 0u32;
        let mut requests = Vec::with_capacity(d.requests.len());
        for r in &d.requests {
            let Some(&inst) = self.requests.get(&r.request) else {
                continue;
            };
            if let Some(arrived) = self.arrived_at_server.remove(&r.request) {
                self.out.queue_s += now.saturating_since(arrived).as_secs_f64();
            }
            let Some(o) = &self.insts[inst].outstanding else {
                continue;
            };
            let bytes = o.obs_bytes;
            if r.refetch {
                // The fetch reaches the robot, which sends a fresh observation back. The chunk
                // stays the recorded one, for the recorded steps (module doc: the work is the
                // recording's).
                let back =
                    now + one_way + one_way + transfer(bytes, self.cfg.network.robot_uplink_mbps);
                ready = ready.max(back);
                self.out.refetches += 1;
            }
            wan_bytes = wan_bytes.saturating_add(bytes);
            requests.push((r.request, inst));
        }
        let mut duration = engine.profile.latency(d.requests.len() as u32);
        if engine.tier == Tier::Cloud {
            duration += engine.rtt + transfer(wan_bytes, self.cfg.network.wan_mbps);
            self.out.cloud_requests += requests.len() as u64;
        }
        self.out.batches += 1;
        let batch = d.batch.0;
        self.batches.insert(
            batch,
            InFlight {
                requests,
                generation: duration,
            },
        );
        if ready > now {
            self.push(ready, Event::BatchStart { batch });
        } else {
            SchedulerTiming::event(&mut self.timing, || {
                self.sched.handle_batch_started(now, d.batch)
            });
        }
        self.push(ready + duration, Event::BatchDone { batch });
    }

    fn batch_done(&mut self, batch: u64, now: Timestamp) -> Result<(), SimError> {
        let Some(flight) = self.batches.remove(&batch) else {
            return Ok(());
        };
        // Generation ends now; the horizon policies take no virtual time, so the outcomes follow
        // at the same instant (the live driver reports both, with the policies in between).
        SchedulerTiming::event(&mut self.timing, || {
            self.sched.handle_generation_ended(now, BatchId(batch))
        });
        // The load the batch's horizon policies see: taken as the live driver takes it, right
        // after the generation ended and before the next dispatch decision.
        let load = self.sched.load(now);
        let one_way = self.one_way();
        let mut outcomes = Vec::with_capacity(flight.requests.len());
        for &(request, inst) in &flight.requests {
            let i = &mut self.insts[inst];
            let Some(o) = &mut i.outstanding else {
                continue;
            };
            o.inference = flight.generation;
            let round_index = o.round;
            let rounds = &i.trace.rounds;
            let r = &rounds[round_index.min(rounds.len() - 1)];
            let horizon = i.horizon.choose_under(
                r,
                round_index as u64,
                i.trace.chunk_len,
                i.trace.control_hz,
                Some(load),
            )?;
            self.out.horizon_sum += u64::from(horizon);
            outcomes.push((request, RoundOutcome::Answered { horizon }));
            self.requests.remove(&request);
            self.push(now + one_way, Event::Reply { inst, horizon });
        }
        SchedulerTiming::event(&mut self.timing, || {
            self.sched
                .handle_batch_finished(now, BatchId(batch), &outcomes)
        });
        self.dispatch(now);
        Ok(())
    }

    fn reply(&mut self, inst: usize, horizon: u32, now: Timestamp) -> Result<(), SimError> {
        let i = &mut self.insts[inst];
        let Some(o) = i.outstanding.take() else {
            return Ok(());
        };
        let (recorded_round, _) = i.round(o.round);
        let confidence = recorded_round.confidence.clone();
        let cut_end = o.aligned.saturating_add(recorded_round.horizon);
        if o.aligned > o.obs_step {
            // The recording's chunk answered a fresher observation than the request's (the
            // server re-fetched it when the trace was recorded): say so, as the robot would.
            record(
                &mut i.recording,
                RoundEvent::Refetched {
                    round: o.round as u64,
                    at_action: o.aligned,
                },
            )?;
        }
        // The recording says which steps the chunk covered. A robot that had to pass the round's
        // recorded index while it waited for the previous reply observed later than the chunk's
        // alignment, which a trace cannot express (a chunk is never aligned before its request):
        // it records the steps left from its observation, the chunk's end unchanged (at least
        // one action, as a trace requires, for a chunk with none left).
        let recorded_horizon = if o.aligned < o.obs_step {
            (o.aligned + horizon).saturating_sub(o.obs_step).max(1)
        } else {
            horizon
        };
        record(
            &mut i.recording,
            RoundEvent::Replied {
                round: o.round as u64,
                received_at_us: now.as_micros(),
                horizon: recorded_horizon,
                inference_us: kairos_core::time::duration_micros(o.inference),
                confidence,
            },
        )?;
        // An idle robot starts the new chunk's first action at once; a request that was only
        // waiting for this reply goes out first, with the observation from before that action
        // (as the SDK runner does: it checks for a due request before its next tick).
        let idle_at = i.exec.is_idle(now).then(|| i.exec.started_at(now));
        let accepted = i.exec.accept(now, o.aligned, horizon);
        match accepted {
            Accepted::Used { from_step, .. } => {
                if let Some((round, from, cut)) = i.running.replace((o.round, from_step, cut_end)) {
                    self.out.beyond_cut_actions +=
                        u64::from(from_step.saturating_sub(from.max(cut)));
                    record(
                        &mut i.recording,
                        RoundEvent::ChunkDone {
                            round: round as u64,
                            executed: from_step - from,
                        },
                    )?;
                }
            }
            Accepted::Stale => record(
                &mut i.recording,
                RoundEvent::ChunkDone {
                    round: o.round as u64,
                    executed: 0,
                },
            )?,
        }
        if let (Some(position), Accepted::Used { .. }) = (idle_at, accepted)
            && i.exec.until() < i.trace.total_actions
            && i.round(i.sent).1 <= position
        {
            self.send_observed(inst, now, position)?;
        }
        self.plan(inst, now);
        Ok(())
    }

    fn wake(&mut self, inst: usize, timer: u64, now: Timestamp) -> Result<(), SimError> {
        let i = &self.insts[inst];
        if i.timer != timer || i.done {
            return Ok(());
        }
        let total = i.trace.total_actions;
        if i.exec.until() >= total && i.exec.started_at(now) >= total {
            return self.finish(inst, now);
        }
        if i.outstanding.is_none() {
            self.send(inst, now)?;
        }
        Ok(())
    }

    fn finish(&mut self, inst: usize, now: Timestamp) -> Result<(), SimError> {
        let i = &mut self.insts[inst];
        i.done = true;
        let total = i.trace.total_actions;
        if let Some((round, from, cut)) = i.running.take() {
            self.out.beyond_cut_actions += u64::from(total.saturating_sub(from.max(cut)));
            record(
                &mut i.recording,
                RoundEvent::ChunkDone {
                    round: round as u64,
                    executed: total.saturating_sub(from),
                },
            )?;
        }
        if let Some(recording) = i.recording.take() {
            self.out.recorded.push(recording.finish(total)?);
        }
        if let Some(Outstanding {
            request: Some(req), ..
        }) = i.outstanding.take()
        {
            SchedulerTiming::event(&mut self.timing, || self.sched.handle_cancel(now, req));
            self.requests.remove(&req);
        }
        let i = &self.insts[inst];
        let report = i.exec.chunk_started_at().map(|started_at| ExecReport {
            started_at,
            actions_remaining: 0,
            control_hz: i.trace.control_hz,
        });
        let (task, robot) = (i.task, i.robot);
        SchedulerTiming::event(&mut self.timing, || {
            self.sched
                .handle_task_end(now, task, robot, TaskEnd::Done, report)
        })
        .map_err(|source| SimError::Admit {
            what: "task end",
            at: now,
            source,
        })?;
        self.out.tasks.push(TaskResult {
            trace_task: i.trace.task,
            started_at: i.started_at,
            latency_s: now.saturating_since(i.started_at).as_secs_f64(),
            execution_s: i.trace.execution_seconds(),
            rounds: i.sent as u32,
        });
        self.out.makespan_s = self.out.makespan_s.max(now.as_secs_f64());
        // Offline fleet: the robot takes the next task on the list straight away.
        if let Load::Fleet { .. } = self.cfg.load
            && let Some(&next) = self.backlog.get(self.next_backlog)
        {
            self.next_backlog += 1;
            let robot = self.insts[inst].robot;
            self.spawn(next, robot, now)?;
        }
        Ok(())
    }

    fn run(&mut self) -> Result<(), SimError> {
        loop {
            let next_event = self.queue.peek().map(|Reverse((t, _, _))| *t);
            let timeout = SchedulerTiming::event(&mut self.timing, || self.sched.poll_timeout());
            if let Some(t) = timeout
                && next_event.is_none_or(|e| t < e)
            {
                SchedulerTiming::event(&mut self.timing, || self.sched.handle_timeout(t));
                self.dispatch(t);
                continue;
            }
            let Some(Reverse((now, _, ev))) = self.queue.pop() else {
                return Ok(());
            };
            self.out.events += 1;
            match ev {
                Event::Start { inst } => {
                    self.insts[inst].started_at = now;
                    self.send(inst, now)?;
                }
                Event::Wake { inst, timer } => self.wake(inst, timer, now)?,
                Event::Submit { inst } => self.submit(inst, now)?,
                Event::BatchStart { batch } => SchedulerTiming::event(&mut self.timing, || {
                    self.sched.handle_batch_started(now, BatchId(batch))
                }),
                Event::BatchDone { batch } => self.batch_done(batch, now)?,
                Event::Reply { inst, horizon } => self.reply(inst, horizon, now)?,
            }
        }
    }
}

/// `tasks` picks from `pool` (uniform, with replacement), the first at time 0 and the others
/// after exponential gaps of mean `1 / rate`: a Poisson process.
fn poisson_arrivals<'a>(
    pool: &[&'a TaskTrace],
    rate: f64,
    tasks: usize,
    rng: &mut StdRng,
) -> Vec<(Timestamp, &'a TaskTrace)> {
    let mut out = Vec::with_capacity(tasks);
    if pool.is_empty() {
        return out;
    }
    let mut t = 0.0f64;
    for _ in 0..tasks {
        let pick = pool[rng.random_range(0..pool.len())];
        out.push((Timestamp::from_secs_f64(t), pick));
        let u: f64 = rng.random::<f64>();
        t += -(1.0 - u).ln() / rate;
    }
    out
}

/// The arrival schedule [`simulate`] replays for an online `cfg` (its load must be
/// [`Load::Poisson`]): which tasks of `traces` under `cfg.setting` start when. A function of
/// the seed only, so the live replay (`kairos bench live`) starts exactly the tasks the
/// simulator replays, at the same instants.
pub fn online_schedule<'a>(
    traces: &'a TraceSet,
    cfg: &SimConfig,
) -> Result<Vec<(Timestamp, &'a TaskTrace)>, SimError> {
    let Load::Poisson { rate, tasks } = cfg.load else {
        return Err(SimError::Config("not an online (Poisson) load".into()));
    };
    if !(rate.is_finite() && rate > 0.0) {
        return Err(SimError::Config(format!(
            "arrival rate {rate} must be positive"
        )));
    }
    let pool: Vec<&TaskTrace> = traces
        .tasks
        .iter()
        .filter(|t| t.setting == cfg.setting)
        .collect();
    if pool.is_empty() {
        return Err(SimError::NoTasks(cfg.setting.clone()));
    }
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    Ok(poisson_arrivals(&pool, rate, tasks, &mut rng))
}

/// Runs one simulation of `traces` under `cfg`.
pub fn simulate(traces: &TraceSet, cfg: &SimConfig) -> Result<SimResult, SimError> {
    simulate_with(traces, cfg, None).map(|(out, _)| out)
}

/// [`simulate`], measuring with a real clock what each call into the scheduler costs. The
/// [`SimResult`] is the one [`simulate`] gives.
pub fn simulate_timed(
    traces: &TraceSet,
    cfg: &SimConfig,
) -> Result<(SimResult, SchedulerTiming), SimError> {
    simulate_with(traces, cfg, Some(SchedulerTiming::default()))
        .map(|(out, timing)| (out, timing.unwrap_or_default()))
}

fn simulate_with(
    traces: &TraceSet,
    cfg: &SimConfig,
    timing: Option<SchedulerTiming>,
) -> Result<(SimResult, Option<SchedulerTiming>), SimError> {
    let pool: Vec<&TaskTrace> = traces.variant(&cfg.setting).collect();
    if pool.is_empty() {
        return Err(SimError::NoTasks(cfg.setting.clone()));
    }
    if cfg.engines.is_empty() {
        return Err(SimError::Config("no engines".into()));
    }
    let (horizons, priorities) = cfg.policies.with_natives();
    let policy = kairos_core::registry::build_priority(&priorities, &cfg.policy)
        .map_err(|e| SimError::Policy(e.to_string()))?;
    let sched = Scheduler::new(cfg.scheduler.clone(), cfg.engines.clone(), policy);
    let mut sim = Sim {
        cfg,
        horizons,
        sched,
        queue: BinaryHeap::new(),
        seq: 0,
        insts: Vec::new(),
        requests: HashMap::new(),
        batches: HashMap::new(),
        backlog: Vec::new(),
        next_backlog: 0,
        arrived_at_server: HashMap::new(),
        out: SimResult::default(),
        timing,
    };
    // Task picks and arrival times come from their own stream, before anything else runs, so
    // every policy and setting sees the same tasks arriving at the same times.
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    match cfg.load {
        Load::Poisson { .. } => {
            for (n, (at, pick)) in online_schedule(traces, cfg)?.into_iter().enumerate() {
                sim.spawn(pick, RobotId(n as u32), at)?;
            }
        }
        Load::Fleet { robots, tasks } => {
            if robots == 0 {
                return Err(SimError::Config("a fleet needs at least one robot".into()));
            }
            sim.backlog = (0..tasks)
                .map(|_| pool[rng.random_range(0..pool.len())])
                .collect();
            // Robots power up within the first second, not in lockstep.
            let starts: Vec<f64> = (0..robots).map(|_| rng.random::<f64>()).collect();
            for (robot, start) in starts.into_iter().enumerate().take(tasks) {
                let trace = sim.backlog[robot];
                sim.next_backlog = robot + 1;
                sim.spawn(
                    trace,
                    RobotId(robot as u32),
                    Timestamp::from_secs_f64(start),
                )?;
            }
        }
        Load::Explicit(ref starts) => {
            for (n, &(at, id)) in starts.iter().enumerate() {
                let trace = pool.iter().find(|t| t.task == id).ok_or_else(|| {
                    SimError::Config(format!("no task {id} under setting `{}`", cfg.setting))
                })?;
                sim.spawn(trace, RobotId(n as u32), at)?;
            }
        }
    }
    let started = sim
        .timing
        .is_some()
        .then(|| (Instant::now(), thread_cpu_time()));
    sim.run()?;
    if let (Some(t), Some((wall, cpu))) = (&mut sim.timing, started) {
        t.run_s = wall.elapsed().as_secs_f64();
        t.run_cpu_s = cpu
            .zip(thread_cpu_time())
            .map_or(0.0, |(a, b)| b.saturating_sub(a).as_secs_f64());
    }
    sim.out.scheduler = *sim.sched.counters();
    Ok((sim.out, sim.timing))
}
