//! The QUIC server: admission, authentication and the per-stream protocol.
//!
//! [`run`] takes a bound quinn endpoint and a shutdown future (mini-redis's `run(listener,
//! shutdown)`). Admission has two budgets, so that clients that never authenticate cannot take
//! robots' places:
//! - A connection attempt takes one of `connections.max_unauthenticated` places for its
//!   handshake and `Hello`, which must both be done within `connections.hello_timeout_ms` of its
//!   first packet. Over that budget the attempt is refused without a handshake (a QUIC
//!   `CONNECTION_REFUSED`); over half of it, an attempt from an address QUIC has not validated
//!   gets a Retry first, so spoofed or half-open handshakes take no place at all.
//! - A `Hello` with a valid token moves the connection to one of its robot's
//!   `connections.max_connections_per_robot` places and to one of `connections.max_connections`
//!   places; over either the connection is closed with `close_code::AT_CAPACITY` and a reason
//!   ([`fairness`]: one tenant cannot take every place).
//! - Wrong tokens are rate-limited per source address ([`admission::FailedAuthLimiter`]): a
//!   source over its budget is refused before its token is looked at, at the first packet.
//!
//! Before `Hello`, a connection may open one stream and have a few KiB in flight; after it, the
//! robot gets `max_streams_per_connection` streams and a receive window of
//! `connections.upload_buffer_frames` frames. Every frame the server reads is bounded by a
//! minimum upload rate and by the connection's budget of partly received bytes
//! ([`kairos_sdk::protocol::ReadBounds`]), so stalled uploads neither pin memory nor last.
//! A wrong token gets an `unauthorized` error frame and the connection is closed with
//! `UNAUTHORIZED`. After that every bidirectional stream the robot opens is served by its own
//! task (`Submit` or `EndTask`), so a malformed frame fails only its own stream, with a typed
//! error frame.
//!
//! Connections are accepted with 0-RTT (see [`tls`] for why that is replay-safe) and connection
//! migration stays on, so a robot that roams to another address keeps its connection. The QUIC
//! transport is the SDK's tuned configuration (`kairos_sdk::transport::TransportTuning`: BBR, a
//! 1 ms ACK delay through the ACK-frequency extension, packet threshold 8, time threshold 1.5),
//! shared with the client so both ends recover from Wi-Fi loss and reordering the same way.
//!
//! Shutdown: the endpoint stops admitting connections, every connection stops accepting new
//! streams, the driver answers what it has accepted, the stream tasks write those answers, and
//! the connections are closed with `SHUTTING_DOWN`.

pub mod admission;
mod admit;
mod connection;
pub mod fairness;
pub mod launch;
pub mod tls;

use std::collections::HashMap;
use std::future::Future;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::client::close_code;
use kairos_sdk::protocol::{Limits, ModelInfo};
use quinn::VarInt;
use tokio::sync::{Semaphore, watch};
use tokio::task::JoinSet;

use crate::config::ConnectionsConfig;
use crate::credentials::RobotCredential;
use crate::driver::DriverHandle;
use crate::validation::{DecodePool, Validator};
use kairos_core::action::ActionManager;
use kairos_core::scheduler::RobotId;

/// How long shutdown waits for connections to deliver the answers of accepted rounds.
pub const DRAIN_TIMEOUT: Duration = Duration::from_secs(10);

/// The robots a server accepts, by token hash.
#[derive(Clone, Debug, Default)]
pub struct RobotTable {
    by_hash: HashMap<[u8; 32], RobotId>,
    names: Vec<String>,
}

impl RobotTable {
    /// A table of `robots`; robot `i` gets `RobotId(i)`.
    pub fn new(robots: &[RobotCredential]) -> RobotTable {
        let mut table = RobotTable::default();
        for (i, robot) in robots.iter().enumerate() {
            let id = RobotId(u32::try_from(i).unwrap_or(u32::MAX));
            table.by_hash.insert(robot.token_hash, id);
            table.names.push(robot.name.clone());
        }
        table
    }

    /// The robot whose token this is. Only the token's SHA-256 is compared, so the lookup's
    /// timing says nothing about how close a guess was to a real token.
    pub fn authenticate(&self, token: &str) -> Option<RobotId> {
        self.by_hash
            .get(&crate::credentials::hash_token(token))
            .copied()
    }

    /// The robot's configured name.
    pub fn name(&self, robot: RobotId) -> &str {
        self.names
            .get(robot.0 as usize)
            .map(String::as_str)
            .unwrap_or("?")
    }

    /// Number of robots.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Whether no robot may connect.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
}

/// Everything a connection task needs, shared by all of them.
pub struct ServerContext {
    /// Who may connect.
    pub robots: RobotTable,
    /// Request checks against the model and limits.
    pub validator: Validator,
    /// Decodes observations' images before the queue, a bounded number at once.
    pub decode: DecodePool,
    /// Builds requests' horizon policies.
    pub actions: Arc<ActionManager>,
    /// The driver.
    pub driver: DriverHandle,
    /// The model as announced in `Welcome`.
    pub model: ModelInfo,
    /// Connection limits.
    pub connections: ConnectionsConfig,
    /// Remote engine workers: their token and `[workers]`.
    pub workers: crate::worker::registration::WorkerGate,
    /// What one robot may take: connection places and round rates, on every transport.
    pub fairness: fairness::Fairness,
    /// The server's metrics, for the counts the connection tasks own.
    pub metrics: crate::metrics::Metrics,
}

impl ServerContext {
    /// The protocol limits.
    pub fn limits(&self) -> &Limits {
        &self.validator.limits
    }
}

/// What [`run`] saw.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TransportStats {
    /// Connections authenticated and admitted.
    pub admitted: u64,
    /// Authenticated connections closed at once because `max_connections` were open, or their
    /// robot held `max_connections_per_robot`.
    pub refused: u64,
    /// Connection attempts refused without a handshake: `max_unauthenticated` were in progress.
    pub refused_unauthenticated: u64,
    /// Connection attempts answered with a Retry (address validation under load).
    pub retried: u64,
    /// Connection attempts refused because their source sent too many wrong tokens.
    pub rate_limited: u64,
}

/// What to do with a connection attempt.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admission {
    /// Take a place in the unauthenticated budget and start the handshake.
    Handshake,
    /// Answer with a Retry: the client must prove it receives at its address first.
    Retry,
    /// Refuse without a handshake: the unauthenticated budget is full.
    Refuse,
    /// Refuse without a handshake: the source sent too many wrong tokens.
    RateLimited,
}

/// The admission rule (see the module docs): `in_progress` of `max_unauthenticated` places are
/// taken; `validated` says whether QUIC has validated the attempt's address, `may_retry` whether
/// a Retry is still allowed for it; `source_allowed` is the failed-token limiter's verdict.
pub fn admission(
    source_allowed: bool,
    validated: bool,
    may_retry: bool,
    in_progress: usize,
    max_unauthenticated: usize,
) -> Admission {
    if !source_allowed {
        Admission::RateLimited
    } else if in_progress >= max_unauthenticated {
        Admission::Refuse
    } else if !validated && may_retry && in_progress * 2 >= max_unauthenticated {
        Admission::Retry
    } else {
        Admission::Handshake
    }
}

/// Admission state shared by [`run`] and the connection tasks.
pub(crate) struct Gate {
    /// Places for authenticated connections (`max_connections`).
    authenticated: Arc<Semaphore>,
    /// Failed tokens per source.
    failed_tokens: Mutex<admission::FailedAuthLimiter>,
    admitted: AtomicU64,
    refused: AtomicU64,
}

impl Gate {
    fn new(config: &ConnectionsConfig) -> Gate {
        Gate {
            authenticated: Arc::new(Semaphore::new(config.max_connections)),
            failed_tokens: Mutex::new(admission::FailedAuthLimiter::new(
                config.failed_token_burst,
                config.failed_tokens_per_minute,
                config.failed_token_sources,
            )),
            admitted: AtomicU64::new(0),
            refused: AtomicU64::new(0),
        }
    }

    fn limiter(&self) -> std::sync::MutexGuard<'_, admission::FailedAuthLimiter> {
        // A panic while holding this lock leaves at worst one bucket stale.
        self.failed_tokens
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Whether `ip` may try a token now.
    pub(crate) fn source_allowed(&self, ip: std::net::IpAddr) -> bool {
        self.limiter().allows(ip, now())
    }

    /// Counts a wrong token from `ip`.
    pub(crate) fn token_failed(&self, ip: std::net::IpAddr) {
        self.limiter().record_failure(ip, now());
    }

    /// A place for an authenticated connection, if one is free.
    pub(crate) fn authenticated(&self) -> Option<tokio::sync::OwnedSemaphorePermit> {
        match self.authenticated.clone().try_acquire_owned() {
            Ok(permit) => {
                self.admitted.fetch_add(1, Ordering::Relaxed);
                Some(permit)
            }
            Err(_) => {
                self.refused.fetch_add(1, Ordering::Relaxed);
                None
            }
        }
    }

    /// Counts an authenticated connection refused because its robot held all its places (it
    /// had been counted as admitted when it took a place among all robots', given back now).
    pub(crate) fn robot_at_capacity(&self) {
        self.admitted.fetch_sub(1, Ordering::Relaxed);
        self.refused.fetch_add(1, Ordering::Relaxed);
    }
}

/// The limiter's clock: tokio's, so tests with a paused clock control it.
fn now() -> std::time::Instant {
    tokio::time::Instant::now().into_std()
}

/// Serves `endpoint` until `shutdown` resolves, then drains (see the module docs).
pub async fn run(
    endpoint: quinn::Endpoint,
    context: Arc<ServerContext>,
    shutdown: impl Future<Output = ()>,
) -> TransportStats {
    let gate = Arc::new(Gate::new(&context.connections));
    context.metrics.watch_connection_places(
        "quic",
        &gate.authenticated,
        context.connections.max_connections,
    );
    let max_unauthenticated = context.connections.max_unauthenticated;
    let unauthenticated = Arc::new(Semaphore::new(max_unauthenticated));
    let (stop_tx, stop_rx) = watch::channel(false);
    let mut connections = JoinSet::new();
    let mut stats = TransportStats::default();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        tokio::select! {
            incoming = endpoint.accept() => {
                let Some(incoming) = incoming else { break };
                let decision = admission(
                    gate.source_allowed(incoming.remote_address().ip()),
                    incoming.remote_address_validated(),
                    incoming.may_retry(),
                    max_unauthenticated - unauthenticated.available_permits(),
                    max_unauthenticated,
                );
                let permit = match decision {
                    Admission::Handshake => unauthenticated.clone().try_acquire_owned().ok(),
                    _ => None,
                };
                match (decision, permit) {
                    (Admission::Handshake, Some(permit)) => {
                        let context = context.clone();
                        let gate = gate.clone();
                        let stop = stop_rx.clone();
                        connections.spawn(async move {
                            connection::serve(incoming, permit, context, gate, stop).await;
                        });
                    }
                    (Admission::Retry, _) => {
                        stats.retried += 1;
                        if let Err(error) = incoming.retry() {
                            error.into_incoming().refuse();
                        }
                    }
                    (Admission::RateLimited, _) => {
                        stats.rate_limited += 1;
                        incoming.refuse();
                    }
                    (Admission::Refuse | Admission::Handshake, _) => {
                        stats.refused_unauthenticated += 1;
                        incoming.refuse();
                    }
                }
            }
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
            () = &mut shutdown => break,
        }
    }
    tracing::info!(
        connections = connections.len(),
        "shutting down: no new connections"
    );
    endpoint.set_server_config(None);
    let _ = stop_tx.send(true);
    let drained = tokio::time::timeout(DRAIN_TIMEOUT, async {
        while connections.join_next().await.is_some() {}
    })
    .await;
    if drained.is_err() {
        tracing::warn!(
            left = connections.len(),
            "connections still busy after the drain timeout"
        );
        connections.abort_all();
    }
    endpoint.close(
        VarInt::from_u32(close_code::SHUTTING_DOWN),
        b"server shutting down",
    );
    let _ = tokio::time::timeout(Duration::from_secs(1), endpoint.wait_idle()).await;
    stats.admitted = gate.admitted.load(Ordering::Relaxed);
    stats.refused = gate.refused.load(Ordering::Relaxed);
    stats
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::credentials::hash_token;

    #[test]
    fn admission_retries_unvalidated_attempts_over_half_and_refuses_when_full() {
        // Under half: everyone gets a handshake.
        assert_eq!(admission(true, false, true, 0, 8), Admission::Handshake);
        assert_eq!(admission(true, false, true, 3, 8), Admission::Handshake);
        // From half on: unvalidated attempts must come back with a Retry token.
        assert_eq!(admission(true, false, true, 4, 8), Admission::Retry);
        assert_eq!(admission(true, true, false, 4, 8), Admission::Handshake);
        assert_eq!(admission(true, true, false, 7, 8), Admission::Handshake);
        // Full: refused without a handshake, validated or not.
        assert_eq!(admission(true, true, false, 8, 8), Admission::Refuse);
        assert_eq!(admission(true, false, true, 8, 8), Admission::Refuse);
        // A rate-limited source is refused whatever the load.
        assert_eq!(admission(false, true, false, 0, 8), Admission::RateLimited);
    }

    #[test]
    fn robot_table_authenticates_by_token_hash() {
        let table = RobotTable::new(&[
            RobotCredential {
                name: "a".into(),
                token_hash: hash_token("ta"),
            },
            RobotCredential {
                name: "b".into(),
                token_hash: hash_token("tb"),
            },
        ]);
        assert_eq!(table.authenticate("tb"), Some(RobotId(1)));
        assert_eq!(table.name(RobotId(1)), "b");
        assert_eq!(table.authenticate("tc"), None);
        assert_eq!(table.authenticate(""), None);
        assert_eq!(table.len(), 2);
    }
}
