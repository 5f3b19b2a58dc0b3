//! Fleets of robots against a server: what `kairos demo`, `kairos bench live`, `kairos robot`
//! and the cross-crate tests share.
//!
//! - [`LocalServer::start`] starts the real server in this process and reads what a robot needs
//!   from its data directory, the way `kairos robot` does: the certificate pin and the generated
//!   robot's token.
//! - [`connect`] opens one QUIC connection per robot, concurrently.
//! - [`run_from`] runs one task per robot, each from its own start time, and collects what each
//!   robot returned in robot order.
//!
//! What a robot does inside its task (the SDK's runner, a trace replay, a hand-written test robot)
//! is the caller's.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use kairos_sdk::client::{Client, ClientConfig, ClientError};
use kairos_sdk::protocol::ModelInfo;
use kairos_sdk::robot::TaskSummary;
use kairos_sdk::tls::Fingerprint;
use tokio::task::JoinError;
use tokio::time::Instant;

use kairos_server::config::{Config, ConfigError, DEFAULT_ROBOT};
use kairos_server::data_dir::DataDir;
use kairos_server::pool::EnginePool;
use kairos_server::transport::launch::{LaunchError, Policies, RunningServer, ServerReport, start};

/// How long a fleet's robot waits for its connection. Generous: hundreds of robots handshake at
/// once on loopback, on a machine that also runs the server and the model.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(20);

/// Why a fleet could not start.
#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    /// The server did not start.
    #[error("starting the server: {0}")]
    Start(#[from] LaunchError),
    /// The server started but its data directory lacks what a robot needs.
    #[error("reading the server's data directory: {0}")]
    DataDir(#[from] ConfigError),
    /// A robot could not connect.
    #[error("robot {robot}: cannot connect: {source}")]
    Connect {
        /// Which robot (0-based).
        robot: usize,
        /// The client's error.
        source: ClientError,
    },
    /// The fleet has no robot to ask the server for its model.
    #[error("the fleet is empty")]
    Empty,
    /// The first robot holds no `Welcome` (which names the model) from the server.
    #[error("connected but got no Welcome")]
    NoWelcome,
}

/// A server running in this process, and what its robots connect with.
pub struct LocalServer {
    /// The server.
    pub server: RunningServer,
    /// The certificate pin, read from the data directory.
    pub pin: Fingerprint,
    /// The generated robot's token (`default`, read from the data directory), or `None` when
    /// the configuration lists its robots (their tokens are the caller's).
    pub token: Option<String>,
}

impl LocalServer {
    /// Starts the server `config` describes on `pool` and reads the pin and the generated
    /// robot's token from its data directory. A server that started but whose data directory
    /// cannot be read is shut down again.
    pub async fn start(
        config: &Config,
        pool: EnginePool,
        policies: Policies,
    ) -> Result<LocalServer, FleetError> {
        let server = start(config, pool, policies).await?;
        let data_dir = DataDir::new(&config.data_dir);
        let credentials = data_dir.read_pin().and_then(|pin| {
            let token = match server.tokens_file {
                Some(_) => Some(data_dir.token(DEFAULT_ROBOT)?),
                None => None,
            };
            Ok((pin, token))
        });
        match credentials {
            Ok((pin, token)) => Ok(LocalServer { server, pin, token }),
            Err(error) => {
                server.shutdown().await;
                Err(error.into())
            }
        }
    }

    /// Where the server listens.
    pub fn addr(&self) -> SocketAddr {
        self.server.local_addr
    }

    /// A client config pinned to this server, for `token`, connecting to `addr` (the server
    /// itself or a proxy in front of it).
    pub fn client_config(&self, addr: SocketAddr, token: &str) -> ClientConfig {
        let mut config = ClientConfig::pinned(addr, self.pin, token);
        config.connect_timeout = CONNECT_TIMEOUT;
        config
    }

    /// The generated robot's client config, connecting directly; `None` when the
    /// configuration lists its robots.
    pub fn generated_robot(&self) -> Option<ClientConfig> {
        let token = self.token.as_deref()?;
        Some(self.client_config(self.addr(), token))
    }

    /// Shuts the server down gracefully and returns what it did.
    pub async fn shutdown(self) -> ServerReport {
        self.server.shutdown().await
    }
}

/// Connects `robots` robots with `config`, concurrently, one QUIC connection each.
pub async fn connect(config: &ClientConfig, robots: usize) -> Result<Vec<Client>, FleetError> {
    futures::future::try_join_all((0..robots).map(|robot| {
        let config = config.clone();
        async move {
            Client::connect(config)
                .await
                .map_err(|source| FleetError::Connect { robot, source })
        }
    }))
    .await
}

/// The model the fleet's server serves, from the first robot's `Welcome`.
pub async fn served_model(clients: &[Client]) -> Result<ModelInfo, FleetError> {
    let first = clients.first().ok_or(FleetError::Empty)?;
    let welcome = first.welcome().await.ok_or(FleetError::NoWelcome)?;
    Ok(welcome.model.clone())
}

/// Runs robot `index`'s task, `robot(index)`, from `t0 + starts[index]`, every robot
/// concurrently on the tokio runtime, and returns what each returned, in robot order; `Err`
/// for a robot whose task panicked.
pub async fn run_from<T, Fut>(
    t0: Instant,
    starts: &[Duration],
    mut robot: impl FnMut(usize) -> Fut,
) -> Vec<Result<T, JoinError>>
where
    T: Send + 'static,
    Fut: Future<Output = T> + Send + 'static,
{
    let mut running = tokio::task::JoinSet::new();
    let mut index_of = HashMap::with_capacity(starts.len());
    for (index, &start) in starts.iter().enumerate() {
        let task = robot(index);
        let handle = running.spawn(async move {
            tokio::time::sleep_until(t0 + start).await;
            task.await
        });
        index_of.insert(handle.id(), index);
    }
    let mut outcomes: Vec<Option<Result<T, JoinError>>> = starts.iter().map(|_| None).collect();
    while let Some(joined) = running.join_next_with_id().await {
        let (id, outcome) = match joined {
            Ok((id, value)) => (id, Ok(value)),
            Err(error) => (error.id(), Err(error)),
        };
        if let Some(&index) = index_of.get(&id) {
            outcomes[index] = Some(outcome);
        }
    }
    // Every spawned task is joined once, so every slot is filled.
    outcomes.into_iter().flatten().collect()
}

/// What a fleet asked for against what its robots got back, round by round: the soak and
/// fault runs' verdict (`scripts/soak.sh`, docs/RELIABILITY.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RoundAccount {
    /// Rounds the fleet's tasks asked for: tasks × rounds per task.
    pub asked: u64,
    /// Distinct `(task, round)` pairs some task summary shows answered.
    pub answered: u64,
    /// Rounds asked for and never answered: `asked − answered`. A robot whose task failed for
    /// good left no summary, so all its rounds count here.
    pub lost: u64,
    /// Replies beyond the first for the same `(task, round)`: a round answered twice.
    pub duplicated: u64,
    /// Round attempts that failed and were retried (the runner's `failed_rounds`).
    pub retried: u64,
    /// Tasks whose `EndTask` failed (`TaskSummary::end_error`): open on the server until its
    /// idle timeout.
    pub unended: u64,
}

impl RoundAccount {
    /// Counts `summaries` against `tasks` tasks of `rounds_per_task` rounds each.
    pub fn of(summaries: &[TaskSummary], tasks: u64, rounds_per_task: u64) -> RoundAccount {
        let mut seen = std::collections::HashSet::new();
        let mut records = 0u64;
        for summary in summaries {
            for round in &summary.rounds {
                records += 1;
                seen.insert((summary.task, round.round));
            }
        }
        let asked = tasks.saturating_mul(rounds_per_task);
        let answered = seen.len() as u64;
        RoundAccount {
            asked,
            answered,
            lost: asked.saturating_sub(answered),
            duplicated: records - answered,
            retried: summaries.iter().map(|s| u64::from(s.failed_rounds)).sum(),
            unended: summaries.iter().filter(|s| s.end_error.is_some()).count() as u64,
        }
    }
}

impl std::fmt::Display for RoundAccount {
    /// One line, stable for scripts: `rounds: asked A, answered B, lost C, answered twice D,
    /// retried E, tasks not ended F`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "rounds: asked {}, answered {}, lost {}, answered twice {}, retried {}, tasks not ended {}",
            self.asked, self.answered, self.lost, self.duplicated, self.retried, self.unended
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn robots_start_at_their_offsets_and_come_back_in_robot_order() {
        let t0 = Instant::now();
        let starts = [
            Duration::from_millis(30),
            Duration::ZERO,
            Duration::from_millis(10),
        ];
        let outcomes = run_from(t0, &starts, |index| async move {
            let started = Instant::now() - t0;
            // The last-started robot finishes first: order must come from the index, not from
            // completion.
            tokio::time::sleep(Duration::from_millis(100) - started).await;
            (index, started)
        })
        .await;
        let outcomes: Vec<(usize, Duration)> = outcomes.into_iter().map(Result::unwrap).collect();
        assert_eq!(
            outcomes,
            [
                (0, Duration::from_millis(30)),
                (1, Duration::ZERO),
                (2, Duration::from_millis(10))
            ]
        );
    }

    #[test]
    fn round_account_counts_lost_and_twice_answered_rounds() {
        use kairos_sdk::protocol::Timing;
        use kairos_sdk::robot::RoundRecord;
        let record = |round: u64| RoundRecord {
            round,
            sent_at_us: 0,
            received_at_us: 1,
            attempts: 1,
            refetches: 0,
            horizon: 4,
            chunk_len: 8,
            discarded: 0,
            executed: 4,
            policy: "threshold".into(),
            timing: Timing::default(),
        };
        let summary = |task: u64, rounds: Vec<RoundRecord>| TaskSummary {
            task,
            rounds,
            started_at_us: 0,
            finished_at_us: 1,
            actions_executed: 0,
            idle_us: 0,
            failed_rounds: 1,
            server_record: None,
            end_error: None,
        };
        // Three tasks of three rounds asked; task 2 got round 1 twice and never round 2;
        // the third task failed and left no summary.
        let mut unended = summary(1, vec![record(0), record(1), record(2)]);
        unended.end_error = Some("unknown_task".into());
        let account = RoundAccount::of(
            &[unended, summary(2, vec![record(0), record(1), record(1)])],
            3,
            3,
        );
        assert_eq!(
            account,
            RoundAccount {
                asked: 9,
                answered: 5,
                lost: 4,
                duplicated: 1,
                retried: 2,
                unended: 1,
            }
        );
        assert_eq!(
            account.to_string(),
            "rounds: asked 9, answered 5, lost 4, answered twice 1, retried 2, tasks not ended 1"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_panicking_robot_is_an_error_in_its_own_slot() {
        let outcomes = run_from(Instant::now(), &[Duration::ZERO; 3], |index| async move {
            assert_ne!(index, 1, "robot 1 panics");
            index
        })
        .await;
        assert_eq!(outcomes.len(), 3);
        assert_eq!(*outcomes[0].as_ref().unwrap(), 0);
        assert!(outcomes[1].as_ref().unwrap_err().is_panic());
        assert_eq!(*outcomes[2].as_ref().unwrap(), 2);
    }
}
