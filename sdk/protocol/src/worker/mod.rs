//! The worker protocol, version 1 (ALPN `kairos-worker/1`; normative text: `docs/PROTOCOL.md`,
//! "Worker protocol").
//!
//! A remote engine worker (`kairos worker`) dials the scheduler's QUIC endpoint with its own
//! ALPN, so a robot connection can never speak it and a worker connection can never speak the
//! robot protocol. Frames are the robot protocol's (`kind: u8 | length: u32 | MessagePack map`,
//! [`super::frame`]), decoded with the same strict envelope ([`super::codec::decode_body`]); the
//! kinds `0x30..=0x36` belong to this protocol and are refused on a robot stream.
//!
//! - The worker opens the connection's first bidirectional stream and sends [`Register`]; the
//!   scheduler answers [`Registered`] or [`Refused`] (then closes the connection). The stream stays
//!   open: the worker sends [`Heartbeat`] on it every `heartbeat_ms`, and [`Drain`] when it is
//!   asked to stop.
//! - For every batch the scheduler opens a bidirectional stream, sends [`RunBatch`] and finishes
//!   its side; the worker answers exactly one [`Chunks`] (or resets the stream). The first
//!   `Chunks` for a `(batch_id, attempt)` wins; anything else is dropped.
//!
//! A worker's messages are untrusted input: `Register`, `Heartbeat`, `Drain` and `Chunks`
//! implement [`Validate`](crate::Validate) (string sizes, tensor bounds, finite and bounded
//! profile numbers), and the scheduler checks them before it uses them.

mod validate;

pub use validate::{MAX_PROFILE_LATENCY_MS, MAX_PROFILE_POINTS, MAX_WORKER_BATCH};

use serde::{Deserialize, Serialize};

use super::codec::{WireBody, decode_body};
use super::frame::{Frame, FrameError};
use super::messages::{ChunkingStrategy, Image, MessageKind, ModelInfo, PrefixSchedule, Tensor};
use super::strict;

/// ALPN identifier of worker protocol version 1.
pub const WORKER_ALPN: &[u8] = b"kairos-worker/1";

/// Worker protocol version spoken by this crate.
pub const WORKER_PROTOCOL_VERSION: u32 = 1;

/// Largest frame body on a worker connection, bytes: a `RunBatch` carries a whole batch of
/// observations and a `Chunks` a whole batch of chunks with their per-step updates. Both ends
/// are authenticated (token and pinned certificate) before any such frame is read.
pub const WORKER_MAX_FRAME: u32 = 64 << 20;

/// Application close codes of worker connections (beside the robot protocol's
/// `client::close_code`, whose `NORMAL`, `PROTOCOL_ERROR`, `UNAUTHORIZED` and `SHUTTING_DOWN`
/// keep their meaning).
pub mod close_code {
    /// The registration was refused (`Refused` was sent first).
    pub const REFUSED: u32 = 0x20;
    /// A batch's deadline passed: the worker is removed.
    pub const DEADLINE: u32 = 0x21;
    /// A batch's stream failed or was answered unusably: the worker is removed.
    pub const BATCH_LOST: u32 = 0x22;
    /// No heartbeat for about three periods: the worker is removed.
    pub const SILENT: u32 = 0x23;
    /// The worker drained and is done.
    pub const DRAINED: u32 = 0x24;
}

/// Where a worker runs, as it declares it at registration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WorkerTier {
    /// Near the robots: placed first.
    Edge,
    /// Far: placed only when its latency plus round trip beats the edge queue.
    Cloud,
    /// Undeclared: the scheduler classifies the worker as edge or cloud from its measured
    /// round trip, and re-classifies it as that moves.
    Auto,
}

/// One measured point of a worker's engine profile.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfilePointWire {
    /// Requests per forward pass.
    pub batch: u32,
    /// Median latency of one whole generation at this batch size, ms.
    pub latency_ms: f64,
}

/// A worker's engine profile: latency versus batch size on its device.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProfileWire {
    /// Model name.
    #[serde(deserialize_with = "strict::text")]
    pub model: String,
    /// Device description.
    #[serde(deserialize_with = "strict::text")]
    pub device: String,
    /// Measured points, batch 1 first.
    pub points: Vec<ProfilePointWire>,
    /// Largest batch worth forming.
    pub max_batch: u32,
}

/// W→S, first message of a worker connection.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Register {
    /// Highest worker protocol version the worker speaks.
    pub protocol: u32,
    /// The worker token (`worker-token.txt` of the scheduler's data directory).
    #[serde(deserialize_with = "strict::text")]
    pub token: String,
    /// A name for logs and metrics (e.g. the pod name); made unique by the scheduler.
    #[serde(deserialize_with = "strict::text")]
    pub worker_id: String,
    /// The shapes of the model the worker serves; must match the site's.
    pub model: ModelInfo,
    /// The worker's measured profile.
    pub profile: ProfileWire,
    /// Largest batch the worker accepts (caps `profile.max_batch`).
    pub max_batch: u32,
    /// Edge or cloud.
    #[serde(deserialize_with = "strict::name")]
    pub tier: WorkerTier,
}

/// S→W, the worker is in the pool.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Registered {
    /// Worker protocol version the scheduler will speak.
    pub protocol: u32,
    /// The name the scheduler gave the engine instance.
    #[serde(deserialize_with = "strict::text")]
    pub engine: String,
    /// How often the worker sends `Heartbeat`, ms. About three missed ones remove it.
    pub heartbeat_ms: u32,
}

/// S→W, the registration was refused; the scheduler then closes the connection.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Refused {
    /// Why.
    #[serde(deserialize_with = "strict::text")]
    pub reason: String,
    /// Whether registering again later may succeed.
    pub retryable: bool,
}

/// W→S, on the registration stream every `heartbeat_ms`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Heartbeat {
    /// Batches the worker is running now (0 or 1).
    pub load: u32,
    /// Batches run since registration.
    pub batches: u64,
}

/// W→S, on the registration stream: the worker is stopping. It takes no new batch and finishes
/// the one it runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Drain {
    /// Why (e.g. `SIGTERM`).
    #[serde(deserialize_with = "strict::text")]
    pub reason: String,
}

/// One observation of a batch, already validated and decoded by the scheduler.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkRequest {
    /// Joint state, `f32 [state_dim]`.
    pub state: Tensor,
    /// Camera images (raw tensors, or the robot's encoded bytes).
    pub images: Vec<Image>,
    /// Task instruction.
    #[serde(deserialize_with = "strict::text")]
    pub instruction: String,
    /// Samples `S` to draw.
    pub samples: u32,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Guidance toward the actions the robot committed to (real-time chunking, a hard
    /// prefix); absent: plain sampling. An older worker ignores the key and samples plainly,
    /// so guidance needs workers of this version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub guidance: Option<WorkGuidance>,
}

/// A request's guidance on the wire (`kairos_engine_types::Guidance`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkGuidance {
    /// `rtc`, `rtc_vjp` or `inpaint`.
    #[serde(deserialize_with = "strict::name")]
    pub mode: ChunkingStrategy,
    /// The previous chunk from the capture on, `f32 [L × action_dim]` (flat: the worker's
    /// model knows its action width).
    pub prefix: Tensor,
    /// Actions the robot executes before the chunk arrives.
    pub delay: u32,
    /// Previous actions that guide the chunk.
    pub execution_horizon: u32,
    /// The weights beyond the committed actions.
    #[serde(deserialize_with = "strict::name")]
    pub schedule: PrefixSchedule,
    /// The cap on the guidance weight.
    pub max_guidance_weight: f32,
}

/// S→W, the only message on a batch stream: run these requests.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunBatch {
    /// The scheduler's batch id.
    pub batch_id: u64,
    /// How many times this batch id was sent before (0 first).
    pub attempt: u32,
    /// The scheduler stops waiting this long after sending, ms: an answer after it is dropped.
    pub deadline_ms: u32,
    /// The requests, in order.
    pub requests: Vec<WorkRequest>,
}

/// One generated chunk: `actions`, `noise` `f32 [S, N, D]`, `updates` `f32 [S, K, N, D]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkChunk {
    /// Final actions.
    pub actions: Tensor,
    /// Per-step updates.
    pub updates: Tensor,
    /// Initial noise.
    pub noise: Tensor,
}

/// The result of one request: a chunk, or the engine's error for it (exactly one is present).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkResult {
    /// The chunk.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chunk: Option<WorkChunk>,
    /// Why the engine produced none. Not retried by the scheduler.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// W→S, the answer on a batch stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Chunks {
    /// The batch id of the `RunBatch`.
    pub batch_id: u64,
    /// Its attempt.
    pub attempt: u32,
    /// Time the forward pass took on the worker, µs (the scheduler subtracts it from the
    /// end-to-end time to measure the round trip).
    pub compute_us: u64,
    /// One per request, in order.
    pub results: Vec<WorkResult>,
}

macro_rules! worker_body {
    ($($body:ident),*) => {$(
        impl WireBody for $body {
            const KIND: MessageKind = MessageKind::$body;
        }

        impl From<$body> for WorkerMessage {
            fn from(message: $body) -> WorkerMessage {
                WorkerMessage::$body(message)
            }
        }
    )*};
}
worker_body!(
    Register, Registered, Refused, Heartbeat, Drain, RunBatch, Chunks
);

/// Any worker protocol message.
#[derive(Clone, Debug, PartialEq)]
#[allow(clippy::large_enum_variant)] // built, sent and dropped; never stored in bulk
pub enum WorkerMessage {
    /// W→S, first message.
    Register(Register),
    /// S→W, accepted.
    Registered(Registered),
    /// S→W, refused.
    Refused(Refused),
    /// W→S, liveness and load.
    Heartbeat(Heartbeat),
    /// W→S, stopping.
    Drain(Drain),
    /// S→W, a batch.
    RunBatch(RunBatch),
    /// W→S, its answer.
    Chunks(Chunks),
}

impl WorkerMessage {
    /// The frame kind this message travels as.
    pub fn kind(&self) -> MessageKind {
        match self {
            WorkerMessage::Register(_) => MessageKind::Register,
            WorkerMessage::Registered(_) => MessageKind::Registered,
            WorkerMessage::Refused(_) => MessageKind::Refused,
            WorkerMessage::Heartbeat(_) => MessageKind::Heartbeat,
            WorkerMessage::Drain(_) => MessageKind::Drain,
            WorkerMessage::RunBatch(_) => MessageKind::RunBatch,
            WorkerMessage::Chunks(_) => MessageKind::Chunks,
        }
    }

    /// Decodes a frame's body as the worker message its kind names; a robot-protocol kind is
    /// refused.
    pub fn decode(frame: &Frame) -> Result<WorkerMessage, FrameError> {
        let kind = frame.kind;
        let body = &frame.body[..];
        Ok(match kind {
            MessageKind::Register => WorkerMessage::Register(decode_body(kind, body)?),
            MessageKind::Registered => WorkerMessage::Registered(decode_body(kind, body)?),
            MessageKind::Refused => WorkerMessage::Refused(decode_body(kind, body)?),
            MessageKind::Heartbeat => WorkerMessage::Heartbeat(decode_body(kind, body)?),
            MessageKind::Drain => WorkerMessage::Drain(decode_body(kind, body)?),
            MessageKind::RunBatch => WorkerMessage::RunBatch(decode_body(kind, body)?),
            MessageKind::Chunks => WorkerMessage::Chunks(decode_body(kind, body)?),
            other => {
                return Err(FrameError::Malformed {
                    kind: other,
                    reason: "a robot-protocol message on a worker stream".into(),
                });
            }
        })
    }

    /// The whole frame, header included, if the body is at most `max_body` bytes.
    pub fn encode(&self, max_body: u32) -> Result<Vec<u8>, super::EncodeError> {
        use super::encode_body;
        match self {
            WorkerMessage::Register(m) => encode_body(m, max_body),
            WorkerMessage::Registered(m) => encode_body(m, max_body),
            WorkerMessage::Refused(m) => encode_body(m, max_body),
            WorkerMessage::Heartbeat(m) => encode_body(m, max_body),
            WorkerMessage::Drain(m) => encode_body(m, max_body),
            WorkerMessage::RunBatch(m) => encode_body(m, max_body),
            WorkerMessage::Chunks(m) => encode_body(m, max_body),
        }
    }

    /// Parses and decodes the first frame of `bytes`; returns the message and the bytes it used.
    pub fn decode_from(bytes: &[u8], max_body: u32) -> Result<(WorkerMessage, usize), FrameError> {
        let mut cursor = std::io::Cursor::new(bytes);
        let frame = Frame::parse(&mut cursor, max_body)?;
        Ok((WorkerMessage::decode(&frame)?, cursor.position() as usize))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ImagePayload, Message};

    fn model() -> ModelInfo {
        ModelInfo {
            name: "m".into(),
            chunk_len: 4,
            action_dim: 2,
            state_dim: 3,
            steps: 2,
            max_images: 1,
            cameras: Vec::new(),
        }
    }

    fn samples() -> Vec<WorkerMessage> {
        let tensor = Tensor::from_f32(vec![3], &[1.0, 2.0, 3.0]).unwrap();
        vec![
            Register {
                protocol: 1,
                token: "kairos_worker_x".into(),
                worker_id: "w0".into(),
                model: model(),
                profile: ProfileWire {
                    model: "m".into(),
                    device: "cpu".into(),
                    points: vec![ProfilePointWire {
                        batch: 1,
                        latency_ms: 2.5,
                    }],
                    max_batch: 4,
                },
                max_batch: 4,
                tier: WorkerTier::Cloud,
            }
            .into(),
            Registered {
                protocol: 1,
                engine: "worker-w0".into(),
                heartbeat_ms: 500,
            }
            .into(),
            Refused {
                reason: "no".into(),
                retryable: false,
            }
            .into(),
            Heartbeat {
                load: 1,
                batches: 7,
            }
            .into(),
            Drain {
                reason: "SIGTERM".into(),
            }
            .into(),
            RunBatch {
                batch_id: 9,
                attempt: 1,
                deadline_ms: 2000,
                requests: vec![WorkRequest {
                    state: tensor.clone(),
                    images: vec![Image {
                        camera: "front".into(),
                        payload: ImagePayload::Raw {
                            tensor: Tensor::from_u8(vec![1, 1, 3], vec![1, 2, 3]).unwrap(),
                        },
                    }],
                    instruction: "pick".into(),
                    samples: 1,
                    seed: 42,
                    guidance: Some(WorkGuidance {
                        mode: ChunkingStrategy::Rtc,
                        prefix: tensor.clone(),
                        delay: 2,
                        execution_horizon: 10,
                        schedule: PrefixSchedule::Exp,
                        max_guidance_weight: 10.0,
                    }),
                }],
            }
            .into(),
            Chunks {
                batch_id: 9,
                attempt: 1,
                compute_us: 1234,
                results: vec![
                    WorkResult {
                        chunk: Some(WorkChunk {
                            actions: tensor.clone(),
                            updates: tensor.clone(),
                            noise: tensor,
                        }),
                        error: None,
                    },
                    WorkResult {
                        chunk: None,
                        error: Some("bad state".into()),
                    },
                ],
            }
            .into(),
        ]
    }

    #[test]
    fn every_worker_message_round_trips_and_robot_streams_refuse_them() {
        for message in samples() {
            let bytes = message.encode(1 << 20).unwrap();
            let (decoded, used) = WorkerMessage::decode_from(&bytes, 1 << 20).unwrap();
            assert_eq!(used, bytes.len());
            assert_eq!(decoded, message);
            // Every tier survives the wire, `auto` included.
            if let WorkerMessage::Register(register) = &message {
                for tier in [WorkerTier::Edge, WorkerTier::Cloud, WorkerTier::Auto] {
                    let with_tier = WorkerMessage::Register(Register {
                        tier,
                        ..register.clone()
                    });
                    let bytes = with_tier.encode(1 << 20).unwrap();
                    let (decoded, _) = WorkerMessage::decode_from(&bytes, 1 << 20).unwrap();
                    assert_eq!(decoded, with_tier);
                }
            }
            // The robot protocol's decoder refuses a worker frame ...
            assert!(matches!(
                Message::decode_from(&bytes, 1 << 20),
                Err(FrameError::Malformed { .. })
            ));
        }
        // ... and the worker decoder a robot frame.
        let hello = Message::Hello(crate::Hello {
            protocol: 1,
            token: "t".into(),
            client: "c".into(),
        })
        .encode(1 << 20)
        .unwrap();
        assert!(matches!(
            WorkerMessage::decode_from(&hello, 1 << 20),
            Err(FrameError::Malformed { .. })
        ));
    }

    #[test]
    fn strict_envelope_applies_to_worker_bodies() {
        // An unknown tier name and a truncated body are refused, not guessed.
        let mut register = samples().remove(0).encode(1 << 20).unwrap();
        let at = register
            .windows(5)
            .position(|w| w == b"cloud")
            .expect("tier in body");
        register[at..at + 5].copy_from_slice(b"cluod");
        assert!(WorkerMessage::decode_from(&register, 1 << 20).is_err());
        let chunks = samples().pop().unwrap().encode(1 << 20).unwrap();
        assert!(matches!(
            WorkerMessage::decode_from(&chunks[..chunks.len() - 1], 1 << 20),
            Err(FrameError::Truncated { .. })
        ));
        // A frame over the receiver's limit is refused before its body is read.
        assert!(matches!(
            WorkerMessage::decode_from(&chunks, 16),
            Err(FrameError::FrameTooLarge { .. })
        ));
    }
}
