//! A worker that holds the real worker token and answers every batch unusably, for the mixed
//! soak (`scripts/soak.sh --mixed`, through the `kairos-hostile-worker` binary) and for tests.
//!
//! It registers with a fast profile (so the scheduler prefers it), answers each batch with the
//! next of [`Misbehaviour`] in turn, and registers again after each removal: what a buggy or
//! compromised worker would keep doing. The scheduler must remove it on each answer, run the
//! batch again elsewhere, and never let what it sent reach a robot.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use kairos_engine::ModelSpec;
use kairos_sdk::protocol::Tensor;
use kairos_sdk::protocol::worker::{
    Chunks, ProfilePointWire, ProfileWire, Register, RunBatch, WORKER_PROTOCOL_VERSION, WorkChunk,
    WorkResult, WorkerMessage, WorkerTier,
};
use kairos_sdk::tls::ServerTrust;
use kairos_server::worker::wire::model_info;

use crate::workers::RawWorker;

/// How one answer is unusable (docs/PROTOCOL.md §16, "Checks").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Misbehaviour {
    /// Chunks of the right shapes, every value NaN.
    NanActions,
    /// One result more than the batch has requests.
    WrongResultCount,
    /// An error text of [`OVERSIZED_ERROR_BYTES`] for each request.
    OversizedError,
}

/// The misbehaviours, in the order the worker cycles through them.
pub const MISBEHAVIOURS: [Misbehaviour; 3] = [
    Misbehaviour::NanActions,
    Misbehaviour::WrongResultCount,
    Misbehaviour::OversizedError,
];

/// Bytes of an oversized error text: far over the protocol's 4096-byte message limit, well
/// within a worker frame.
pub const OVERSIZED_ERROR_BYTES: usize = 100_000;

/// What the hostile worker did so far.
#[derive(Debug, Default)]
pub struct HostileCounters {
    /// `Register`s the scheduler accepted.
    pub registered: AtomicU64,
    /// `Register`s it refused (or connects that failed).
    pub refused: AtomicU64,
    /// Batches answered unusably.
    pub answered: AtomicU64,
    /// Registered connections the scheduler ended (a removal: its answers are unusable).
    pub removed: AtomicU64,
}

impl HostileCounters {
    /// One line: `registered A, refused B, batches answered unusably C, removed D`.
    pub fn summary(&self) -> String {
        format!(
            "registered {}, refused {}, batches answered unusably {}, removed {}",
            self.registered.load(Ordering::Relaxed),
            self.refused.load(Ordering::Relaxed),
            self.answered.load(Ordering::Relaxed),
            self.removed.load(Ordering::Relaxed),
        )
    }
}

/// The hostile worker's `Register` for a site serving `spec`: a one-point profile of
/// `latency_ms` at batch 1, so that it looks faster than any real engine.
pub fn hostile_register(spec: &ModelSpec, token: String, latency_ms: f64) -> Register {
    let model = model_info(spec);
    Register {
        protocol: WORKER_PROTOCOL_VERSION,
        token,
        worker_id: format!("hostile-{}", std::process::id()),
        profile: ProfileWire {
            model: model.name.clone(),
            device: "kairos-hostile-worker".into(),
            points: vec![ProfilePointWire {
                batch: 1,
                latency_ms,
            }],
            max_batch: 1,
        },
        model,
        max_batch: 1,
        tier: WorkerTier::Edge,
    }
}

/// The unusable answer `misbehaviour` to `run`, for a site serving `spec`.
pub fn unusable_answer(misbehaviour: Misbehaviour, run: &RunBatch, spec: &ModelSpec) -> Chunks {
    let chunk = |samples: u32| -> Option<WorkChunk> {
        let (k, n, d) = (
            u32::try_from(spec.steps).ok()?,
            u32::try_from(spec.chunk_len).ok()?,
            u32::try_from(spec.action_dim).ok()?,
        );
        let s = samples.max(1);
        let tensor = |shape: Vec<u32>| {
            let len = shape.iter().map(|&x| x as usize).product::<usize>();
            Tensor::from_f32(shape, &vec![f32::NAN; len]).ok()
        };
        Some(WorkChunk {
            actions: tensor(vec![s, n, d])?,
            updates: tensor(vec![s, k, n, d])?,
            noise: tensor(vec![s, n, d])?,
        })
    };
    let mut results: Vec<WorkResult> = run
        .requests
        .iter()
        .map(|request| match misbehaviour {
            Misbehaviour::NanActions | Misbehaviour::WrongResultCount => WorkResult {
                chunk: chunk(request.samples),
                error: None,
            },
            Misbehaviour::OversizedError => WorkResult {
                chunk: None,
                error: Some("x".repeat(OVERSIZED_ERROR_BYTES)),
            },
        })
        .collect();
    if misbehaviour == Misbehaviour::WrongResultCount {
        results.push(WorkResult {
            chunk: None,
            error: Some("one result too many".into()),
        });
    }
    Chunks {
        batch_id: run.batch_id,
        attempt: run.attempt,
        compute_us: 10,
        results,
    }
}

/// Runs the hostile worker against the scheduler at `addr` until its task is dropped: registers
/// with `register`, answers each batch unusably (cycling through [`MISBEHAVIOURS`]), and
/// `rejoin` after each removal registers again.
pub async fn run_hostile_worker(
    addr: SocketAddr,
    trust: ServerTrust,
    register: Register,
    spec: ModelSpec,
    rejoin: Duration,
    counters: Arc<HostileCounters>,
) {
    let mut turn = 0usize;
    loop {
        match RawWorker::dial(addr, &trust, &register).await {
            Ok((worker, WorkerMessage::Registered(_))) => {
                counters.registered.fetch_add(1, Ordering::Relaxed);
                while let Ok(batch) = worker.next_batch().await {
                    let misbehaviour = MISBEHAVIOURS[turn % MISBEHAVIOURS.len()];
                    turn = turn.wrapping_add(1);
                    let answer = unusable_answer(misbehaviour, &batch.run, &spec);
                    if batch.answer(&answer).await.is_ok() {
                        counters.answered.fetch_add(1, Ordering::Relaxed);
                    }
                }
                counters.removed.fetch_add(1, Ordering::Relaxed);
                worker.close().await;
            }
            Ok((worker, _)) => {
                counters.refused.fetch_add(1, Ordering::Relaxed);
                worker.close().await;
            }
            Err(_) => {
                counters.refused.fetch_add(1, Ordering::Relaxed);
            }
        }
        tokio::time::sleep(rejoin).await;
    }
}
