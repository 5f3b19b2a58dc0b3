//! One connection: `Hello`/`Welcome`, then a task per round stream.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::client::{STREAM_REFUSED, close_code};
use kairos_sdk::protocol::{
    ErrorReply, FetchObservation, Message, PROTOCOL_VERSION, ReadFrameError, Welcome, read_message,
    write_message,
};
use quinn::{Connection, RecvStream, SendStream, VarInt};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

use super::ServerContext;
use crate::driver::RefetchAsk;
use crate::scheduler::RobotId;
use crate::time::Timestamp;
use crate::validation::{ClockEstimator, ClockMap, RequestError};

/// How long the server waits, after a stream's final frame, for the client to acknowledge it or
/// finish its own side.
const LINGER: Duration = Duration::from_secs(1);

/// The per-connection state shared by its stream tasks.
struct Peer {
    connection: Connection,
    robot: RobotId,
    clock: Mutex<ClockEstimator>,
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

/// Accepts `incoming` only to close it with a reason: the server is at `limit` connections.
pub(super) async fn refuse_at_capacity(incoming: quinn::Incoming, limit: usize) {
    let Ok(connecting) = incoming.accept() else {
        return;
    };
    if let Ok(connection) = connecting.await {
        let reason = format!("server at capacity ({limit} connections); retry later");
        connection.close(VarInt::from_u32(close_code::AT_CAPACITY), reason.as_bytes());
    }
}

/// Serves one connection until the client closes it or the server shuts down.
pub(super) async fn serve(
    incoming: quinn::Incoming,
    context: Arc<ServerContext>,
    mut stop: watch::Receiver<bool>,
) {
    let remote = incoming.remote_address();
    let connecting = match incoming.accept() {
        Ok(connecting) => connecting,
        Err(error) => {
            tracing::debug!(%remote, %error, "handshake refused");
            return;
        }
    };
    // 0.5-RTT: the server may answer streams the client sent as 0-RTT data right away. Safe
    // because tickets are single-use (see `tls`).
    let connection = match connecting.into_0rtt() {
        Ok((connection, _accepted)) => connection,
        Err(connecting) => match connecting.await {
            Ok(connection) => connection,
            Err(error) => {
                tracing::debug!(%remote, %error, "handshake failed");
                return;
            }
        },
    };
    let hello_timeout = context.connections.hello_timeout();
    let robot = match tokio::time::timeout(hello_timeout, hello(&connection, &context)).await {
        Ok(Ok(robot)) => robot,
        Ok(Err((code, reason))) => {
            connection.close(VarInt::from_u32(code), reason.as_bytes());
            return;
        }
        Err(_) => {
            connection.close(
                VarInt::from_u32(close_code::PROTOCOL_ERROR),
                b"no Hello in time",
            );
            return;
        }
    };
    tracing::debug!(%remote, robot = context.robots.name(robot), "robot connected");
    let peer = Arc::new(Peer {
        connection: connection.clone(),
        robot,
        clock: Mutex::new(ClockEstimator::default()),
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

/// The `Hello`/`Welcome` exchange on the connection's first stream. On refusal returns the close
/// code and reason, after the error frame has been delivered (or `LINGER` has passed).
async fn hello(connection: &Connection, context: &ServerContext) -> Result<RobotId, (u32, String)> {
    let protocol_error = |reason: String| (close_code::PROTOCOL_ERROR, reason);
    let (mut send, mut recv) = connection
        .accept_bi()
        .await
        .map_err(|e| protocol_error(e.to_string()))?;
    let refused = match read_message(&mut recv, context.limits()).await {
        Ok(Some(Message::Hello(hello))) => match context.validator.hello(&hello) {
            Ok(_) => match context.robots.authenticate(&hello.token) {
                Some(robot) => {
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
                    return Ok(robot);
                }
                None => (close_code::UNAUTHORIZED, RequestError::Unauthorized),
            },
            Err(error) => (close_code::PROTOCOL_ERROR, error),
        },
        Ok(Some(other)) => (
            close_code::PROTOCOL_ERROR,
            RequestError::UnexpectedMessage {
                expected: "Hello",
                got: other.kind().to_string(),
            },
        ),
        Ok(None) => return Err(protocol_error("stream closed before Hello".into())),
        Err(ReadFrameError::Frame(error)) => (close_code::PROTOCOL_ERROR, error.into()),
        Err(ReadFrameError::Read(error)) => return Err(protocol_error(error.to_string())),
    };
    let (code, error) = refused;
    tracing::info!(remote = %connection.remote_address(), %error, "connection refused");
    let _ = recv.stop(VarInt::from_u32(STREAM_REFUSED));
    send_error(&mut send, &error, context).await;
    let _ = tokio::time::timeout(LINGER, send.stopped()).await;
    Err((code, error.to_string()))
}

/// Writes `error` as the stream's final frame and finishes the stream.
async fn send_error(send: &mut SendStream, error: &RequestError, context: &ServerContext) {
    let mut reply = ErrorReply::from(error);
    let max = context.limits().max_message_bytes as usize;
    if reply.message.len() > max {
        let mut cut = max;
        while !reply.message.is_char_boundary(cut) {
            cut -= 1;
        }
        reply.message.truncate(cut);
    }
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
    let message = read_message(&mut recv, context.limits()).await;
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
        Err(ReadFrameError::Frame(error)) => Err(error.into()),
        // The stream or the connection is gone; nobody to answer.
        Err(ReadFrameError::Read(_)) => Ok(()),
    };
    if let Err(error) = outcome {
        tracing::debug!(robot = context.robots.name(peer.robot), %error, "request refused");
        let _ = recv.stop(VarInt::from_u32(STREAM_REFUSED));
        send_error(&mut send, &error, &context).await;
    }
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
        .map_err(|_| RequestError::ShuttingDown)?;
    let message = match answer {
        Ok(ended) => Message::TaskEnded(ended),
        Err(error) => Message::Error(error),
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
    let clock = peer.clock(context, submit.sent_at_us, submit.attempt == 0);
    let (task, round) = (submit.task, submit.round);
    let (link, mut asks) = mpsc::channel::<RefetchAsk>(1);
    let mut pending = context
        .admit(submit, peer.robot, clock, received, link)
        .await?;
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
        Ok(Err(error)) => Message::Error(error),
        // The driver stopped without answering.
        Err(_) => return Err(RequestError::ShuttingDown),
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
        age_us: crate::time::duration_micros(ask.age),
    });
    if write_message(send, &fetch, context.limits().max_frame)
        .await
        .is_err()
    {
        return;
    }
    let fresh = tokio::select! {
        message = read_message(recv, context.limits()) => message,
        // The driver gave up waiting.
        () = ask.reply.closed() => return,
    };
    match fresh {
        Ok(Some(Message::FreshObservation(fresh))) => {
            let clock = peer.clock(context, fresh.sent_at_us, true);
            let checked = match context.validator.fresh(fresh, clock) {
                Ok(observation) => context.validator.decode(observation).await,
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
