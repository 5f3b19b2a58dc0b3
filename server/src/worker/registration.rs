//! The scheduler's side of a remote engine worker's connection (ALPN `kairos-worker/1`,
//! `kairos_sdk::protocol::worker`): `Register` checked against the worker token, the protocol's
//! rules (a worker is untrusted input: string sizes, a finite, positive and bounded profile)
//! and the site's model shapes, the worker added to the pool as a [`RemoteEngine`], then
//! heartbeats until it drains, goes silent, breaks the protocol or disconnects, when it leaves
//! the pool. Its batches run on streams the [`RemoteEngine`] opens; this task only watches the
//! registration stream. Every removal, and every registration refused for breaking the
//! protocol's rules, is counted once by reason ([`Removal`]).

use std::sync::Arc;
use std::time::Duration;

use kairos_sdk::client::close_code;
use kairos_sdk::protocol::worker::{
    Refused, Register, Registered, WORKER_PROTOCOL_VERSION, WorkerMessage, WorkerTier,
    close_code as worker_close,
};
use kairos_sdk::protocol::{
    Limits, ReadBounds, ReadFrameError, Validate, read_frame_bounded, write_body,
};
use quinn::{Connection, RecvStream, SendStream, VarInt};
use tokio::sync::watch;
use tokio::time::Instant;

use super::RemoteEngine;
use super::readmission::Readmission;
use super::removal::{Removal, truncated};
use super::wire::{model_spec, profile_from_wire};
use crate::config::WorkersConfig;
use crate::credentials::hash_token;
use crate::metrics::{Metrics, WorkerRemoval};
use crate::pool::{EngineInstance, same_shapes};
use crate::transport::refusals::{Door, Reason};
use crate::transport::{Gate, ServerContext};
use kairos_core::scheduler::Tier;

/// Who may register as a worker, and how workers are treated.
#[derive(Clone, Debug)]
pub struct WorkerGate {
    /// SHA-256 of the worker token; `None`: workers are refused (`[workers] enabled = false`).
    pub token_hash: Option<[u8; 32]>,
    /// `[workers]`.
    pub config: WorkersConfig,
    /// Where removed workers are counted (`kairos_worker_removed_total`).
    pub metrics: Metrics,
    /// Workers removed for unusable answers, refused registration until their delay ends
    /// (`[workers] readmit_after_invalid_ms`).
    pub readmission: Arc<Readmission>,
}

impl WorkerGate {
    /// The gate of a scheduler that accepts workers holding the token whose hash is
    /// `token_hash` (`None`: none), treated as `config` says, counted in `metrics`.
    pub fn new(token_hash: Option<[u8; 32]>, config: WorkersConfig, metrics: Metrics) -> Self {
        let readmission = Arc::new(Readmission::new(config.readmit_after_invalid()));
        WorkerGate {
            token_hash,
            config,
            metrics,
            readmission,
        }
    }
}

/// The largest `Register` body read: names, a token and a profile of a few dozen points.
const REGISTER_MAX_FRAME: u32 = 64 << 10;

/// Serves one worker connection until it leaves. Registration must complete by `deadline`
/// (the robot's `hello_timeout_ms`).
pub(crate) async fn serve(
    connection: Connection,
    unauthenticated: tokio::sync::OwnedSemaphorePermit,
    context: Arc<ServerContext>,
    gate: Arc<Gate>,
    deadline: Instant,
    mut stop: watch::Receiver<bool>,
) {
    let remote = connection.remote_address();
    let registered = tokio::select! {
        registered = tokio::time::timeout_at(deadline, register(&connection, &context, &gate)) => registered,
        _ = stop.wait_for(|stopping| *stopping) => return,
    };
    let (engine, removal, send, recv) = match registered {
        Ok(Ok(registered)) => registered,
        Ok(Err(Refusal {
            code,
            reason,
            logged,
        })) => {
            // A guard's refusal (a wrong token, a readmission delay) is counted and warn-logged,
            // rate-limited, where it happens: a worker retrying every 100 ms must not write a
            // line each time.
            if logged {
                tracing::debug!(%remote, %reason, "worker refused");
            } else {
                tracing::info!(%remote, %reason, "worker refused");
            }
            connection.close(VarInt::from_u32(code), truncated(&reason, 200).as_bytes());
            return;
        }
        Err(_) => {
            context.refusals.refuse(
                Door::Workers,
                Reason::RegisterTimeout,
                remote,
                &"no Register within hello_timeout_ms",
            );
            connection.close(
                VarInt::from_u32(close_code::PROTOCOL_ERROR),
                b"no Register in time",
            );
            return;
        }
    };
    drop(unauthenticated);
    let _send = send;
    let why = watch_worker(&connection, recv, &context, engine, &removal, &mut stop).await;
    context.driver.remove_engine(engine).await;
    tracing::info!(%remote, ?engine, why, "worker left the pool");
}

/// Heartbeats until the worker leaves; returns why, for the log (a removal is counted by
/// [`Removal`]). A `Drain` takes the worker out of placement at once; its running batch still finishes and the connection is closed once the
/// worker finishes its registration stream. A worker that goes silent, sends anything but a
/// valid `Heartbeat` or `Drain`, or loses its connection is removed.
async fn watch_worker(
    connection: &Connection,
    mut recv: RecvStream,
    context: &ServerContext,
    engine: kairos_core::scheduler::EngineId,
    removal: &Removal,
    stop: &mut watch::Receiver<bool>,
) -> &'static str {
    let idle = context.workers.config.idle_timeout();
    let limits = Limits {
        max_frame: REGISTER_MAX_FRAME,
        ..Limits::default()
    };
    let mut draining = false;
    let mut stopping = false;
    loop {
        tokio::select! {
            frame = tokio::time::timeout(idle, read_frame_bounded(&mut recv, &limits, &ReadBounds::UNBOUNDED)) => {
                match frame {
                    Err(_) if !draining => {
                        removal.remove(WorkerRemoval::Silent, "no heartbeat");
                        return "silent";
                    }
                    // A draining worker is finishing its batch; its connection's keep-alive
                    // and the batch deadline watch it from here.
                    Err(_) => {}
                    Ok(Ok(Some(frame))) => match decode_checked(&frame, &limits) {
                        Ok(WorkerMessage::Heartbeat(_)) => {}
                        Ok(WorkerMessage::Drain(drain)) => {
                            tracing::info!(?engine, reason = %drain.reason, "worker draining");
                            draining = true;
                            context.driver.remove_engine(engine).await;
                        }
                        Ok(other) => {
                            let reason = format!("unexpected on the registration stream: {}", other.kind());
                            removal.remove(WorkerRemoval::ProtocolError, &reason);
                            return "protocol error";
                        }
                        Err(reason) => {
                            removal.remove(WorkerRemoval::ProtocolError, &reason);
                            return "protocol error";
                        }
                    },
                    // The worker finished its registration stream: it is done.
                    Ok(Ok(None)) => {
                        removal.left();
                        let _ = tokio::time::timeout(Duration::from_secs(1), connection.closed()).await;
                        connection.close(VarInt::from_u32(worker_close::DRAINED), b"drained");
                        return "drained";
                    }
                    Ok(Err(ReadFrameError::Read(error))) => {
                        removal.remove(WorkerRemoval::ConnectionLost, &error.to_string());
                        return "connection lost";
                    }
                    // An oversized or malformed frame.
                    Ok(Err(error)) => {
                        removal.remove(WorkerRemoval::ProtocolError, &error.to_string());
                        return "protocol error";
                    }
                }
            }
            closed = connection.closed() => {
                // Already counted if a batch removed it.
                if !draining && !stopping {
                    removal.remove(WorkerRemoval::ConnectionLost, &closed.to_string());
                }
                return "connection closed";
            }
            // The scheduler stops: the worker keeps serving while the driver answers the rounds
            // it accepted; the transport closes the connection when it is done draining.
            () = async { let _ = stop.wait_for(|stopping| *stopping).await; }, if !stopping => {
                stopping = true;
                removal.left();
            }
            // Every accepted round is answered: the worker is told at once (it reconnects to
            // the next scheduler) instead of holding the shutdown until the drain timeout.
            () = context.driver.stopped(), if stopping => {
                connection.close(VarInt::from_u32(close_code::SHUTTING_DOWN), b"scheduler stopped");
                return "scheduler_stopped";
            }
        }
    }
}

/// A message of the registration stream, decoded and checked against the protocol's rules.
fn decode_checked(
    frame: &kairos_sdk::protocol::Frame,
    limits: &Limits,
) -> Result<WorkerMessage, String> {
    let message = WorkerMessage::decode(frame).map_err(|e| e.to_string())?;
    let checked = match &message {
        WorkerMessage::Register(m) => m.validate(limits),
        WorkerMessage::Heartbeat(m) => m.validate(limits),
        WorkerMessage::Drain(m) => m.validate(limits),
        WorkerMessage::Chunks(m) => m.validate(limits),
        // Sent by the scheduler, never to it: the caller refuses them by kind.
        WorkerMessage::Registered(_) | WorkerMessage::Refused(_) | WorkerMessage::RunBatch(_) => {
            Ok(())
        }
    };
    checked.map_err(|error| format!("{}: {error}", message.kind()))?;
    Ok(message)
}

type Registration = (
    kairos_core::scheduler::EngineId,
    Removal,
    SendStream,
    RecvStream,
);

/// Why a registration ended without the worker in the pool.
struct Refusal {
    /// The connection's close code.
    code: u32,
    /// The close reason, also the `Refused` text.
    reason: String,
    /// Counted and logged already by a guard (`kairos_refusals_total`).
    logged: bool,
}

/// What [`check`] refused: the close code, the reason, whether the worker may retry, and whether
/// a guard counted and logged it already.
type CheckRefusal = (u32, String, bool, bool);

/// `Register` → checks → the pool → `Registered`; or the close code and reason after `Refused`.
async fn register(
    connection: &Connection,
    context: &ServerContext,
    gate: &Gate,
) -> Result<Registration, Refusal> {
    let protocol_error = |reason: String| Refusal {
        code: close_code::PROTOCOL_ERROR,
        reason,
        logged: false,
    };
    let (mut send, mut recv) = connection
        .accept_bi()
        .await
        .map_err(|e| protocol_error(e.to_string()))?;
    let limits = Limits {
        max_frame: REGISTER_MAX_FRAME,
        ..Limits::default()
    };
    let frame = match read_frame_bounded(&mut recv, &limits, &ReadBounds::UNBOUNDED).await {
        Ok(Some(frame)) => frame,
        Ok(None) => return Err(protocol_error("stream closed before Register".into())),
        Err(error) => return Err(protocol_error(error.to_string())),
    };
    let register = match WorkerMessage::decode(&frame) {
        Ok(WorkerMessage::Register(register)) => register,
        Ok(other) => {
            return Err(protocol_error(format!(
                "expected Register, got {}",
                other.kind()
            )));
        }
        Err(error) => return Err(protocol_error(error.to_string())),
    };
    let verdict = check(context, gate, connection.remote_address(), &register);
    let (code, reason, retryable, logged) = match verdict {
        Ok(()) => {
            let profile = match profile_from_wire(register.profile.clone()) {
                Ok(mut profile) => {
                    profile.max_batch = profile.max_batch.min(register.max_batch);
                    profile
                }
                Err(reason) => {
                    context
                        .workers
                        .metrics
                        .record_worker_removed(WorkerRemoval::InvalidRegistration);
                    return refuse(send, (worker_close::REFUSED, reason, false, false)).await;
                }
            };
            let removal = Removal::new(connection.clone(), context.workers.metrics.clone())
                .barring(context.workers.readmission.clone(), &register.worker_id);
            let declared = match register.tier {
                WorkerTier::Edge => Some(Tier::Edge),
                WorkerTier::Cloud => Some(Tier::Cloud),
                WorkerTier::Auto => None,
            };
            let name = format!(
                "worker:{}@{}",
                register.worker_id,
                connection.remote_address()
            );
            // The worker's batches and their chunks need more than the registration window.
            connection.set_receive_window(VarInt::from_u32(
                kairos_sdk::protocol::worker::WORKER_MAX_FRAME,
            ));
            let engine = RemoteEngine::new(
                name.clone(),
                model_spec(&register.model),
                profile,
                declared,
                connection.clone(),
                removal.clone(),
                context.workers.config.clone(),
            );
            let tier = engine.tier();
            match context.driver.add_engine(Arc::new(engine)).await {
                Ok(Ok(id)) => {
                    let registered = Registered {
                        protocol: WORKER_PROTOCOL_VERSION,
                        engine: name.clone(),
                        heartbeat_ms: context.workers.config.heartbeat_ms,
                    };
                    if let Err(error) = write_body(&mut send, &registered, REGISTER_MAX_FRAME).await
                    {
                        context.driver.remove_engine(id).await;
                        return Err(protocol_error(error.to_string()));
                    }
                    tracing::info!(engine = %name, ?id, ?tier, "worker registered");
                    return Ok((id, removal, send, recv));
                }
                Ok(Err(error)) => (close_code::PROTOCOL_ERROR, error.to_string(), false, false),
                Err(gone) => (close_code::SHUTTING_DOWN, gone.to_string(), true, false),
            }
        }
        Err(refusal) => refusal,
    };
    refuse(send, (code, reason, retryable, logged)).await
}

/// Token, version and shapes, in that order (the token first, so a stranger learns nothing
/// about the model).
fn check(
    context: &ServerContext,
    gate: &Gate,
    remote: std::net::SocketAddr,
    register: &Register,
) -> Result<(), CheckRefusal> {
    let ip = remote.ip();
    let Some(expected) = context.workers.token_hash else {
        return Err((
            worker_close::REFUSED,
            "this scheduler accepts no workers ([workers] enabled = false)".into(),
            false,
            false,
        ));
    };
    if !gate.source_allowed(ip) {
        let reason = "too many wrong tokens from this address; retry later";
        context
            .refusals
            .refuse(Door::Workers, Reason::WrongTokenLimit, remote, &reason);
        return Err((close_code::UNAUTHORIZED, reason.into(), true, true));
    }
    if hash_token(&register.token) != expected {
        gate.token_failed(ip);
        context.refusals.refuse(
            Door::Workers,
            Reason::Unauthorized,
            remote,
            &"unknown worker token",
        );
        return Err((
            close_code::UNAUTHORIZED,
            "unknown worker token (robot tokens cannot register workers)".into(),
            false,
            true,
        ));
    }
    // The token was right: from here on the worker learns why it is refused.
    if let Err(error) = register.validate(&Limits::default()) {
        context
            .workers
            .metrics
            .record_worker_removed(WorkerRemoval::InvalidRegistration);
        return Err((
            worker_close::REFUSED,
            format!("Register breaks the protocol's rules: {error}"),
            false,
            false,
        ));
    }
    if let Err(wait) = context
        .workers
        .readmission
        .check(&register.worker_id, ip, Instant::now())
    {
        let reason = format!(
            "worker `{}` was removed for an unusable answer; it may register again in {} ms",
            register.worker_id,
            wait.as_millis()
        );
        context
            .refusals
            .refuse(Door::Workers, Reason::ReadmitDelay, remote, &reason);
        return Err((worker_close::REFUSED, reason, true, true));
    }
    if register.protocol < WORKER_PROTOCOL_VERSION {
        return Err((
            worker_close::REFUSED,
            format!(
                "worker protocol {} is not supported (this scheduler speaks {WORKER_PROTOCOL_VERSION})",
                register.protocol
            ),
            false,
            false,
        ));
    }
    let spec = model_spec(&register.model);
    if !same_shapes(&spec, &context.validator.spec) {
        return Err((
            worker_close::REFUSED,
            format!(
                "the worker serves {spec:?}, but this site serves {:?}",
                context.validator.spec
            ),
            false,
            false,
        ));
    }
    Ok(())
}

/// Sends `Refused` and waits briefly for it to be delivered; returns the close code and reason.
async fn refuse<T>(
    mut send: SendStream,
    (code, reason, retryable, logged): CheckRefusal,
) -> Result<T, Refusal> {
    let refused = Refused {
        reason: reason.clone(),
        retryable,
    };
    let _ = write_body(&mut send, &refused, REGISTER_MAX_FRAME).await;
    let _ = send.finish();
    let _ = tokio::time::timeout(Duration::from_secs(1), send.stopped()).await;
    Err(Refusal {
        code,
        reason,
        logged,
    })
}
