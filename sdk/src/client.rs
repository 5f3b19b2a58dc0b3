//! The async robot client: one QUIC connection to a Kairos server, shared by the tasks of one
//! robot, that survives connection loss.
//!
//! ```no_run
//! # async fn demo(observation: kairos_sdk::protocol::Observation) -> Result<(), kairos_sdk::client::ClientError> {
//! use kairos_sdk::client::{Client, ClientConfig, NoRefetch, RoundRequest};
//! let pin = "sha256:0000000000000000000000000000000000000000000000000000000000000000".parse().unwrap();
//! let client = Client::connect(ClientConfig::pinned("127.0.0.1:4433".parse().unwrap(), pin, "token")).await?;
//! let mut task = client.task(42);
//! let round = task.submit(RoundRequest::new(observation), &mut NoRefetch).await?;
//! println!("{} actions", round.reply.horizon);
//! # Ok(()) }
//! ```
//!
//! Resume: a round whose connection fails is sent again, with the same round id, on a new
//! connection (bounded exponential backoff). The server attaches the resent `Submit` to the round
//! it already has, or replays its reply, so a round never runs twice. Round ids are consumed when
//! a round is first sent, so the next round always gets a fresh, larger id.

use std::future::Future;
use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use quinn::{ConnectionError, ReadError, RecvStream, VarInt, WriteError};
use tokio::sync::Mutex;
use tokio::time::Instant;

use crate::protocol::{
    self, ChunkingSelection, EndTask, ErrorCode, ErrorReply, FetchObservation, FreshObservation,
    Hello, HorizonSelection, LastExecInfo, Limits, Message, Observation, ReadFrameError,
    RemainingHint, Reply, Submit, TaskEnded, TaskOutcome, Validate, ValidationError, Welcome,
    WriteFrameError,
};
use crate::tls::{Fingerprint, PinMismatchSlot, ServerTrust, TlsConfigError};
use crate::transport::TransportTuning;

/// The client's clock: a monotonic clock (tokio's, so tests can pause it) counted in µs from an
/// arbitrary origin. The server never compares it with its own clock directly; it maps client
/// timestamps through each message's `sent_at_us`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Clock {
    origin: Instant,
}

impl Clock {
    /// A clock whose origin is now.
    pub fn start() -> Clock {
        Clock {
            origin: Instant::now(),
        }
    }

    /// Microseconds since the origin.
    pub fn now_us(&self) -> u64 {
        self.to_us(Instant::now())
    }

    /// An instant in µs since the origin (0 for instants before it).
    pub fn to_us(&self, instant: Instant) -> u64 {
        u64::try_from(instant.saturating_duration_since(self.origin).as_micros())
            .unwrap_or(u64::MAX)
    }
}

/// Application close codes (QUIC `CONNECTION_CLOSE` of type application) used by Kairos.
pub mod close_code {
    /// The client or server is done with the connection.
    pub const NORMAL: u32 = 0;
    /// The peer broke the protocol (e.g. a frame that is not `Hello` first).
    pub const PROTOCOL_ERROR: u32 = 1;
    /// The `Hello` token was refused.
    pub const UNAUTHORIZED: u32 = 2;
    /// The server is shutting down; reconnect later.
    pub const SHUTTING_DOWN: u32 = 3;
    /// The server is at its connection limit; reconnect later.
    pub const AT_CAPACITY: u32 = 4;
}

/// Stream error code a client uses to stop a round stream it abandons (`STOP_SENDING`), so the
/// server can drop the queued round.
pub const ROUND_CANCELLED: u32 = 0x10;

/// Stream error code a server may stop a client's send side with after answering a request with
/// an error, so a client still uploading (e.g. an oversized frame) stops.
pub const STREAM_REFUSED: u32 = 0x11;

/// Whether a connection that ended this way is worth reconnecting (and resending) for: not when
/// this side closed it, nor when the server closed it for a protocol violation or a bad token.
fn reconnect_helps(error: &ConnectionError) -> bool {
    match error {
        ConnectionError::LocallyClosed | ConnectionError::VersionMismatch => false,
        ConnectionError::ApplicationClosed(close) => !matches!(
            u32::try_from(close.error_code.into_inner()),
            Ok(close_code::PROTOCOL_ERROR | close_code::UNAUTHORIZED)
        ),
        _ => true,
    }
}

/// How the client retries after losing its connection.
#[derive(Clone, Debug, PartialEq)]
pub struct ReconnectPolicy {
    /// Wait before the first reconnect attempt.
    pub initial_backoff: Duration,
    /// Longest wait between attempts (the wait doubles up to this).
    pub max_backoff: Duration,
    /// Connection attempts per lost connection before giving up.
    pub max_attempts: u32,
}

impl Default for ReconnectPolicy {
    fn default() -> ReconnectPolicy {
        ReconnectPolicy {
            initial_backoff: Duration::from_millis(50),
            max_backoff: Duration::from_secs(2),
            max_attempts: 8,
        }
    }
}

impl ReconnectPolicy {
    /// The wait before reconnect attempt `attempt` (1-based).
    pub fn backoff(&self, attempt: u32) -> Duration {
        let doubled = self
            .initial_backoff
            .saturating_mul(1u32 << attempt.saturating_sub(1).min(20));
        doubled.min(self.max_backoff)
    }
}

/// Everything [`Client::connect`] needs.
#[derive(Clone, Debug)]
pub struct ClientConfig {
    /// The server's UDP address.
    pub server: SocketAddr,
    /// TLS server name (SNI). With a pinned certificate any name works; with CA verification it
    /// must match the certificate.
    pub server_name: String,
    /// How to trust the server's certificate.
    pub trust: ServerTrust,
    /// The robot's auth token.
    pub token: String,
    /// Client software name sent in `Hello`.
    pub client_name: String,
    /// Local address to bind; `None` picks an ephemeral port of the server's address family.
    pub bind: Option<SocketAddr>,
    /// QUIC tuning (the default is the shared tuned config).
    pub transport: TransportTuning,
    /// Limit on the QUIC handshake plus the `Hello`/`Welcome` exchange.
    pub connect_timeout: Duration,
    /// Retries after a lost connection.
    pub reconnect: ReconnectPolicy,
    /// Limit on one round, from first send to reply; `None` waits as long as the server queues.
    pub round_timeout: Option<Duration>,
    /// Try 0-RTT when reconnecting to a server seen before.
    pub zero_rtt: bool,
    /// Limits on what the client accepts from the server.
    pub receive_limits: Limits,
}

impl ClientConfig {
    /// A config for a server whose self-signed certificate has fingerprint `pin`.
    pub fn pinned(server: SocketAddr, pin: Fingerprint, token: impl Into<String>) -> ClientConfig {
        ClientConfig::new(server, ServerTrust::Pinned(pin), token)
    }

    /// A config with the given trust and defaults for everything else.
    pub fn new(server: SocketAddr, trust: ServerTrust, token: impl Into<String>) -> ClientConfig {
        ClientConfig {
            server,
            server_name: "kairos".to_owned(),
            trust,
            token: token.into(),
            client_name: concat!("kairos-sdk/", env!("CARGO_PKG_VERSION")).to_owned(),
            bind: None,
            transport: TransportTuning::default(),
            connect_timeout: Duration::from_secs(5),
            reconnect: ReconnectPolicy::default(),
            round_timeout: None,
            zero_rtt: true,
            receive_limits: Limits::default(),
        }
    }
}

/// What went wrong talking to the server.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The TLS configuration could not be built.
    #[error(transparent)]
    Tls(#[from] TlsConfigError),
    /// The local socket could not be bound.
    #[error("cannot bind the client socket: {0}")]
    Bind(#[source] std::io::Error),
    /// The connection could not be started (bad server name, unusable address).
    #[error("cannot connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    /// The server's certificate is not the pinned one.
    #[error("the server's certificate is {actual}, not the pinned {expected}")]
    PinMismatch {
        /// The pin.
        expected: Fingerprint,
        /// What the server presented.
        actual: Fingerprint,
    },
    /// The server refused the token.
    #[error("unauthorized: {0}")]
    Unauthorized(String),
    /// The server does not speak this client's protocol version.
    #[error("protocol version mismatch: client speaks {client}, server: {server}")]
    VersionMismatch {
        /// Our version.
        client: u32,
        /// What the server said.
        server: String,
    },
    /// The connection failed (and reconnecting, where it applies, did not help).
    #[error("connection: {0}")]
    Connection(#[from] ConnectionError),
    /// Connecting or a round took longer than its limit.
    #[error("{what} timed out after {after:?}")]
    Timeout {
        /// What was waited for.
        what: &'static str,
        /// The limit.
        after: Duration,
    },
    /// The server answered with an error.
    #[error("server error {}: {}", .0.code, .0.message)]
    Server(ErrorReply),
    /// A request breaks the server's limits; it was not sent.
    #[error("request not sent: {0}")]
    Invalid(#[from] ValidationError),
    /// A request could not be encoded within the server's frame limit; it was not sent.
    #[error("request not sent: {0}")]
    Encode(#[from] protocol::EncodeError),
    /// The server broke the protocol.
    #[error("protocol violation by the server: {0}")]
    Protocol(String),
    /// The server reset the round's stream.
    #[error("the server reset the stream with code {0}")]
    StreamReset(u64),
    /// The client was closed.
    #[error("the client is closed")]
    Closed,
    /// The blocking client's runtime could not be started.
    #[error("cannot start the client runtime: {0}")]
    Runtime(#[source] std::io::Error),
}

impl ClientError {
    /// Whether trying again later may succeed: lost connections, timeouts, and server errors the
    /// server marked retryable.
    pub fn is_retryable(&self) -> bool {
        match self {
            ClientError::Connection(error) => reconnect_helps(error),
            ClientError::Timeout { .. } => true,
            ClientError::Server(reply) => reply.retryable,
            _ => false,
        }
    }
}

/// Counters of what the client has done, for tests and monitoring.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ClientStats {
    /// Connections established (Welcome received).
    pub connects: u64,
    /// Of those, connections whose 0-RTT data the server accepted.
    pub zero_rtt_accepted: u64,
    /// Rounds sent again after a lost connection.
    pub resent_rounds: u64,
    /// Fresh observations sent in answer to `FetchObservation`.
    pub refetches: u64,
}

#[derive(Default)]
struct Counters {
    connects: AtomicU64,
    zero_rtt_accepted: AtomicU64,
    resent_rounds: AtomicU64,
    refetches: AtomicU64,
}

/// One established connection.
#[derive(Clone)]
struct Session {
    connection: quinn::Connection,
    welcome: Arc<Welcome>,
}

struct Inner {
    config: ClientConfig,
    endpoint: quinn::Endpoint,
    quinn_config: quinn::ClientConfig,
    mismatch: Option<Arc<PinMismatchSlot>>,
    session: Mutex<Option<Session>>,
    closed: AtomicBool,
    clock: Clock,
    counters: Counters,
}

impl Drop for Inner {
    fn drop(&mut self) {
        if let Some(session) = self.session.get_mut() {
            session
                .connection
                .close(VarInt::from_u32(close_code::NORMAL), b"client dropped");
        }
    }
}

/// A connection to a Kairos server. Cheap to clone; the connection closes when the last clone is
/// dropped.
#[derive(Clone)]
pub struct Client {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("server", &self.inner.config.server)
            .finish_non_exhaustive()
    }
}

/// A source of fresh observations, asked when the server re-fetches a stale one (Algorithm 1,
/// `fetch_obs`) on the round's own stream.
pub trait ObservationSource: Send {
    /// A fresh observation for `fetch`, or `None` to send the round's current one again.
    fn fresh_observation(
        &mut self,
        fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send;
}

/// Never has a fresher observation: a re-fetch is answered with the one already submitted.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoRefetch;

impl ObservationSource for NoRefetch {
    fn fresh_observation(
        &mut self,
        _fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send {
        std::future::ready(None)
    }
}

impl<F> ObservationSource for F
where
    F: FnMut(&FetchObservation) -> Option<Observation> + Send,
{
    fn fresh_observation(
        &mut self,
        fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send {
        std::future::ready(self(fetch))
    }
}

/// The parts of a `Submit` the caller chooses; the task fills in ids and timestamps.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundRequest {
    /// The observation.
    pub observation: Observation,
    /// The execution phase running now; `None` on a task's first round.
    pub last_exec: Option<LastExecInfo>,
    /// Horizon policy; `None` = the server's default.
    pub horizon: Option<HorizonSelection>,
    /// Remaining-work hint.
    pub remaining: Option<RemainingHint>,
    /// The robot's control rate, Hz, if known: lets the server account the execution of the
    /// chunk it answers on a task's first round, before any `last_exec` reports the rate.
    pub control_hz: Option<f32>,
    /// Seed of the sampler noise; `None` = the server derives it from task and round.
    pub seed: Option<u64>,
    /// The chunking strategy; `None` = the server's default (docs/PROTOCOL.md §12).
    pub chunking: Option<ChunkingSelection>,
}

impl RoundRequest {
    /// A request carrying only an observation.
    pub fn new(observation: Observation) -> RoundRequest {
        RoundRequest {
            observation,
            last_exec: None,
            horizon: None,
            remaining: None,
            control_hz: None,
            seed: None,
            chunking: None,
        }
    }
}

/// A completed round.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundReply {
    /// The server's reply.
    pub reply: Reply,
    /// Client clock, µs, when the round was first sent.
    pub sent_at_us: u64,
    /// Client clock, µs, when the reply arrived.
    pub received_at_us: u64,
    /// Times the round was sent (1 unless a connection was lost).
    pub attempts: u32,
    /// Fresh observations sent for this round.
    pub refetches: u32,
    /// The observation the server generated from (the last one sent).
    pub observation_captured_at_us: u64,
}

/// How one attempt at a round ended without a reply.
enum AttemptError {
    /// The connection is gone; resend on a new one.
    ConnectionLost(ConnectionError),
    /// Anything else: give up.
    Fatal(ClientError),
}

impl From<ClientError> for AttemptError {
    fn from(error: ClientError) -> AttemptError {
        AttemptError::Fatal(error)
    }
}

fn from_write(error: WriteFrameError) -> AttemptError {
    match error {
        WriteFrameError::Encode(error) => AttemptError::Fatal(error.into()),
        WriteFrameError::Write(WriteError::ConnectionLost(error)) => {
            AttemptError::ConnectionLost(error)
        }
        WriteFrameError::Write(error) => {
            AttemptError::Fatal(ClientError::Protocol(format!("writing a request: {error}")))
        }
    }
}

fn from_read(error: ReadFrameError) -> AttemptError {
    match error {
        ReadFrameError::Read(ReadError::ConnectionLost(error)) => {
            AttemptError::ConnectionLost(error)
        }
        ReadFrameError::Read(ReadError::Reset(code)) => {
            AttemptError::Fatal(ClientError::StreamReset(code.into_inner()))
        }
        ReadFrameError::Read(error) => {
            AttemptError::Fatal(ClientError::Protocol(format!("reading a reply: {error}")))
        }
        error @ (ReadFrameError::Frame(_) | ReadFrameError::TooSlow { .. }) => {
            AttemptError::Fatal(ClientError::Protocol(error.to_string()))
        }
    }
}

/// Stops the receive side with [`ROUND_CANCELLED`] if the round is abandoned before its reply.
struct CancelOnDrop<'a> {
    recv: &'a mut RecvStream,
    done: bool,
}

impl Drop for CancelOnDrop<'_> {
    fn drop(&mut self) {
        if !self.done {
            // Already stopped or finished: nothing left to cancel.
            let _ = self.recv.stop(VarInt::from_u32(ROUND_CANCELLED));
        }
    }
}

impl Client {
    /// Connects, authenticates (`Hello`/`Welcome`) and returns the client. Fails fast: the first
    /// connection is not retried, so a wrong pin, token or address is reported at once.
    pub async fn connect(config: ClientConfig) -> Result<Client, ClientError> {
        let tls = crate::tls::client_tls(&config.trust)?;
        let quinn_config = crate::transport::client_config_with(tls.config, &config.transport)?;
        let bind = config.bind.unwrap_or(match config.server {
            SocketAddr::V4(_) => SocketAddr::from(([0, 0, 0, 0], 0)),
            SocketAddr::V6(_) => SocketAddr::from(([0u16; 8], 0)),
        });
        let endpoint = quinn::Endpoint::client(bind).map_err(ClientError::Bind)?;
        let client = Client {
            inner: Arc::new(Inner {
                config,
                endpoint,
                quinn_config,
                mismatch: tls.mismatch,
                session: Mutex::new(None),
                closed: AtomicBool::new(false),
                clock: Clock::start(),
                counters: Counters::default(),
            }),
        };
        let session = client.establish().await?;
        *client.inner.session.lock().await = Some(session);
        Ok(client)
    }

    /// Microseconds on this client's clock. Every timestamp sent to the server, observation
    /// capture times included, must be on it.
    pub fn now_us(&self) -> u64 {
        self.inner.clock.now_us()
    }

    /// This client's clock.
    pub fn clock(&self) -> Clock {
        self.inner.clock
    }

    /// The `Welcome` of the current connection (model shapes, limits), if connected.
    pub async fn welcome(&self) -> Option<Arc<Welcome>> {
        self.inner
            .session
            .lock()
            .await
            .as_ref()
            .map(|session| session.welcome.clone())
    }

    /// What the client has done so far.
    pub fn stats(&self) -> ClientStats {
        let c = &self.inner.counters;
        ClientStats {
            connects: c.connects.load(Ordering::Relaxed),
            zero_rtt_accepted: c.zero_rtt_accepted.load(Ordering::Relaxed),
            resent_rounds: c.resent_rounds.load(Ordering::Relaxed),
            refetches: c.refetches.load(Ordering::Relaxed),
        }
    }

    /// The local address the client sends from.
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.inner.endpoint.local_addr()
    }

    /// Moves the connection to a new local socket (Wi-Fi roaming, a new interface). QUIC
    /// connection migration keeps the connection and its rounds in flight.
    pub fn rebind(&self, socket: UdpSocket) -> std::io::Result<()> {
        self.inner.endpoint.rebind(socket)
    }

    /// Closes the connection (rounds in flight fail with [`ClientError::Closed`]) and waits
    /// briefly for the close to reach the server.
    pub async fn close(&self) {
        self.inner.closed.store(true, Ordering::Relaxed);
        if let Some(session) = self.inner.session.lock().await.take() {
            session
                .connection
                .close(VarInt::from_u32(close_code::NORMAL), b"client closed");
        }
        let _ = tokio::time::timeout(Duration::from_secs(1), self.inner.endpoint.wait_idle()).await;
    }

    /// A handle for task `task`, starting at round 0.
    pub fn task(&self, task: u64) -> Task {
        self.task_from(task, 0)
    }

    /// A handle for task `task` whose next round id is `next_round` (to continue a task after
    /// the process restarted; round ids must keep increasing).
    pub fn task_from(&self, task: u64, next_round: u64) -> Task {
        Task {
            client: self.clone(),
            task,
            next_round,
        }
    }

    /// Forcibly closes the current connection as if the network dropped it: the next round
    /// reconnects and resumes. For tests of resume paths and for operators.
    pub async fn drop_connection(&self) {
        if let Some(session) = self.inner.session.lock().await.as_ref() {
            session
                .connection
                .close(VarInt::from_u32(close_code::NORMAL), b"dropped by client");
        }
    }

    /// The live session, reconnecting (with backoff) if the last one is gone.
    async fn session(&self) -> Result<Session, ClientError> {
        let mut slot = self.inner.session.lock().await;
        if let Some(session) = slot.as_ref()
            && session.connection.close_reason().is_none()
        {
            return Ok(session.clone());
        }
        *slot = None;
        if self.inner.closed.load(Ordering::Relaxed) {
            return Err(ClientError::Closed);
        }
        let policy = self.inner.config.reconnect.clone();
        let mut attempt = 0;
        loop {
            attempt += 1;
            tokio::time::sleep(policy.backoff(attempt)).await;
            match self.establish().await {
                Ok(session) => {
                    *slot = Some(session.clone());
                    return Ok(session);
                }
                Err(error) if error.is_retryable() && attempt < policy.max_attempts => {
                    tracing::debug!(attempt, %error, "reconnect failed, retrying");
                }
                Err(error) => return Err(error),
            }
        }
    }

    /// Forgets `failed` if it is still the current session.
    async fn invalidate(&self, failed: &Session) {
        let mut slot = self.inner.session.lock().await;
        if let Some(current) = slot.as_ref()
            && current.connection.stable_id() == failed.connection.stable_id()
        {
            *slot = None;
        }
    }

    /// One connection attempt: QUIC handshake (0-RTT when possible) and `Hello`/`Welcome`.
    async fn establish(&self) -> Result<Session, ClientError> {
        let inner = &self.inner;
        let timeout = inner.config.connect_timeout;
        let result = tokio::time::timeout(timeout, self.establish_inner()).await;
        let result = match result {
            Ok(result) => result,
            Err(_) => Err(ClientError::Timeout {
                what: "connecting",
                after: timeout,
            }),
        };
        // A server that refuses the token may close the connection before its error frame is
        // read; the close code says the same thing.
        if let Err(ClientError::Connection(ConnectionError::ApplicationClosed(close))) = &result
            && close.error_code.into_inner() == u64::from(close_code::UNAUTHORIZED)
        {
            return Err(ClientError::Unauthorized(
                String::from_utf8_lossy(&close.reason).into_owned(),
            ));
        }
        // A failed handshake reports a TLS alert; the verifier knows whether it was the pin.
        if result.is_err()
            && let (Some(slot), ServerTrust::Pinned(expected)) =
                (&inner.mismatch, &inner.config.trust)
            && let Some(actual) = slot.take()
        {
            return Err(ClientError::PinMismatch {
                expected: *expected,
                actual,
            });
        }
        result
    }

    async fn establish_inner(&self) -> Result<Session, ClientError> {
        let inner = &self.inner;
        let connecting = inner.endpoint.connect_with(
            inner.quinn_config.clone(),
            inner.config.server,
            &inner.config.server_name,
        )?;
        let (connection, zero_rtt) = if inner.config.zero_rtt {
            match connecting.into_0rtt() {
                Ok((connection, accepted)) => (connection, Some(accepted)),
                Err(connecting) => (connecting.await?, None),
            }
        } else {
            (connecting.await?, None)
        };
        let welcome = match self.hello(&connection).await {
            Err(HelloError::ZeroRttRejected) => {
                // The server refused the early data; the handshake completed as a full one, and
                // the Hello goes again in 1-RTT.
                match self.hello(&connection).await {
                    Ok(welcome) => welcome,
                    Err(error) => return Err(error.into_client_error()),
                }
            }
            Err(error) => return Err(error.into_client_error()),
            Ok(welcome) => {
                if let Some(accepted) = zero_rtt
                    && accepted.await
                {
                    inner
                        .counters
                        .zero_rtt_accepted
                        .fetch_add(1, Ordering::Relaxed);
                }
                welcome
            }
        };
        inner.counters.connects.fetch_add(1, Ordering::Relaxed);
        Ok(Session {
            connection,
            welcome: Arc::new(welcome),
        })
    }

    async fn hello(&self, connection: &quinn::Connection) -> Result<Welcome, HelloError> {
        let inner = &self.inner;
        let (mut send, mut recv) = connection.open_bi().await?;
        let hello = Message::Hello(Hello {
            protocol: protocol::PROTOCOL_VERSION,
            token: inner.config.token.clone(),
            client: inner.config.client_name.clone(),
        });
        match protocol::write_message(&mut send, &hello, Limits::default().max_frame).await {
            Ok(()) => {}
            Err(WriteFrameError::Write(WriteError::ZeroRttRejected)) => {
                return Err(HelloError::ZeroRttRejected);
            }
            Err(WriteFrameError::Write(WriteError::ConnectionLost(error))) => {
                return Err(error.into());
            }
            Err(error) => return Err(HelloError::Client(ClientError::Protocol(error.to_string()))),
        }
        // Finishing an already-reset stream fails; the read below reports why.
        let _ = send.finish();
        let message = match protocol::read_message(&mut recv, &inner.config.receive_limits).await {
            Ok(message) => message,
            Err(ReadFrameError::Read(ReadError::ZeroRttRejected)) => {
                return Err(HelloError::ZeroRttRejected);
            }
            Err(ReadFrameError::Read(ReadError::ConnectionLost(error))) => {
                return Err(error.into());
            }
            Err(error) => return Err(HelloError::Client(ClientError::Protocol(error.to_string()))),
        };
        match message {
            Some(Message::Welcome(welcome)) => {
                if welcome.protocol != protocol::PROTOCOL_VERSION {
                    return Err(HelloError::Client(ClientError::VersionMismatch {
                        client: protocol::PROTOCOL_VERSION,
                        server: format!("answered with version {}", welcome.protocol),
                    }));
                }
                welcome
                    .validate(&inner.config.receive_limits)
                    .map_err(|error| ClientError::Protocol(format!("Welcome: {error}")))?;
                Ok(welcome)
            }
            Some(Message::Error(error)) => Err(HelloError::Client(match error.code {
                ErrorCode::Unauthorized => ClientError::Unauthorized(error.message),
                ErrorCode::UnsupportedVersion => ClientError::VersionMismatch {
                    client: protocol::PROTOCOL_VERSION,
                    server: error.message,
                },
                _ => ClientError::Server(error),
            })),
            Some(other) => Err(HelloError::Client(ClientError::Protocol(format!(
                "expected Welcome, got {}",
                other.kind()
            )))),
            None => Err(HelloError::Client(ClientError::Protocol(
                "the server finished the Hello stream without a Welcome".to_owned(),
            ))),
        }
    }

    /// One attempt at a round on `session`.
    async fn attempt_round(
        &self,
        session: &Session,
        submit: &mut Submit,
        source: &mut impl ObservationSource,
        refetches: &mut u32,
    ) -> Result<Reply, AttemptError> {
        let limits = &session.welcome.limits;
        let (mut send, mut recv) = session
            .connection
            .open_bi()
            .await
            .map_err(AttemptError::ConnectionLost)?;
        let mut guard = CancelOnDrop {
            recv: &mut recv,
            done: false,
        };
        submit.sent_at_us = self.now_us();
        protocol::write_body(&mut send, &*submit, limits.max_frame)
            .await
            .map_err(from_write)?;
        loop {
            let message = protocol::read_message(guard.recv, &self.inner.config.receive_limits)
                .await
                .map_err(from_read)?;
            match message {
                Some(Message::Reply(reply)) => {
                    guard.done = true;
                    let _ = send.finish();
                    if reply.task != submit.task || reply.round != submit.round {
                        return Err(ClientError::Protocol(format!(
                            "reply for task {} round {} on the stream of task {} round {}",
                            reply.task, reply.round, submit.task, submit.round
                        ))
                        .into());
                    }
                    reply
                        .validate(&self.inner.config.receive_limits)
                        .map_err(|error| ClientError::Protocol(format!("Reply: {error}")))?;
                    return Ok(reply);
                }
                Some(Message::FetchObservation(fetch)) => {
                    if fetch.task != submit.task || fetch.round != submit.round {
                        return Err(ClientError::Protocol(format!(
                            "FetchObservation for task {} round {} on the stream of task {} round {}",
                            fetch.task, fetch.round, submit.task, submit.round
                        ))
                        .into());
                    }
                    if let Some(observation) = source.fresh_observation(&fetch).await {
                        observation.validate(limits).map_err(ClientError::from)?;
                        submit.observation = observation;
                    }
                    let fresh = FreshObservation {
                        sent_at_us: self.now_us(),
                        observation: submit.observation.clone(),
                    };
                    protocol::write_body(&mut send, &fresh, limits.max_frame)
                        .await
                        .map_err(from_write)?;
                    *refetches += 1;
                    self.inner
                        .counters
                        .refetches
                        .fetch_add(1, Ordering::Relaxed);
                }
                Some(Message::Error(error)) => {
                    guard.done = true;
                    return Err(ClientError::Server(error).into());
                }
                Some(other) => {
                    return Err(ClientError::Protocol(format!(
                        "unexpected {} on a round stream",
                        other.kind()
                    ))
                    .into());
                }
                None => {
                    return Err(ClientError::Protocol(
                        "the server finished the round stream without a reply".to_owned(),
                    )
                    .into());
                }
            }
        }
    }

    /// Sends `message` on a new stream and reads one answer, resending on a new connection if
    /// the connection is lost. Used for `EndTask`.
    async fn request(&self, message: &Message) -> Result<Message, ClientError> {
        let mut lost = 0;
        loop {
            let session = self.session().await?;
            let result: Result<Message, AttemptError> = async {
                let (mut send, mut recv) = session
                    .connection
                    .open_bi()
                    .await
                    .map_err(AttemptError::ConnectionLost)?;
                protocol::write_message(&mut send, message, session.welcome.limits.max_frame)
                    .await
                    .map_err(from_write)?;
                let _ = send.finish();
                protocol::read_message(&mut recv, &self.inner.config.receive_limits)
                    .await
                    .map_err(from_read)?
                    .ok_or_else(|| {
                        AttemptError::Fatal(ClientError::Protocol(format!(
                            "no answer to {}",
                            message.kind()
                        )))
                    })
            }
            .await;
            match result {
                Ok(answer) => return Ok(answer),
                Err(AttemptError::Fatal(error)) => return Err(error),
                Err(AttemptError::ConnectionLost(error)) => {
                    self.invalidate(&session).await;
                    if !reconnect_helps(&error) && !matches!(error, ConnectionError::LocallyClosed)
                    {
                        return Err(error.into());
                    }
                    lost += 1;
                    if lost > self.inner.config.reconnect.max_attempts {
                        return Err(error.into());
                    }
                }
            }
        }
    }
}

enum HelloError {
    ZeroRttRejected,
    Client(ClientError),
}

impl HelloError {
    fn into_client_error(self) -> ClientError {
        match self {
            HelloError::ZeroRttRejected => {
                ClientError::Protocol("0-RTT rejected twice on one connection".to_owned())
            }
            HelloError::Client(error) => error,
        }
    }
}

impl From<ConnectionError> for HelloError {
    fn from(error: ConnectionError) -> HelloError {
        HelloError::Client(error.into())
    }
}

impl From<ClientError> for HelloError {
    fn from(error: ClientError) -> HelloError {
        HelloError::Client(error)
    }
}

/// One task: a sequence of rounds with strictly increasing round ids. Holding `&mut Task` while
/// a round runs keeps one round in flight per task.
#[derive(Debug)]
pub struct Task {
    client: Client,
    task: u64,
    next_round: u64,
}

impl Task {
    /// The task id.
    pub fn id(&self) -> u64 {
        self.task
    }

    /// The id the next round will get.
    pub fn next_round(&self) -> u64 {
        self.next_round
    }

    /// The client this task talks through.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// Runs one round: sends `request` as the next round, answers the server's re-fetches from
    /// `source`, and returns the reply. A lost connection is resumed transparently (same round
    /// id); any other failure consumes the round id, and the next call uses a new one.
    pub async fn submit(
        &mut self,
        request: RoundRequest,
        source: &mut impl ObservationSource,
    ) -> Result<RoundReply, ClientError> {
        let round = self.next_round;
        self.next_round += 1;
        let client = self.client.clone();
        let mut submit = Submit {
            task: self.task,
            round,
            sent_at_us: client.now_us(),
            observation: request.observation,
            last_exec: request.last_exec,
            horizon: request.horizon,
            remaining: request.remaining,
            attempt: 0,
            control_hz: request.control_hz,
            seed: request.seed,
            chunking: request.chunking,
        };
        let sent_at_us = submit.sent_at_us;
        let mut refetches = 0;
        let run = async {
            loop {
                let session = client.session().await?;
                submit
                    .validate(&session.welcome.limits)
                    .map_err(ClientError::from)?;
                match client
                    .attempt_round(&session, &mut submit, source, &mut refetches)
                    .await
                {
                    Ok(reply) => return Ok(reply),
                    Err(AttemptError::Fatal(error)) => return Err(error),
                    Err(AttemptError::ConnectionLost(error)) => {
                        client.invalidate(&session).await;
                        if client.inner.closed.load(Ordering::Relaxed) {
                            return Err(ClientError::Closed);
                        }
                        // `drop_connection` closes locally on purpose; any other local close
                        // is the client going away.
                        if !reconnect_helps(&error)
                            && !matches!(error, ConnectionError::LocallyClosed)
                        {
                            return Err(ClientError::Connection(error));
                        }
                        submit.attempt += 1;
                        if submit.attempt > client.inner.config.reconnect.max_attempts {
                            return Err(ClientError::Connection(error));
                        }
                        client
                            .inner
                            .counters
                            .resent_rounds
                            .fetch_add(1, Ordering::Relaxed);
                        tracing::debug!(task = submit.task, round, %error, "connection lost mid-round, resending");
                    }
                }
            }
        };
        let reply = match client.inner.config.round_timeout {
            Some(limit) => {
                tokio::time::timeout(limit, run)
                    .await
                    .map_err(|_| ClientError::Timeout {
                        what: "round",
                        after: limit,
                    })??
            }
            None => run.await?,
        };
        Ok(RoundReply {
            reply,
            sent_at_us,
            received_at_us: client.now_us(),
            attempts: submit.attempt + 1,
            refetches,
            observation_captured_at_us: submit.observation.captured_at_us,
        })
    }

    /// Ends the task and returns the server's record of it.
    pub async fn end(
        self,
        outcome: TaskOutcome,
        last_exec: Option<LastExecInfo>,
    ) -> Result<TaskEnded, ClientError> {
        let message = Message::EndTask(EndTask {
            task: self.task,
            outcome,
            sent_at_us: self.client.now_us(),
            last_exec,
        });
        match self.client.request(&message).await? {
            Message::TaskEnded(ended) => Ok(ended),
            Message::Error(error) => Err(ClientError::Server(error)),
            other => Err(ClientError::Protocol(format!(
                "expected TaskEnded, got {}",
                other.kind()
            ))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_up_to_the_cap() {
        let policy = ReconnectPolicy {
            initial_backoff: Duration::from_millis(50),
            max_backoff: Duration::from_millis(300),
            max_attempts: 10,
        };
        let waits: Vec<u128> = (1..=6).map(|a| policy.backoff(a).as_millis()).collect();
        assert_eq!(waits, [50, 100, 200, 300, 300, 300]);
        assert_eq!(policy.backoff(u32::MAX), Duration::from_millis(300));
    }

    #[test]
    fn retryability() {
        assert!(ClientError::Connection(ConnectionError::TimedOut).is_retryable());
        let closed = |code: u32| {
            ClientError::Connection(ConnectionError::ApplicationClosed(
                quinn::ApplicationClose {
                    error_code: VarInt::from_u32(code),
                    reason: bytes::Bytes::from_static(b"why"),
                },
            ))
        };
        assert!(closed(close_code::SHUTTING_DOWN).is_retryable());
        assert!(closed(close_code::AT_CAPACITY).is_retryable());
        assert!(!closed(close_code::UNAUTHORIZED).is_retryable());
        assert!(!closed(close_code::PROTOCOL_ERROR).is_retryable());
        assert!(!ClientError::Connection(ConnectionError::LocallyClosed).is_retryable());
        assert!(!ClientError::Unauthorized("no".into()).is_retryable());
        assert!(ClientError::Server(ErrorReply::new(ErrorCode::Overloaded, "busy")).is_retryable());
        assert!(
            !ClientError::Server(ErrorReply::new(ErrorCode::InvalidRequest, "bad")).is_retryable()
        );
    }
}
