//! Where the driver's state machine runs, measured (docs/BENCHMARKS.md, "Driver hand-off").
//!
//! `hop/*` compares the three ways a connection task can hand an event to the scheduler's state
//! machine and get its answer back, on a two-worker tokio runtime like the server's on a 2-core
//! machine. The state machine's own work is one counter increment, so only the hand-off is
//! timed:
//! - `tokio_task` (the baseline, the driver before issue #11): an actor task on the runtime
//!   behind an mpsc, answering on a oneshot. Policies would run on a tokio worker.
//! - `dedicated_thread`: the same channel read with `blocking_recv` by an OS thread of its own
//!   (what the driver does now).
//! - `blocking_pool`: an actor task that moves the state machine onto tokio's blocking pool
//!   (`spawn_blocking`) for every event and awaits it back.
//!
//! `driver/*` measures the real driver on a dedicated thread: a `stats` query round trip, and a
//! whole round (submit, batch on an engine that answers at once, horizon policy on the blocking
//! pool, reply).

use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_core::action::ActionManager;
use kairos_core::clock_map::ClockMap;
use kairos_core::registry::native_horizon_policies;
use kairos_core::scheduler::fifo::Fifo;
use kairos_core::scheduler::{RobotId, Scheduler, SchedulerConfig, Tier};
use kairos_engine::{ActionChunk, ActionRequest, EngineProfile, ModelSpec, ProfilePoint};
use kairos_sdk::protocol::{Limits, Observation, Submit, Tensor};
use kairos_server::driver::{DriverConfig, RefetchAsk};
use kairos_server::pool::{BatchChunks, EngineInstance, EnginePool, PoolError};
use kairos_server::validation::Validator;
use tokio::sync::{mpsc, oneshot, watch};

type Event = (u64, oneshot::Sender<u64>);

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime")
}

/// Sends `iters` events one after another from a task and awaits each answer.
fn round_trips(rt: &tokio::runtime::Runtime, tx: &mpsc::Sender<Event>, iters: u64) -> Duration {
    let tx = tx.clone();
    rt.block_on(async move {
        tokio::spawn(async move {
            let start = Instant::now();
            for i in 0..iters {
                let (answer, rx) = oneshot::channel();
                tx.send((i, answer)).await.expect("actor running");
                rx.await.expect("answered");
            }
            start.elapsed()
        })
        .await
        .expect("client task")
    })
}

fn hop(c: &mut Criterion) {
    let mut group = c.benchmark_group("hop");
    let rt = runtime();

    let (tx, mut rx) = mpsc::channel::<Event>(8192);
    rt.spawn(async move {
        let mut state = 0u64;
        while let Some((event, answer)) = rx.recv().await {
            state = state.wrapping_add(event);
            let _ = answer.send(state);
        }
    });
    group.bench_function("tokio_task", |b| {
        b.iter_custom(|iters| round_trips(&rt, &tx, iters))
    });
    drop(tx);

    let (tx, mut rx) = mpsc::channel::<Event>(8192);
    let thread = std::thread::spawn(move || {
        let mut state = 0u64;
        while let Some((event, answer)) = rx.blocking_recv() {
            state = state.wrapping_add(event);
            let _ = answer.send(state);
        }
    });
    group.bench_function("dedicated_thread", |b| {
        b.iter_custom(|iters| round_trips(&rt, &tx, iters))
    });
    drop(tx);
    let _ = thread.join();

    let (tx, mut rx) = mpsc::channel::<Event>(8192);
    rt.spawn(async move {
        let mut state = Some(0u64);
        while let Some((event, answer)) = rx.recv().await {
            let Some(mut machine) = state.take() else {
                break;
            };
            let stepped = tokio::task::spawn_blocking(move || {
                machine = machine.wrapping_add(event);
                machine
            })
            .await;
            match stepped {
                Ok(machine) => {
                    state = Some(machine);
                    let _ = answer.send(machine);
                }
                Err(_) => break,
            }
        }
    });
    group.bench_function("blocking_pool", |b| {
        b.iter_custom(|iters| round_trips(&rt, &tx, iters))
    });
    drop(tx);
    group.finish();
}

/// An engine that answers at once with a constant chunk (no thread, no model).
struct Instant0 {
    spec: ModelSpec,
    profile: EngineProfile,
}

impl EngineInstance for Instant0 {
    fn name(&self) -> &str {
        "instant"
    }
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }
    fn profile(&self) -> &EngineProfile {
        &self.profile
    }
    fn tier(&self) -> Tier {
        Tier::Edge
    }
    fn rtt(&self) -> Duration {
        Duration::ZERO
    }
    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        let s = self.spec.clone();
        let chunks = batch
            .iter()
            .map(|_| {
                Ok(ActionChunk {
                    samples: 1,
                    steps: s.steps,
                    chunk_len: s.chunk_len,
                    action_dim: s.action_dim,
                    actions: vec![0.0; s.chunk_len * s.action_dim],
                    updates: vec![0.0; s.steps * s.chunk_len * s.action_dim],
                    noise: vec![0.0; s.chunk_len * s.action_dim],
                })
            })
            .collect();
        async move { Ok(chunks) }.boxed()
    }
}

fn driver(c: &mut Criterion) {
    let mut group = c.benchmark_group("driver");
    let rt = runtime();
    let spec = ModelSpec {
        cameras: Vec::new(),
        camera_aliases: Default::default(),
        name: "instant".into(),
        chunk_len: 8,
        action_dim: 2,
        state_dim: 3,
        steps: 2,
        max_images: 0,
    };
    let engine = Instant0 {
        spec: spec.clone(),
        profile: EngineProfile {
            model: "instant".into(),
            device: "cpu".into(),
            points: vec![ProfilePoint {
                batch: 1,
                latency_ms: 1.0,
            }],
            max_batch: 1,
        },
    };
    let pool = EnginePool::new(vec![Arc::new(engine)]).expect("pool");
    let natives = native_horizon_policies();
    let actions = Arc::new(
        ActionManager::new(
            natives.clone(),
            &natives,
            "static",
            [("h".to_string(), 4.0)].into(),
        )
        .expect("actions"),
    );
    let config = SchedulerConfig {
        stale_after: Duration::from_secs(3600),
        ..SchedulerConfig::default()
    };
    let scheduler = Scheduler::new(config, pool.specs(), Box::new(Fifo::default()));
    let (_stop, stop_rx) = watch::channel(false);
    let (handle, _join) = rt.block_on(async {
        kairos_server::driver::spawn(
            scheduler,
            pool,
            actions.clone(),
            DriverConfig::default(),
            stop_rx,
        )
    });
    let validator = Validator {
        spec,
        limits: Limits::default(),
        chunking: Default::default(),
    };

    group.bench_function("stats_query", |b| {
        b.iter_custom(|iters| {
            let handle = handle.clone();
            rt.block_on(async move {
                let start = Instant::now();
                for _ in 0..iters {
                    handle.stats().await.expect("driver running");
                }
                start.elapsed()
            })
        })
    });

    let mut round = 0u64;
    group.bench_function("round", |b| {
        b.iter_custom(|iters| {
            let (handle, validator, actions) = (handle.clone(), &validator, actions.clone());
            let first = round;
            round += iters;
            rt.block_on(async move {
                let clock = ClockMap::new(handle.clock().now(), 0, Duration::ZERO);
                let start = Instant::now();
                for r in first..first + iters {
                    let now = clock.to_client(handle.clock().now());
                    let submit = Submit {
                        task: 1,
                        round: r,
                        sent_at_us: now,
                        observation: Observation {
                            captured_at_us: now,
                            state: Tensor::from_f32(vec![3], &[1.0, 0.0, 0.0]).expect("tensor"),
                            images: Vec::new(),
                            instruction: String::new(),
                        },
                        last_exec: None,
                        horizon: None,
                        remaining: None,
                        attempt: 0,
                        control_hz: None,
                        seed: None,
                        chunking: None,
                    };
                    let valid = validator
                        .submit(submit, RobotId(0), &actions, clock)
                        .expect("valid");
                    let (link, _asks) = mpsc::channel::<RefetchAsk>(1);
                    let pending = handle
                        .submit(valid, handle.clock().now(), link)
                        .await
                        .expect("driver running");
                    pending.answer.await.expect("answered").expect("reply");
                }
                start.elapsed()
            })
        })
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .without_plots()
        .sample_size(30)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    targets = hop, driver
}
criterion_main!(benches);
