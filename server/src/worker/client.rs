//! `kairos worker`: a remote engine worker. It dials the scheduler over QUIC with ALPN
//! `kairos-worker/1` (dialling out works behind NAT and with any orchestrator), pins the
//! scheduler's certificate, registers its model spec, profile, max batch and tier with the
//! worker token, then runs every `RunBatch` the scheduler sends on its [`EngineInstance`] (a
//! `LocalEngine`: the model on its own OS thread, never on a tokio worker) and heartbeats. On
//! shutdown (SIGTERM) it sends `Drain`, finishes the batches it holds and exits. It holds no
//! task state: a batch it never answers is run again elsewhere by the scheduler. A connection
//! that drops without a drain (the scheduler restarted or removed it, the network failed) is
//! dialled again with exponential backoff ([`reconnect_delay`]) and the worker registers anew;
//! the scheduler's `host:port` may be a DNS name, resolved at every attempt. It counts what it
//! does in its own [`Metrics::for_worker`] registry.

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

use super::removal::truncated;
use super::wire::{chunk_to_wire, model_info, profile_to_wire, request_from_wire};
use crate::metrics::{Metrics, WorkerConnection};
use crate::pool::EngineInstance;

/// Where and as whom a worker registers.
#[derive(Clone, Debug)]
pub struct WorkerOptions {
    /// The scheduler's QUIC address, `host:port` (an IP address or a DNS name, resolved with
    /// `tokio::net::lookup_host` at every connection attempt; IPv4 addresses are tried first).
    pub server: String,
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
    /// The scheduler's name did not resolve to an address.
    #[error("cannot resolve the scheduler's address {server}: {reason}")]
    Resolve {
        /// The `host:port` given.
        server: String,
        /// Why.
        reason: String,
    },
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
    /// The name the scheduler gave it (at its last registration).
    pub engine: String,
    /// Batches answered, over all its connections.
    pub batches: u64,
    /// Times it registered (more than one: it reconnected after losing the scheduler).
    pub registrations: u64,
}

/// Shared between the batch tasks, the heartbeat and the drain.
#[derive(Default)]
struct Load {
    running: AtomicU32,
    done: AtomicU64,
    idle: Notify,
}

/// First wait before reconnecting after the connection to the scheduler dropped; it doubles
/// with every failed attempt up to [`RECONNECT_MAX`], and starts over once registered again.
pub const RECONNECT_FIRST: Duration = Duration::from_millis(100);
/// Longest wait between reconnection attempts.
pub const RECONNECT_MAX: Duration = Duration::from_secs(5);
/// Longest a connection attempt to one address may take (QUIC ignores ICMP unreachable, so a
/// scheduler that is not there yet would otherwise cost a whole idle timeout).
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// The wait before reconnection attempt `attempt` (0-based): [`RECONNECT_FIRST`] doubled per
/// attempt, at most [`RECONNECT_MAX`]. Pure.
pub fn reconnect_delay(attempt: u32) -> Duration {
    RECONNECT_FIRST
        .checked_mul(1u32.checked_shl(attempt.min(31)).unwrap_or(u32::MAX))
        .unwrap_or(RECONNECT_MAX)
        .min(RECONNECT_MAX)
}

/// Registers with the scheduler and serves batches until `shutdown` resolves (then drains and
/// returns). When the connection drops without a drain (the scheduler restarted, a network
/// failure, the scheduler removed it), the worker dials again after [`reconnect_delay`] and
/// registers anew, for as long as it is not shut down; the `--server` name is resolved again at
/// every attempt. A first connection that fails, and any refusal, end it with the error.
pub async fn run(
    options: WorkerOptions,
    engine: Arc<dyn EngineInstance>,
    shutdown: impl Future<Output = ()>,
) -> Result<WorkerReport, WorkerError> {
    let metrics = options.metrics.clone();
    metrics.add_engine(engine.name());
    let mut shutdown = std::pin::pin!(shutdown);
    let mut report = WorkerReport::default();
    let mut attempt = 0u32;
    let ended = loop {
        metrics.set_worker_connection(WorkerConnection::Connecting);
        let registrations = report.registrations;
        let served = serve(&options, &engine, shutdown.as_mut(), &mut report).await;
        metrics.set_worker_connection(WorkerConnection::Disconnected);
        if report.registrations > registrations {
            attempt = 0;
        }
        let error = match served {
            Ok(()) => break Ok(report),
            Err(error) => error,
        };
        // Only a worker that was in a pool once dials again: one that never got in (a wrong
        // address, a wrong pin) would retry a mistake forever.
        let retry = match &error {
            WorkerError::Lost(_) | WorkerError::Connect { .. } | WorkerError::Resolve { .. } => {
                report.registrations > 0
            }
            WorkerError::Setup(_) | WorkerError::Refused(_) | WorkerError::Protocol(_) => false,
        };
        if !retry {
            break Err(error);
        }
        let delay = reconnect_delay(attempt);
        attempt = attempt.saturating_add(1);
        tracing::warn!(%error, ?delay, "reconnecting to the scheduler");
        tokio::select! {
            () = tokio::time::sleep(delay) => {}
            () = shutdown.as_mut() => break Ok(report),
        }
    };
    metrics.set_worker_connection(WorkerConnection::Disconnected);
    ended
}

/// One connection: dial, register, serve until drained (`Ok`) or lost. Adds its registration
/// and the batches it answered to `report`.
async fn serve(
    options: &WorkerOptions,
    engine: &Arc<dyn EngineInstance>,
    mut shutdown: std::pin::Pin<&mut impl Future<Output = ()>>,
    report: &mut WorkerReport,
) -> Result<(), WorkerError> {
    let metrics = options.metrics.clone();
    let connection = tokio::select! {
        connected = connect(options) => connected?,
        // Shut down before it could connect: there is nothing to drain.
        () = shutdown.as_mut() => return Ok(()),
    };
    let (mut control, engine_name, heartbeat) = register(&connection, options, engine.as_ref())
        .await
        .inspect_err(|_| connection.close(VarInt::from_u32(0), b"refused"))?;
    tracing::info!(engine = %engine_name, server = %options.server, "registered");
    metrics.set_worker_connection(WorkerConnection::Registered);
    report.engine = engine_name;
    report.registrations += 1;
    let load = Arc::new(Load::default());
    // Batches answered on this connection go into the report however it ends.
    struct Tally<'a>(&'a mut WorkerReport, Arc<Load>);
    impl Drop for Tally<'_> {
        fn drop(&mut self) {
            self.0.batches += self.1.done.load(Ordering::SeqCst);
        }
    }
    let tally = Tally(report, load.clone());
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
                Err(error) => {
                    wait_idle(&load).await;
                    return Err(WorkerError::Lost(error.to_string()));
                }
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
                    wait_idle(&load).await;
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
            () = shutdown.as_mut(), if !draining => {
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
    drop(tally);
    Ok(())
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

/// Resolves `options.server` and dials its addresses in turn (IPv4 first), each within
/// [`CONNECT_TIMEOUT`]; the last failure if none answers.
async fn connect(options: &WorkerOptions) -> Result<Connection, WorkerError> {
    let resolve_error = |reason: String| WorkerError::Resolve {
        server: options.server.clone(),
        reason,
    };
    let mut addrs: Vec<SocketAddr> = tokio::net::lookup_host(options.server.as_str())
        .await
        .map_err(|e| resolve_error(e.to_string()))?
        .collect();
    addrs.sort_by_key(SocketAddr::is_ipv6);
    let mut failed = resolve_error("no address".into());
    for addr in addrs {
        match connect_to(options, addr).await {
            Ok(connection) => return Ok(connection),
            Err(error) => {
                tracing::debug!(%error, "connection attempt failed");
                failed = error;
            }
        }
    }
    Err(failed)
}

async fn connect_to(options: &WorkerOptions, addr: SocketAddr) -> Result<Connection, WorkerError> {
    let config = worker_client_config(&options.trust, &TransportTuning::default())
        .map_err(|e| WorkerError::Setup(e.to_string()))?;
    let bind: SocketAddr = if addr.is_ipv6() {
        (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
    } else {
        (std::net::Ipv4Addr::UNSPECIFIED, 0).into()
    };
    let mut endpoint =
        quinn::Endpoint::client(bind).map_err(|e| WorkerError::Setup(e.to_string()))?;
    endpoint.set_default_client_config(config);
    let connect_error = |reason: String| WorkerError::Connect { addr, reason };
    let connecting = endpoint
        .connect(addr, "kairos")
        .map_err(|e| connect_error(e.to_string()))?;
    match tokio::time::timeout(CONNECT_TIMEOUT, connecting).await {
        Ok(connected) => connected.map_err(|e| connect_error(e.to_string())),
        Err(_) => Err(connect_error(format!(
            "no handshake within {CONNECT_TIMEOUT:?}"
        ))),
    }
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
    // The scheduler removes a worker whose error texts are over the protocol's limit.
    let max_text = Limits::default().max_message_bytes as usize;
    for result in &mut results {
        if let Some(error) = &mut result.error {
            let keep = truncated(error, max_text).len();
            error.truncate(keep);
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reconnection_backs_off_exponentially_up_to_the_cap() {
        let waits: Vec<u64> = (0..8)
            .map(|attempt| reconnect_delay(attempt).as_millis() as u64)
            .collect();
        assert_eq!(waits, [100, 200, 400, 800, 1600, 3200, 5000, 5000]);
        assert_eq!(reconnect_delay(u32::MAX), RECONNECT_MAX);
    }
}
