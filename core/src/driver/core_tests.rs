//! The driver core alone: events in, effects out, time as an argument. No runtime, no threads.

use std::sync::Arc;
use std::time::Duration;

use kairos_engine_types::{ActionChunk, ActionRequest};
use kairos_protocol::{ErrorCode, Reply};

use super::core::{BatchJob, DriverCore, Effect};
use super::*;
use crate::action::ActionManager;
use crate::chunking::RoundChunking;
use crate::registry::native_horizon_policies;
use crate::round::{ValidObservation, ValidSubmit, round_seed};
use crate::scheduler::fifo::Fifo;
use crate::scheduler::{
    EngineId, EngineSpec, ExecReport, RequestId, RoundSubmit, Scheduler, SchedulerConfig, Tier,
};

struct Bench {
    core: DriverCore,
    actions: Arc<ActionManager>,
    /// The robot's clock equals the server's.
    clock: ClockMap,
}

fn ms(ms: u64) -> Timestamp {
    Timestamp::from_micros(ms * 1_000)
}

/// Chunk length, action dimension and steps of [`linear_flow`].
const CHUNK: usize = 4;
const DIM: usize = 2;
const STEPS: usize = 2;

/// What the engine would answer, deterministically: Euler steps of a linear velocity field that
/// moves every action from its noise (the seed) towards the state's first element.
fn linear_flow(request: &ActionRequest) -> ActionChunk {
    let n = request.samples.max(1) * CHUNK * DIM;
    let noise: Vec<f32> = (0..n).map(|i| request.seed as f32 + i as f32).collect();
    let mut x = noise.clone();
    let mut updates = Vec::new();
    for _ in 0..STEPS {
        let dt = 1.0 / STEPS as f32;
        let u: Vec<f32> = x.iter().map(|v| dt * (request.state[0] - v)).collect();
        x.iter_mut().zip(&u).for_each(|(v, d)| *v += d);
        updates.extend(u);
    }
    ActionChunk {
        samples: request.samples.max(1),
        steps: STEPS,
        chunk_len: CHUNK,
        action_dim: DIM,
        actions: x,
        updates,
        noise,
    }
}

/// A core over one engine instance taking batches of one.
fn bench(stale_after: Duration, task_idle_timeout: Duration) -> Bench {
    let engine = EngineSpec {
        name: "e0".into(),
        tier: Tier::Edge,
        profile: kairos_engine_types::EngineProfile {
            model: "linear-flow".into(),
            device: "cpu".into(),
            points: vec![kairos_engine_types::ProfilePoint {
                batch: 1,
                latency_ms: 1.0,
            }],
            max_batch: 1,
        },
        rtt: Duration::ZERO,
    };
    let config = SchedulerConfig {
        stale_after,
        task_idle_timeout,
        ..SchedulerConfig::default()
    };
    let scheduler = Scheduler::new(config, vec![engine], Box::new(Fifo::default()));
    let natives = native_horizon_policies();
    let actions = Arc::new(
        ActionManager::new(
            natives.clone(),
            &natives,
            "static",
            [("h".to_string(), 2.0)].into(),
        )
        .unwrap(),
    );
    Bench {
        core: DriverCore::new(scheduler, 16),
        actions,
        clock: ClockMap::new(Timestamp::ZERO, 0, Duration::ZERO),
    }
}

impl Bench {
    fn valid(&self, robot: u32, task: u64, round: u64, at: Timestamp, state0: f32) -> ValidSubmit {
        self.valid_after(robot, task, round, at, state0, None)
    }

    /// [`Bench::valid`] with the robot's Last Exec Info.
    fn valid_after(
        &self,
        robot: u32,
        task: u64,
        round: u64,
        at: Timestamp,
        state0: f32,
        last_exec: Option<kairos_protocol::LastExecInfo>,
    ) -> ValidSubmit {
        let at = self.clock.to_server(at.as_micros());
        let (exec_round, exec_delay) = (
            last_exec.and_then(|e| e.round),
            last_exec.and_then(|e| e.delay),
        );
        let last_exec = last_exec.map(|e| ExecReport {
            started_at: self.clock.to_server(e.exec_started_at_us),
            actions_remaining: e.actions_remaining,
            control_hz: e.control_hz,
        });
        ValidSubmit {
            round: RoundSubmit {
                task: TaskId(task),
                robot: RobotId(robot),
                round,
                sent_at: at,
                obs_captured_at: at,
                last_exec,
                remaining: None,
                control_hz: None,
            },
            observation: ValidObservation {
                captured_at: at,
                request: ActionRequest {
                    state: vec![state0, 0.0, 0.0],
                    images: Vec::new(),
                    cameras: Vec::new(),
                    instruction: String::new(),
                    samples: 1,
                    seed: round_seed(task, round),
                    guidance: None,
                },
            },
            policy: self.actions.build(None, None).unwrap(),
            samples: 1,
            control_hz: last_exec.map(|e| e.control_hz),
            clock: self.clock,
            chunking: RoundChunking::default(),
            exec_round,
            exec_delay,
        }
    }

    fn effects(&mut self) -> Vec<Effect> {
        std::iter::from_fn(|| self.core.poll_effect()).collect()
    }

    /// What the shell does with a batch, synchronously: the model, then the horizon policies.
    fn answers(&self, job: BatchJob) -> Vec<(RequestId, RoundAnswer)> {
        let chunks = job.inputs.iter().map(|r| Ok(linear_flow(r))).collect();
        self.actions.answer_batch(job.rounds, chunks, None)
    }
}

fn only_batch(effects: Vec<Effect>) -> BatchJob {
    let mut jobs: Vec<BatchJob> = effects
        .into_iter()
        .filter_map(|e| match e {
            Effect::RunBatch(job) => Some(job),
            _ => None,
        })
        .collect();
    assert_eq!(jobs.len(), 1, "one batch");
    jobs.remove(0)
}

fn answers_of(effects: &[Effect]) -> Vec<(Vec<WaiterId>, &RoundAnswer)> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Answer { waiters, answer } => Some((waiters.clone(), answer)),
            _ => None,
        })
        .collect()
}

#[test]
fn the_engine_takes_the_next_batch_while_horizon_policies_run() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    let first = b.valid(0, 1, 0, ms(0), 1.0);
    b.core.submit(ms(0), first, ms(0), WaiterId(1));
    let job1 = only_batch(b.effects());
    assert_eq!((job1.engine, job1.rounds.len()), (EngineId(0), 1));
    let second = b.valid(1, 2, 0, ms(1), 2.0);
    b.core.submit(ms(1), second, ms(1), WaiterId(2));
    assert!(b.effects().is_empty(), "the only engine is busy");

    // G.end of batch 1: the engine is idle, so task 2's round starts before batch 1's horizons
    // are known.
    b.core
        .generation_ended(ms(10), job1.batch, Duration::from_millis(9));
    let job2 = only_batch(b.effects());
    assert_eq!(job2.rounds[0].task, 2);

    let batch1 = job1.batch;
    let answers1 = b.answers(job1);
    b.core.batch_done(ms(15), batch1, answers1);
    let effects = b.effects();
    let answers = answers_of(&effects);
    assert_eq!(answers.len(), 1);
    assert_eq!(answers[0].0, vec![WaiterId(1)]);
    let reply = answers[0].1.as_ref().unwrap();
    assert_eq!((reply.task, reply.horizon), (1, 2));
    assert_eq!(reply.timing.inference_us, 9_000);
    assert_eq!(
        reply.timing.total_us, 15_000,
        "from the frame read to the reply"
    );
    assert_eq!(reply.timing.queue_us, 0);
    // The lifecycle records G.end at the end of generation, not when the horizon was chosen.
    let record = b.core.scheduler().task(TaskId(1)).unwrap();
    let g = record.history().last().unwrap().generation;
    assert_eq!((g.start, g.end), (ms(0), ms(10)));
    assert_eq!(b.core.stats().replies, 1);
}

#[test]
fn a_stale_round_is_refetched_through_its_newest_stream() {
    let mut b = bench(Duration::ZERO, Duration::MAX);
    // Task 1 holds the engine so task 2's round is queued when its stream reconnects.
    let busy = b.valid(0, 1, 0, ms(0), 1.0);
    b.core.submit(ms(0), busy, ms(0), WaiterId(1));
    let busy_job = only_batch(b.effects());
    let first = b.valid(0, 2, 0, ms(1), 2.0);
    b.core.submit(ms(1), first, ms(1), WaiterId(2));
    let resent = b.valid(0, 2, 0, ms(2), 2.0);
    b.core.submit(ms(2), resent, ms(2), WaiterId(3));
    assert_eq!(b.core.stats().attached, 1);
    b.effects();

    let busy_batch = busy_job.batch;
    let busy_answers = b.answers(busy_job);
    b.core
        .generation_ended(ms(5), busy_batch, Duration::from_millis(5));
    let effects = b.effects();
    let ask = effects.iter().find_map(|e| match e {
        Effect::Refetch {
            batch,
            request,
            waiter,
            age,
        } => Some((*batch, *request, *waiter, *age)),
        _ => None,
    });
    let (batch, request, waiter, age) = ask.expect("a re-fetch ask");
    assert_eq!(waiter, WaiterId(3), "the newest stream is asked");
    assert_eq!(
        age,
        Duration::from_millis(3),
        "the re-sent observation is the queued one"
    );
    assert!(
        !effects.iter().any(|e| matches!(e, Effect::RunBatch(_))),
        "the batch waits for its re-fetch"
    );
    b.core.batch_done(ms(6), busy_batch, busy_answers);
    b.effects();

    b.core.refetched(ms(9), batch, request, None);
    let job = only_batch(b.effects());
    let answers = b.answers(job);
    b.core.batch_done(ms(20), batch, answers);
    let effects = b.effects();
    let answers = answers_of(&effects);
    assert_eq!(answers[0].0, vec![WaiterId(2), WaiterId(3)]);
    let reply = answers[0].1.as_ref().unwrap();
    assert_eq!(reply.timing.refetch_us, 4_000);
    let stats = b.core.stats();
    assert_eq!((stats.refetch_asked, stats.refetch_used), (1, 0));
}

#[test]
fn the_timer_follows_the_idle_deadline_and_expiry_keeps_a_snapshot() {
    let mut b = bench(Duration::from_secs(10), Duration::from_secs(60));
    let submit = b.valid(0, 5, 0, ms(0), 1.0);
    b.core.submit(ms(0), submit, ms(0), WaiterId(1));
    let job = only_batch(b.effects());
    let batch = job.batch;
    let answers = b.answers(job);
    b.core
        .generation_ended(ms(4), batch, Duration::from_millis(4));
    b.core.batch_done(ms(4), batch, answers);
    let effects = b.effects();
    let timers: Vec<_> = effects
        .iter()
        .filter_map(|e| match e {
            Effect::SetTimer(t) => Some(*t),
            _ => None,
        })
        .collect();
    assert_eq!(timers, vec![Some(ms(60_004))], "idle from the answer on");

    // A timer that fires early expires nothing and is asked for again.
    b.core.timeout(ms(30_000));
    let effects = b.effects();
    assert!(matches!(effects[..], [Effect::SetTimer(Some(t))] if t == ms(60_004)));
    assert!(!b.core.snapshot(TaskId(5)).unwrap().ended);

    b.core.timeout(ms(60_004));
    assert!(
        b.effects().is_empty(),
        "no deadline left: no timer asked for"
    );
    let snapshot = b.core.snapshot(TaskId(5)).unwrap();
    assert!(snapshot.ended);
    assert_eq!(snapshot.rounds_completed, 1);
    assert_eq!(snapshot.generated.get(&0), Some(&1));
    assert_eq!(b.core.stats().tasks_ended, 1);
}

#[test]
fn the_owner_comes_from_the_scheduler_and_a_draining_core_refuses_rounds() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    let submit = b.valid(0, 1, 0, ms(0), 1.0);
    b.core.submit(ms(0), submit, ms(0), WaiterId(1));
    let job = only_batch(b.effects());
    let batch = job.batch;
    let answers = b.answers(job);
    b.core.batch_done(ms(3), batch, answers);
    b.effects();
    assert_eq!(b.core.snapshot(TaskId(1)).unwrap().owner, RobotId(0));

    // The same round from another robot: refused by the scheduler's ownership check (answered
    // like an unknown task, so a prober learns nothing), not answered from the cache.
    let other = b.valid(1, 1, 0, ms(4), 1.0);
    b.core.submit(ms(4), other, ms(4), WaiterId(2));
    let effects = b.effects();
    let answers = answers_of(&effects);
    assert_eq!(
        answers[0].1.as_ref().unwrap_err().code,
        ErrorCode::UnknownTask
    );
    let own = b.valid(0, 1, 0, ms(5), 1.0);
    b.core.submit(ms(5), own, ms(5), WaiterId(3));
    let effects = b.effects();
    assert!(
        answers_of(&effects)[0].1.is_ok(),
        "the owner gets the cached reply"
    );

    b.core.shut_down();
    assert!(b.core.is_done(), "nothing in flight");
    let late = b.valid(0, 1, 1, ms(6), 1.0);
    b.core.submit(ms(6), late, ms(6), WaiterId(4));
    let effects = b.effects();
    assert_eq!(
        answers_of(&effects)[0].1.as_ref().unwrap_err().code,
        ErrorCode::ShuttingDown
    );
}

fn remote_spec(name: &str) -> EngineSpec {
    EngineSpec {
        name: name.into(),
        tier: Tier::Edge,
        profile: kairos_engine_types::EngineProfile {
            model: "linear-flow".into(),
            device: "remote".into(),
            points: vec![kairos_engine_types::ProfilePoint {
                batch: 1,
                latency_ms: 1.0,
            }],
            max_batch: 2,
        },
        rtt: Duration::from_millis(2),
    }
}

#[test]
fn a_lost_batch_runs_again_on_another_engine_and_each_round_is_answered_once() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    // The local engine leaves (as if it were a worker that drained): rounds wait.
    b.core.remove_engine(ms(0), EngineId(0));
    for task in 1..=2 {
        let submit = b.valid(0, task, 0, ms(1), task as f32);
        b.core.submit(ms(1), submit, ms(1), WaiterId(task));
    }
    assert!(
        !b.effects().iter().any(|e| matches!(e, Effect::RunBatch(_))),
        "no live engine: the rounds wait"
    );
    // A worker registers: both rounds go to it in one batch.
    let worker = b.core.add_engine(ms(2), remote_spec("worker:a"));
    assert_eq!(worker, EngineId(1));
    let lost = only_batch(b.effects());
    assert_eq!(
        (lost.engine, lost.rounds.len(), lost.attempt),
        (worker, 2, 0)
    );
    // Another worker registers while the first runs: nothing to place yet.
    let other = b.core.add_engine(ms(3), remote_spec("worker:b"));
    assert!(!b.effects().iter().any(|e| matches!(e, Effect::RunBatch(_))));
    // The first worker is lost: the batch is given back and placed on the other at once.
    let (batch, requests) = (
        lost.batch,
        lost.rounds.iter().map(|r| r.request).collect::<Vec<_>>(),
    );
    b.core.batch_lost(
        ms(10),
        batch,
        crate::error::LossReason::ConnectionLost,
        lost.inputs,
        lost.rounds,
    );
    let again = only_batch(b.effects());
    assert_eq!(again.engine, other);
    assert_eq!(again.attempt, 1, "its rounds ran once before");
    assert_ne!(again.batch, batch, "a new batch id");
    assert_eq!(
        again.rounds.iter().map(|r| r.request).collect::<Vec<_>>(),
        requests,
        "same requests, same order (original arrival)"
    );
    let stats = b.core.stats();
    assert_eq!(stats.redispatched.connection_lost, 2);
    assert_eq!(stats.redispatched.total(), 2);
    let engines: Vec<(EngineId, bool)> = b
        .core
        .scheduler()
        .engines()
        .map(|e| (e.id, e.live))
        .collect();
    assert_eq!(
        engines,
        [(other, true)],
        "the lost worker left the pool, and the core forgot it with the local engine"
    );
    // A late answer of the lost batch is dropped; the new one answers each round once.
    let late = b.answers(BatchJob {
        batch,
        engine: worker,
        attempt: 0,
        inputs: again.inputs.clone(),
        rounds: Vec::new(),
    });
    b.core
        .generation_ended(ms(11), batch, Duration::from_millis(1));
    b.core.batch_done(ms(11), batch, late);
    assert!(answers_of(&b.effects()).is_empty(), "late result dropped");
    let batch2 = again.batch;
    let answers = b.answers(again);
    b.core
        .generation_ended(ms(12), batch2, Duration::from_millis(1));
    b.core.batch_done(ms(12), batch2, answers);
    let effects = b.effects();
    let answered = answers_of(&effects);
    assert_eq!(answered.len(), 2);
    assert!(answered.iter().all(|(_, a)| a.is_ok()));
    let mut waiters: Vec<WaiterId> = answered.iter().flat_map(|(w, _)| w.clone()).collect();
    waiters.sort();
    assert_eq!(waiters, [WaiterId(1), WaiterId(2)]);
    assert_eq!(b.core.stats().failed, 0);
    // Only the engine left in the pool has facts kept about it.
    assert_eq!(b.core.engine_facts_held(), 1);
    let report = b.core.report();
    assert_eq!(report.engines.len(), 1);
    assert_eq!(report.engines[0].name, "worker:b");
}

#[test]
fn a_round_out_of_attempts_or_time_gets_a_retryable_error_instead() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    b.core.set_redispatch_rule(RedispatchRule {
        max_attempts: 2,
        within: Duration::from_secs(1),
    });
    b.core.remove_engine(ms(0), EngineId(0));
    let submit = b.valid(0, 1, 0, ms(0), 1.0);
    b.core.submit(ms(0), submit, ms(0), WaiterId(1));
    let mut engine = b.core.add_engine(ms(0), remote_spec("worker:0"));
    // First loss: run again; second loss: out of attempts.
    for (attempt, at) in [(0u32, 5u64), (1, 6)] {
        let job = only_batch(b.effects());
        assert_eq!((job.engine, job.attempt), (engine, attempt));
        b.core.batch_lost(
            ms(at),
            job.batch,
            crate::error::LossReason::Deadline,
            job.inputs,
            job.rounds,
        );
        engine = b.core.add_engine(ms(at), remote_spec("worker:n"));
    }
    let effects = b.effects();
    let answered = answers_of(&effects);
    assert_eq!(answered.len(), 1, "exactly one answer");
    let error = answered[0].1.as_ref().unwrap_err();
    assert_eq!(error.code, ErrorCode::Internal);
    assert!(error.retryable, "{error:?}");
    let stats = b.core.stats();
    assert_eq!(
        (stats.redispatched.deadline, stats.redispatch_given_up),
        (1, 1)
    );
    // The task may send the round again.
    let again = b.valid(0, 1, 0, ms(7), 1.0);
    b.core.submit(ms(7), again, ms(7), WaiterId(2));
    assert_eq!(only_batch(b.effects()).engine, engine);

    // The rule itself: attempts first, then age.
    let rule = RedispatchRule {
        max_attempts: 3,
        within: Duration::from_secs(1),
    };
    assert_eq!(rule.decide(ms(500), ms(0), 1), Redispatch::Again);
    assert_eq!(rule.decide(ms(1000), ms(0), 2), Redispatch::Again);
    assert_eq!(rule.decide(ms(1001), ms(0), 2), Redispatch::TooLate);
    assert_eq!(rule.decide(ms(10), ms(0), 3), Redispatch::OutOfAttempts);
}

/// The core counts what `/metrics` exports in its report: batch sizes, round latencies, engine
/// busy time, queue depth, and a deadline miss for a round answered after its robot ran out of
/// actions.
#[test]
fn the_report_follows_the_rounds_and_counts_a_late_reply_as_a_deadline_miss() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    let busy = |b: &Bench| b.core.report().engines[0].busy_time;
    assert_eq!(busy(&b), Duration::ZERO);

    // Round 0 runs alone; round 1 of another task waits behind it (batches of one).
    b.core
        .submit(ms(0), b.valid(0, 1, 0, ms(0), 1.0), ms(0), WaiterId(1));
    b.core
        .submit(ms(1), b.valid(1, 2, 0, ms(1), 1.0), ms(1), WaiterId(2));
    let job = only_batch(b.effects());
    assert_eq!(b.core.report().queue_depth, 1);
    assert!(b.core.report().engines[0].busy);
    let batch = job.batch;
    let answers = b.answers(job);
    let answered_horizon = answers[0].1.as_ref().map(|reply| reply.horizon).unwrap();
    b.core
        .generation_ended(ms(4), batch, Duration::from_millis(4));
    b.core.batch_done(ms(5), batch, answers);
    let job = only_batch(b.effects());
    let report = b.core.report();
    assert_eq!(report.queue_depth, 0);
    assert_eq!(report.stats.round_latency.count(), 1);
    assert!((report.stats.round_latency.sum() - 0.005).abs() < 1e-12);
    let latency = report.stats.round_latency.cumulative();
    assert_eq!(
        latency
            .iter()
            .find(|(bound, _)| *bound >= 0.005)
            .map(|b| b.1),
        Some(1),
        "5 ms falls in the 8 ms bucket"
    );
    assert_eq!(latency[0], (0.001, 0), "not in the 1 ms bucket");
    assert_eq!(report.stats.batch_size.count(), 2);
    // The reply's horizon is counted once, in its own bucket.
    assert_eq!(report.stats.horizon.count(), 1);
    let horizon = f64::from(answered_horizon);
    assert_eq!(report.stats.horizon.sum(), horizon);
    assert_eq!(busy(&b), Duration::from_millis(4));
    let batch = job.batch;
    let answers = b.answers(job);
    b.core
        .generation_ended(ms(6), batch, Duration::from_millis(1));
    b.core.batch_done(ms(6), batch, answers);
    let _ = b.effects();
    assert_eq!(b.core.report().stats.deadline_misses, 0, "no E yet");

    // Task 1's next round: the robot reports it will run dry at 20 ms + 1 action at 100 Hz.
    let mut next = |round: u64, at: u64, answered: u64| {
        let exec = kairos_protocol::LastExecInfo {
            exec_started_at_us: ms(at).as_micros(),
            actions_remaining: 1,
            control_hz: 100.0,
            round: None,
            delay: None,
        };
        let submit = b.valid_after(0, 1, round, ms(at), 1.0, Some(exec));
        b.core.submit(ms(at), submit, ms(at), WaiterId(10 + round));
        let job = only_batch(b.effects());
        let batch = job.batch;
        let answers = b.answers(job);
        b.core
            .generation_ended(ms(answered), batch, Duration::from_millis(1));
        b.core.batch_done(ms(answered), batch, answers);
        let _ = b.effects();
        b.core.report().stats.deadline_misses
    };
    assert_eq!(next(1, 20, 25), 0, "dry at 30 ms, answered at 25: in time");
    assert_eq!(
        next(2, 40, 60),
        1,
        "dry at 50 ms, answered at 60: the robot waited"
    );
}

/// A worker's new round trip and tier (an `auto` worker re-classified by its `RemoteEngine`)
/// reach the scheduler and the report at once.
#[test]
fn a_reclassified_worker_moves_tier_in_the_scheduler_and_the_report() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    let worker = b.core.add_engine(ms(0), remote_spec("worker:w"));
    let ready = |b: &Bench, tier: Tier| {
        b.core
            .report()
            .engines
            .iter()
            .filter(|e| e.tier == tier && e.state == super::stats::EngineState::Ready)
            .count()
    };
    let view = |b: &Bench| {
        let e = b.core.scheduler().engine(worker).unwrap();
        (e.spec.tier, e.spec.rtt)
    };
    b.core
        .engine_link(worker, Duration::from_millis(30), Tier::Edge);
    assert_eq!(view(&b), (Tier::Edge, Duration::from_millis(30)));
    assert_eq!((ready(&b, Tier::Edge), ready(&b, Tier::Cloud)), (2, 0));
    b.core
        .engine_link(worker, Duration::from_millis(60), Tier::Cloud);
    assert_eq!(view(&b), (Tier::Cloud, Duration::from_millis(60)));
    assert_eq!((ready(&b, Tier::Edge), ready(&b, Tier::Cloud)), (1, 1));
    let report = b.core.report();
    let rtt = |name: &str| report.engines.iter().find(|e| e.name == name).unwrap().rtt;
    assert_eq!(rtt("worker:w"), Some(Duration::from_millis(60)));
    assert_eq!(rtt("e0"), None, "a local engine has no measured round trip");
    // A worker that leaves with nothing running leaves the report.
    b.core.remove_engine(ms(1), worker);
    assert!(b.core.report().engines.iter().all(|e| e.name != "worker:w"));
}

/// The driver predicts every round's `d` from the robot's Last Exec Info, the engine profile's
/// time for the batch, the server's own reply time and the task's network time; puts it and the
/// start index in the reply; plans the round with its strategy; and compares the prediction with
/// what the robot's next Last Exec Info says, per task and in the report.
#[test]
fn the_driver_predicts_d_plans_the_strategy_and_scores_the_prediction() {
    let mut b = bench(Duration::from_secs(10), Duration::MAX);
    // An engine whose profile says 25 ms at batch 1.
    let engine = EngineSpec {
        name: "e0".into(),
        tier: Tier::Edge,
        profile: kairos_engine_types::EngineProfile {
            model: "linear-flow".into(),
            device: "cpu".into(),
            points: vec![kairos_engine_types::ProfilePoint {
                batch: 1,
                latency_ms: 25.0,
            }],
            max_batch: 1,
        },
        rtt: Duration::ZERO,
    };
    let scheduler = Scheduler::new(
        SchedulerConfig {
            task_idle_timeout: Duration::MAX,
            ..SchedulerConfig::default()
        },
        vec![engine],
        Box::new(Fifo::default()),
    );
    b.core = DriverCore::new(scheduler, 16);
    b.core.set_chunking_model(ChunkingModel {
        action_dim: DIM,
        action_space: kairos_engine_types::ActionSpace::Unspecified,
    });
    let answer = |b: &mut Bench, job: BatchJob, generated: u64, sent: u64| -> Reply {
        let batch = job.batch;
        let answers = b.answers(job);
        b.core
            .generation_ended(ms(generated), batch, Duration::from_millis(1));
        b.core.batch_done(ms(sent), batch, answers);
        let effects = b.effects();
        let answers = answers_of(&effects);
        answers[0].1.clone().unwrap()
    };

    // Round 0: the robot is idle (no Last Exec Info): nothing to skip. The server's own time
    // from the end of generation to the reply is 5 ms.
    b.core
        .submit(ms(0), b.valid(0, 1, 0, ms(0), 1.0), ms(0), WaiterId(1));
    let job = only_batch(b.effects());
    assert!(job.inputs[0].guidance.is_none());
    let r0 = answer(&mut b, job, 25, 30);
    assert_eq!((r0.start, r0.delay), (Some(0), Some(0)));
    assert_eq!(r0.chunking.as_deref(), Some("skip"));
    assert_eq!(r0.horizon, 2, "static h = 2");

    // Round 1 at 100 ms: the robot (100 Hz, ticks from 60 ms) has 1 action of round 0 left.
    // The batch starts at once; the chunk is expected at 100 + 25 (profile) + 5 (reply time)
    // + 0 (network) = 130 ms: ticks at 110, 120, 130 are 3 steps, of which the robot spends
    // 1 executing its last action.
    let exec = |started: u64, remaining: u32, round: Option<u64>, delay: Option<u32>| {
        kairos_protocol::LastExecInfo {
            exec_started_at_us: ms(started).as_micros(),
            actions_remaining: remaining,
            control_hz: 100.0,
            round,
            delay,
        }
    };
    let mut submit = b.valid_after(0, 1, 1, ms(100), 1.0, Some(exec(60, 1, Some(0), Some(0))));
    submit.chunking = RoundChunking::with_defaults(
        kairos_protocol::ChunkingStrategy::Rtc,
        &crate::chunking::ChunkingDefaults::default(),
    );
    b.core.submit(ms(100), submit, ms(100), WaiterId(2));
    let job = only_batch(b.effects());
    // rtc guides toward round 0's reply from the capture on: its last action.
    let guidance = job.inputs[0].guidance.clone().unwrap();
    let r0_actions = r0.actions.to_f32().unwrap();
    assert_eq!(guidance.prefix, r0_actions[DIM..]);
    assert_eq!(guidance.delay, 1);
    let r1 = answer(&mut b, job, 125, 130);
    assert_eq!((r1.start, r1.delay), (Some(1), Some(3)));
    assert_eq!(r1.chunking.as_deref(), Some("rtc"));
    // Round 0 was predicted 0 and the robot said 0.
    let snapshot = b.core.snapshot(TaskId(1)).unwrap();
    assert_eq!(
        (snapshot.delay_errors.rounds, snapshot.delay_errors.exact),
        (1, 1)
    );

    // Round 2 at 200 ms: the robot says round 1's actual d was 2 (the prediction, 3, was one
    // too many) and it has 2 of round 1's actions left; it asks for `arrival_state` with its
    // own forecast of its state after each of them.
    let mut submit = b.valid_after(0, 1, 2, ms(200), 1.0, Some(exec(140, 1, Some(1), Some(2))));
    submit.chunking = RoundChunking {
        forecast: Some(vec![vec![7.0, 7.0, 7.0], vec![8.0, 8.0, 8.0]]),
        ..RoundChunking::with_defaults(
            kairos_protocol::ChunkingStrategy::ArrivalState,
            &crate::chunking::ChunkingDefaults::default(),
        )
    };
    b.core.submit(ms(200), submit, ms(200), WaiterId(3));
    let job = only_batch(b.effects());
    // Arrival at 200 + 25 + 5 = 230 ms; ticks at 210, 220, 230; the robot has 1 action left,
    // so it plans from the forecast after that one action.
    assert_eq!(job.inputs[0].state, vec![7.0, 7.0, 7.0]);
    let r2 = answer(&mut b, job, 225, 230);
    assert_eq!((r2.start, r2.delay), (Some(1), Some(3)));
    // Action 0 of the reply is round 1's committed action, then the chunk planned from the
    // forecast state.
    let r1_actions = r1.actions.to_f32().unwrap();
    let r2_actions = r2.actions.to_f32().unwrap();
    assert_eq!(&r2_actions[..DIM], &r1_actions[r1_actions.len() - DIM..]);
    assert_eq!(r2.horizon, 3, "1 committed + the chunk's 2");
    let errors = b.core.snapshot(TaskId(1)).unwrap().delay_errors;
    assert_eq!((errors.rounds, errors.exact, errors.sum_error), (2, 1, 1));
    assert_eq!(errors.max_abs_error, 1);

    // Round 3 at 300 ms from a client that does not report `delay`: the server takes the
    // actual d from when the robot started round 2's chunk (250 ms, 5 ticks after the 200 ms
    // capture); it predicted 3.
    b.core.submit(
        ms(300),
        b.valid_after(0, 1, 3, ms(300), 1.0, Some(exec(250, 1, None, None))),
        ms(300),
        WaiterId(4),
    );
    let job = only_batch(b.effects());
    let _ = answer(&mut b, job, 325, 330);
    let errors = b.core.snapshot(TaskId(1)).unwrap().delay_errors;
    assert_eq!(
        (errors.rounds, errors.sum_error, errors.sum_abs_error),
        (3, -1, 3)
    );
    let report = b.core.report();
    assert_eq!(report.stats.delay_error.count(), 3);
    assert_eq!(report.stats.delay_error.sum(), 3.0);
    assert_eq!(report.stats.delay_error_signed, -1);
    assert_eq!(report.stats.delay_predicted.count(), 4);
    let counts: Vec<(String, u64)> = report
        .stats
        .chunking
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|(s, n)| (s.to_string(), n))
        .collect();
    assert_eq!(
        counts,
        [
            ("skip".to_string(), 2),
            ("arrival_state".to_string(), 1),
            ("rtc".to_string(), 1)
        ]
    );
    assert_eq!(report.stats.chunking.fallbacks, 0);
}
