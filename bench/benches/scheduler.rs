//! Cost of one scheduling decision (`Scheduler::poll_dispatch`) with 100 / 1,000 / 10,000 pending
//! requests, for each native priority policy. Target (issue #2): at most 20 µs per pending
//! request at 10,000 pending. FIFO is the baseline measured in the same run.
//!
//! Every task has a realistic history (several answered rounds with generation- and
//! execution-dominated phases and varied wait ratios) and one pending request. The measured engine
//! is an idle edge instance with max batch 16; a second instance used only to build the histories
//! stays busy. Each iteration times one decision, then (untimed) finishes the dispatched batch and
//! resubmits the next round of the 16 served tasks, so every decision sees `n` pending requests in
//! a steady state.
//!
//! Run: `cargo bench -p kairos-server --bench scheduler`. Criterion reports time per decision and
//! throughput in pending requests per second; time per pending request = time / n.

use std::collections::HashMap;
use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use kairos_core::scheduler::{
    BatchId, EngineSpec, ExecReport, RequestId, RobotId, RoundOutcome, RoundSubmit, Scheduler,
    SchedulerConfig, TaskId, Tier, build_policy,
};
use kairos_core::time::Timestamp;
use kairos_engine::{EngineProfile, ProfilePoint};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const HISTORY_ROUNDS: u64 = 6;
const MEASURED_BATCH: u32 = 16;

fn profile(max_batch: u32, ms: f64) -> EngineProfile {
    EngineProfile {
        model: "bench".into(),
        device: "virtual".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms: ms,
            },
            ProfilePoint {
                batch: 16,
                latency_ms: ms * 2.0,
            },
        ],
        max_batch,
    }
}

/// A scheduler in steady state with `n` pending requests, and what is needed to keep it there.
struct Fixture {
    sched: Scheduler,
    now: u64,
    rng: StdRng,
    /// Per task: next round id and when its last chunk was answered (µs).
    tasks: HashMap<TaskId, (u64, u64)>,
}

impl Fixture {
    fn new(policy: &str, n: usize) -> Self {
        let engines = vec![
            EngineSpec {
                name: "edge".into(),
                tier: Tier::Edge,
                profile: profile(MEASURED_BATCH, 80.0),
                rtt: Duration::ZERO,
            },
            EngineSpec {
                name: "setup".into(),
                tier: Tier::Edge,
                profile: profile(1_000_000, 80.0),
                rtt: Duration::ZERO,
            },
        ];
        let config = SchedulerConfig {
            max_pending: 1_000_000,
            ..SchedulerConfig::default()
        };
        let sched = Scheduler::new(
            config,
            engines,
            build_policy(&policy.parse().expect("policy spec")).expect("policy"),
        );
        let mut f = Fixture {
            sched,
            now: 0,
            rng: StdRng::seed_from_u64(42),
            tasks: HashMap::new(),
        };
        // Tasks start at different times so their lifetimes (and wait ratios) differ.
        for round in 0..HISTORY_ROUNDS {
            for t in 0..n as u64 {
                if round == 0 && f.rng.random_bool(0.3) {
                    continue; // a later starter
                }
                f.submit(TaskId(t));
            }
            f.run_all();
        }
        // Park the setup engine on a batch that never ends.
        for t in 0..=u64::from(MEASURED_BATCH) {
            f.submit(TaskId(u64::MAX - t));
        }
        let parked = f.sched.poll_dispatch(Timestamp::from_micros(f.now));
        for d in &parked {
            f.sched
                .handle_batch_started(Timestamp::from_micros(f.now), d.batch);
            if d.engine.0 == 0 {
                f.finish(
                    d.batch,
                    &d.requests.iter().map(|r| r.request).collect::<Vec<_>>(),
                );
            }
        }
        for t in 0..n as u64 {
            f.submit(TaskId(t));
        }
        assert_eq!(f.sched.pending_len(), n);
        f
    }

    fn submit(&mut self, task: TaskId) {
        self.now += self.rng.random_range(1..200);
        let (round, answered) = self.tasks.get(&task).copied().unwrap_or((1, 0));
        let exec = (round > 1).then(|| ExecReport {
            started_at: Timestamp::from_micros(answered.min(self.now)),
            actions_remaining: self.rng.random_range(0..40),
            control_hz: 30.0,
        });
        let now = Timestamp::from_micros(self.now);
        let submit = RoundSubmit {
            task,
            robot: RobotId(task.0 as u32),
            round,
            sent_at: now,
            obs_captured_at: now,
            last_exec: exec,
            remaining: None,
            control_hz: None,
        };
        self.sched.handle_submit(now, submit).expect("admitted");
        self.tasks.insert(task, (round + 1, answered));
    }

    fn finish(&mut self, batch: BatchId, requests: &[RequestId]) {
        self.now += self.rng.random_range(50_000..150_000);
        let outcomes: Vec<_> = requests
            .iter()
            .map(|&r| (r, RoundOutcome::Answered { horizon: 10 }))
            .collect();
        self.sched
            .handle_batch_finished(Timestamp::from_micros(self.now), batch, &outcomes);
    }

    /// Dispatches and answers everything pending (history building).
    fn run_all(&mut self) {
        let now = Timestamp::from_micros(self.now);
        let dispatches = self.sched.poll_dispatch(now);
        for d in &dispatches {
            self.sched.handle_batch_started(now, d.batch);
        }
        for d in dispatches {
            let ids: Vec<_> = d.requests.iter().map(|r| r.request).collect();
            self.finish(d.batch, &ids);
            for r in &d.requests {
                if let Some(entry) = self.tasks.get_mut(&r.task) {
                    entry.1 = self.now;
                }
            }
        }
    }

    /// One timed decision, then the untimed restore.
    fn decide(&mut self) -> Duration {
        self.now += 1_000;
        let now = Timestamp::from_micros(self.now);
        let start = Instant::now();
        let dispatches = black_box(self.sched.poll_dispatch(now));
        let elapsed = start.elapsed();
        for d in dispatches {
            self.sched.handle_batch_started(now, d.batch);
            let ids: Vec<_> = d.requests.iter().map(|r| r.request).collect();
            self.finish(d.batch, &ids);
            for r in &d.requests {
                if let Some(entry) = self.tasks.get_mut(&r.task) {
                    entry.1 = self.now;
                }
                self.submit(r.task);
            }
        }
        elapsed
    }
}

fn decision(c: &mut Criterion) {
    let mut group = c.benchmark_group("poll_dispatch");
    group.sample_size(30);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(3));
    for n in [100usize, 1_000, 10_000] {
        group.throughput(Throughput::Elements(n as u64));
        for policy in ["fifo", "plas", "kairos"] {
            let mut fixture = Fixture::new(policy, n);
            group.bench_with_input(BenchmarkId::new(policy, n), &n, |b, _| {
                b.iter_custom(|iters| (0..iters).map(|_| fixture.decide()).sum());
            });
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    // No plots: the HTML plot backend needs system fonts the CI machines do not have.
    config = Criterion::default().without_plots();
    targets = decision
}
criterion_main!(benches);
