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
//! Bounds: a message over `limits.max_frame` bytes is refused by the websocket layer before it is
//! buffered whole; msgpack decoding is bounded in depth and value count ([`MAX_VALUES`]) and runs
//! on the connection's task (a bounded, linear pass); image decoding, validation and inference
//! run where they do for QUIC rounds, never on a runtime worker. A bad frame fails only its own
//! connection.

pub mod exec;
pub mod msgpack;
pub mod observation;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use futures::{SinkExt, StreamExt};
use kairos_sdk::protocol::{
    EndTask, ErrorCode, ErrorReply, HorizonSelection, Reply, Submit, TaskOutcome,
};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, mpsc, watch};
use tokio::task::JoinSet;
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{StatusCode, header};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

use self::exec::ExecEstimate;
use self::msgpack::Writer;
use crate::config::OpenpiConfig;
use crate::driver::RefetchAsk;
use crate::transport::{DRAIN_TIMEOUT, ServerContext};
use crate::validation::RequestError;
use kairos_core::clock_map::ClockMap;
use kairos_core::scheduler::RobotId;

/// Most msgpack values one request may hold (an observation dict has tens).
pub const MAX_VALUES: usize = 4096;

/// What the endpoint did, returned when it stops.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OpenpiStats {
    /// Websocket connections accepted (authenticated).
    pub connections: u64,
    /// Connections refused: unauthorised, a failed handshake, or over `max_connections`.
    pub refused: u64,
}

/// Binds the endpoint's TCP listener.
pub async fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    TcpListener::bind(addr).await
}

/// Serves openpi clients on `listener` until `stop` is set, then lets the connections answer
/// their pending request and close (`going away`), for up to [`DRAIN_TIMEOUT`].
pub async fn run(
    listener: TcpListener,
    context: Arc<ServerContext>,
    config: Arc<OpenpiConfig>,
    mut stop: watch::Receiver<bool>,
) -> OpenpiStats {
    let permits = Arc::new(Semaphore::new(context.connections.max_connections));
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
                    let Ok(permit) = permits.clone().try_acquire_owned() else {
                        tracing::info!(%remote, "openpi connection refused: at capacity");
                        stats.refused += 1;
                        continue;
                    };
                    let (context, config) = (context.clone(), config.clone());
                    let stop = sessions_stop.clone();
                    connections.spawn(async move {
                        let served = connection(stream, remote, context, config, stop).await;
                        drop(permit);
                        served
                    });
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
    match joined {
        Ok(true) => stats.connections += 1,
        _ => stats.refused += 1,
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

/// Serves one TCP connection: the authenticated upgrade, then the session. Returns whether the
/// upgrade was accepted.
async fn connection(
    stream: TcpStream,
    remote: SocketAddr,
    context: Arc<ServerContext>,
    config: Arc<OpenpiConfig>,
    stop: watch::Receiver<bool>,
) -> bool {
    let _ = stream.set_nodelay(true);
    let max = context.limits().max_frame as usize;
    let ws_config = WebSocketConfig::default()
        .max_message_size(Some(max))
        .max_frame_size(Some(max));
    let mut robot = None;
    // The signature is tungstenite's `Callback`; its error is the HTTP response to send.
    #[allow(clippy::result_large_err)]
    let callback = |request: &Request, response: Response| -> Result<Response, ErrorResponse> {
        match authorize(request, &context) {
            Ok(id) => {
                robot = Some(id);
                Ok(response)
            }
            Err(reason) => {
                tracing::info!(%remote, reason, "openpi connection refused");
                let mut refusal = ErrorResponse::new(Some(format!("unauthorized: {reason}\n")));
                *refusal.status_mut() = StatusCode::UNAUTHORIZED;
                refusal.headers_mut().insert(
                    header::WWW_AUTHENTICATE,
                    header::HeaderValue::from_static("Api-Key"),
                );
                Err(refusal)
            }
        }
    };
    let upgrade = tokio::time::timeout(
        context.connections.hello_timeout(),
        tokio_tungstenite::accept_hdr_async_with_config(stream, callback, Some(ws_config)),
    )
    .await;
    let ws = match upgrade {
        Ok(Ok(ws)) => ws,
        Ok(Err(error)) => {
            tracing::debug!(%remote, %error, "openpi handshake failed");
            return false;
        }
        Err(_) => {
            tracing::debug!(%remote, "openpi handshake timed out");
            return false;
        }
    };
    let Some(robot) = robot else {
        return false;
    };
    tracing::debug!(%remote, robot = context.robots.name(robot), "openpi client connected");
    let exec = ExecEstimate::new(config.control_hz);
    Session {
        context,
        config,
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
    robot: RobotId,
    task: u64,
    next_round: u64,
    exec: ExecEstimate,
    /// From the previous request's arrival to its reply written (openpi's `prev_total_ms`).
    prev_total: Option<Duration>,
}

type Ws = WebSocketStream<TcpStream>;

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
                match message {
                    Some(Ok(Message::Binary(frame))) => {
                        if let Err(end) = self.round(&mut ws, &frame).await {
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
                    Some(Ok(Message::Close(_))) | None => break End::Closed,
                    // Pings are answered by the websocket layer.
                    Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                    Some(Err(WsError::Capacity(error))) => {
                        let max = self.context.limits().max_frame as usize;
                        break End::too_large(error, max);
                    }
                    Some(Err(_)) => break End::Closed,
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

    /// One request: decode, map, admit, wait (answering pings, noticing a close), reply.
    async fn round(&mut self, ws: &mut Ws, frame: &[u8]) -> Result<(), End> {
        let clock = self.context.driver.clock();
        let received = clock.now();
        let at_us = received.as_micros();
        let observation = {
            let dict = msgpack::decode(frame, MAX_VALUES).map_err(|e| {
                End::refused(&RequestError::Invalid {
                    field: "message".into(),
                    reason: e.to_string(),
                })
            })?;
            let mut observation = observation::observation(&dict, &self.config, at_us)
                .map_err(|e| End::refused(&e))?;
            observation::name_cameras(
                &mut observation,
                &self.config,
                &self.context.validator.spec.cameras,
            );
            observation
        };
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
            .map_err(|e| End::refused(&e))?;
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
                    _ => {
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
