//! An openpi-compatible websocket endpoint: robots that run openpi's `WebsocketClientPolicy`
//! (PyPI `openpi-client`) are served, unmodified, by this server's scheduler and engines.
//!
//! The protocol is openpi's (`openpi/serving/websocket_policy_server.py`,
//! `openpi_client/msgpack_numpy.py`):
//! 1. The client opens a websocket, with `Authorization: Api-Key <key>` when it has a key. Here
//!    the key is a robot token: a missing or unknown key is refused with HTTP 401 during the
//!    upgrade, before any observation is read.
//! 2. The server sends one binary msgpack map, its metadata (model shapes, the key map, the task
//!    id of the connection).
//! 3. Each request is one binary msgpack map, the observation dict, with numpy arrays in
//!    msgpack-numpy form ([`msgpack`]); the reply is one binary msgpack map with `actions`
//!    (`[H, action_dim]` float32, as the model produced them) and openpi's `server_timing`
//!    (`infer_ms`, `prev_total_ms`) and `policy_timing` (`infer_ms`), plus Kairos' own fields.
//! 4. An error is sent as a text message, then the connection is closed (openpi's client raises
//!    on a text reply).
//!
//! **Every connection is a robot task** in the same scheduler and batcher as QUIC robots: the
//! connection gets a task id, each request becomes the next round of that task as a protocol
//! `Submit` built through the configured key map ([`observation`]), and it goes through the same
//! [`ServerContext::admit`] (validator, decode pool, driver) as a QUIC round. openpi clients send
//! no execution information, so the Last Exec Info is inferred from call timing ([`exec`]); they
//! cannot be asked for a fresher observation, so their rounds are never re-fetched. The task
//! ends (`done`) when the websocket closes, and (`failed`) when the server closes it over an
//! error.
//!
//! **Guards**, the QUIC endpoint's, from the same code ([`crate::transport::admission`],
//! [`kairos_sdk::protocol::ReadBounds`]), each refusal counted and logged through
//! [`Refusals`](crate::transport::refusals::Refusals) with `door="openpi"`:
//! - a TCP connection takes one of the endpoint's `max_unauthenticated` handshake places from
//!   its accept until its upgrade is answered, at most `max_unauthenticated_per_source` per
//!   source address; over either it is answered 503 and closed at once, before a byte is read;
//! - the upgrade must be done within `hello_timeout_ms`;
//! - a source over its wrong-token budget (the server's [`WrongTokens`], shared with QUIC) is
//!   answered 429 before its key is looked at; a wrong or missing key is 401 and counts against
//!   that budget; an accepted key takes one of `max_connections` places and one of its robot's
//!   `max_connections_per_robot` places, shared with its QUIC connections (503 when either is
//!   full);
//! - every message must arrive at `min_upload_bytes_per_s` after `upload_grace_ms`, from its
//!   first byte ([`upload`]); all openpi connections of one robot share one budget of
//!   `upload_buffer_frames × max_frame` bytes of partly received messages;
//! - a message over `limits.max_frame` bytes is refused by the websocket layer before it is
//!   buffered whole; msgpack decoding is bounded in depth and value count ([`MAX_VALUES`]); the
//!   key map checks sizes against `[limits]` before it copies, converts or transposes an array
//!   ([`observation`]); image decoding, validation and inference run where they do for QUIC
//!   rounds, never on a runtime worker. A bad frame fails only its own connection.
//!
//! [`WrongTokens`]: crate::transport::admission::WrongTokens

pub mod exec;
pub mod msgpack;
pub mod observation;
pub mod upload;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::{SinkExt, StreamExt};
use kairos_sdk::protocol::{
    EndTask, ErrorCode, ErrorReply, HorizonSelection, ReadBounds, Reply, Submit, TaskOutcome,
};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio::task::JoinSet;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{StatusCode, header};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

use self::exec::ExecEstimate;
use self::msgpack::Writer;
use self::upload::BoundedStream;
use crate::config::OpenpiConfig;
use crate::driver::RefetchAsk;
use crate::transport::admission::{HandshakePlace, HandshakeRefusal, Handshakes};
use crate::transport::fairness::RobotPlace;
use crate::transport::refusals::{Door, Reason};
use crate::transport::{DRAIN_TIMEOUT, Gate, ServerContext};
use crate::validation::RequestError;
use kairos_core::clock_map::ClockMap;
use kairos_core::scheduler::RobotId;
use kairos_core::sync::lock;

/// Most msgpack values one request may hold (an observation dict has tens).
pub const MAX_VALUES: usize = 4096;

/// What the endpoint did, returned when it stops (its refusals are in
/// [`ServerContext::refusals`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OpenpiStats {
    /// Websocket connections accepted (authenticated).
    pub connections: u64,
}

/// Connections the kernel may queue before the endpoint accepts them (the kernel caps it at
/// `net.core.somaxconn`): under a connection flood the accept loop refuses fast, and a longer
/// queue keeps a real client's connection in line instead of dropping its SYN (which would cost
/// it a retransmission, a second or more).
const LISTEN_BACKLOG: u32 = 4096;

/// Binds the endpoint's TCP listener.
pub async fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        tokio::net::TcpSocket::new_v4()?
    } else {
        tokio::net::TcpSocket::new_v6()?
    };
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(LISTEN_BACKLOG)
}

/// The websocket layer's read buffer (tungstenite's default is 128 KiB): an idle connection
/// costs this much.
const READ_BUFFER: usize = 64 << 10;

/// The endpoint's admission state, shared by its accept loop and its connections.
struct Endpoint {
    context: Arc<ServerContext>,
    config: Arc<OpenpiConfig>,
    /// Places for authenticated connections, and the server's wrong-token limiter.
    gate: Gate,
    /// Connections between their accept and an answered upgrade.
    handshakes: Handshakes,
    /// Per robot, the budget of partly received messages all its connections share.
    budgets: Mutex<HashMap<RobotId, Arc<Semaphore>>>,
    /// Each budget's size, bytes.
    budget_bytes: usize,
}

impl Endpoint {
    fn new(context: Arc<ServerContext>, config: Arc<OpenpiConfig>) -> Endpoint {
        let budget_bytes = context
            .connections
            .upload_buffer_bytes(context.limits().max_frame);
        let gate = Gate::new(&context);
        gate.export_places("openpi", &context);
        Endpoint {
            gate,
            handshakes: Handshakes::for_door(&context.connections),
            budgets: Mutex::new(HashMap::new()),
            budget_bytes: usize::try_from(budget_bytes)
                .unwrap_or(Semaphore::MAX_PERMITS)
                .min(Semaphore::MAX_PERMITS),
            context,
            config,
        }
    }

    fn refuse(&self, reason: Reason, remote: SocketAddr, detail: &dyn std::fmt::Display) {
        self.context
            .refusals
            .refuse(Door::Openpi, reason, remote, detail);
    }

    /// How `robot`'s messages are read: the minimum rate, and its budget (one per robot; the
    /// table holds at most one entry per configured robot).
    fn read_bounds(&self, robot: RobotId) -> ReadBounds {
        let budget = lock(&self.budgets)
            .entry(robot)
            .or_insert_with(|| Arc::new(Semaphore::new(self.budget_bytes)))
            .clone();
        ReadBounds {
            min_rate: self.context.connections.min_upload_rate(),
            budget: Some(budget),
        }
    }

    /// The upgrade request's verdict: the robot and its place among the authenticated
    /// connections, or the HTTP response that refuses it (see the module docs for the order).
    // The error is what tungstenite's `Callback` returns: the response to send, built once per
    // refused upgrade.
    #[allow(clippy::result_large_err)]
    fn admit(
        &self,
        request: &Request,
        remote: SocketAddr,
    ) -> Result<(RobotId, Places), ErrorResponse> {
        let ip = remote.ip();
        if !self.gate.source_allowed(ip) {
            let detail = "too many wrong keys from this address; retry later";
            self.refuse(Reason::WrongTokenLimit, remote, &detail);
            let wait = self.context.wrong_tokens.retry_after(ip);
            return Err(http_refusal(
                StatusCode::TOO_MANY_REQUESTS,
                detail,
                Some(retry_after_secs(wait)),
            ));
        }
        let robot = match authorize(request, &self.context) {
            Ok(robot) => robot,
            Err(reason) => {
                self.gate.token_failed(ip);
                self.refuse(Reason::Unauthorized, remote, &reason);
                let mut refusal = http_refusal(
                    StatusCode::UNAUTHORIZED,
                    &format!("unauthorized: {reason}"),
                    None,
                );
                refusal.headers_mut().insert(
                    header::WWW_AUTHENTICATE,
                    header::HeaderValue::from_static("Api-Key"),
                );
                return Err(refusal);
            }
        };
        let Some(place) = self.gate.authenticated() else {
            let limit = self.context.connections.max_connections;
            let detail = format!("server at capacity ({limit} openpi connections); retry later");
            self.refuse(Reason::AtCapacity, remote, &detail);
            return Err(http_refusal(
                StatusCode::SERVICE_UNAVAILABLE,
                &detail,
                Some(1),
            ));
        };
        let robot_places = &self.context.fairness.places;
        let Some(robot_place) = robot_places.take(robot) else {
            self.gate.robot_at_capacity();
            let detail = format!(
                "robot `{}` is at its capacity of {} connections \
                 ([connections] max_connections_per_robot); retry later",
                self.context.robots.name(robot),
                robot_places.cap()
            );
            self.refuse(Reason::RobotAtCapacity, remote, &detail);
            return Err(http_refusal(
                StatusCode::SERVICE_UNAVAILABLE,
                &detail,
                Some(1),
            ));
        };
        Ok((
            robot,
            Places {
                _robot: robot_place,
                _all: place,
            },
        ))
    }
}

/// An authenticated connection's places: one of its robot's (shared with its QUIC
/// connections), one of the endpoint's `max_connections`. Given back when dropped.
struct Places {
    _robot: RobotPlace,
    _all: OwnedSemaphorePermit,
}

/// `Retry-After` in whole seconds, at least 1, at most a day.
fn retry_after_secs(wait: Duration) -> u64 {
    wait.as_secs()
        .saturating_add(u64::from(wait.subsec_nanos() > 0))
        .clamp(1, 86_400)
}

/// An HTTP refusal of an upgrade: `status`, `text` as the body, `Retry-After` when given.
// The type is tungstenite's `Callback` error: the response to send.
#[allow(clippy::result_large_err)]
fn http_refusal(status: StatusCode, text: &str, retry_after: Option<u64>) -> ErrorResponse {
    let mut refusal = ErrorResponse::new(Some(format!("{text}\n")));
    *refusal.status_mut() = status;
    if let Some(secs) = retry_after
        && let Ok(value) = header::HeaderValue::from_str(&secs.to_string())
    {
        refusal.headers_mut().insert(header::RETRY_AFTER, value);
    }
    refusal
}

/// The answer to a connection refused at its accept, written without waiting (the socket's send
/// buffer is empty) and without reading the request.
const BUSY: &[u8] = b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\n\
Content-Length: 32\r\nConnection: close\r\n\r\ntoo many connections; retry later\n";

/// Serves openpi clients on `listener` until `stop` is set, then lets the connections answer
/// their pending request and close (`going away`), for up to [`DRAIN_TIMEOUT`].
pub async fn run(
    listener: TcpListener,
    context: Arc<ServerContext>,
    config: Arc<OpenpiConfig>,
    mut stop: watch::Receiver<bool>,
) -> OpenpiStats {
    let endpoint = Arc::new(Endpoint::new(context, config));
    let mut connections = JoinSet::new();
    let mut stats = OpenpiStats::default();
    let sessions_stop = stop.clone();
    let stopped = async move {
        let _ = stop.wait_for(|stopping| *stopping).await;
    };
    tokio::pin!(stopped);
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, remote)) => {
                    let place = match endpoint.handshakes.try_take(Some(remote.ip())) {
                        Ok(place) => place,
                        Err(refusal) => {
                            let (reason, detail) = match refusal {
                                HandshakeRefusal::Full => (
                                    Reason::HandshakeBudget,
                                    "every handshake place is taken",
                                ),
                                HandshakeRefusal::SourceBusy => (
                                    Reason::SourceHandshakes,
                                    "this address has its share of handshakes in progress",
                                ),
                            };
                            endpoint.refuse(reason, remote, &detail);
                            let _ = stream.try_write(BUSY);
                            continue;
                        }
                    };
                    let endpoint = endpoint.clone();
                    let stop = sessions_stop.clone();
                    connections.spawn(connection(stream, remote, place, endpoint, stop));
                }
                Err(error) => {
                    // Out of file descriptors, say: back off instead of spinning.
                    tracing::warn!(%error, "openpi accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
            Some(joined) = connections.join_next(), if !connections.is_empty() => {
                count(&mut stats, joined);
            }
            () = &mut stopped => break,
        }
    }
    drop(listener);
    let drained = tokio::time::timeout(DRAIN_TIMEOUT, async {
        while let Some(joined) = connections.join_next().await {
            count(&mut stats, joined);
        }
    })
    .await;
    if drained.is_err() {
        connections.abort_all();
    }
    stats
}

fn count(stats: &mut OpenpiStats, joined: Result<bool, tokio::task::JoinError>) {
    if let Ok(true) = joined {
        stats.connections += 1;
    }
}

/// The robot whose token the request's `Authorization: Api-Key <token>` carries.
fn authorize(request: &Request, context: &ServerContext) -> Result<RobotId, &'static str> {
    let value = request
        .headers()
        .get(header::AUTHORIZATION)
        .ok_or("missing `Authorization: Api-Key <token>` header")?;
    let value = value
        .to_str()
        .map_err(|_| "the Authorization header is not text")?;
    let key = match value.split_once(' ') {
        Some((scheme, key)) if scheme.eq_ignore_ascii_case("api-key") => key.trim(),
        _ => return Err("the Authorization header is not `Api-Key <token>`"),
    };
    context.robots.authenticate(key).ok_or("unknown key")
}

/// Whether a failed upgrade was the client's malformed request (as opposed to a connection that
/// went away before its request was complete, or the server's own refusal).
fn bad_upgrade(error: &WsError) -> bool {
    use tokio_tungstenite::tungstenite::error::ProtocolError;
    match error {
        WsError::Protocol(ProtocolError::HandshakeIncomplete) => false,
        WsError::Protocol(_)
        | WsError::HttpFormat(_)
        | WsError::Utf8(_)
        | WsError::AttackAttempt
        | WsError::Capacity(_) => true,
        _ => false,
    }
}

/// Serves one TCP connection: the authenticated upgrade, then the session. `place` is its
/// handshake place, held until the upgrade is answered. Returns whether the upgrade was accepted.
async fn connection(
    stream: TcpStream,
    remote: SocketAddr,
    place: HandshakePlace,
    endpoint: Arc<Endpoint>,
    stop: watch::Receiver<bool>,
) -> bool {
    let _ = stream.set_nodelay(true);
    let context = endpoint.context.clone();
    let max = context.limits().max_frame as usize;
    let ws_config = WebSocketConfig::default()
        .max_message_size(Some(max))
        .max_frame_size(Some(max))
        .read_buffer_size(READ_BUFFER);
    let mut admitted = None;
    let mut refused = false;
    // The signature is tungstenite's `Callback`; its error is the HTTP response to send.
    #[allow(clippy::result_large_err)]
    let callback = |request: &Request, response: Response| -> Result<Response, ErrorResponse> {
        match endpoint.admit(request, remote) {
            Ok(robot_and_place) => {
                admitted = Some(robot_and_place);
                Ok(response)
            }
            Err(refusal) => {
                refused = true;
                Err(refusal)
            }
        }
    };
    let upgrade = tokio::time::timeout(
        context.connections.hello_timeout(),
        tokio_tungstenite::accept_hdr_async_with_config(
            BoundedStream::new(stream),
            callback,
            Some(ws_config),
        ),
    )
    .await;
    drop(place);
    let mut ws = match upgrade {
        Ok(Ok(ws)) => ws,
        Ok(Err(error)) => {
            if !refused && bad_upgrade(&error) {
                endpoint.refuse(Reason::BadUpgrade, remote, &error);
            } else {
                tracing::debug!(%remote, %error, "openpi handshake failed");
            }
            return false;
        }
        Err(_) => {
            endpoint.refuse(
                Reason::HandshakeTimeout,
                remote,
                &"websocket upgrade not done within hello_timeout_ms",
            );
            return false;
        }
    };
    let Some((robot, _place)) = admitted else {
        return false;
    };
    ws.get_mut()
        .arm(endpoint.read_bounds(robot), endpoint.budget_bytes);
    tracing::debug!(%remote, robot = context.robots.name(robot), "openpi client connected");
    let config = endpoint.config.clone();
    let exec = ExecEstimate::new(config.control_hz);
    Session {
        context,
        config,
        remote,
        robot,
        task: rand::random::<u64>() >> 1,
        next_round: 0,
        exec,
        prev_total: None,
    }
    .run(ws, stop)
    .await;
    true
}

/// How a session ends.
enum End {
    /// The client closed the websocket (or the connection broke).
    Closed,
    /// The server is shutting down.
    Shutdown,
    /// An error: sent as text, then the websocket is closed with `code`.
    Refused {
        /// The text message.
        text: String,
        /// The close code.
        code: CloseCode,
    },
}

impl End {
    fn refused(error: &RequestError) -> End {
        End::from(ErrorReply::from(error))
    }

    fn too_slow(slow: &kairos_sdk::protocol::TooSlow) -> End {
        End::refused(&RequestError::TooSlow(slow.to_string()))
    }

    fn too_large(error: impl std::fmt::Display, max: usize) -> End {
        End::Refused {
            text: format!(
                "{}: {error} (the limit is {max} bytes, `limits.max_frame`)",
                ErrorCode::TooLarge
            ),
            code: CloseCode::Size,
        }
    }
}

impl From<ErrorReply> for End {
    fn from(reply: ErrorReply) -> End {
        let code = match reply.code {
            ErrorCode::ShuttingDown => CloseCode::Away,
            ErrorCode::Overloaded => CloseCode::Again,
            ErrorCode::Internal => CloseCode::Error,
            ErrorCode::TooLarge => CloseCode::Size,
            _ => CloseCode::Policy,
        };
        End::Refused {
            text: format!("{}: {}", reply.code, reply.message),
            code,
        }
    }
}

/// How long a refused connection waits for the client's side of the close.
const LINGER: Duration = Duration::from_secs(1);

/// After the server's close frame: waits (up to [`LINGER`]) for the client's close, so that
/// closing the socket does not reset a client that is still sending (the kernel answers unread
/// data with a reset, which the client would see instead of the error text). After a message
/// over the limit the websocket layer cannot parse the rest of it, so the raw bytes are read and
/// discarded instead.
async fn linger(ws: &mut Ws, raw: bool) {
    use tokio::io::AsyncReadExt;
    // The session is over: what is left is discarded, outside the budget and the rate.
    ws.get_mut().disarm();
    let drain = async {
        if raw {
            let mut buf = vec![0u8; 64 << 10];
            while let Ok(1..) = ws.get_mut().read(&mut buf).await {}
        } else {
            while let Some(Ok(_)) = ws.next().await {}
        }
    };
    let _ = tokio::time::timeout(LINGER, drain).await;
}

/// One openpi connection: one task.
struct Session {
    context: Arc<ServerContext>,
    config: Arc<OpenpiConfig>,
    remote: SocketAddr,
    robot: RobotId,
    task: u64,
    next_round: u64,
    exec: ExecEstimate,
    /// From the previous request's arrival to its reply written (openpi's `prev_total_ms`).
    prev_total: Option<Duration>,
}

type Ws = WebSocketStream<BoundedStream<TcpStream>>;

impl Session {
    async fn run(mut self, mut ws: Ws, mut stop: watch::Receiver<bool>) {
        let metadata = self.metadata();
        let end = match ws.send(Message::binary(metadata)).await {
            Err(_) => End::Closed,
            Ok(()) => loop {
                let message = tokio::select! {
                    message = ws.next() => message,
                    _ = stop.wait_for(|stopping| *stopping) => break End::Shutdown,
                };
                if let Some(Ok(Message::Binary(_) | Message::Text(_))) = &message {
                    ws.get_mut().message_done();
                }
                match message {
                    Some(Ok(Message::Binary(frame))) => {
                        if let Err(end) = self.round(&mut ws, frame).await {
                            break end;
                        }
                    }
                    Some(Ok(Message::Text(_))) => {
                        break End::Refused {
                            text: format!(
                                "{}: expected a binary msgpack message, got text",
                                ErrorCode::BadFrame
                            ),
                            code: CloseCode::Unsupported,
                        };
                    }
                    Some(Ok(Message::Close(_))) => break End::Closed,
                    // Pings are answered by the websocket layer.
                    Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                    Some(Err(error)) => break self.read_failed(error),
                    None => break End::Closed,
                }
            },
        };
        let failed = matches!(end, End::Refused { .. });
        match end {
            End::Closed => {
                let _ = ws.close(None).await;
            }
            End::Shutdown => {
                let _ = ws
                    .close(Some(CloseFrame {
                        code: CloseCode::Away,
                        reason: "server shutting down".into(),
                    }))
                    .await;
            }
            End::Refused { text, code } => {
                tracing::debug!(task = self.task, %text, "openpi request refused");
                let _ = ws.send(Message::text(text)).await;
                let _ = ws
                    .close(Some(CloseFrame {
                        code,
                        reason: "request refused; the reason is in the previous message".into(),
                    }))
                    .await;
                linger(&mut ws, code == CloseCode::Size).await;
            }
        }
        self.end_task(failed).await;
    }

    /// How a failed read ends the session: a message over the frame limit or one that fell
    /// behind the minimum rate is refused (and counted); anything else means the connection is
    /// gone.
    fn read_failed(&self, error: WsError) -> End {
        let refuse = |reason: Reason, detail: &dyn std::fmt::Display| {
            self.context
                .refusals
                .refuse(Door::Openpi, reason, self.remote, detail);
        };
        match error {
            WsError::Capacity(error) => {
                refuse(Reason::TooLarge, &error);
                End::too_large(error, self.context.limits().max_frame as usize)
            }
            WsError::Io(error) => match upload::too_slow(&error) {
                Some(slow) => {
                    refuse(Reason::TooSlow, slow);
                    End::too_slow(slow)
                }
                None => End::Closed,
            },
            _ => End::Closed,
        }
    }

    /// The metadata map sent on connect.
    fn metadata(&self) -> Vec<u8> {
        let model = &self.context.model;
        let config = &self.config;
        let mut w = Writer::new();
        w.map(9);
        w.str("server")
            .str(&format!("kairos/{}", env!("CARGO_PKG_VERSION")));
        w.str("robot").str(self.context.robots.name(self.robot));
        w.str("task").uint(self.task);
        w.str("model").str(&model.name);
        w.str("chunk_len").uint(u64::from(model.chunk_len));
        w.str("action_dim").uint(u64::from(model.action_dim));
        w.str("state_dim").uint(u64::from(model.state_dim));
        w.str("max_images").uint(u64::from(model.max_images));
        w.str("keys").map(3);
        w.str("cameras").array(config.cameras.len());
        for key in &config.cameras {
            w.str(key);
        }
        w.str("state").array(config.state.len());
        for key in &config.state {
            w.str(key);
        }
        w.str("prompt").str(&config.prompt);
        w.finish()
    }

    /// The horizon selection of every round: the configured policy, or the whole chunk.
    fn horizon(&self) -> HorizonSelection {
        match &self.config.horizon {
            Some(policy) => HorizonSelection {
                policy: policy.clone(),
                params: self.config.horizon_params.clone(),
                samples: 1,
            },
            None => HorizonSelection {
                policy: "static".into(),
                params: [("h".to_string(), f64::from(self.context.model.chunk_len))].into(),
                samples: 1,
            },
        }
    }

    /// One request: decode, map, admit, wait (answering pings, noticing a close), reply. The
    /// frame is dropped once mapped: only the observation waits in the queue.
    async fn round(
        &mut self,
        ws: &mut Ws,
        frame: tokio_tungstenite::tungstenite::Bytes,
    ) -> Result<(), End> {
        let clock = self.context.driver.clock();
        let received = clock.now();
        let at_us = received.as_micros();
        let observation = {
            let dict = msgpack::decode(&frame, MAX_VALUES).map_err(|e| {
                End::refused(&RequestError::Invalid {
                    field: "message".into(),
                    reason: e.to_string(),
                })
            })?;
            let limits = self.context.limits();
            let mut observation = observation::observation(&dict, &self.config, at_us, limits)
                .map_err(|e| End::refused(&e))?;
            observation::name_cameras(
                &mut observation,
                &self.config,
                &self.context.validator.spec.cameras,
            );
            observation
        };
        drop(frame);
        let round = self.next_round;
        let submit = Submit {
            task: self.task,
            round,
            sent_at_us: at_us,
            observation,
            last_exec: self.exec.on_request(received),
            horizon: Some(self.horizon()),
            remaining: None,
            attempt: 0,
            // The configured or estimated rate: the task's idle clock then covers the chunk the
            // client executes before its next call, from the first round on.
            control_hz: self.exec.control_hz(),
            seed: None,
            chunking: None,
        };
        // The server clock is the "robot" clock here: the identity mapping.
        let identity = ClockMap::new(received, at_us, Duration::ZERO);
        // No re-fetch: the receiver is dropped, so the driver uses the queued observation.
        let (link, _) = mpsc::channel::<RefetchAsk>(1);
        let mut pending = self
            .context
            .admit(submit, self.robot, identity, received, link)
            .await
            .map_err(|e| {
                if matches!(e, RequestError::RateLimited { .. }) {
                    self.context
                        .refusals
                        .refuse(Door::Openpi, Reason::RoundRate, self.remote, &e);
                }
                End::refused(&e)
            })?;
        self.next_round = round + 1;
        let answer = loop {
            tokio::select! {
                answer = &mut pending.answer => break answer,
                message = ws.next() => match message {
                    Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                    Some(Ok(Message::Binary(_) | Message::Text(_))) => {
                        self.context.driver.detach(&pending).await;
                        return Err(End::Refused {
                            text: format!(
                                "{}: a request arrived before the reply to the previous one \
                                 (openpi clients send one at a time)",
                                ErrorCode::BadFrame
                            ),
                            code: CloseCode::Policy,
                        });
                    }
                    Some(Err(error)) => {
                        self.context.driver.detach(&pending).await;
                        return Err(self.read_failed(error));
                    }
                    Some(Ok(Message::Close(_))) | None => {
                        self.context.driver.detach(&pending).await;
                        return Err(End::Closed);
                    }
                },
            }
        };
        let reply = match answer {
            Ok(Ok(reply)) => reply,
            Ok(Err(error)) => return Err(End::from(error)),
            Err(_) => return Err(End::refused(&RequestError::SHUTTING_DOWN)),
        };
        let frame = self.reply_frame(&reply);
        if ws.send(Message::binary(frame)).await.is_err() {
            return Err(End::Closed);
        }
        let sent = clock.now();
        self.exec.on_reply(sent, reply.horizon, reply.round);
        self.prev_total = Some(sent.saturating_since(received));
        Ok(())
    }

    /// The reply map: `actions`, openpi's timing fields, and Kairos' round facts.
    fn reply_frame(&self, reply: &Reply) -> Vec<u8> {
        let ms = |us: u64| us as f64 / 1e3;
        let t = &reply.timing;
        let mut w = Writer::new();
        w.map(4);
        w.str("actions");
        let mut shape: Vec<usize> = reply.actions.shape.iter().map(|&d| d as usize).collect();
        // From the server's start index on: the actions whose time had passed at the arrival
        // are not sent.
        let skip = (reply.start.unwrap_or(0) as usize).min(shape.first().copied().unwrap_or(0));
        let width: usize = shape.iter().skip(1).product();
        if let Some(rows) = shape.first_mut() {
            *rows -= skip;
        }
        match reply.actions.dtype {
            kairos_sdk::protocol::DType::F32 => {
                w.ndarray_raw(&shape, "<f4", &reply.actions.data[skip * width * 4..]);
            }
            _ => {
                let values = reply.actions.to_f32().unwrap_or_default();
                w.ndarray_f32(&shape, &values[(skip * width).min(values.len())..]);
            }
        }
        w.str("server_timing")
            .map(if self.prev_total.is_some() { 5 } else { 4 });
        // openpi's `infer_ms` is the wall time of the policy call on the server: here from the
        // request's arrival to its answer, queueing included.
        w.str("infer_ms").float(ms(t.total_us));
        if let Some(prev) = self.prev_total {
            w.str("prev_total_ms").float(prev.as_secs_f64() * 1e3);
        }
        w.str("queue_ms").float(ms(t.queue_us));
        w.str("inference_ms").float(ms(t.inference_us));
        w.str("batch_size").uint(u64::from(t.batch_size));
        w.str("policy_timing").map(1);
        w.str("infer_ms").float(ms(t.inference_us));
        w.str("kairos").map(8);
        w.str("task").uint(reply.task);
        w.str("round").uint(reply.round);
        w.str("horizon").uint(u64::from(reply.horizon));
        w.str("chunk_len").uint(u64::from(reply.chunk_len));
        w.str("policy").str(&reply.policy);
        // The client gets the chunk from the server's start index on (its actions that belong
        // to the reply's arrival); a blocking client executes nothing while it waits, so that
        // is the whole chunk (`exec`'s module docs).
        w.str("start").uint(u64::from(reply.start.unwrap_or(0)));
        w.str("delay").uint(u64::from(reply.delay.unwrap_or(0)));
        w.str("chunking")
            .str(reply.chunking.as_deref().unwrap_or("skip"));
        w.finish()
    }

    /// Ends the connection's task, if it has one: `done` when the client closed, `failed` when
    /// the server closed it over an error.
    async fn end_task(&self, failed: bool) {
        if self.next_round == 0 {
            return;
        }
        let now = self.context.driver.clock().now();
        let at_us = now.as_micros();
        let end = EndTask {
            task: self.task,
            outcome: if failed {
                TaskOutcome::Failed
            } else {
                TaskOutcome::Done
            },
            sent_at_us: at_us,
            last_exec: self.exec.on_close(),
        };
        let identity = ClockMap::new(now, at_us, Duration::ZERO);
        match self.context.validator.end_task(end, identity) {
            Ok(end) => match self.context.driver.end_task(self.robot, end).await {
                Ok(Ok(_)) => {}
                Ok(Err(error)) => {
                    tracing::debug!(task = self.task, error = %error.message, "openpi task end")
                }
                Err(_) => {}
            },
            Err(error) => tracing::debug!(task = self.task, %error, "openpi task end"),
        }
    }
}
