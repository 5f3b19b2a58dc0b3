//! Scheduler tests through the public event API: a tiny virtual-time loop, the hand-computed
//! four-task example, placement, the API's edge cases, and property tests.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap, HashMap};
use std::time::Duration;

use kairos_engine::{EngineProfile, ProfilePoint};

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
            let spec = sched.engines().nth(d.engine.0).unwrap().spec.clone();
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
