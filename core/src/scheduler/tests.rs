//! Scheduler tests through the public event API: a tiny virtual-time loop, the hand-computed
//! four-task example, placement, the API's edge cases, and property tests.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap, HashMap, HashSet};
use std::time::Duration;

use kairos_engine_types::{EngineProfile, ProfilePoint};
use proptest::prelude::*;

use super::*;
use crate::time::Timestamp;

fn ms(v: u64) -> Timestamp {
    Timestamp::from_micros(v * 1_000)
}

/// A profile with a fixed latency for every batch size up to `max_batch`.
fn flat_profile(latency_ms: f64, max_batch: u32) -> EngineProfile {
    EngineProfile {
        model: "test".into(),
        device: "virtual".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms,
            },
            ProfilePoint {
                batch: max_batch.max(2),
                latency_ms,
            },
        ],
        max_batch,
    }
}

fn engine(tier: Tier, latency_ms: f64, max_batch: u32, rtt_ms: u64) -> EngineSpec {
    EngineSpec {
        name: format!("{tier:?}"),
        tier,
        profile: flat_profile(latency_ms, max_batch),
        rtt: Duration::from_millis(rtt_ms),
    }
}

fn policy(spec: &str) -> Box<dyn PriorityPolicy> {
    build_policy(&spec.parse().unwrap()).unwrap()
}

fn submit_at(task: u64, round: u64, at: Timestamp, exec: Option<ExecReport>) -> RoundSubmit {
    RoundSubmit {
        task: TaskId(task),
        robot: RobotId(task as u32),
        round,
        sent_at: at,
        obs_captured_at: at,
        last_exec: exec,
        remaining: None,
        control_hz: None,
    }
}

/// A robot task in the virtual-time loop: it arrives, then runs synchronously — each chunk is
/// executed in full (`exec_ms[i]` for round `i`) before the next request is sent, which reports
/// that execution (started when the chunk arrived, no actions remaining).
#[derive(Clone, Debug)]
struct RobotTask {
    arrive_ms: u64,
    exec_ms: Vec<u64>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Event {
    /// Task index, round index, exec report (start ms) for the previous chunk.
    Submit(usize, u64, Option<u64>),
    BatchEnd(BatchId),
    /// Task index, start of its last execution.
    End(usize, u64),
}

/// What the loop records.
#[derive(Default, Debug)]
struct Trace {
    /// (time ms, task index, round index) in dispatch order.
    dispatched: Vec<(u64, usize, u64)>,
    summaries: BTreeMap<usize, TaskSummary>,
    /// Highest skip count seen per request, with the request's |E_last| in ms.
    max_skipped: HashMap<RequestId, (u32, Option<u64>)>,
}

/// Runs `tasks` to completion against a scheduler and returns what happened. The engine's batch
/// starts as soon as it is dispatched and ends after its profile latency (+ RTT).
fn run(mut sched: Scheduler, tasks: &[RobotTask]) -> Trace {
    let mut trace = Trace::default();
    let mut queue: BinaryHeap<Reverse<(u64, u64, Event)>> = BinaryHeap::new();
    let mut seq = 0u64;
    let mut push = |queue: &mut BinaryHeap<_>, at: u64, e: Event| {
        seq += 1;
        queue.push(Reverse((at, seq, e)));
    };
    for (i, t) in tasks.iter().enumerate() {
        push(&mut queue, t.arrive_ms, Event::Submit(i, 0, None));
    }
    let mut request_of: HashMap<RequestId, (usize, u64)> = HashMap::new();
    let mut batch_latency: HashMap<BatchId, Vec<RequestId>> = HashMap::new();
    let mut last_exec: HashMap<RequestId, Option<u64>> = HashMap::new();
    while let Some(Reverse((now, _, _))) = queue.peek().copied() {
        while let Some(Reverse((at, _, event))) = queue.peek().copied() {
            if at != now {
                break;
            }
            queue.pop();
            match event {
                Event::Submit(i, round, exec_start) => {
                    let exec = exec_start.map(|start| ExecReport {
                        started_at: ms(start),
                        actions_remaining: 0,
                        control_hz: 30.0,
                    });
                    let id = sched
                        .handle_submit(ms(now), submit_at(i as u64, round + 1, ms(now), exec))
                        .unwrap();
                    request_of.insert(id, (i, round));
                    last_exec.insert(id, exec_start.map(|s| now - s));
                }
                Event::BatchEnd(batch) => {
                    let requests = batch_latency.remove(&batch).unwrap();
                    let outcomes: Vec<_> = requests
                        .iter()
                        .map(|&r| (r, RoundOutcome::Answered { horizon: 1 }))
                        .collect();
                    sched.handle_batch_finished(ms(now), batch, &outcomes);
                    for r in requests {
                        let (i, round) = request_of[&r];
                        let exec = tasks[i].exec_ms[round as usize];
                        if (round as usize) + 1 < tasks[i].exec_ms.len() {
                            push(
                                &mut queue,
                                now + exec,
                                Event::Submit(i, round + 1, Some(now)),
                            );
                        } else {
                            push(&mut queue, now + exec, Event::End(i, now));
                        }
                    }
                }
                Event::End(i, exec_start) => {
                    let report = ExecReport {
                        started_at: ms(exec_start),
                        actions_remaining: 0,
                        control_hz: 30.0,
                    };
                    let s = sched
                        .handle_task_end(
                            ms(now),
                            TaskId(i as u64),
                            RobotId(i as u32),
                            TaskEnd::Done,
                            Some(report),
                        )
                        .unwrap();
                    trace.summaries.insert(i, s);
                }
            }
        }
        let pending: Vec<RequestId> = request_of
            .keys()
            .copied()
            .filter(|r| sched.is_pending(*r))
            .collect();
        for r in pending {
            let s = sched.skipped(r).unwrap();
            let entry = trace.max_skipped.entry(r).or_insert((0, last_exec[&r]));
            entry.0 = entry.0.max(s);
        }
        let busy_before: Vec<bool> = sched.engines().map(|e| e.batch.is_some()).collect();
        for d in sched.poll_dispatch(ms(now)) {
            assert!(!busy_before[d.engine.0], "dispatched to a busy engine");
            let spec = sched.engine(d.engine).unwrap().spec.clone();
            assert!(d.requests.len() <= spec.profile.max_batch.max(1) as usize);
            sched.handle_batch_started(ms(now), d.batch);
            let latency = spec.profile.latency(d.requests.len() as u32) + spec.rtt;
            let end = now + latency.as_millis() as u64;
            for r in &d.requests {
                let (i, round) = request_of[&r.request];
                trace.dispatched.push((now, i, round));
            }
            batch_latency.insert(d.batch, d.requests.iter().map(|r| r.request).collect());
            push(&mut queue, end, Event::BatchEnd(d.batch));
        }
    }
    assert_eq!(sched.pending_len(), 0, "everything was dispatched");
    trace
}

/// The four tasks of the hand-computed example (ms). Generation takes 1 s on one engine with
/// batch 1; robots are synchronous. Task 4 arrives later than the others.
fn four_tasks() -> Vec<RobotTask> {
    vec![
        RobotTask {
            arrive_ms: 0,
            exec_ms: vec![500, 400, 500],
        },
        RobotTask {
            arrive_ms: 0,
            exec_ms: vec![2_500, 1_000],
        },
        RobotTask {
            arrive_ms: 0,
            exec_ms: vec![750, 1_000],
        },
        RobotTask {
            arrive_ms: 1_750,
            exec_ms: vec![5_000, 1_000],
        },
    ]
}

fn four_task_run(spec: &str) -> Trace {
    let sched = Scheduler::new(
        SchedulerConfig::default(),
        vec![engine(Tier::Edge, 1_000.0, 1, 0)],
        policy(spec),
    );
    run(sched, &four_tasks())
}

/// Dispatch order as (task number 1–4, round), and per task (wait, latency) in ms.
type Outcome = (Vec<(usize, u64)>, Vec<(u64, u64)>);

fn outcome(trace: &Trace) -> Outcome {
    let order = trace
        .dispatched
        .iter()
        .map(|&(_, i, r)| (i + 1, r))
        .collect();
    let waits = trace
        .summaries
        .values()
        .map(|s| (s.wait.as_millis() as u64, s.latency().as_millis() as u64))
        .collect();
    (order, waits)
}

// The four-task example, in the spirit of the paper's Fig. "scheduling_example": synchronous
// robots, unit (1 s) generation, one engine, batch 1. T1 has three short executions (0.5, 0.4,
// 0.5 s: generation-dominated), T2 a long then a short one (2.5, 1 s), T3 (0.75, 1 s), T4 arrives
// at 1.75 s with a 5 s execution. Rounds are written TkRr; times in seconds.
//
// All policies agree up to t=2:
//   t=0 T1R0 [0,1] (all tie; wait ratios are 0 at t_start), t=1 T2R0 [1,2] (tie, arrival).
//   T1R1 arrives 1.5 (E_0 = [1, 1.5]), T4R0 arrives 1.75.
//   t=2 pending T3R0 (arr 0), T1R1 (arr 1.5, service 1 s), T4R0 (arr 1.75):
//     FIFO: T3R0. PLAS: T3, T4 in queue 0, T1 in queue 1 -> T3R0 (earlier).
//     Kairos: T3 w = 2/2 = 1 -> bucket 9; T4 w = 0.25/0.25 = 1 -> 9; T1 gen-dominated
//     (|G_0| = 1 >= |E_0| = 0.5), W = 2-1 = 1, w = 0.5 -> bucket 5. Bucket 9 ties on
//     |E_last| = 0 -> arrival -> T3R0.
//   T3R0 [2,3]; T3R1 arrives 3.75. T2R1 arrives 4.5 (E_0 = [2, 4.5]).
// t=3 pending T1R1 (arr 1.5, service 1), T4R0 (arr 1.75, service 0):
//   FIFO: T1R1. PLAS: T4 (queue 0) first. Kairos: T1 w = (3-1)/3 -> bucket 6; T4 w = 1 -> 9: T4R0.
//
// FIFO from t=3: T1R1 [3,4] (T1R2 at 4.4); t=4 T4R0 [4,5] (T4R1 at 10); t=5 T3R1 [5,6]
//   (arr 3.75 < 4.4 < 4.5); t=6 T1R2 [6,7]; t=7 T2R1 [7,8]; t=10 T4R1 [10,11].
//   Waits: T1 0 + (3-1) + (6-4) = 4, ends 7.5.  T2 1 + exec-dominated (|E_0| 2.5 > 1):
//   E_1.start - E_0.end = 8 - 4.5 -> 4.5, ends 9.  T3 2 + (5-3) = 4, ends 7.
//   T4 (4-1.75) + exec: 11 - 10 = 3.25, latency 12 - 1.75 = 10.25. Sum 15.75.
//
// PLAS from t=3: T4R0 [3,4] (T4R1 at 9). t=4: T1R1, T3R1 both service 1 s (queue 1; T1 queued
//   2.5 s < beta 8 x 1 s) -> FIFO: T1R1 [4,5] (T1R2 at 5.4). t=5: T3R1 (3.75), T2R1 (4.5),
//   T1R2 (5.4, service 2 s, still queue 1 since thresholds are 1 s, 3 s) -> T3R1 [5,6];
//   t=6 T2R1 [6,7]; t=7 T1R2 [7,8]; t=9 T4R1 [9,10].
//   Waits: T1 0 + 3 + 2 = 5 (ends 8.5). T2 1 + (7 - 4.5) = 3.5 (ends 8). T3 2 + 2 = 4 (ends 7).
//   T4 1.25 + (10 - 9) = 2.25 (latency 9.25). Sum 14.75.
//
// Kairos from t=3: T4R0 [3,4]. t=4: T1R1 (skipped twice) and T3R1 (fresh): T1 wait 3/4 = 0.75,
//   T3 (2 + (4-3))/4 = 0.75: both bucket 7. Longest execution first with aging:
//   T1 0.5 x (1+2) = 1.5 > T3 0.75 x 1 -> T1R1 [4,5]. t=5: T3 (2+2)/5 = 0.8 -> bucket 8;
//   T2 exec-dominated: 1 + (5-4.5) = 1.5 -> 0.3; T1 (3+0)/5 = 0.6 -> T3R1 [5,6]. t=6:
//   T1 (3 + (6-5))/6 = 0.67 -> bucket 6 beats T2 (1 + 1.5)/6 = 0.42 -> bucket 4: the
//   generation-dominated T1 (whose queueing is all wait) goes before T2, whose queueing was
//   partly hidden by its long execution: T1R2 [6,7], T2R1 [7,8], T4R1 [9,10].
//   Waits: T1 0 + 3 + 1 = 4 (ends 7.5). T2 1 + (8 - 4.5) = 4.5 (ends 9). T3 4 (ends 7).
//   T4 2.25 (latency 9.25). Sum 14.75.
//
// Totals (wait / latency): FIFO 15.75 / 33.75 s, PLAS 14.75 / 32.75 s, Kairos 14.75 / 32.75 s.
// Kairos and PLAS beat FIFO by serving the late task T4 before T1's queued round; Kairos then
// orders T1/T2 by execution-aware wait, PLAS by FIFO within equal service.
#[test]
fn four_task_example_matches_the_hand_computation() {
    let fifo = outcome(&four_task_run("fifo"));
    assert_eq!(
        fifo.0,
        vec![
            (1, 0),
            (2, 0),
            (3, 0),
            (1, 1),
            (4, 0),
            (3, 1),
            (1, 2),
            (2, 1),
            (4, 1)
        ]
    );
    assert_eq!(
        fifo.1,
        vec![
            (4_000, 7_500),
            (4_500, 9_000),
            (4_000, 7_000),
            (3_250, 10_250)
        ]
    );

    let plas = outcome(&four_task_run("plas"));
    assert_eq!(
        plas.0,
        vec![
            (1, 0),
            (2, 0),
            (3, 0),
            (4, 0),
            (1, 1),
            (3, 1),
            (2, 1),
            (1, 2),
            (4, 1)
        ]
    );
    assert_eq!(
        plas.1,
        vec![
            (5_000, 8_500),
            (3_500, 8_000),
            (4_000, 7_000),
            (2_250, 9_250)
        ]
    );

    let kairos = outcome(&four_task_run("kairos"));
    assert_eq!(
        kairos.0,
        vec![
            (1, 0),
            (2, 0),
            (3, 0),
            (4, 0),
            (1, 1),
            (3, 1),
            (1, 2),
            (2, 1),
            (4, 1)
        ]
    );
    assert_eq!(
        kairos.1,
        vec![
            (4_000, 7_500),
            (4_500, 9_000),
            (4_000, 7_000),
            (2_250, 9_250)
        ]
    );
}

fn one_edge(latency_ms: f64, max_batch: u32, spec: &str) -> Scheduler {
    Scheduler::new(
        SchedulerConfig::default(),
        vec![engine(Tier::Edge, latency_ms, max_batch, 0)],
        policy(spec),
    )
}

/// FIFO on one 100 ms edge instance with `config`.
fn fifo_edge(config: SchedulerConfig, max_batch: u32) -> Scheduler {
    Scheduler::new(
        config,
        vec![engine(Tier::Edge, 100.0, max_batch, 0)],
        policy("fifo"),
    )
}

/// One decision at `start_ms` whose batches run until `end_ms` and are all answered with
/// `horizon`. Returns the requests served.
fn serve(s: &mut Scheduler, start_ms: u64, end_ms: u64, horizon: u32) -> Vec<RequestId> {
    let mut served = Vec::new();
    for d in s.poll_dispatch(ms(start_ms)) {
        s.handle_batch_started(ms(start_ms), d.batch);
        let outcomes: Vec<_> = d
            .requests
            .iter()
            .map(|r| (r.request, RoundOutcome::Answered { horizon }))
            .collect();
        s.handle_batch_finished(ms(end_ms), d.batch, &outcomes);
        served.extend(d.requests.iter().map(|r| r.request));
    }
    served
}

#[test]
fn cloud_gets_requests_only_when_its_latency_plus_rtt_beats_the_edge_queue() {
    // One edge instance (1 s per batch of 1) and one cloud instance (batch 2). Three requests at
    // t=0: the edge takes the first; the second would wait 1 s for the edge, the third 2 s.
    for (cloud_ms, rtt_ms, offloaded) in [
        (300.0, 200, vec![1, 2]), // 500 ms beats both waits
        (900.0, 100, vec![2]),    // 1 s does not beat 1 s (equal), beats 2 s
        (1_200.0, 900, vec![]),   // 2.1 s beats neither
    ] {
        let mut s = Scheduler::new(
            SchedulerConfig::default(),
            vec![
                engine(Tier::Edge, 1_000.0, 1, 0),
                engine(Tier::Cloud, cloud_ms, 2, rtt_ms),
            ],
            policy("fifo"),
        );
        let ids: Vec<_> = (0..3)
            .map(|t| {
                s.handle_submit(ms(0), submit_at(t, 1, ms(0), None))
                    .unwrap()
            })
            .collect();
        let d = s.poll_dispatch(ms(0));
        assert_eq!(d[0].engine, EngineId(0));
        assert_eq!(d[0].requests[0].request, ids[0]);
        let cloud: Vec<_> = d
            .iter()
            .filter(|d| d.engine == EngineId(1))
            .flat_map(|d| d.requests.iter().map(|r| r.request))
            .collect();
        let expected: Vec<_> = offloaded.iter().map(|&i| ids[i]).collect();
        assert_eq!(cloud, expected, "cloud {cloud_ms} ms + rtt {rtt_ms} ms");
        assert_eq!(s.last_decision().unwrap().offloaded, expected.len());
        if expected.is_empty() {
            // Both left behind were skipped once; a decision that dispatches nothing (only the
            // slow cloud is idle) does not count as a skip.
            assert_eq!(s.skipped(ids[1]), Some(1));
            assert!(s.poll_dispatch(ms(10)).is_empty());
            assert_eq!(s.last_decision().unwrap().dispatched, 0);
            assert_eq!(s.skipped(ids[1]), Some(1));
        }
    }
}

#[test]
fn batches_never_exceed_max_batch_and_only_idle_engines_get_work() {
    let mut s = Scheduler::new(
        SchedulerConfig::default(),
        vec![
            engine(Tier::Edge, 100.0, 3, 0),
            engine(Tier::Edge, 100.0, 2, 0),
        ],
        policy("fifo"),
    );
    for t in 0..8 {
        s.handle_submit(ms(0), submit_at(t, 1, ms(0), None))
            .unwrap();
    }
    let d = s.poll_dispatch(ms(0));
    assert_eq!(d.len(), 2);
    assert_eq!(d[0].requests.len(), 3);
    assert_eq!(d[1].requests.len(), 2);
    assert_eq!(s.pending_len(), 3);
    assert!(
        s.poll_dispatch(ms(1)).is_empty(),
        "no idle engine, no decision"
    );
    assert_eq!(s.counters().decisions, 1);
    s.handle_batch_started(ms(1), d[1].batch);
    assert_eq!(
        s.engine(EngineId(1)).unwrap().busy_until,
        Some(ms(101)),
        "busy until start + profile latency"
    );
    s.handle_batch_finished(
        ms(101),
        d[1].batch,
        &d[1]
            .requests
            .iter()
            .map(|r| (r.request, RoundOutcome::Answered { horizon: 4 }))
            .collect::<Vec<_>>(),
    );
    let d2 = s.poll_dispatch(ms(101));
    assert_eq!(d2.len(), 1);
    assert_eq!(d2[0].engine, EngineId(1));
    assert_eq!(d2[0].requests.len(), 2);
    let t = s.task(d[1].requests[0].task).unwrap();
    assert_eq!(t.rounds_completed(), 1);
    assert_eq!(t.recent_horizons(), &[4]);
    assert_eq!(t.attained_service(), Duration::from_millis(100));
}

#[test]
fn load_reports_the_queue_the_running_batches_and_the_backlog() {
    // One 100 ms edge instance taking batches of 2.
    let mut s = fifo_edge(SchedulerConfig::default(), 2);
    assert_eq!(s.load(ms(0)), ServerLoad::default(), "idle and empty");
    for t in 0..5 {
        s.handle_submit(ms(0), submit_at(t, 1, ms(0), None))
            .unwrap();
    }
    let d = s.poll_dispatch(ms(0));
    s.handle_batch_started(ms(0), d[0].batch);
    // At 40 ms: 2 running until 100 ms, 3 queued (batches of 2 then 1, 100 ms each).
    assert_eq!(
        s.load(ms(40)),
        ServerLoad {
            queued: 3,
            running: 2,
            open_tasks: 5,
            backlog: Duration::from_millis(60 + 100 + 100),
        }
    );
    // The generation ended: the batch no longer counts as running, the engine is free.
    s.handle_generation_ended(ms(100), d[0].batch);
    let load = s.load(ms(100));
    assert_eq!((load.queued, load.running), (3, 0));
    assert_eq!(load.backlog, Duration::from_millis(200));
}

#[test]
fn stale_observations_are_flagged_for_refetch() {
    let mut s = fifo_edge(
        SchedulerConfig {
            stale_after: Duration::from_millis(100),
            ..SchedulerConfig::default()
        },
        4,
    );
    let fresh = s
        .handle_submit(ms(1_000), submit_at(1, 1, ms(1_000), None))
        .unwrap();
    let old = RoundSubmit {
        obs_captured_at: ms(850),
        ..submit_at(2, 1, ms(950), None)
    };
    let old = s.handle_submit(ms(1_000), old).unwrap();
    let d = s.poll_dispatch(ms(1_000));
    let flags: HashMap<_, _> = d[0]
        .requests
        .iter()
        .map(|r| (r.request, r.refetch))
        .collect();
    assert!(!flags[&fresh]);
    assert!(flags[&old], "150 ms old > 100 ms");
    assert_eq!(s.last_decision().unwrap().refetch, 1);
}

#[test]
fn with_refetch_off_no_observation_is_flagged() {
    let mut s = fifo_edge(
        SchedulerConfig {
            refetch: false,
            stale_after: Duration::from_millis(100),
            ..SchedulerConfig::default()
        },
        4,
    );
    let old = RoundSubmit {
        obs_captured_at: ms(500),
        ..submit_at(1, 1, ms(950), None)
    };
    s.handle_submit(ms(1_000), old).unwrap();
    let d = s.poll_dispatch(ms(1_000));
    assert_eq!(d[0].requests.len(), 1);
    assert!(!d[0].requests[0].refetch, "500 ms old, but re-fetch is off");
    assert_eq!(s.last_decision().unwrap().refetch, 0);
}

#[test]
fn newer_round_supersedes_a_pending_one_and_inherits_its_skips() {
    let mut s = one_edge(100.0, 1, "fifo");
    let a = s
        .handle_submit(ms(0), submit_at(1, 1, ms(0), None))
        .unwrap();
    let b = s
        .handle_submit(ms(0), submit_at(2, 1, ms(0), None))
        .unwrap();
    s.poll_dispatch(ms(0)); // a runs, b skipped once
    assert_eq!(s.skipped(b), Some(1));
    let b2 = s
        .handle_submit(ms(5), submit_at(2, 2, ms(5), None))
        .unwrap();
    assert_eq!(
        s.take_superseded(),
        vec![Superseded {
            request: b,
            task: TaskId(2),
            by: b2
        }]
    );
    assert!(s.take_superseded().is_empty());
    assert!(!s.is_pending(b));
    assert_eq!(s.skipped(b2), Some(1));
    assert_eq!(s.pending_len(), 1);
    // A newer round of the running task abandons it: its answer is no round, but its
    // generation still counts as service.
    let a2 = s
        .handle_submit(ms(6), submit_at(1, 2, ms(6), None))
        .unwrap();
    assert_eq!(s.handle_cancel(ms(6), a), CancelOutcome::Running);
    let batch = s.engine_busy(EngineId(0)).unwrap();
    s.handle_batch_started(ms(0), batch);
    s.handle_batch_finished(
        ms(100),
        batch,
        &[(a, RoundOutcome::Answered { horizon: 3 })],
    );
    let t1 = s.task(TaskId(1)).unwrap();
    assert_eq!(t1.rounds_completed(), 0);
    assert_eq!(t1.attained_service(), Duration::from_millis(100));
    assert_eq!(t1.current_request(), Some((a2, 2)));
    assert_eq!(s.counters().abandoned, 1);
}

#[test]
fn admission_errors() {
    let mut s = fifo_edge(
        SchedulerConfig {
            max_pending: 2,
            ..SchedulerConfig::default()
        },
        1,
    );
    let a = s
        .handle_submit(ms(0), submit_at(1, 3, ms(0), None))
        .unwrap();
    s.handle_submit(ms(0), submit_at(2, 1, ms(0), None))
        .unwrap();
    assert_eq!(
        s.handle_submit(ms(0), submit_at(3, 1, ms(0), None)),
        Err(AdmitError::Overloaded { pending: 2 })
    );
    assert!(
        s.task(TaskId(3)).is_none(),
        "a refused submit opens no task"
    );
    // Superseding frees its own slot, so it is admitted when full.
    assert!(s.handle_submit(ms(1), submit_at(1, 4, ms(1), None)).is_ok());
    let stolen = RoundSubmit {
        robot: RobotId(99),
        ..submit_at(1, 5, ms(2), None)
    };
    assert_eq!(
        s.handle_submit(ms(2), stolen),
        Err(AdmitError::Forbidden { task: TaskId(1) })
    );
    assert_eq!(
        s.handle_submit(ms(2), submit_at(1, 2, ms(2), None)),
        Err(AdmitError::RoundOutOfOrder { last: 4, got: 2 })
    );
    assert!(matches!(
        s.handle_submit(ms(2), submit_at(1, 4, ms(2), None)),
        Err(AdmitError::RoundInProgress { round: 4, .. })
    ));
    let bad_exec = submit_at(
        1,
        6,
        ms(2),
        Some(ExecReport {
            started_at: ms(1),
            actions_remaining: 1,
            control_hz: -3.0,
        }),
    );
    assert!(matches!(
        s.handle_submit(ms(2), bad_exec),
        Err(AdmitError::InvalidExecInfo(_))
    ));
    assert_eq!(s.counters().refused, 5);
    let _ = a;
    assert_eq!(
        s.handle_task_end(ms(3), TaskId(77), RobotId(77), TaskEnd::Done, None),
        Err(AdmitError::UnknownTask { task: TaskId(77) })
    );
    assert_eq!(
        s.handle_task_end(ms(3), TaskId(1), RobotId(2), TaskEnd::Done, None),
        Err(AdmitError::Forbidden { task: TaskId(1) })
    );
}

#[test]
fn cancel_removes_pending_and_lets_the_round_be_sent_again() {
    let mut s = one_edge(100.0, 1, "fifo");
    let a = s
        .handle_submit(ms(0), submit_at(1, 1, ms(0), None))
        .unwrap();
    assert_eq!(s.handle_cancel(ms(1), a), CancelOutcome::Removed);
    assert_eq!(s.handle_cancel(ms(1), a), CancelOutcome::NotFound);
    assert_eq!(s.pending_len(), 0);
    let again = s
        .handle_submit(ms(2), submit_at(1, 1, ms(2), None))
        .unwrap();
    assert_ne!(again, a, "request ids are never reused");
    // A failed round may also be retried with the same id; a request missing from the
    // batch's outcomes counts as failed.
    let d = s.poll_dispatch(ms(2));
    s.handle_batch_finished(ms(50), d[0].batch, &[]);
    assert_eq!(s.counters().failed, 1);
    assert!(
        s.handle_submit(ms(60), submit_at(1, 1, ms(60), None))
            .is_ok()
    );
    // Events about unknown batches are counted, not fatal.
    s.handle_batch_started(ms(61), BatchId(999));
    s.handle_batch_finished(ms(61), BatchId(999), &[]);
    assert_eq!(s.counters().ignored_events, 2);
}

#[test]
fn task_end_drops_its_pending_request_and_reports_a_summary() {
    let mut s = one_edge(100.0, 1, "fifo");
    let a = s
        .handle_submit(ms(0), submit_at(1, 1, ms(0), None))
        .unwrap();
    assert_eq!(serve(&mut s, 0, 100, 7), vec![a]);
    let exec = ExecReport {
        started_at: ms(120),
        actions_remaining: 2,
        control_hz: 10.0,
    };
    let b = s
        .handle_submit(ms(500), submit_at(1, 2, ms(500), Some(exec)))
        .unwrap();
    let summary = s
        .handle_task_end(ms(600), TaskId(1), RobotId(1), TaskEnd::Failed, None)
        .unwrap();
    assert_eq!(summary.open_request, Some(b));
    assert_eq!(summary.rounds, 1);
    assert_eq!(summary.actions, 7);
    assert_eq!(summary.end, TaskEnd::Failed);
    // |G_0| = 100 < |E_0| = 580 (120 -> 500 + 200): execution-dominated, the open wait is
    // max(0, 600 - 700) = 0.
    assert_eq!(summary.wait, Duration::ZERO);
    assert_eq!(s.pending_len(), 0);
    assert!(s.task(TaskId(1)).is_none());
    assert_eq!(s.take_finished(), vec![summary]);
    assert_eq!(
        s.handle_submit(ms(700), submit_at(1, 3, ms(700), None)),
        Err(AdmitError::TaskEnded { task: TaskId(1) })
    );
}

#[test]
fn idle_tasks_expire() {
    let mut s = fifo_edge(
        SchedulerConfig {
            task_idle_timeout: Duration::from_secs(5),
            ..SchedulerConfig::default()
        },
        1,
    );
    let a = s
        .handle_submit(ms(0), submit_at(1, 1, ms(0), None))
        .unwrap();
    assert_eq!(s.poll_timeout(), None);
    assert_eq!(serve(&mut s, 0, 100, 1), vec![a]);
    assert_eq!(s.poll_timeout(), Some(ms(5_100)));
    assert!(s.handle_timeout(ms(5_099)).is_empty());
    assert_eq!(s.handle_timeout(ms(5_100)), vec![TaskId(1)]);
    let finished = s.take_finished();
    assert_eq!(finished.len(), 1);
    assert_eq!(finished[0].end, TaskEnd::Expired);
    assert_eq!(s.poll_timeout(), None);
}

/// Answers a fixed order of the wrong length: the scheduler must fall back to arrival order.
struct Broken;

impl PriorityPolicy for Broken {
    fn name(&self) -> &str {
        "broken"
    }
    fn order(
        &mut self,
        _now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        order.extend((0..pending.len()).rev().skip(1));
        Ok(())
    }
}

#[test]
fn an_invalid_policy_order_falls_back_to_arrival_order() {
    let mut s = Scheduler::new(
        SchedulerConfig::default(),
        vec![engine(Tier::Edge, 100.0, 1, 0)],
        Box::new(Broken),
    );
    let first = s
        .handle_submit(ms(0), submit_at(1, 1, ms(0), None))
        .unwrap();
    s.handle_submit(ms(1), submit_at(2, 1, ms(1), None))
        .unwrap();
    let d = s.poll_dispatch(ms(2));
    assert_eq!(d[0].requests[0].request, first);
    assert!(s.last_decision().unwrap().policy_failed);
    assert_eq!(s.counters().policy_errors, 1);
}

fn view(request: u64, arrived_ms: u64, started_ms: u64, wait_ms: u64) -> PendingView {
    PendingView {
        request: RequestId(request),
        task: TaskId(request),
        round_index: 1,
        arrived_at: ms(arrived_ms),
        task_started_at: ms(started_ms),
        skipped: 0,
        wait: Duration::from_millis(wait_ms),
        attained_service: Duration::ZERO,
        queued: Duration::ZERO,
        last_exec: None,
        exec_ends_at: None,
        last_gen: None,
        rounds_completed: 1,
        remaining: None,
    }
}

fn order_of(policy: &mut dyn PriorityPolicy, now_ms: u64, views: &[PendingView]) -> Vec<u64> {
    let mut order = Vec::new();
    policy.order(ms(now_ms), views, &mut order).unwrap();
    validate_order(views.len(), &order).unwrap();
    order.iter().map(|&i| views[i].request.0).collect()
}

#[test]
fn kairos_buckets_aging_and_intra_bucket_order() {
    let now = 10_000;
    // Wait ratios 0.55, 0.58 (same bucket 5), 0.95 (bucket 9), 0.12 (bucket 1).
    let mut v = vec![
        view(0, 100, 0, 5_500),
        view(1, 200, 0, 5_800),
        view(2, 300, 0, 9_500),
        view(3, 50, 0, 1_200),
    ];
    v[0].last_exec = Some(Duration::from_millis(300));
    v[1].last_exec = Some(Duration::from_millis(100));
    let mut k = kairos::Kairos::new(kairos::KairosConfig::default());
    assert_eq!(order_of(&mut k, now, &v), vec![2, 0, 1, 3]);
    // Skips scale the execution estimate: 100 x (1+3) = 400 > 300.
    v[1].skipped = 3;
    assert_eq!(order_of(&mut k, now, &v), vec![2, 1, 0, 3]);
    // Aging: 8 skips at A = 4 lift request 3 from bucket 1 by 2 buckets to 3, still below 5;
    // 16 skips lift it by 4 to bucket 5, where its ê = 0 puts it last in the bucket; 32 skips
    // put it in the top bucket (clamped at B-1 = 9), tied with request 2 on ê = 0, and it
    // arrived first.
    v[3].skipped = 8;
    assert_eq!(order_of(&mut k, now, &v), vec![2, 1, 0, 3]);
    v[3].skipped = 16;
    assert_eq!(k.priority(ms(now), &v[3]), 5);
    assert_eq!(order_of(&mut k, now, &v), vec![2, 1, 0, 3]);
    v[3].skipped = 32;
    assert_eq!(k.priority(ms(now), &v[3]), 9);
    assert_eq!(order_of(&mut k, now, &v), vec![3, 2, 1, 0]);
    // Intra-bucket FIFO ablation: arrival order inside bucket 5.
    v[3].skipped = 0;
    let mut fifo_intra = kairos::Kairos::new(kairos::KairosConfig {
        intra: kairos::IntraBucket::Fifo,
        ..kairos::KairosConfig::default()
    });
    assert_eq!(order_of(&mut fifo_intra, now, &v), vec![2, 0, 1, 3]);
    // B = infinity: the continuous ratio decides (0.58 > 0.55).
    let mut inf = kairos::Kairos::new(kairos::KairosConfig {
        buckets: None,
        ..kairos::KairosConfig::default()
    });
    assert_eq!(order_of(&mut inf, now, &v), vec![2, 1, 0, 3]);
    // B = 2: 0.55 and 0.58 and 0.95 share the top bucket; ê decides (400, 300, 0).
    let mut two = kairos::Kairos::new(kairos::KairosConfig {
        buckets: Some(2),
        ..kairos::KairosConfig::default()
    });
    assert_eq!(order_of(&mut two, now, &v), vec![1, 0, 2, 3]);
    // A ratio of exactly 1 is clamped into the top bucket.
    let full = view(9, 0, 0, 10_000);
    assert_eq!(k.priority(ms(now), &full), 9);
}

#[test]
fn plas_queues_by_attained_service_with_anti_starvation() {
    let mut p = plas::Plas::new(plas::PlasConfig::default());
    let mut v = vec![view(0, 0, 0, 0), view(1, 10, 0, 0), view(2, 20, 0, 0)];
    // Thresholds 1 s, 3 s, 7 s, ...: 3.5 s -> queue 2; 0.9 s -> queue 0; 1 s -> queue 1.
    v[0].attained_service = Duration::from_millis(3_500);
    v[1].attained_service = Duration::from_millis(1_000);
    v[2].attained_service = Duration::from_millis(900);
    assert_eq!(p.queue_of(&v[0]), 2);
    assert_eq!(p.queue_of(&v[1]), 1);
    assert_eq!(p.queue_of(&v[2]), 0);
    assert_eq!(order_of(&mut p, 0, &v), vec![2, 1, 0]);
    // Queued 8 x 3.5 s: promoted to queue 0, ahead of request 2 by arrival.
    v[0].queued = Duration::from_millis(28_000);
    assert_eq!(p.queue_of(&v[0]), 0);
    assert_eq!(order_of(&mut p, 0, &v), vec![0, 2, 1]);
    // No service yet: the floor is one quantum, so 7.9 s queued is not starving.
    v[2].attained_service = Duration::ZERO;
    v[2].queued = Duration::from_millis(7_900);
    assert_eq!(p.queue_of(&v[2]), 0);
    let last = plas::Plas::new(plas::PlasConfig {
        queues: 3,
        ..plas::PlasConfig::default()
    });
    v[1].attained_service = Duration::from_secs(1_000);
    assert_eq!(last.queue_of(&v[1]), 2, "the last queue is unbounded");
}

#[test]
fn fifo_orders_by_arrival_then_id() {
    let v = vec![view(5, 30, 0, 0), view(2, 10, 0, 0), view(7, 10, 0, 0)];
    assert_eq!(order_of(&mut fifo::Fifo::default(), 100, &v), vec![2, 7, 5]);
}

/// Engines for a property case: `edges` edge instances and optionally one cloud instance.
fn arb_engines(with_cloud: bool) -> impl Strategy<Value = Vec<EngineSpec>> {
    let edge = (100u32..1_500, 1u32..5).prop_map(|(l, b)| engine(Tier::Edge, f64::from(l), b, 0));
    let cloud = (50u32..800, 1u32..5, 0u64..400)
        .prop_map(|(l, b, rtt)| engine(Tier::Cloud, f64::from(l), b, rtt));
    (
        proptest::collection::vec(edge, 1..3),
        proptest::option::weighted(0.6, cloud),
    )
        .prop_map(move |(mut engines, cloud)| {
            if with_cloud {
                engines.extend(cloud);
            }
            engines
        })
}

fn arb_tasks(
    max_tasks: usize,
    exec_ms: std::ops::Range<u64>,
) -> impl Strategy<Value = Vec<RobotTask>> {
    let task = (0u64..4_000, proptest::collection::vec(exec_ms, 1..6))
        .prop_map(|(arrive_ms, exec_ms)| RobotTask { arrive_ms, exec_ms });
    proptest::collection::vec(task, 1..max_tasks)
}

const POLICIES: &[&str] = &[
    "fifo",
    "plas",
    "plas:beta=1,quantum_ms=200",
    "kairos",
    "kairos:buckets=inf",
    "kairos:buckets=2,aging=1",
    "kairos:intra=fifo",
];

/// The largest number of phase-2 skips `L` allowed by
/// `L <= (N-1) * (1 + log_{ρ/(ρ-1)}((S0 + L) / (1 + S0)))` (docs/SCHEDULER.md, "Starvation").
fn phase_two_bound(tasks: u64, rho: f64, s0: u64) -> u64 {
    let others = tasks.saturating_sub(1) as f64;
    if rho <= 1.0 {
        return tasks.saturating_sub(1);
    }
    let base = (rho / (rho - 1.0)).ln();
    let mut l = 0u64;
    loop {
        let next = l + 1;
        let rhs = others * (1.0 + ((s0 + next) as f64 / (1 + s0) as f64).ln() / base);
        if next as f64 > rhs {
            return l;
        }
        l = next;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Every request is dispatched exactly once, batches respect max_batch and idle engines
    /// (asserted inside `run`), every policy answers a valid order, and every task ends.
    #[test]
    fn every_request_is_dispatched_exactly_once(
        engines in arb_engines(true),
        tasks in arb_tasks(14, 0..3_000),
        which in 0..POLICIES.len(),
    ) {
        let sched = Scheduler::new(SchedulerConfig::default(), engines, policy(POLICIES[which]));
        let trace = run(sched, &tasks);
        let rounds: usize = tasks.iter().map(|t| t.exec_ms.len()).sum();
        prop_assert_eq!(trace.dispatched.len(), rounds);
        let mut seen = std::collections::HashSet::new();
        for &(_, task, round) in &trace.dispatched {
            prop_assert!(seen.insert((task, round)), "dispatched twice");
        }
        prop_assert_eq!(trace.summaries.len(), tasks.len());
        for (i, s) in &trace.summaries {
            prop_assert_eq!(s.rounds as usize, tasks[*i].exec_ms.len());
            prop_assert!(s.wait <= s.latency());
        }
    }

    /// Kairos on edge instances, with every execution phase in [E_min, E_max]: a request with a
    /// reported execution is skipped at most A(B-1) + L* times, L* from `phase_two_bound`.
    #[test]
    fn kairos_skips_are_bounded(
        engines in arb_engines(false),
        mut tasks in arb_tasks(30, 50..400),
        buckets in 1u32..12,
        aging in 1u32..6,
        equal_exec in any::<bool>(),
    ) {
        if equal_exec {
            // rho = 1: the bound tightens to A(B-1) + N - 1.
            let e = tasks[0].exec_ms[0];
            tasks.iter_mut().for_each(|t| t.exec_ms.iter_mut().for_each(|x| *x = e));
        }
        let spec = format!("kairos:buckets={buckets},aging={aging}");
        let sched = Scheduler::new(SchedulerConfig::default(), engines, policy(&spec));
        let trace = run(sched, &tasks);
        let (e_min, e_max) = tasks
            .iter()
            .flat_map(|t| t.exec_ms.iter().copied())
            .fold((u64::MAX, 0), |(lo, hi), e| (lo.min(e), hi.max(e)));
        let s0 = u64::from(aging) * u64::from(buckets - 1);
        let bound = s0 + phase_two_bound(tasks.len() as u64, e_max as f64 / e_min as f64, s0);
        for (request, (skipped, exec)) in &trace.max_skipped {
            if exec.is_some() {
                prop_assert!(
                    u64::from(*skipped) <= bound,
                    "{request:?} skipped {skipped} > bound {bound}"
                );
            }
        }
    }
}

#[derive(Clone, Debug)]
enum Op {
    /// Task sends its next round (the robot may do so while the previous one is pending or
    /// running: that supersedes or abandons it).
    Submit(u64),
    /// Client of the n-th request issued so far goes away.
    Cancel(usize),
    Poll,
    /// Oldest running batch ends: 0 answered, 1 failed, 2 outcomes missing.
    Finish(u8),
    End(u64),
    Advance(u64),
}

fn arb_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => (0u64..5).prop_map(Op::Submit),
        1 => (0usize..40).prop_map(Op::Cancel),
        3 => Just(Op::Poll),
        3 => (0u8..3).prop_map(Op::Finish),
        1 => (0u64..5).prop_map(Op::End),
        2 => (1u64..500).prop_map(Op::Advance),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// Under arbitrary interleavings of submits, cancels, supersedes, failures and task ends,
    /// every request the scheduler accepted leaves it exactly one way: dispatched, cancelled
    /// while pending, superseded, or named as the open request of its ended task.
    #[test]
    fn every_request_leaves_exactly_once(
        ops in proptest::collection::vec(arb_op(), 1..120),
        which in 0..POLICIES.len(),
        cloud in any::<bool>(),
    ) {
        let mut engines = vec![engine(Tier::Edge, 200.0, 2, 0)];
        if cloud {
            engines.push(engine(Tier::Cloud, 50.0, 2, 30));
        }
        let mut s = Scheduler::new(SchedulerConfig::default(), engines, policy(POLICIES[which]));
        let mut now = 0u64;
        let mut issued: Vec<RequestId> = Vec::new();
        let mut next_round: HashMap<u64, u64> = HashMap::new();
        let mut exits: HashMap<RequestId, &'static str> = HashMap::new();
        let mut running: std::collections::VecDeque<(BatchId, Vec<RequestId>)> = Default::default();
        let exit = |exits: &mut HashMap<RequestId, &'static str>, r: RequestId, how: &'static str| {
            let before = exits.insert(r, how);
            assert!(before.is_none(), "{r:?} left twice: {before:?} then {how}");
        };
        let mut ended: HashSet<u64> = HashSet::new();
        for op in ops.into_iter().chain([Op::Poll]) {
            match op {
                Op::Submit(t) if !ended.contains(&t) => {
                    let round = next_round.entry(t).or_insert(1);
                    let r = s.handle_submit(ms(now), submit_at(t, *round, ms(now), None)).unwrap();
                    *round += 1;
                    issued.push(r);
                    for sup in s.take_superseded() {
                        exit(&mut exits, sup.request, "superseded");
                    }
                }
                Op::Submit(_) => {}
                Op::Cancel(n) => {
                    if let Some(&r) = issued.get(n)
                        && s.handle_cancel(ms(now), r) == CancelOutcome::Removed
                    {
                        exit(&mut exits, r, "cancelled");
                    }
                }
                Op::Poll => {
                    for d in s.poll_dispatch(ms(now)) {
                        s.handle_batch_started(ms(now), d.batch);
                        let ids: Vec<_> = d.requests.iter().map(|r| r.request).collect();
                        for &r in &ids {
                            exit(&mut exits, r, "dispatched");
                        }
                        running.push_back((d.batch, ids));
                    }
                }
                Op::Finish(kind) => {
                    if let Some((batch, ids)) = running.pop_front() {
                        let outcomes: Vec<_> = match kind {
                            0 => ids.iter().map(|&r| (r, RoundOutcome::Answered { horizon: 2 })).collect(),
                            1 => ids.iter().map(|&r| (r, RoundOutcome::Failed)).collect(),
                            _ => Vec::new(),
                        };
                        s.handle_batch_finished(ms(now), batch, &outcomes);
                    }
                }
                Op::End(t) => {
                    if let Ok(summary) = s.handle_task_end(ms(now), TaskId(t), RobotId(t as u32), TaskEnd::Done, None) {
                        ended.insert(t);
                        // A running open request already left as dispatched.
                        if let Some(r) = summary.open_request
                            && !exits.contains_key(&r)
                        {
                            exit(&mut exits, r, "task ended");
                        }
                    }
                }
                Op::Advance(d) => now += d,
            }
            prop_assert_eq!(
                s.pending_len(),
                issued.iter().filter(|r| !exits.contains_key(r)).count(),
                "pending = issued - left"
            );
        }
        prop_assert_eq!(s.counters().policy_errors, 0);
    }
}

mod membership {
    //! Engines joining and leaving (remote workers): ids never reused, placement over live
    //! instances only, a lost batch's requests back in the queue as they were.
    use super::*;

    #[test]
    fn requeued_requests_keep_their_place_and_only_live_engines_are_placed() {
        let mut s = Scheduler::new(
            SchedulerConfig::default(),
            Vec::new(),
            Box::new(crate::scheduler::fifo::Fifo::default()),
        );
        let spec = |name: &str| EngineSpec {
            name: name.into(),
            tier: Tier::Edge,
            profile: kairos_engine_types::EngineProfile {
                model: "m".into(),
                device: "d".into(),
                points: vec![kairos_engine_types::ProfilePoint {
                    batch: 1,
                    latency_ms: 10.0,
                }],
                max_batch: 2,
            },
            rtt: Duration::ZERO,
        };
        let t = |ms: u64| Timestamp::from_micros(ms * 1000);
        let submit = |task: u64, at: Timestamp| RoundSubmit {
            task: TaskId(task),
            robot: RobotId(0),
            round: 0,
            sent_at: at,
            obs_captured_at: at,
            last_exec: None,
            remaining: None,
            control_hz: None,
        };
        let r: Vec<RequestId> = (0..3)
            .map(|i| s.handle_submit(t(i), submit(i, t(i))).unwrap())
            .collect();
        assert!(s.poll_dispatch(t(3)).is_empty(), "no engine yet");
        let a = s.add_engine(spec("a"));
        let first = s.poll_dispatch(t(4));
        assert_eq!(first.len(), 1);
        assert_eq!(first[0].engine, a);
        let placed: Vec<RequestId> = first[0].requests.iter().map(|d| d.request).collect();
        assert_eq!(placed, [r[0], r[1]]);
        s.handle_batch_started(t(4), first[0].batch);
        // `a` is lost: its two requests come back ahead of r[2] (arrival order).
        assert_eq!(s.remove_engine(a), Some(first[0].batch));
        assert_eq!(s.requeue_batch(t(6), first[0].batch), placed);
        assert_eq!(s.pending_len(), 3);
        assert!(
            s.poll_dispatch(t(6)).is_empty(),
            "the lost engine gets nothing"
        );
        let b = s.add_engine(spec("b"));
        assert_ne!(a, b, "ids are never reused");
        let second = s.poll_dispatch(t(7));
        assert_eq!(second[0].engine, b);
        let placed: Vec<RequestId> = second[0].requests.iter().map(|d| d.request).collect();
        assert_eq!(placed, [r[0], r[1]], "front of the queue again");
        // The lost forward pass counts as queueing: round 0's queueing runs from its arrival.
        assert_eq!(s.counters().requeued, 2);
        assert_eq!(s.live_engines(), 1);
        // A request that will not run again fails and leaves the queue.
        assert!(s.fail_pending(t(8), r[2]));
        assert_eq!(s.pending_len(), 0);
        assert!(!s.fail_pending(t(8), r[2]));
        // `a` left with its batch gone: the scheduler forgot it, and its id is refused.
        assert!(s.engine(a).is_none());
        assert_eq!(s.remove_engine(a), None);
        assert_eq!(s.engines().map(|e| e.id).collect::<Vec<_>>(), [b]);
    }

    /// A worker that registers and leaves in a loop: the scheduler's per-instance storage stays
    /// at what is in the pool, and no event about an instance that left reaches a newer one.
    #[test]
    fn engines_that_come_and_go_leave_nothing_behind_and_their_ids_are_refused() {
        let mut s = Scheduler::new(
            SchedulerConfig::default(),
            vec![spec_named("local")],
            Box::new(crate::scheduler::fifo::Fifo::default()),
        );
        let local = EngineId(0);
        let t = |ms: u64| Timestamp::from_micros(ms * 1000);
        // The local engine runs one long batch the whole time, so rounds go to the workers.
        let busy = RoundSubmit {
            task: TaskId(u64::MAX),
            robot: RobotId(0),
            round: 0,
            sent_at: t(0),
            obs_captured_at: t(0),
            last_exec: None,
            remaining: None,
            control_hz: None,
        };
        s.handle_submit(t(0), busy).unwrap();
        assert_eq!(s.poll_dispatch(t(0))[0].engine, local);
        let mut stale = Vec::new();
        for cycle in 0..10_000u64 {
            let id = s.add_engine(spec_named("worker"));
            assert_eq!(
                id,
                EngineId(1 + cycle as usize),
                "ids move on, never reused"
            );
            if cycle % 2 == 0 {
                // Idle when it leaves: forgotten at once.
                assert_eq!(s.remove_engine(id), None);
            } else {
                // Busy when it leaves: kept until its batch is given back, then forgotten.
                let submit = RoundSubmit {
                    task: TaskId(cycle),
                    sent_at: t(cycle),
                    obs_captured_at: t(cycle),
                    ..busy
                };
                let request = s.handle_submit(t(cycle), submit).unwrap();
                let d = s.poll_dispatch(t(cycle));
                assert_eq!((d.len(), d[0].engine), (1, id));
                assert_eq!(s.remove_engine(id), Some(d[0].batch));
                assert!(s.engine(id).is_some_and(|e| !e.live), "kept while it runs");
                assert_eq!(s.requeue_batch(t(cycle), d[0].batch), [request]);
                assert!(s.fail_pending(t(cycle), request));
            }
            assert!(s.engine(id).is_none(), "forgotten once it left and is idle");
            stale.push(id);
            assert_eq!(
                s.engine_records(),
                1,
                "cycle {cycle}: only the local engine is held"
            );
        }
        assert_eq!(s.live_engines(), 1);
        // Every stale id is refused, and a new instance gets an id none of them had.
        let newest = s.add_engine(spec_named("newest"));
        for &id in &stale {
            assert_ne!(id, newest);
            assert!(s.engine(id).is_none());
            assert_eq!(s.remove_engine(id), None);
            assert_eq!(s.engine_busy(id), None);
            assert!(!s.set_engine_tier(id, Tier::Cloud));
            s.set_engine_rtt(id, Duration::from_secs(1));
        }
        let newest_state = s.engine(newest).unwrap();
        assert!(newest_state.live);
        assert_eq!(
            newest_state.spec.rtt,
            Duration::ZERO,
            "stale events did not reach it"
        );
        assert_eq!(newest_state.spec.tier, Tier::Edge);
        assert_eq!(s.engine_records(), 2);
    }

    fn spec_named(name: &str) -> EngineSpec {
        EngineSpec {
            name: name.into(),
            tier: Tier::Edge,
            profile: kairos_engine_types::EngineProfile {
                model: "m".into(),
                device: "d".into(),
                points: vec![kairos_engine_types::ProfilePoint {
                    batch: 1,
                    latency_ms: 10.0,
                }],
                max_batch: 1,
            },
            rtt: Duration::ZERO,
        }
    }
}

/// Online profile refinement through the event API. The start-up profile measured batch 2 on a
/// busy machine (3.5x batch 1), so it batches nothing; the engine really takes 1.8x. Without
/// refinement every batch has one request for good; with it, probes of batch 2 and the real
/// batch times bring batching back. One injected slow batch (10x) afterwards moves batch 2's
/// estimate by a bounded step: with batch 2 only 11% ahead of batch 1 in throughput, that may
/// switch batching off, but only until the next probes measure batch 2 again.
#[test]
fn refined_profiles_recover_from_a_noisy_start_up_measurement() {
    let noisy = EngineProfile {
        model: "test".into(),
        device: "virtual".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms: 100.0,
            },
            ProfilePoint {
                batch: 2,
                latency_ms: 350.0,
            },
        ],
        max_batch: 1,
    };
    let real = |size: usize| Duration::from_millis(if size >= 2 { 180 } else { 100 });
    let run = |refine: bool, rounds: u64, slow_at: Option<u64>| -> (Vec<usize>, Scheduler) {
        let mut s = Scheduler::new(
            SchedulerConfig::default(),
            vec![EngineSpec {
                name: "edge".into(),
                tier: Tier::Edge,
                profile: noisy.clone(),
                rtt: Duration::ZERO,
            }],
            policy("fifo"),
        );
        if refine {
            s.refine_profiles(refine::RefineConfig::default());
        }
        let (mut now, mut sizes, mut task) = (Timestamp::ZERO, Vec::new(), 0u64);
        for round in 0..rounds {
            while s.pending_len() < 4 {
                s.handle_submit(now, submit_at(task, 1, now, None)).unwrap();
                task += 1;
            }
            for d in s.poll_dispatch(now) {
                s.handle_batch_started(now, d.batch);
                let size = d.requests.len();
                let took = if slow_at == Some(round) {
                    real(size) * 10
                } else {
                    real(size)
                };
                let end = now + took;
                s.handle_generation_ended(end, d.batch);
                let outcomes: Vec<_> = d
                    .requests
                    .iter()
                    .map(|r| (r.request, RoundOutcome::Answered { horizon: 1 }))
                    .collect();
                s.handle_batch_finished(end, d.batch, &outcomes);
                sizes.push(size);
                now = end;
            }
        }
        (sizes, s)
    };
    let (plain, _) = run(false, 600, None);
    assert!(
        plain.iter().all(|&n| n == 1),
        "the noisy profile batches nothing"
    );
    let (refined, s) = run(true, 600, None);
    assert!(refined[..10].iter().all(|&n| n == 1));
    assert!(
        refined[refined.len() - 100..].iter().all(|&n| n == 2),
        "batching is back: {:?}",
        &refined[refined.len() - 100..]
    );
    assert_eq!(s.engines().next().unwrap().spec.profile.max_batch, 2);
    let (slowed, s) = run(true, 600, Some(300));
    assert_eq!(slowed[..300], refined[..300]);
    assert!(
        slowed[slowed.len() - 100..].iter().all(|&n| n == 2),
        "batching is back after the slow batch: {:?}",
        &slowed[slowed.len() - 100..]
    );
    assert_eq!(s.engines().next().unwrap().spec.profile.max_batch, 2);
}
