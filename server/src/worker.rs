//! `kairos worker`: a remote engine worker. It dials the scheduler over QUIC with ALPN
//! `kairos-worker/1` (dialling out works behind NAT and with any orchestrator), pins the
//! scheduler's certificate, registers its model spec, profile, max batch and tier with the
//! worker token, then runs every `RunBatch` the scheduler sends on its [`EngineInstance`] (a
//! `LocalEngine`: the model on its own OS thread, never on a tokio worker) and heartbeats. On
//! shutdown (SIGTERM) it sends `Drain`, finishes the batches it holds and exits. It holds no
//! task state: a batch it never answers is run again elsewhere by the scheduler.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::Duration;

use kairos_sdk::protocol::worker::{
    Chunks, Drain, Heartbeat, Register, RunBatch, WORKER_MAX_FRAME, WORKER_PROTOCOL_VERSION,
    WorkResult, WorkerMessage, WorkerTier,
};
use kairos_sdk::protocol::{Limits, read_frame, write_body};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, worker_client_config};
use quinn::{Connection, RecvStream, SendStream, VarInt};
use tokio::sync::Notify;

use crate::metrics::{Metrics, WorkerConnection};
use crate::pool::EngineInstance;
use crate::pool::remote::{chunk_to_wire, model_info, profile_to_wire, request_from_wire};

/// Where and as whom a worker registers.
#[derive(Clone, Debug)]
pub struct WorkerOptions {
    /// The scheduler's QUIC address.
    pub server: SocketAddr,
    /// How the scheduler's certificate is checked (a pin, normally).
    pub trust: ServerTrust,
    /// The worker token.
    pub token: String,
    /// A name for logs and metrics.
    pub worker_id: String,
    /// Edge, cloud, or auto (the scheduler classifies it from its measured round trip).
    pub tier: WorkerTier,
    /// Largest batch to accept (caps the profile's).
    pub max_batch: u32,
    /// Where the worker counts what it does (a [`Metrics::for_worker`] registry, served on
    /// `--metrics-listen` when given).
    pub metrics: Metrics,
}

/// Why a worker stopped other than by draining.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The QUIC or TLS setup.
    #[error("cannot set up the connection: {0}")]
    Setup(String),
    /// Dialling or the handshake failed (a wrong pin ends here).
    #[error("cannot connect to the scheduler at {addr}: {reason}")]
    Connect {
        /// The scheduler.
        addr: SocketAddr,
        /// Why.
        reason: String,
    },
    /// The scheduler refused the registration.
    #[error("the scheduler refused the worker: {0}")]
    Refused(String),
    /// The protocol broke (unexpected or malformed messages).
    #[error("worker protocol error: {0}")]
    Protocol(String),
    /// The connection was lost while serving.
    #[error("the connection to the scheduler was lost: {0}")]
    Lost(String),
}

/// What a worker did.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WorkerReport {
    /// The name the scheduler gave it.
    pub engine: String,
    /// Batches answered.
    pub batches: u64,
}

/// Shared between the batch tasks, the heartbeat and the drain.
#[derive(Default)]
struct Load {
    running: AtomicU32,
    done: AtomicU64,
    idle: Notify,
}

/// Registers with the scheduler and serves batches until `shutdown` resolves (then drains and
/// returns) or the connection is lost (an error).
pub async fn run(
    options: WorkerOptions,
    engine: Arc<dyn EngineInstance>,
    shutdown: impl Future<Output = ()>,
) -> Result<WorkerReport, WorkerError> {
    let metrics = options.metrics.clone();
    metrics.add_engine(engine.name());
    metrics.set_worker_connection(WorkerConnection::Connecting);
    let served = serve(options, engine, shutdown).await;
    metrics.set_worker_connection(WorkerConnection::Disconnected);
    served
}

async fn serve(
    options: WorkerOptions,
    engine: Arc<dyn EngineInstance>,
    shutdown: impl Future<Output = ()>,
) -> Result<WorkerReport, WorkerError> {
    let metrics = options.metrics.clone();
    let connection = connect(&options).await?;
    let (mut control, engine_name, heartbeat) = register(&connection, &options, engine.as_ref())
        .await
        .inspect_err(|_| connection.close(VarInt::from_u32(0), b"refused"))?;
    tracing::info!(engine = %engine_name, server = %options.server, "registered");
    metrics.set_worker_connection(WorkerConnection::Registered);
    let load = Arc::new(Load::default());
    let mut shutdown = std::pin::pin!(shutdown);
    let mut ticker = tokio::time::interval(heartbeat);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut draining = false;
    let mut finished = false;
    let mut drain_grace = tokio::time::Instant::now();
    loop {
        tokio::select! {
            accepted = connection.accept_bi() => match accepted {
                Ok((send, recv)) => {
                    let (engine, load, metrics) = (engine.clone(), load.clone(), metrics.clone());
                    load.running.fetch_add(1, Ordering::SeqCst);
                    tokio::spawn(async move {
                        if let Err(error) = serve_batch(engine.as_ref(), &metrics, send, recv).await {
                            tracing::warn!(%error, "batch not answered");
                            metrics.record_worker_failed_batch();
                        } else {
                            load.done.fetch_add(1, Ordering::SeqCst);
                        }
                        if load.running.fetch_sub(1, Ordering::SeqCst) == 1 {
                            load.idle.notify_waiters();
                        }
                    });
                }
                Err(error) if draining => {
                    tracing::info!(%error, "connection closed after draining");
                    break;
                }
                Err(error) => return Err(WorkerError::Lost(error.to_string())),
            },
            _ = ticker.tick() => {
                let beat = Heartbeat {
                    load: load.running.load(Ordering::SeqCst),
                    batches: load.done.load(Ordering::SeqCst),
                };
                if finished {
                    continue;
                }
                if let Err(error) = write_body(&mut control, &beat, WORKER_MAX_FRAME).await {
                    if draining {
                        break;
                    }
                    return Err(WorkerError::Lost(error.to_string()));
                }
                metrics.record_worker_heartbeat();
            }
            // Batches placed before the scheduler read `Drain` may still arrive during a
            // heartbeat period: they are served as usual. Then, once none is running, the
            // registration stream ends and the scheduler closes the connection (a batch that
            // would still come then runs elsewhere).
            () = async {
                tokio::time::sleep_until(drain_grace).await;
                wait_idle(&load).await;
            }, if draining && !finished => {
                finished = true;
                let _ = control.finish();
            }
            () = &mut shutdown, if !draining => {
                draining = true;
                metrics.set_worker_connection(WorkerConnection::Draining);
                tracing::info!("draining: no new batches; finishing the ones held");
                let drain = Drain { reason: "shutdown".into() };
                if write_body(&mut control, &drain, WORKER_MAX_FRAME).await.is_err() {
                    break;
                }
                drain_grace = tokio::time::Instant::now() + heartbeat;
            }
        }
    }
    wait_idle(&load).await;
    connection.close(VarInt::from_u32(0), b"drained");
    Ok(WorkerReport {
        engine: engine_name,
        batches: load.done.load(Ordering::SeqCst),
    })
}

async fn wait_idle(load: &Load) {
    loop {
        let notified = load.idle.notified();
        if load.running.load(Ordering::SeqCst) == 0 {
            return;
        }
        notified.await;
    }
}

async fn connect(options: &WorkerOptions) -> Result<Connection, WorkerError> {
    let config = worker_client_config(&options.trust, &TransportTuning::default())
        .map_err(|e| WorkerError::Setup(e.to_string()))?;
    let bind: SocketAddr = if options.server.is_ipv6() {
        "[::]:0"
            .parse()
            .map_err(|e| WorkerError::Setup(format!("{e}")))?
    } else {
        "0.0.0.0:0"
            .parse()
            .map_err(|e| WorkerError::Setup(format!("{e}")))?
    };
    let mut endpoint =
        quinn::Endpoint::client(bind).map_err(|e| WorkerError::Setup(e.to_string()))?;
    endpoint.set_default_client_config(config);
    let connect_error = |reason: String| WorkerError::Connect {
        addr: options.server,
        reason,
    };
    endpoint
        .connect(options.server, "kairos")
        .map_err(|e| connect_error(e.to_string()))?
        .await
        .map_err(|e| connect_error(e.to_string()))
}

/// `Register` → `Registered` (the engine's name and the heartbeat period) or `Refused`.
async fn register(
    connection: &Connection,
    options: &WorkerOptions,
    engine: &dyn EngineInstance,
) -> Result<(SendStream, String, Duration), WorkerError> {
    let protocol = |e: String| WorkerError::Protocol(e);
    let (mut send, mut recv) = connection
        .open_bi()
        .await
        .map_err(|e| WorkerError::Lost(e.to_string()))?;
    let register = Register {
        protocol: WORKER_PROTOCOL_VERSION,
        token: options.token.clone(),
        worker_id: options.worker_id.clone(),
        model: model_info(engine.spec()),
        profile: profile_to_wire(engine.profile()),
        max_batch: options.max_batch.max(1),
        tier: options.tier,
    };
    write_body(&mut send, &register, WORKER_MAX_FRAME)
        .await
        .map_err(|e| WorkerError::Lost(e.to_string()))?;
    let limits = Limits::default();
    let frame = read_frame(&mut recv, &limits)
        .await
        .map_err(|e| WorkerError::Refused(format!("no answer to Register: {e}")))?
        .ok_or_else(|| WorkerError::Refused("the scheduler closed the stream".into()))?;
    match WorkerMessage::decode(&frame).map_err(|e| protocol(e.to_string()))? {
        WorkerMessage::Registered(registered) => Ok((
            send,
            registered.engine,
            Duration::from_millis(u64::from(registered.heartbeat_ms.max(1))),
        )),
        WorkerMessage::Refused(refused) => Err(WorkerError::Refused(refused.reason)),
        other => Err(protocol(format!(
            "expected Registered, got {}",
            other.kind()
        ))),
    }
}

/// One batch stream: `RunBatch` in, the engine's answers out as `Chunks`.
async fn serve_batch(
    engine: &dyn EngineInstance,
    metrics: &Metrics,
    mut send: SendStream,
    mut recv: RecvStream,
) -> Result<(), String> {
    let limits = Limits {
        max_frame: WORKER_MAX_FRAME,
        ..Limits::default()
    };
    let frame = read_frame(&mut recv, &limits)
        .await
        .map_err(|e| e.to_string())?
        .ok_or("the batch stream ended before RunBatch")?;
    let run: RunBatch = match WorkerMessage::decode(&frame).map_err(|e| e.to_string())? {
        WorkerMessage::RunBatch(run) => run,
        other => return Err(format!("expected RunBatch, got {}", other.kind())),
    };
    let (batch_id, attempt) = (run.batch_id, run.attempt);
    let mut inputs = Vec::with_capacity(run.requests.len());
    let mut refused = Vec::new();
    for (i, request) in run.requests.into_iter().enumerate() {
        match request_from_wire(request) {
            Ok(input) => inputs.push(input),
            Err(reason) => refused.push((i, reason)),
        }
    }
    let n = inputs.len() + refused.len();
    let started = tokio::time::Instant::now();
    let inputs_empty = inputs.is_empty();
    let answered = if inputs_empty {
        Vec::new()
    } else {
        engine.run(inputs).await.map_err(|e| e.to_string())?
    };
    let compute = started.elapsed();
    if !inputs_empty {
        metrics.record_engine_busy(engine.name(), compute);
    }
    let mut answered = answered.into_iter();
    let mut results = Vec::with_capacity(n);
    for i in 0..n {
        if let Some((_, reason)) = refused.iter().find(|(at, _)| *at == i) {
            results.push(WorkResult {
                chunk: None,
                error: Some(format!("request {i}: {reason}")),
            });
            continue;
        }
        let result = match answered.next() {
            Some(Ok(chunk)) => match chunk_to_wire(&chunk) {
                Ok(chunk) => WorkResult {
                    chunk: Some(chunk),
                    error: None,
                },
                Err(reason) => WorkResult {
                    chunk: None,
                    error: Some(reason),
                },
            },
            Some(Err(error)) => WorkResult {
                chunk: None,
                error: Some(error.to_string()),
            },
            None => WorkResult {
                chunk: None,
                error: Some("the engine returned too few results".into()),
            },
        };
        results.push(result);
    }
    let chunks = Chunks {
        batch_id,
        attempt,
        compute_us: u64::try_from(compute.as_micros()).unwrap_or(u64::MAX),
        results,
    };
    write_body(&mut send, &chunks, WORKER_MAX_FRAME)
        .await
        .map_err(|e| e.to_string())?;
    let _ = send.finish();
    metrics.record_worker_batch(n, compute);
    // Wait for the scheduler to read it, so that the stream is not cut by a close after it.
    let _ = tokio::time::timeout(Duration::from_secs(2), send.stopped()).await;
    Ok(())
}
