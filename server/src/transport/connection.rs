//! One connection: `Hello`/`Welcome`, then a task per round stream.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::client::{STREAM_REFUSED, close_code};
use kairos_sdk::protocol::{
    ErrorReply, FetchObservation, FrameError, HEADER_LEN, Limits, Message, PROTOCOL_VERSION,
    ReadBounds, ReadFrameError, Welcome, read_message_bounded, write_message,
};
use quinn::{Connection, RecvStream, SendStream, VarInt};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio::task::JoinSet;
use tokio::time::Instant;

use super::admission::HandshakePlace;
use super::fairness::{RobotPlace, TokenBucket};
use super::refusals::{Door, Reason};
use super::{Gate, ServerContext};
use crate::driver::RefetchAsk;
use crate::validation::RequestError;
use kairos_core::clock_map::{ClockEstimator, ClockMap};
use kairos_core::scheduler::RobotId;
use kairos_core::sync::lock;
use kairos_core::time::Timestamp;

/// How long the server waits, after a stream's final frame, for the client to acknowledge it or
/// finish its own side.
const LINGER: Duration = Duration::from_secs(1);

/// Bytes a connection may have in flight before `Hello` is accepted (QUIC connection receive
/// window): room for the largest `Hello` and then some.
pub(super) const HELLO_WINDOW: u32 = 16 << 10;

/// The largest `Hello` frame body the server reads: a token, a client name and MessagePack
/// framing around them.
fn hello_limits(limits: &Limits) -> Limits {
    Limits {
        max_frame: limits
            .max_token_bytes
            .saturating_add(limits.max_name_bytes)
            .saturating_add(256),
        ..limits.clone()
    }
}

/// The per-connection state shared by its stream tasks.
struct Peer {
    connection: Connection,
    robot: RobotId,
    clock: Mutex<ClockEstimator>,
    /// How its frames are read: the minimum rate and the connection's upload budget.
    bounds: ReadBounds,
    /// Its round rate (`[connections] rounds_per_s_per_connection`).
    rounds: Mutex<TokenBucket>,
}

impl Peer {
    fn rounds(&self) -> std::sync::MutexGuard<'_, TokenBucket> {
        // A bucket is two numbers: a panic while holding the lock leaves it usable.
        lock(&self.rounds)
    }
}

impl Peer {
    /// The clock mapping for a message sent at `sent_at_us` and read now.
    fn clock(&self, context: &ServerContext, sent_at_us: u64, first_attempt: bool) -> ClockMap {
        let now = context.driver.clock().now();
        let rtt = self.connection.rtt();
        match self.clock.lock() {
            Ok(mut estimator) => estimator.observe(now, sent_at_us, rtt, first_attempt),
            // A panic while holding this lock cannot leave the estimator inconsistent.
            Err(poisoned) => poisoned
                .into_inner()
                .observe(now, sent_at_us, rtt, first_attempt),
        }
    }
}

/// Serves one connection until the client closes it or the server shuts down. `unauthenticated`
/// is its place in the handshake budget, given back once `Hello` is answered either way. A
/// connection still in its handshake or `Hello` when the server shuts down is dropped at once:
/// it has no round to drain.
pub(super) async fn serve(
    incoming: quinn::Incoming,
    unauthenticated: HandshakePlace,
    context: Arc<ServerContext>,
    gate: Arc<Gate>,
    mut stop: watch::Receiver<bool>,
) {
    let remote = incoming.remote_address();
    let admitted = tokio::select! {
        admitted = admit(incoming, &context, &gate) => admitted,
        _ = stop.wait_for(|stopping| *stopping) => None,
    };
    let (connection, robot, _places) = match admitted {
        Some(Admitted::Robot(connection, robot, places)) => (connection, robot, places),
        Some(Admitted::Worker(connection, deadline)) => {
            // A worker takes no robot place; its registration holds the handshake budget's place
            // (its source's share is given back: the handshake that share guarded is done).
            crate::worker::registration::serve(
                connection,
                unauthenticated.into_door_place(),
                context,
                gate,
                deadline,
                stop,
            )
            .await;
            return;
        }
        None => return,
    };
    drop(unauthenticated);
    tracing::debug!(%remote, robot = context.robots.name(robot), "robot connected");
    let budget = context
        .connections
        .upload_buffer_bytes(context.limits().max_frame);
    let peer = Arc::new(Peer {
        connection: connection.clone(),
        robot,
        clock: Mutex::new(ClockEstimator::default()),
        bounds: ReadBounds {
            min_rate: context.connections.min_upload_rate(),
            budget: Some(Arc::new(Semaphore::new(
                usize::try_from(budget).unwrap_or(Semaphore::MAX_PERMITS),
            ))),
        },
        rounds: Mutex::new(context.fairness.connection_rounds()),
    });
    let mut streams = JoinSet::new();
    loop {
        tokio::select! {
            accepted = connection.accept_bi() => match accepted {
                Ok((send, recv)) => {
                    streams.spawn(stream(peer.clone(), context.clone(), send, recv));
                }
                Err(error) => {
                    tracing::debug!(%remote, %error, "connection ended");
                    break;
                }
            },
            Some(_) = streams.join_next(), if !streams.is_empty() => {}
            _ = stop.wait_for(|stopping| *stopping) => break,
        }
    }
    // Streams already accepted finish: the driver answers what it took, refuses the rest.
    while streams.join_next().await.is_some() {}
    if *stop.borrow() {
        connection.close(
            VarInt::from_u32(close_code::SHUTTING_DOWN),
            b"server shutting down",
        );
    }
}

/// An authenticated connection's places: one of its robot's, one of all robots'. Given back
/// when dropped.
struct Places {
    _robot: RobotPlace,
    _all: OwnedSemaphorePermit,
}

/// What a connection turned out to be.
enum Admitted {
    /// A robot that sent a valid `Hello`, with its places among the authenticated connections.
    Robot(Connection, RobotId, Places),
    /// A connection with ALPN `kairos-worker/1`: it must register by the deadline.
    Worker(Connection, Instant),
}

/// The handshake and `Hello`, both within `hello_timeout_ms` of the first packet: the connection,
/// its robot and its place among the authenticated connections, or `None` after closing it. A
/// worker connection (by its ALPN) is returned after the handshake, for
/// `worker::registration::serve`.
async fn admit(
    incoming: quinn::Incoming,
    context: &ServerContext,
    gate: &Gate,
) -> Option<Admitted> {
    let deadline = Instant::now() + context.connections.hello_timeout();
    let remote = incoming.remote_address();
    let connecting = match incoming.accept() {
        Ok(connecting) => connecting,
        Err(error) => {
            tracing::debug!(%remote, %error, "handshake refused");
            return None;
        }
    };
    // 0.5-RTT: the server may answer streams the client sent as 0-RTT data right away. Safe
    // because tickets are single-use (see `tls`).
    let handshake = async {
        match connecting.into_0rtt() {
            Ok((connection, _accepted)) => Ok(connection),
            Err(connecting) => connecting.await,
        }
    };
    // Dropping an unfinished handshake abandons it.
    let connection = match tokio::time::timeout_at(deadline, handshake).await {
        Ok(Ok(connection)) => connection,
        Ok(Err(error)) => {
            tracing::debug!(%remote, %error, "handshake failed");
            return None;
        }
        Err(_) => {
            context.refusals.refuse(
                Door::Quic,
                Reason::HandshakeTimeout,
                remote,
                &"handshake not done within hello_timeout_ms",
            );
            return None;
        }
    };
    if is_worker(&connection) {
        return Some(Admitted::Worker(connection, deadline));
    }
    match tokio::time::timeout_at(deadline, hello(&connection, context, gate)).await {
        Ok(Ok((robot, place))) => Some(Admitted::Robot(connection, robot, place)),
        Ok(Err((code, reason))) => {
            connection.close(VarInt::from_u32(code), reason.as_bytes());
            None
        }
        Err(_) => {
            context.refusals.refuse(
                Door::Quic,
                Reason::HelloTimeout,
                remote,
                &"no accepted Hello within hello_timeout_ms",
            );
            connection.close(
                VarInt::from_u32(close_code::PROTOCOL_ERROR),
                b"no Hello in time",
            );
            None
        }
    }
}

/// Whether the handshake chose the worker protocol's ALPN.
fn is_worker(connection: &Connection) -> bool {
    connection
        .handshake_data()
        .and_then(|data| data.downcast::<quinn::crypto::rustls::HandshakeData>().ok())
        .and_then(|data| data.protocol)
        .is_some_and(|alpn| alpn == kairos_sdk::protocol::worker::WORKER_ALPN)
}

/// The `Hello`/`Welcome` exchange on the connection's first stream. A source over its budget
/// of wrong tokens is refused before its token is looked at; a robot that holds
/// `max_connections_per_robot` connections, or over `max_connections`, is refused after it. On
/// success returns the robot and its places among the authenticated connections, after opening
/// the connection's windows to the robot's (see the module docs).
/// On refusal returns the close code and reason, after the error frame has been delivered (or
/// `LINGER` has passed).
async fn hello(
    connection: &Connection,
    context: &ServerContext,
    gate: &Gate,
) -> Result<(RobotId, Places), (u32, String)> {
    let protocol_error = |reason: String| (close_code::PROTOCOL_ERROR, reason);
    let (mut send, mut recv) = connection
        .accept_bi()
        .await
        .map_err(|e| protocol_error(e.to_string()))?;
    let remote = connection.remote_address();
    let ip = remote.ip();
    let bounds = ReadBounds {
        min_rate: context.connections.min_upload_rate(),
        budget: None,
    };
    let limits = hello_limits(context.limits());
    let refuse = |reason: Reason, detail: &dyn std::fmt::Display| {
        context.refusals.refuse(Door::Quic, reason, remote, detail);
    };
    let refused = match read_message_bounded(&mut recv, &limits, &bounds).await {
        Ok(Some(Message::Hello(hello))) => match context.validator.hello(&hello) {
            Ok(_) if !gate.source_allowed(ip) => {
                // Not even hashed: this source has used up its wrong tokens.
                let reason = "too many wrong tokens from this address; retry later";
                refuse(Reason::WrongTokenLimit, &reason);
                return Err((close_code::UNAUTHORIZED, reason.into()));
            }
            Ok(_) => match context.robots.authenticate(&hello.token) {
                Some(robot) => {
                    let Some(place) = gate.authenticated() else {
                        let limit = context.connections.max_connections;
                        let reason =
                            format!("server at capacity ({limit} connections); retry later");
                        refuse(Reason::AtCapacity, &reason);
                        return Err((close_code::AT_CAPACITY, reason));
                    };
                    let places = &context.fairness.places;
                    let Some(robot_place) = places.take(robot) else {
                        gate.robot_at_capacity();
                        let reason = format!(
                            "robot `{}` is at its capacity of {} connections \
                             ([connections] max_connections_per_robot); retry later",
                            context.robots.name(robot),
                            places.cap()
                        );
                        refuse(Reason::RobotAtCapacity, &reason);
                        return Err((close_code::AT_CAPACITY, reason));
                    };
                    let places = Places {
                        _robot: robot_place,
                        _all: place,
                    };
                    open_windows(connection, context);
                    let welcome = Message::Welcome(Welcome {
                        protocol: PROTOCOL_VERSION,
                        server: format!("kairos/{}", env!("CARGO_PKG_VERSION")),
                        robot: context.robots.name(robot).to_string(),
                        model: context.model.clone(),
                        limits: context.limits().clone(),
                    });
                    write_message(&mut send, &welcome, u32::MAX)
                        .await
                        .map_err(|e| protocol_error(e.to_string()))?;
                    let _ = send.finish();
                    return Ok((robot, places));
                }
                None => {
                    gate.token_failed(ip);
                    refuse(Reason::Unauthorized, &"unknown token");
                    (close_code::UNAUTHORIZED, RequestError::Unauthorized)
                }
            },
            Err(error) => {
                refuse(Reason::BadHello, &error);
                (close_code::PROTOCOL_ERROR, error)
            }
        },
        Ok(Some(other)) => {
            let error = RequestError::UnexpectedMessage {
                expected: "Hello",
                got: other.kind().to_string(),
            };
            refuse(Reason::BadHello, &error);
            (close_code::PROTOCOL_ERROR, error)
        }
        Ok(None) => return Err(protocol_error("stream closed before Hello".into())),
        Err(ReadFrameError::Frame(error)) => {
            let error = RequestError::from(error);
            refuse(Reason::BadHello, &error);
            (close_code::PROTOCOL_ERROR, error)
        }
        Err(ReadFrameError::TooSlow(slow)) => {
            refuse(Reason::TooSlow, &slow);
            (
                close_code::PROTOCOL_ERROR,
                RequestError::TooSlow(slow.to_string()),
            )
        }
        Err(ReadFrameError::Read(error)) => return Err(protocol_error(error.to_string())),
    };
    let (code, error) = refused;
    let _ = recv.stop(VarInt::from_u32(STREAM_REFUSED));
    send_error(&mut send, &error, context).await;
    let _ = tokio::time::timeout(LINGER, send.stopped()).await;
    Err((code, error.to_string()))
}

/// Gives an authenticated robot its streams and its receive window: `upload_buffer_frames`
/// frames for the connection (the server's own transport config starts every connection at
/// one stream and [`HELLO_WINDOW`]).
fn open_windows(connection: &Connection, context: &ServerContext) {
    let connections = &context.connections;
    let window = connections.upload_buffer_bytes(context.limits().max_frame);
    connection.set_receive_window(VarInt::from_u64(window).unwrap_or(VarInt::MAX));
    connection
        .set_max_concurrent_bi_streams(VarInt::from_u32(connections.max_streams_per_connection));
}

/// The per-stream QUIC receive window: one whole frame (a stream carries one request frame, and
/// later at most one `FreshObservation`), never more than the connection's.
pub(super) fn stream_window(context_limits: &Limits, connection_window: u64) -> u64 {
    (u64::from(context_limits.max_frame) + HEADER_LEN as u64).min(connection_window)
}

/// `reply` with its message cut to the protocol's `max_message_bytes` (on a character
/// boundary): an error may quote what others sent (a worker's engine error, a plugin's
/// refusal), and the robot would refuse an oversized message.
fn within_limits(mut reply: ErrorReply, context: &ServerContext) -> ErrorReply {
    let max = context.limits().max_message_bytes as usize;
    if reply.message.len() > max {
        let mut cut = max;
        while !reply.message.is_char_boundary(cut) {
            cut -= 1;
        }
        reply.message.truncate(cut);
    }
    reply
}

/// Writes `error` as the stream's final frame and finishes the stream.
async fn send_error(send: &mut SendStream, error: &RequestError, context: &ServerContext) {
    let reply = within_limits(ErrorReply::from(error), context);
    let _ = write_message(send, &Message::Error(reply), context.limits().max_frame).await;
    let _ = send.finish();
}

/// One stream: a round (`Submit`) or a task end (`EndTask`).
async fn stream(
    peer: Arc<Peer>,
    context: Arc<ServerContext>,
    mut send: SendStream,
    mut recv: RecvStream,
) {
    let message = read_message_bounded(&mut recv, context.limits(), &peer.bounds).await;
    let received = context.driver.clock().now();
    let outcome = match message {
        Ok(Some(Message::Submit(submit))) => {
            round(&peer, &context, submit, received, &mut send, &mut recv).await
        }
        Ok(Some(Message::EndTask(end))) => end_task(&peer, &context, end, &mut send).await,
        Ok(Some(other)) => Err(RequestError::UnexpectedMessage {
            expected: "Submit or EndTask",
            got: other.kind().to_string(),
        }),
        Ok(None) => Ok(()),
        Err(ReadFrameError::Frame(error)) => {
            if matches!(error, FrameError::FrameTooLarge { .. }) {
                let remote = peer.connection.remote_address();
                context
                    .refusals
                    .refuse(Door::Quic, Reason::TooLarge, remote, &error);
            }
            Err(error.into())
        }
        Err(ReadFrameError::TooSlow(slow)) => {
            let remote = peer.connection.remote_address();
            context
                .refusals
                .refuse(Door::Quic, Reason::TooSlow, remote, &slow);
            Err(RequestError::TooSlow(slow.to_string()))
        }
        // The stream or the connection is gone; nobody to answer.
        Err(ReadFrameError::Read(_)) => Ok(()),
    };
    if let Err(error) = outcome {
        tracing::debug!(robot = context.robots.name(peer.robot), %error, "request refused");
        let _ = recv.stop(VarInt::from_u32(STREAM_REFUSED));
        send_error(&mut send, &error, &context).await;
    }
    // The stream's last frame is only queued: wait (briefly) until the client has it. A
    // connection that is shutting down closes once its streams end, and a close discards what
    // was not yet sent: a round refused `shutting_down` at that moment (a dead driver, a drain)
    // would reach its robot as a lost connection, and the robot would spend its reconnect
    // attempts on a server that is going away instead of reading the refusal.
    let _ = tokio::time::timeout(LINGER, send.stopped()).await;
}

async fn end_task(
    peer: &Peer,
    context: &ServerContext,
    end: kairos_sdk::protocol::EndTask,
    send: &mut SendStream,
) -> Result<(), RequestError> {
    let clock = peer.clock(context, end.sent_at_us, true);
    let end = context.validator.end_task(end, clock)?;
    let answer = context
        .driver
        .end_task(peer.robot, end)
        .await
        .map_err(|_| RequestError::SHUTTING_DOWN)?;
    let message = match answer {
        Ok(ended) => Message::TaskEnded(ended),
        Err(error) => Message::Error(within_limits(error, context)),
    };
    let _ = write_message(send, &message, context.limits().max_frame).await;
    let _ = send.finish();
    Ok(())
}

async fn round(
    peer: &Peer,
    context: &ServerContext,
    submit: kairos_sdk::protocol::Submit,
    received: Timestamp,
    send: &mut SendStream,
    recv: &mut RecvStream,
) -> Result<(), RequestError> {
    let over_rate = |error: RequestError| {
        let remote = peer.connection.remote_address();
        context
            .refusals
            .refuse(Door::Quic, Reason::RoundRate, remote, &error);
        error
    };
    peer.rounds()
        .try_take(super::fairness::now())
        .map_err(|retry_after| {
            over_rate(RequestError::RateLimited {
                who: "this connection".into(),
                limit: "rounds_per_s_per_connection",
                retry_after,
            })
        })?;
    let clock = peer.clock(context, submit.sent_at_us, submit.attempt == 0);
    let (task, round) = (submit.task, submit.round);
    let (link, mut asks) = mpsc::channel::<RefetchAsk>(1);
    let admitted = context
        .admit(submit, peer.robot, clock, received, link)
        .await;
    let mut pending = match admitted {
        Ok(pending) => pending,
        Err(error) => {
            if matches!(error, RequestError::RateLimited { .. }) {
                // Refused for its robot's rate, not this connection's.
                peer.rounds().give_back();
                return Err(over_rate(error));
            }
            return Err(error);
        }
    };
    let stopped = send.stopped();
    tokio::pin!(stopped);
    let answer = loop {
        tokio::select! {
            answer = &mut pending.answer => break answer,
            Some(ask) = asks.recv() => {
                refetch(peer, context, task, round, ask, send, recv).await;
            }
            _ = &mut stopped => {
                // The client stopped reading (abandoned the round) or the connection is gone.
                context.driver.detach(&pending).await;
                return Ok(());
            }
        }
    };
    let message = match answer {
        Ok(Ok(reply)) => Message::Reply(reply),
        Ok(Err(error)) => Message::Error(within_limits(error, context)),
        // The driver stopped without answering.
        Err(_) => return Err(RequestError::SHUTTING_DOWN),
    };
    let _ = write_message(send, &message, context.limits().max_frame).await;
    let _ = send.finish();
    drain(recv).await;
    Ok(())
}

/// Reads and discards what the client still sends on a finished round (a `FreshObservation`
/// that missed the re-fetch deadline) until it finishes its side, which the client does on
/// reading the reply. Dropping the stream earlier would stop the client's send side mid-write.
async fn drain(recv: &mut RecvStream) {
    let discard = async { while let Ok(Some(_)) = recv.read_chunk(usize::MAX, false).await {} };
    if tokio::time::timeout(LINGER, discard).await.is_err() {
        let _ = recv.stop(VarInt::from_u32(STREAM_REFUSED));
    }
}

/// Asks the client for a fresher observation on the round's stream and hands it to the driver.
/// Any failure just drops `ask`: the driver then uses the queued observation.
async fn refetch(
    peer: &Peer,
    context: &ServerContext,
    task: u64,
    round: u64,
    mut ask: RefetchAsk,
    send: &mut SendStream,
    recv: &mut RecvStream,
) {
    let fetch = Message::FetchObservation(FetchObservation {
        task,
        round,
        age_us: kairos_core::time::duration_micros(ask.age),
    });
    if write_message(send, &fetch, context.limits().max_frame)
        .await
        .is_err()
    {
        return;
    }
    let fresh = tokio::select! {
        message = read_message_bounded(recv, context.limits(), &peer.bounds) => message,
        // The driver gave up waiting.
        () = ask.reply.closed() => return,
    };
    match fresh {
        Ok(Some(Message::FreshObservation(fresh))) => {
            let clock = peer.clock(context, fresh.sent_at_us, true);
            let checked = match context.validator.fresh(fresh, clock) {
                Ok(observation) => context.decode.decode(observation).await,
                Err(error) => Err(error),
            };
            match checked {
                Ok(observation) => {
                    let _ = ask.reply.send(observation);
                }
                Err(error) => tracing::debug!(%error, "fresh observation refused"),
            }
        }
        Ok(Some(other)) => {
            tracing::debug!(got = %other.kind(), "expected FreshObservation")
        }
        Ok(None) | Err(_) => {}
    }
}
