//! A minimal protocol responder for client tests: real QUIC, real TLS (a fresh self-signed
//! certificate), the real codec, on 127.0.0.1. It answers every round with a synthetic chunk,
//! caches replies per (task, round) the way the server must for resume, and can be told to drop
//! a connection at a chosen point of a round.

#![allow(dead_code, clippy::unwrap_used)]

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::protocol::*;
use kairos_sdk::tls::Fingerprint;
use kairos_sdk::transport::{TransportTuning, server_config};
use quinn::VarInt;
use rustls::pki_types::{PrivateKeyDer, PrivatePkcs8KeyDer};

/// Where the responder drops the connection, once, on a round's first attempt.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kill {
    /// Right after reading the Submit, before generating.
    BeforeGeneration,
    /// After generating (the reply is cached) but before sending it.
    AfterGeneration,
}

/// Holds a round between reading its Submit and generating it, so a test can act while the
/// round is in flight on the server (an event, not a guess at how long that takes).
#[derive(Debug, Default)]
pub struct Hold {
    /// Notified when a round reaches the hold (the permit is kept if nobody waits yet).
    pub entered: tokio::sync::Notify,
    /// Notify to let the held round generate and answer.
    pub release: tokio::sync::Notify,
}

/// How the responder behaves.
#[derive(Clone, Debug)]
pub struct Behavior {
    pub token: String,
    pub horizon: u32,
    pub chunk_len: u32,
    pub action_dim: u32,
    pub generation: Duration,
    pub kill: Option<(u64, Kill)>,
    pub fetch_observation: bool,
    /// Answer this round with an `Error` frame instead of a reply.
    pub fail_round: Option<(u64, ErrorCode)>,
    /// QUIC tuning of the server side.
    pub tuning: TransportTuning,
    /// The version `Welcome` announces.
    pub welcome_protocol: u32,
    /// Hold every round before generating it until the test releases it.
    pub hold: Option<Arc<Hold>>,
}

impl Default for Behavior {
    fn default() -> Behavior {
        Behavior {
            token: "secret".to_owned(),
            horizon: 4,
            chunk_len: 8,
            action_dim: 2,
            generation: Duration::from_millis(5),
            kill: None,
            fetch_observation: false,
            fail_round: None,
            tuning: TransportTuning::default(),
            welcome_protocol: PROTOCOL_VERSION,
            hold: None,
        }
    }
}

/// What the responder saw.
#[derive(Debug, Default)]
pub struct Seen {
    pub connections: u32,
    /// Every Submit: (task, round, attempt).
    pub submits: Vec<(u64, u64, u32)>,
    /// Rounds actually generated: (task, round).
    pub generated: Vec<(u64, u64)>,
    /// `captured_at_us` of every FreshObservation.
    pub fresh: Vec<u64>,
    /// Last Exec Info of every Submit that had one: (round, info).
    pub last_exec: Vec<(u64, LastExecInfo)>,
    pub ended: Vec<(u64, TaskOutcome)>,
    pub killed: bool,
    /// Stream codes of rounds the client abandoned: (round, STOP_SENDING code).
    pub cancelled: Vec<(u64, u64)>,
    /// Notified (one stored permit) when a round is added to `cancelled`.
    pub cancellation: Arc<tokio::sync::Notify>,
}

pub struct Responder {
    pub addr: SocketAddr,
    pub fingerprint: Fingerprint,
    pub seen: Arc<Mutex<Seen>>,
    replies: Arc<Mutex<HashMap<(u64, u64), Reply>>>,
    endpoint: quinn::Endpoint,
}

impl Drop for Responder {
    fn drop(&mut self) {
        self.endpoint.close(VarInt::from_u32(0), b"test over");
    }
}

impl Responder {
    pub fn start(behavior: Behavior) -> Responder {
        let certified = rcgen::generate_simple_self_signed(vec!["kairos".to_owned()]).unwrap();
        let cert = certified.cert.der().clone();
        let fingerprint = Fingerprint::of(&cert);
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(
            certified.signing_key.serialize_der(),
        ));
        let config = server_config(vec![cert], key, &behavior.tuning, 64).unwrap();
        let endpoint =
            quinn::Endpoint::server(config, SocketAddr::from(([127, 0, 0, 1], 0))).unwrap();
        let addr = endpoint.local_addr().unwrap();
        let seen = Arc::new(Mutex::new(Seen::default()));
        let replies = Arc::new(Mutex::new(HashMap::new()));
        let responder = Responder {
            addr,
            fingerprint,
            seen: seen.clone(),
            replies: replies.clone(),
            endpoint: endpoint.clone(),
        };
        let behavior = Arc::new(behavior);
        tokio::spawn(async move {
            while let Some(incoming) = endpoint.accept().await {
                let (behavior, seen, replies) = (behavior.clone(), seen.clone(), replies.clone());
                tokio::spawn(async move {
                    if let Ok(connection) = incoming.await {
                        serve_connection(connection, behavior, seen, replies).await;
                    }
                });
            }
        });
        responder
    }

    pub fn seen(&self) -> std::sync::MutexGuard<'_, Seen> {
        self.seen.lock().unwrap()
    }
}

async fn serve_connection(
    connection: quinn::Connection,
    behavior: Arc<Behavior>,
    seen: Arc<Mutex<Seen>>,
    replies: Arc<Mutex<HashMap<(u64, u64), Reply>>>,
) {
    seen.lock().unwrap().connections += 1;
    let limits = Limits::default();
    let Ok((mut send, mut recv)) = connection.accept_bi().await else {
        return;
    };
    let Ok(Some(Message::Hello(hello))) = read_message(&mut recv, &limits).await else {
        connection.close(VarInt::from_u32(1), b"expected Hello");
        return;
    };
    if hello.token != behavior.token {
        let error = ErrorReply::new(ErrorCode::Unauthorized, "unknown token");
        write_message(&mut send, &Message::Error(error), limits.max_frame)
            .await
            .unwrap();
        send.finish().unwrap();
        let _ = send.stopped().await;
        connection.close(VarInt::from_u32(2), b"unauthorized");
        return;
    }
    let welcome = Welcome {
        protocol: behavior.welcome_protocol,
        server: "test-responder".to_owned(),
        robot: "robot-0".to_owned(),
        model: ModelInfo {
            name: "synthetic".to_owned(),
            chunk_len: behavior.chunk_len,
            action_dim: behavior.action_dim,
            state_dim: 2,
            steps: 10,
            max_images: 2,
            cameras: Vec::new(),
        },
        limits: limits.clone(),
    };
    write_message(&mut send, &Message::Welcome(welcome), limits.max_frame)
        .await
        .unwrap();
    let _ = send.finish();
    while let Ok((send, recv)) = connection.accept_bi().await {
        let (connection, behavior, seen, replies) = (
            connection.clone(),
            behavior.clone(),
            seen.clone(),
            replies.clone(),
        );
        tokio::spawn(async move {
            serve_stream(connection, send, recv, &behavior, &seen, &replies).await;
        });
    }
}

async fn serve_stream(
    connection: quinn::Connection,
    mut send: quinn::SendStream,
    mut recv: quinn::RecvStream,
    behavior: &Behavior,
    seen: &Mutex<Seen>,
    replies: &Mutex<HashMap<(u64, u64), Reply>>,
) {
    let limits = Limits::default();
    let message = match read_message(&mut recv, &limits).await {
        Ok(Some(message)) => message,
        _ => return,
    };
    let submit = match message {
        Message::Submit(submit) => submit,
        Message::EndTask(end) => {
            seen.lock().unwrap().ended.push((end.task, end.outcome));
            let generated = seen
                .lock()
                .unwrap()
                .generated
                .iter()
                .filter(|(task, _)| *task == end.task)
                .count() as u32;
            let ended = TaskEnded {
                task: end.task,
                rounds: generated,
                wait_us: 0,
                attained_service_us: 0,
                history: vec![],
            };
            let _ = write_message(&mut send, &Message::TaskEnded(ended), limits.max_frame).await;
            let _ = send.finish();
            return;
        }
        _ => return,
    };
    submit.validate(&limits).unwrap();
    if submit.observation.captured_at_us > submit.sent_at_us {
        let error = ErrorReply::new(
            ErrorCode::InvalidRequest,
            "observation captured after the message was sent",
        );
        let _ = write_message(&mut send, &Message::Error(error), limits.max_frame).await;
        let _ = send.finish();
        return;
    }
    let key = (submit.task, submit.round);
    let kill_here = |point: Kill| {
        let mut seen = seen.lock().unwrap();
        if behavior.kill == Some((submit.round, point)) && submit.attempt == 0 && !seen.killed {
            seen.killed = true;
            true
        } else {
            false
        }
    };
    {
        let mut seen = seen.lock().unwrap();
        seen.submits
            .push((submit.task, submit.round, submit.attempt));
        if let Some(info) = submit.last_exec {
            seen.last_exec.push((submit.round, info));
        }
    }
    if kill_here(Kill::BeforeGeneration) {
        connection.close(VarInt::from_u32(0), b"killed by the test");
        return;
    }
    if let Some((round, code)) = behavior.fail_round
        && round == submit.round
    {
        let error = ErrorReply::new(code, "failed on purpose");
        let _ = write_message(&mut send, &Message::Error(error), limits.max_frame).await;
        let _ = send.finish();
        return;
    }
    let cached = replies.lock().unwrap().get(&key).cloned();
    let reply = match cached {
        Some(reply) => reply,
        None => {
            if behavior.fetch_observation {
                let fetch = FetchObservation {
                    task: submit.task,
                    round: submit.round,
                    age_us: 1234,
                };
                write_message(
                    &mut send,
                    &Message::FetchObservation(fetch),
                    limits.max_frame,
                )
                .await
                .unwrap();
                match read_message(&mut recv, &limits).await {
                    Ok(Some(Message::FreshObservation(fresh))) => {
                        fresh.validate(&limits).unwrap();
                        seen.lock()
                            .unwrap()
                            .fresh
                            .push(fresh.observation.captured_at_us);
                    }
                    other => panic!("expected FreshObservation, got {other:?}"),
                }
            }
            if let Some(hold) = &behavior.hold {
                hold.entered.notify_one();
                hold.release.notified().await;
            }
            tokio::select! {
                () = tokio::time::sleep(behavior.generation) => {}
                stopped = send.stopped() => {
                    if let Ok(Some(code)) = stopped {
                        let mut seen = seen.lock().unwrap();
                        seen.cancelled.push((submit.round, code.into_inner()));
                        seen.cancellation.notify_one();
                    }
                    return;
                }
            }
            let h = behavior.horizon;
            let values: Vec<f32> = (0..h * behavior.action_dim)
                .map(|i| submit.round as f32 + i as f32 / 1000.0)
                .collect();
            let reply = Reply {
                task: submit.task,
                round: submit.round,
                horizon: h,
                chunk_len: behavior.chunk_len,
                actions: Tensor::from_f32(vec![h, behavior.action_dim], &values).unwrap(),
                policy: "static".to_owned(),
                timing: Timing {
                    queue_us: 10,
                    refetch_us: 0,
                    inference_us: behavior.generation.as_micros() as u64,
                    total_us: behavior.generation.as_micros() as u64 + 10,
                    batch_size: 1,
                },
                start: None,
                delay: None,
                chunking: None,
            };
            seen.lock().unwrap().generated.push(key);
            replies.lock().unwrap().insert(key, reply.clone());
            reply
        }
    };
    if kill_here(Kill::AfterGeneration) {
        connection.close(VarInt::from_u32(0), b"killed by the test");
        return;
    }
    let _ = write_message(&mut send, &Message::Reply(reply), limits.max_frame).await;
    let _ = send.finish();
    let _ = send.stopped().await;
}

/// A small valid observation on the client's clock.
pub fn observation(captured_at_us: u64) -> Observation {
    Observation {
        captured_at_us,
        state: Tensor::from_f32(vec![2], &[0.1, 0.2]).unwrap(),
        images: vec![Image {
            camera: "front".to_owned(),
            payload: ImagePayload::Raw {
                tensor: Tensor::from_u8(vec![4, 4, 3], vec![7; 48]).unwrap(),
            },
        }],
        instruction: "pick up the cube".to_owned(),
    }
}
