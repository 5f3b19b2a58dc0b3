//! The QUIC server: admission, authentication and the per-stream protocol.
//!
//! [`run`] takes a bound quinn endpoint and a shutdown future (mini-redis's `run(listener,
//! shutdown)`). Each incoming connection is admitted against a semaphore of
//! `connections.max_connections` permits; over the cap it is accepted only to be closed at once
//! with `close_code::AT_CAPACITY` and a reason the client can show. An admitted connection has
//! `connections.hello_timeout_ms` to open its first stream and send `Hello`; a wrong token gets an
//! `unauthorized` error frame and the connection is closed with `UNAUTHORIZED`. After that every
//! bidirectional stream the robot opens is served by its own task (`Submit` or `EndTask`), so a
//! malformed frame fails only its own stream, with a typed error frame.
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

mod admit;
mod connection;
pub mod launch;
pub mod tls;

use std::collections::HashMap;
use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use kairos_sdk::client::close_code;
use kairos_sdk::protocol::{Limits, ModelInfo};
use quinn::VarInt;
use tokio::sync::{Semaphore, watch};
use tokio::task::JoinSet;

use crate::action::ActionManager;
use crate::config::{ConnectionsConfig, RobotCredential};
use crate::driver::DriverHandle;
use crate::scheduler::RobotId;
use crate::validation::Validator;

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
        self.by_hash.get(&crate::config::hash_token(token)).copied()
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
    /// Builds requests' horizon policies.
    pub actions: Arc<ActionManager>,
    /// The driver.
    pub driver: DriverHandle,
    /// The model as announced in `Welcome`.
    pub model: ModelInfo,
    /// Connection limits.
    pub connections: ConnectionsConfig,
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
    /// Connections admitted.
    pub admitted: u64,
    /// Connections closed at once because the server was at capacity.
    pub refused: u64,
}

/// Serves `endpoint` until `shutdown` resolves, then drains (see the module docs).
pub async fn run(
    endpoint: quinn::Endpoint,
    context: Arc<ServerContext>,
    shutdown: impl Future<Output = ()>,
) -> TransportStats {
    let permits = Arc::new(Semaphore::new(context.connections.max_connections));
    let (stop_tx, stop_rx) = watch::channel(false);
    let mut connections = JoinSet::new();
    let mut stats = TransportStats::default();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        tokio::select! {
            incoming = endpoint.accept() => {
                let Some(incoming) = incoming else { break };
                match permits.clone().try_acquire_owned() {
                    Ok(permit) => {
                        stats.admitted += 1;
                        let context = context.clone();
                        let stop = stop_rx.clone();
                        connections.spawn(async move {
                            connection::serve(incoming, context, stop).await;
                            drop(permit);
                        });
                    }
                    Err(_) => {
                        stats.refused += 1;
                        let limit = context.connections.max_connections;
                        connections.spawn(connection::refuse_at_capacity(incoming, limit));
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
    stats
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::hash_token;

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
