//! Simulator tests: recordings replayed alone come back unchanged, runs are deterministic, and
//! small scenarios give the latencies computed by hand in the comments.

use std::collections::BTreeMap;
use std::time::Duration;

use kairos_engine::{EngineProfile, ProfilePoint};
use kairos_sdk::trace::{
    HorizonSetting, RoundTrace, TaskTrace, TraceHeader, TraceSet, TraceSource,
};

use super::experiment::{self, Experiment, Plan};
use super::*;
use crate::workload::generate::{self, DYNAMIC, STATIC};
use crate::workload::tests_support::tiny;

fn ms(v: u64) -> Timestamp {
    Timestamp::from_micros(v * 1000)
}

/// One edge engine taking `latency_ms` per batch whatever its size, batches of at most
/// `max_batch`.
fn flat_engine(latency_ms: f64, max_batch: u32) -> EngineSpec {
    EngineSpec {
        name: "edge".into(),
        tier: Tier::Edge,
        profile: EngineProfile {
            model: "test".into(),
            device: "test".into(),
            points: vec![
                ProfilePoint {
                    batch: 1,
                    latency_ms,
                },
                ProfilePoint {
                    batch: 64,
                    latency_ms,
                },
            ],
            max_batch,
        },
        rtt: Duration::ZERO,
    }
}

fn config(policy: &str, setting: &str, load: Load, engines: Vec<EngineSpec>) -> SimConfig {
    SimConfig {
        engines,
        scheduler: SchedulerConfig::default(),
        policy: policy.parse().unwrap(),
        setting: setting.to_string(),
        network: SimNetwork {
            robot_rtt: Duration::ZERO,
            robot_uplink_mbps: 1000.0,
            wan_mbps: 1000.0,
        },
        hints: false,
        load,
        seed: 1,
        record: false,
        policies: Default::default(),
        replay_horizon: None,
    }
}

/// A hand-written static-horizon task at 10 Hz (100 ms per action): `rounds` as
/// `(issued_at_action, horizon)`, zero-byte observations.
fn task(id: u64, total: u32, rounds: &[(u32, u32)]) -> TaskTrace {
    TaskTrace {
        task: id,
        label: None,
        setting: STATIC.into(),
        horizon: HorizonSetting {
            policy: "static".into(),
            params: BTreeMap::from([("h".to_string(), 1.0)]),
        },
        control_hz: 10.0,
        chunk_len: 16,
        total_actions: total,
        rounds: rounds
            .iter()
            .map(|&(at, h)| RoundTrace {
                aligned_at_action: None,
                issued_at_action: at,
                horizon: h,
                executed: 0,
                gen_latency_us: 100_000,
                round_trip_us: None,
                obs_bytes: 0,
                confidence: None,
            })
            .collect(),
    }
}

fn set(tasks: Vec<TaskTrace>) -> TraceSet {
    TraceSet {
        header: TraceHeader::new(TraceSource::Generated),
        tasks,
    }
}

/// Latency (ms) per trace task id.
fn latencies(r: &SimResult) -> BTreeMap<u64, u64> {
    r.tasks
        .iter()
        .map(|t| (t.trace_task, (t.latency_s * 1000.0).round() as u64))
        .collect()
}

/// Runs hand-written static-horizon `traces` on one engine of 100 ms per batch of 1 and returns
/// the latency (ms) per task.
fn run_on_one_engine(
    traces: &TraceSet,
    policy: &str,
    hints: bool,
    load: Load,
) -> BTreeMap<u64, u64> {
    let mut cfg = config(policy, STATIC, load, vec![flat_engine(100.0, 1)]);
    cfg.hints = hints;
    latencies(&simulate(traces, &cfg).unwrap())
}

#[test]
fn replaying_a_recording_alone_reproduces_it_exactly() {
    let w = tiny();
    let traces = generate::generate(&w, 5).unwrap();
    let cfg_for = |setting: &str, id: u64| {
        let mut c = experiment::config(
            &w,
            &experiment::online_variants()[2],
            Load::Explicit(vec![(Timestamp::ZERO, id)]),
            1,
        );
        c.setting = setting.to_string();
        c.record = true;
        c
    };
    for original in &traces.tasks {
        let r = simulate(&traces, &cfg_for(&original.setting, original.task)).unwrap();
        assert_eq!(r.recorded.len(), 1);
        let replayed = &r.recorded[0];
        assert_eq!(
            replayed.rounds, original.rounds,
            "task {} ({}) replayed alone differs from its recording",
            original.task, original.setting
        );
        assert_eq!(replayed.total_actions, original.total_actions);
        assert_eq!(r.refetches, 0, "nothing waits in isolation");
    }
}

#[test]
fn same_seed_same_numbers_other_seed_other_numbers() {
    let w = tiny();
    let traces = generate::generate(&w, 9).unwrap();
    let variant = &experiment::online_variants()[2];
    let load = Load::Poisson {
        rate: 3.0,
        tasks: 60,
    };
    let a = simulate(&traces, &experiment::config(&w, variant, load.clone(), 11)).unwrap();
    let b = simulate(&traces, &experiment::config(&w, variant, load.clone(), 11)).unwrap();
    let c = simulate(&traces, &experiment::config(&w, variant, load, 12)).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.tasks.len(), 60);
    assert_ne!(a.latencies(), c.latencies());
}

#[test]
fn thread_count_never_changes_a_number() {
    let mut w = tiny();
    w.experiments.tasks_per_run = 30;
    w.experiments.fleet_tasks = 12;
    let traces = vec![generate::generate(&w, 3).unwrap()];
    let jobs = experiment::plan(
        std::slice::from_ref(&w),
        &Plan {
            experiments: vec![Experiment::Online, Experiment::Fleet],
            seed: 4,
            extra: Vec::new(),
            task_scale: 1.0,
            policies: Default::default(),
            scale: Default::default(),
        },
    );
    let one = experiment::run_jobs(&jobs, &traces, 1, &|_| {});
    let two = experiment::run_jobs(&jobs, &traces, 2, &|_| {});
    let one: Vec<_> = one.into_iter().map(Result::unwrap).collect();
    let two: Vec<_> = two.into_iter().map(Result::unwrap).collect();
    assert_eq!(one, two);
}

#[test]
fn one_robot_alone_executes_then_waits_for_each_round() {
    // 4 actions per chunk, the next request when all 4 have started (inference after the last
    // action has started),
    // 100 ms generation, no network delay.
    //   t=0    round 0 sent; generated 0..100
    //   t=100  actions 0,1,2,3 start at 100, 200, 300, 400; round 1 sent at 400 (4 started)
    //   t=500  round 1 arrives; the robot idles from 500 (no action 4 in chunk 0), so action 4
    //          starts at once: actions 4..7 at 500, 600, 700, 800.
    // Latency: first request (0) to the last action (800) = 800 ms.
    let traces = set(vec![task(1, 8, &[(0, 4), (4, 4)])]);
    let load = Load::Explicit(vec![(ms(0), 1)]);
    assert_eq!(
        run_on_one_engine(&traces, "fifo", false, load),
        BTreeMap::from([(1, 800)])
    );
}

#[test]
fn a_request_sent_before_the_new_chunk_starts_is_accepted() {
    // Chunks of 4 at 10 Hz, a request after every started action, 100 ms generation:
    //   round 0 0..100; action 0 at 100; round 1 sent at once (1 started), 100..200;
    //   at 200 action 1 starts, then round 1 arrives: its first action runs at the next tick
    //   (300), but round 2 goes out at 200 already (2 started). Last Exec Info must then report
    //   the chunk as starting at the send time, as the SDK does, or the scheduler refuses it.
    //   Round 2 (observation after 2 starts) covers [2, 6); actions keep their 100 ms ticks:
    //   the last (5) at 600 -> 600 ms.
    let traces = set(vec![task(1, 6, &[(0, 4), (1, 4), (2, 4)])]);
    let load = Load::Explicit(vec![(ms(0), 1)]);
    assert_eq!(
        run_on_one_engine(&traces, "kairos", false, load),
        BTreeMap::from([(1, 600)])
    );
}

#[test]
fn two_robots_contend_for_one_engine_first_come_first_served() {
    // Task 1 arrives at 0, task 2 at 50 ms; one engine, batches of 1, 100 ms each.
    //   task 1: round 0 runs 0..100; actions 0..3 at 100..400; round 1 sent at 400, runs
    //           400..500; actions 4..7 at 500..800. Latency 800 ms.
    //   task 2: round 0 waits for the engine, runs 100..200; actions 0..3 at 200..500; round 1
    //           sent at 500 as task 1's round 1 ends, runs 500..600; actions 4..7 at 600..900.
    //           Latency 900 − 50 = 850 ms.
    let traces = set(vec![
        task(1, 8, &[(0, 4), (4, 4)]),
        task(2, 8, &[(0, 4), (4, 4)]),
    ]);
    let load = Load::Explicit(vec![(ms(0), 1), (ms(50), 2)]);
    assert_eq!(
        run_on_one_engine(&traces, "fifo", false, load),
        BTreeMap::from([(1, 800), (2, 850)])
    );
}

/// Three tasks at 10 Hz, one engine, batches of 1, 100 ms per batch:
/// - A (id 1): 6 actions in two rounds of 3, arrives at 0;
/// - C (id 3): 3 actions in one round, arrives at 290 ms and occupies the engine 290..390;
/// - B (id 2): 3 actions in one round, arrives at 320 ms.
///
/// A's round 0 runs 0..100, its actions 0..2 start at 100, 200, 300, and its round 1 goes out at
/// 300 (3 started). At 390 two requests wait: A's round 1 (arrived 300) and B's round 0 (320).
fn contention() -> TraceSet {
    set(vec![
        task(1, 6, &[(0, 3), (3, 3)]),
        task(2, 3, &[(0, 3)]),
        task(3, 3, &[(0, 3)]),
    ])
}

fn contention_load() -> Load {
    Load::Explicit(vec![(ms(0), 1), (ms(290), 3), (ms(320), 2)])
}

#[test]
fn fifo_serves_the_earlier_request_first() {
    // FIFO at 390 takes A's round 1 (arrived first): it runs 390..490; A idled from 400 and
    // resumes at 490: actions 3..5 at 490, 590, 690 -> A 690 ms. B's round 0 runs 490..590:
    // actions at 590, 690, 790 -> B 790 − 320 = 470 ms. C: actions at 390, 490, 590 -> 300 ms.
    assert_eq!(
        run_on_one_engine(&contention(), "fifo", false, contention_load()),
        BTreeMap::from([(1, 690), (2, 470), (3, 300)])
    );
}

#[test]
fn kairos_serves_the_higher_wait_ratio_first() {
    // Kairos at 390: B's first round has waited its whole life (wait ratio 1, top bucket); A has
    // waited only since its robot ran out of actions: E_0 = [100, 300] (reported with round 1:
    // started at 100, 0 actions left at 300), execution-dominated (200 ms vs G_0 = 100 ms), so
    // W = 390 − 300 = 90 ms of a 390 ms life, ratio 0.23, bucket 2. B runs 390..490 (actions at
    // 490, 590, 690 -> 370 ms); A runs 490..590 (actions at 590, 690, 790 -> 790 ms); C 300 ms.
    assert_eq!(
        run_on_one_engine(&contention(), "kairos", false, contention_load()),
        BTreeMap::from([(1, 790), (2, 370), (3, 300)])
    );
}

#[test]
fn srw_serves_due_requests_by_remaining_work_aged_by_waiting() {
    // SRW at 390: both requests are due (A's robot ran dry at 300, B has no chunk yet). With
    // the hint both have 1 round left; B's wait ratio 1 divides its urgency by 0.01, A's 0.23 by
    // 0.77: B first, as Kairos. Without hints (and no finished tasks to learn from) both
    // urgencies are 0 and arrival order decides, as FIFO.
    assert_eq!(
        run_on_one_engine(&contention(), "srw", true, contention_load()),
        BTreeMap::from([(1, 790), (2, 370), (3, 300)])
    );
    assert_eq!(
        run_on_one_engine(&contention(), "srw", false, contention_load()),
        BTreeMap::from([(1, 690), (2, 470), (3, 300)])
    );
}

#[test]
fn srw_lets_a_request_with_slack_wait_for_one_that_is_due() {
    // One engine, batches of 1, 100 ms. Task 1: 12 actions, chunks of 10, next request after
    // 2 started. Task 2: 3 actions, chunks of 2, next request after 1 started. Task 3: a single
    // action, arriving at 150 ms to keep the engine busy 200..300. Tasks 1 and 2 arrive at 0.
    //   0..100 task 1 round 0; 100..200 task 2 round 0; 200..300 task 3 round 0.
    //   Task 1: actions from 100; round 1 sent at 200 (2 started) with 8 actions left: its
    //           deadline (E_0.end) is 200 + 800 = 1000.
    //   Task 2: action 0 at 200; round 1 sent at once (1 started) with 1 action left:
    //           deadline 300; its robot idles from 400.
    //   Task 3: action 0 at 300 -> 150 ms.
    // At 300 both round-1 requests wait (same arrival time, task 1's submitted first).
    // FIFO: task 1 300..400 (no effect on its robot: last action 11 at 1200 -> 1200 ms); task 2
    //   400..500: idle from 400, action 2 at 500 -> 500 ms.
    // SRW: task 2 is due (300 <= 300), task 1 is not (1000): task 2 300..400, its chunk arrives as
    //   the robot runs dry: action 2 at 400 -> 400 ms; task 1 400..500 -> still 1200 ms.
    let traces = set(vec![
        task(1, 12, &[(0, 10), (2, 10)]),
        task(2, 3, &[(0, 2), (1, 2)]),
        task(3, 1, &[(0, 1)]),
    ]);
    let load = Load::Explicit(vec![(ms(0), 1), (ms(0), 2), (ms(150), 3)]);
    assert_eq!(
        run_on_one_engine(&traces, "fifo", false, load.clone()),
        BTreeMap::from([(1, 1200), (2, 500), (3, 150)])
    );
    assert_eq!(
        run_on_one_engine(&traces, "srw", false, load),
        BTreeMap::from([(1, 1200), (2, 400), (3, 150)])
    );
}

#[test]
fn dynamic_horizon_halves_the_rounds_of_the_tiny_workload_under_replay() {
    let w = tiny();
    let traces = generate::generate(&w, 2).unwrap();
    let load = Load::Poisson {
        rate: 1.0,
        tasks: 40,
    };
    let run = |setting: &str| {
        let mut c = experiment::config(&w, &experiment::online_variants()[0], load.clone(), 3);
        c.setting = setting.to_string();
        simulate(&traces, &c).unwrap()
    };
    let (s, d) = (run(STATIC), run(DYNAMIC));
    assert!(
        (d.requests as f64) < 0.8 * s.requests as f64,
        "dynamic {} vs static {} requests",
        d.requests,
        s.requests
    );
}

#[test]
fn bad_configurations_are_refused() {
    let traces = set(vec![task(1, 8, &[(0, 4), (4, 4)])]);
    let base = config(
        "fifo",
        STATIC,
        Load::Explicit(vec![(ms(0), 1)]),
        vec![flat_engine(100.0, 1)],
    );
    let mut c = base.clone();
    c.setting = DYNAMIC.into();
    assert!(matches!(simulate(&traces, &c), Err(SimError::NoTasks(_))));
    let mut c = base.clone();
    c.engines.clear();
    assert!(matches!(simulate(&traces, &c), Err(SimError::Config(_))));
    let mut c = base.clone();
    c.policy = "nope".parse().unwrap();
    assert!(matches!(simulate(&traces, &c), Err(SimError::Policy(_))));
    let mut c = base;
    c.load = Load::Explicit(vec![(ms(0), 99)]);
    assert!(matches!(simulate(&traces, &c), Err(SimError::Config(_))));
}

/// A shipped workload file (`workloads/NAME.toml`).
fn shipped(name: &str) -> crate::workload::Workload {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../workloads")
        .join(format!("{name}.toml"));
    crate::workload::Workload::load(&path).unwrap()
}

#[test]
fn every_system_issues_exactly_the_recorded_rounds_of_each_task() {
    // Under load (each workload's peak rate, where requests queue and most observations go
    // stale), every system of the online experiment and of the re-fetch ablation asks for the
    // same work: each task issues exactly its recorded rounds, at their recorded action indices,
    // and the recording of what each robot experienced is a valid trace.
    let mut w_tiny = tiny();
    w_tiny.experiments.rates = vec![4.0];
    let workloads = [w_tiny, shipped("libero-smolvla"), shipped("isaac-gr00t")];
    for w in &workloads {
        let traces = generate::generate(w, 42).unwrap();
        let peak = *w.experiments.rates.last().unwrap();
        let mut variants = experiment::online_variants();
        variants.extend(
            variants
                .clone()
                .iter()
                .map(experiment::Variant::refetch_flipped),
        );
        let mut refetched = 0;
        for v in &variants {
            let load = Load::Poisson {
                rate: peak,
                tasks: 60,
            };
            let mut cfg = experiment::config(w, v, load, 1);
            cfg.record = true;
            let r = simulate(&traces, &cfg).unwrap();
            assert_eq!(r.tasks.len(), 60, "{} {}", w.name, v.key);
            let recorded = |id: u64| traces.variant(&v.setting).find(|t| t.task == id).unwrap();
            let mut expected = 0;
            for t in &r.tasks {
                let original = recorded(t.trace_task);
                assert_eq!(
                    t.rounds as usize,
                    original.rounds.len(),
                    "{} {}: task {} issued {} rounds, recorded {}",
                    w.name,
                    v.key,
                    t.trace_task,
                    t.rounds,
                    original.rounds.len()
                );
                expected += original.rounds.len() as u64;
            }
            assert_eq!(r.requests, expected, "{} {}", w.name, v.key);
            for replayed in &r.recorded {
                // Round by round: never issued before its recorded index (later only when the
                // robot passed it waiting for the previous reply), and its chunk ends where the
                // recorded one did: the same steps to execute.
                let original = recorded(replayed.task);
                assert_eq!(replayed.rounds.len(), original.rounds.len());
                for (a, b) in replayed.rounds.iter().zip(&original.rounds) {
                    assert!(
                        a.issued_at_action >= b.issued_at_action,
                        "{} {}",
                        w.name,
                        v.key
                    );
                    let end = |r: &RoundTrace| r.aligned_at_action() + r.horizon;
                    if end(b) > a.issued_at_action {
                        assert_eq!(end(a), end(b), "{} {}", w.name, v.key);
                    }
                }
                let executed: u32 = replayed.rounds.iter().map(|r| r.executed).sum();
                assert_eq!(executed, original.total_actions, "{} {}", w.name, v.key);
                assert_eq!(replayed.total_actions, original.total_actions);
                replayed.validate().unwrap();
            }
            if v.refetch {
                assert!(r.refetches > 0, "{} {}: nothing re-fetched", w.name, v.key);
                refetched += 1;
            } else {
                assert_eq!(r.refetches, 0, "{} {} re-fetched", w.name, v.key);
            }
        }
        assert!(refetched >= 4, "{}: too few systems re-fetched", w.name);
    }
}

#[test]
fn a_recorded_refetch_keeps_its_alignment_on_replay() {
    // 10 Hz, 100 ms per batch, no network. Round 0 (sent at 0) arrives at 100: actions 0..3 at
    // 100, 200, 300, 400. Round 1 was issued after 2 actions (sent at 200) and, when recorded,
    // answered a re-fetched observation captured after 3: its chunk covers steps [3, 7). It
    // arrives at 300, as action 2 starts: round 0 executed 0, 1, 2; round 1 executes 3..6 at
    // 400..700 -> 700 ms, and its recording says it was aligned at 3.
    let mut t = task(1, 7, &[(0, 4), (2, 4)]);
    t.rounds[1].aligned_at_action = Some(3);
    t.validate().unwrap();
    let mut cfg = config(
        "kairos",
        STATIC,
        Load::Explicit(vec![(ms(0), 1)]),
        vec![flat_engine(100.0, 1)],
    );
    cfg.record = true;
    let r = simulate(&set(vec![t]), &cfg).unwrap();
    assert_eq!(latencies(&r), BTreeMap::from([(1, 700)]));
    assert_eq!(r.requests, 2, "the recorded work, no extra round");
    let replayed = &r.recorded[0];
    let rounds: Vec<_> = replayed
        .rounds
        .iter()
        .map(|r| (r.issued_at_action, r.aligned_at_action, r.executed))
        .collect();
    assert_eq!(rounds, vec![(0, None, 3), (2, Some(3), 4)]);
}

#[test]
fn the_scale_experiment_serves_every_round_of_every_robot() {
    // 200 robots on 10 workers, one task each: the scale experiment at a size a test can run.
    let w = tiny();
    let traces = generate::generate(&w, 5).unwrap();
    let jobs = experiment::plan(
        std::slice::from_ref(&w),
        &Plan {
            experiments: vec![Experiment::Scale],
            seed: 2,
            extra: Vec::new(),
            task_scale: 1.0,
            policies: Default::default(),
            scale: scale::ScalePlan {
                robots: vec![200],
                robots_per_worker: 20,
            },
        },
    );
    assert_eq!(jobs.len(), 1);
    let job = &jobs[0];
    assert_eq!(job.x, 200.0);
    assert_eq!(
        job.config.load,
        Load::Fleet {
            robots: 200,
            tasks: 200
        }
    );
    assert_eq!(job.config.engines.len(), 10);
    assert!(job.config.engines.iter().all(|e| e.tier == Tier::Edge));
    let max_batch = u64::from(job.config.engines[0].profile.max_batch);

    // Timing the scheduler leaves the simulation unchanged.
    let plain = simulate(&traces, &job.config).unwrap();
    let (timed, timing) = simulate_timed(&traces, &job.config).unwrap();
    assert_eq!(plain, timed);

    // Every robot finished its task, having asked for exactly its recording's rounds, and every
    // round was answered once.
    assert_eq!(timed.tasks.len(), 200);
    let recorded: BTreeMap<u64, usize> = traces
        .variant(DYNAMIC)
        .map(|t| (t.task, t.rounds.len()))
        .collect();
    for t in &timed.tasks {
        assert_eq!(
            t.rounds as usize, recorded[&t.trace_task],
            "task {}",
            t.trace_task
        );
    }
    let rounds: u64 = timed.tasks.iter().map(|t| u64::from(t.rounds)).sum();
    assert_eq!(timed.requests, rounds);
    let c = &timed.scheduler;
    assert_eq!(
        (
            c.submitted,
            c.dispatched,
            c.answered,
            c.failed,
            c.refused,
            c.tasks_ended
        ),
        (rounds, rounds, rounds, 0, 0, 200)
    );
    assert!(timed.batches * max_batch >= rounds);

    // Every decision was timed, and the run's report adds up.
    assert_eq!(timing.decisions.len() as u64, c.decisions);
    #[cfg(unix)]
    assert_eq!(timing.decisions_cpu.len(), timing.decisions.len());
    assert_eq!(timing.decision_batches, timed.batches);
    assert!((1..=200).contains(&timing.max_pending));
    let result = experiment::run_job(job, &traces).unwrap();
    let s = result
        .scale
        .as_ref()
        .expect("a scale job reports its scale statistics");
    assert_eq!((s.robots, s.workers, s.tasks), (200, 10, 200));
    assert_eq!(
        (s.rounds, s.answered, s.batches),
        (rounds, rounds, timed.batches)
    );
    assert_eq!(s.decisions, c.decisions);
    assert_eq!(s.makespan_s, timed.makespan_s);
    assert!(s.rounds_per_virtual_s() > 0.0 && s.scheduler_share() <= 1.0);
    let report = experiment::Report {
        workloads: std::slice::from_ref(&w),
        jobs: &jobs,
        results: std::slice::from_ref(&result),
    };
    let csv = report.scale_csv();
    assert_eq!(csv.lines().count(), 2);
    assert!(
        csv.lines()
            .nth(1)
            .unwrap()
            .starts_with(&format!("{},200,10,200,{rounds},{rounds},", w.name))
    );
    assert!(report.scale_table().contains("| 200 | 10 |"));
}
