//! Message bodies of protocol version 1.
//!
//! Field names are the MessagePack map keys. Timestamps on the client side are microseconds on
//! the client's own monotonic clock; the server maps them onto its clock with `sent_at_us`, so
//! robots need no clock synchronisation. Tensors are little-endian, row-major.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::limits::Limits;
use super::strict;

/// Frame kind byte of each message.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum MessageKind {
    /// C→S, first message of a connection.
    Hello = 0x01,
    /// S→C, answer to `Hello`.
    Welcome = 0x02,
    /// C→S, opens a round.
    Submit = 0x10,
    /// S→C, asks for a fresher observation of the round on the same stream.
    FetchObservation = 0x11,
    /// C→S, answer to `FetchObservation`.
    FreshObservation = 0x12,
    /// S→C, the round's action chunk.
    Reply = 0x13,
    /// C→S, ends a task explicitly (own stream).
    EndTask = 0x20,
    /// S→C, answer to `EndTask`: the task's record as the server saw it.
    TaskEnded = 0x21,
    /// W→S (worker protocol), first message of a worker connection.
    Register = 0x30,
    /// S→W (worker protocol), the worker is in the pool.
    Registered = 0x31,
    /// S→W (worker protocol), the registration was refused.
    Refused = 0x32,
    /// W→S (worker protocol), liveness and load.
    Heartbeat = 0x33,
    /// W→S (worker protocol), the worker is stopping.
    Drain = 0x34,
    /// S→W (worker protocol), a batch to run, on its own stream.
    RunBatch = 0x35,
    /// W→S (worker protocol), the batch's chunks.
    Chunks = 0x36,
    /// S→C, the request on this stream failed.
    Error = 0x7F,
}

impl MessageKind {
    /// Every kind, in wire-byte order: the robot protocol's, then the worker protocol's
    /// (`protocol::worker`).
    pub const ALL: [MessageKind; 16] = [
        MessageKind::Hello,
        MessageKind::Welcome,
        MessageKind::Submit,
        MessageKind::FetchObservation,
        MessageKind::FreshObservation,
        MessageKind::Reply,
        MessageKind::EndTask,
        MessageKind::TaskEnded,
        MessageKind::Register,
        MessageKind::Registered,
        MessageKind::Refused,
        MessageKind::Heartbeat,
        MessageKind::Drain,
        MessageKind::RunBatch,
        MessageKind::Chunks,
        MessageKind::Error,
    ];

    /// The kind a frame's first byte names, or `None` for a byte protocol v1 does not define.
    pub fn from_byte(byte: u8) -> Option<MessageKind> {
        MessageKind::ALL
            .into_iter()
            .find(|kind| *kind as u8 == byte)
    }

    /// The message name as `docs/PROTOCOL.md` spells it.
    pub fn name(self) -> &'static str {
        match self {
            MessageKind::Hello => "Hello",
            MessageKind::Welcome => "Welcome",
            MessageKind::Submit => "Submit",
            MessageKind::FetchObservation => "FetchObservation",
            MessageKind::FreshObservation => "FreshObservation",
            MessageKind::Reply => "Reply",
            MessageKind::EndTask => "EndTask",
            MessageKind::TaskEnded => "TaskEnded",
            MessageKind::Register => "Register",
            MessageKind::Registered => "Registered",
            MessageKind::Refused => "Refused",
            MessageKind::Heartbeat => "Heartbeat",
            MessageKind::Drain => "Drain",
            MessageKind::RunBatch => "RunBatch",
            MessageKind::Chunks => "Chunks",
            MessageKind::Error => "Error",
        }
    }
}

impl std::fmt::Display for MessageKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} (0x{:02x})", self.name(), *self as u8)
    }
}

/// Element types of a [`Tensor`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    /// 32-bit IEEE float.
    F32,
    /// 16-bit IEEE float.
    F16,
    /// bfloat16.
    Bf16,
    /// Unsigned byte.
    U8,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F32 => 4,
            DType::F16 | DType::Bf16 => 2,
            DType::U8 => 1,
        }
    }
}

/// A dense tensor: `data.len() == shape.product() * dtype.size()`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tensor {
    /// Element type.
    #[serde(deserialize_with = "strict::name")]
    pub dtype: DType,
    /// Dimensions, outermost first.
    pub shape: Vec<u32>,
    /// Little-endian, row-major elements.
    #[serde(with = "strict::bin")]
    pub data: Vec<u8>,
}

/// How a camera image travels.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "encoding", rename_all = "lowercase")]
pub enum ImagePayload {
    /// JPEG file bytes.
    Jpeg {
        /// The file.
        #[serde(with = "strict::bin")]
        data: Vec<u8>,
    },
    /// PNG file bytes.
    Png {
        /// The file.
        #[serde(with = "strict::bin")]
        data: Vec<u8>,
    },
    /// Raw pixels `[height, width, channels]`, dtype `u8` or `f32`.
    Raw {
        /// The pixels.
        tensor: Tensor,
    },
}

/// The wire form of [`ImagePayload`], read field by field: serde's internally tagged enums
/// would accept the `encoding` tag as a variant index or as `bin`, and buffer the image bytes
/// once more before decoding them.
#[derive(Deserialize)]
struct PayloadWire {
    #[serde(deserialize_with = "strict::name")]
    encoding: PayloadEncoding,
    #[serde(default, deserialize_with = "strict::opt_bin")]
    data: Option<Vec<u8>>,
    #[serde(default)]
    tensor: Option<Tensor>,
}

#[derive(Deserialize)]
#[serde(rename_all = "lowercase")]
enum PayloadEncoding {
    Jpeg,
    Png,
    Raw,
}

impl<'de> Deserialize<'de> for ImagePayload {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let wire = PayloadWire::deserialize(deserializer)?;
        let data = |data: Option<Vec<u8>>| data.ok_or_else(|| D::Error::missing_field("data"));
        Ok(match wire.encoding {
            PayloadEncoding::Jpeg => ImagePayload::Jpeg {
                data: data(wire.data)?,
            },
            PayloadEncoding::Png => ImagePayload::Png {
                data: data(wire.data)?,
            },
            PayloadEncoding::Raw => ImagePayload::Raw {
                tensor: wire
                    .tensor
                    .ok_or_else(|| D::Error::missing_field("tensor"))?,
            },
        })
    }
}

/// One named camera image.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Camera name, e.g. `front`, `wrist`.
    #[serde(deserialize_with = "strict::text")]
    pub camera: String,
    /// The pixels.
    pub payload: ImagePayload,
}

/// What the robot sees at one instant.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    /// Client clock, µs, when this observation was captured.
    pub captured_at_us: u64,
    /// Joint state vector, 1-D `f32`.
    pub state: Tensor,
    /// Camera images.
    pub images: Vec<Image>,
    /// Task instruction text.
    #[serde(deserialize_with = "strict::text")]
    pub instruction: String,
}

/// Last Exec Info (paper §4): the execution phase running when this round was requested.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LastExecInfo {
    /// Client clock, µs, when the robot started executing the previous chunk.
    pub exec_started_at_us: u64,
    /// Actions of that chunk not yet executed when this request was sent.
    pub actions_remaining: u32,
    /// Control frequency, actions per second.
    pub control_hz: f32,
    /// The round whose chunk this is, so the server knows which of its replies the robot is
    /// executing (the committed actions a chunking strategy plans around). Absent from older
    /// clients: the server then assumes the task's last reply.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round: Option<u64>,
    /// The actual `d` of that round: actions the robot executed between the capture of the
    /// round's observation and the arrival of its chunk. The server compares it with the `d` it
    /// predicted (`Reply::delay`); absent, it estimates it from the timestamps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub delay: Option<u32>,
}

/// What the server does about the actions a robot executes while its round is in flight
/// (docs/PROTOCOL.md §12, "Chunking strategies").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChunkingStrategy {
    /// The chunk is planned from the observation; the robot skips the actions whose time passed.
    Skip,
    /// The chunk is planned from the observation and executed from its first action on arrival.
    FromStart,
    /// The chunk is planned from the state the robot will have on arrival (rolled forward
    /// through its committed actions, or the robot's own forecast).
    ArrivalState,
    /// Real-time chunking as LeRobot 0.6.1 has it (`RTCProcessor.denoise_step`, whose
    /// vector–Jacobian product is the identity).
    Rtc,
    /// Real-time chunking with the true vector–Jacobian product through the velocity network
    /// (the paper's guidance); only on model paths with autograd.
    RtcVjp,
    /// A hard prefix: the committed actions are written into the sample at every step.
    Inpaint,
    /// LeRobot's blend of the overlap, 0.3 × previous chunk + 0.7 × new chunk, on the server.
    Ensemble,
}

impl ChunkingStrategy {
    /// Every strategy, in the order docs/PROTOCOL.md lists them.
    pub const ALL: [ChunkingStrategy; 7] = [
        ChunkingStrategy::Skip,
        ChunkingStrategy::FromStart,
        ChunkingStrategy::ArrivalState,
        ChunkingStrategy::Rtc,
        ChunkingStrategy::RtcVjp,
        ChunkingStrategy::Inpaint,
        ChunkingStrategy::Ensemble,
    ];

    /// The name on the wire (`snake_case`).
    pub fn as_str(self) -> &'static str {
        match self {
            ChunkingStrategy::Skip => "skip",
            ChunkingStrategy::FromStart => "from_start",
            ChunkingStrategy::ArrivalState => "arrival_state",
            ChunkingStrategy::Rtc => "rtc",
            ChunkingStrategy::RtcVjp => "rtc_vjp",
            ChunkingStrategy::Inpaint => "inpaint",
            ChunkingStrategy::Ensemble => "ensemble",
        }
    }

    /// The strategy named `name` (its wire name).
    pub fn from_name(name: &str) -> Option<ChunkingStrategy> {
        ChunkingStrategy::ALL
            .into_iter()
            .find(|s| s.as_str() == name)
    }
}

impl std::fmt::Display for ChunkingStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How real-time chunking weighs the previous chunk's actions beyond the committed ones
/// (LeRobot 0.6.1's `RTCAttentionSchedule`, `get_prefix_weights`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PrefixSchedule {
    /// Weight 1 on the committed actions, 0 after.
    Zeros,
    /// Weight 1 up to the execution horizon, 0 after.
    Ones,
    /// 1 on the committed actions, then falling linearly to 0 at the execution horizon.
    Linear,
    /// As `Linear`, shaped by `w · expm1(w) / (e − 1)`.
    Exp,
}

impl PrefixSchedule {
    /// The name on the wire.
    pub fn as_str(self) -> &'static str {
        match self {
            PrefixSchedule::Zeros => "zeros",
            PrefixSchedule::Ones => "ones",
            PrefixSchedule::Linear => "linear",
            PrefixSchedule::Exp => "exp",
        }
    }

    /// The schedule named `name`.
    pub fn from_name(name: &str) -> Option<PrefixSchedule> {
        [
            PrefixSchedule::Zeros,
            PrefixSchedule::Ones,
            PrefixSchedule::Linear,
            PrefixSchedule::Exp,
        ]
        .into_iter()
        .find(|s| s.as_str() == name)
    }
}

/// `Submit.chunking`: the round's chunking strategy and its settings; absent settings take the
/// server's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChunkingSelection {
    /// The strategy.
    #[serde(deserialize_with = "strict::name")]
    pub strategy: ChunkingStrategy,
    /// `rtc`, `rtc_vjp`: the prefix schedule.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "strict::opt_name"
    )]
    pub schedule: Option<PrefixSchedule>,
    /// `rtc`, `rtc_vjp`: the most the guidance weight may reach (LeRobot's
    /// `max_guidance_weight`), finite and > 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_guidance_weight: Option<f32>,
    /// `rtc`, `rtc_vjp`: how many of the previous chunk's actions guide the new one (LeRobot's
    /// `execution_horizon`), ≥ 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execution_horizon: Option<u32>,
    /// `arrival_state`: the robot's own forecast of its state, `f32` `[M, state_dim]`: row `j`
    /// is the state after it executes `j + 1` more of its committed actions. The server takes
    /// the row of the `d` it predicts (the observed state for `d = 0`, the last row past `M`).
    /// Absent: the server rolls the state forward itself, which only a model whose actions are
    /// absolute position targets allows.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forecast: Option<Tensor>,
}

impl ChunkingSelection {
    /// `strategy` with the server's settings.
    pub fn new(strategy: ChunkingStrategy) -> ChunkingSelection {
        ChunkingSelection {
            strategy,
            schedule: None,
            max_guidance_weight: None,
            execution_horizon: None,
            forecast: None,
        }
    }
}

/// Which horizon policy to apply to this round's chunk, with its parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HorizonSelection {
    /// Policy name: `threshold` (default, §3.1), `static`, or a loaded plugin's name.
    #[serde(deserialize_with = "strict::text")]
    pub policy: String,
    /// Parameters, e.g. `{"t": 0.4, "h_min": 8}` or `{"h": 10}`.
    #[serde(default, deserialize_with = "strict::text_keyed_f64")]
    pub params: BTreeMap<String, f64>,
    /// Samples of the chunk to draw for the policy (1 = none extra).
    #[serde(default = "one")]
    pub samples: u32,
}

fn one() -> u32 {
    1
}

/// The client's estimate of the work its task has left.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RemainingHint {
    /// Rounds left, this one included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rounds: Option<u32>,
    /// Seconds of execution left.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f32>,
}

/// C→S: first message of a connection.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    /// Highest protocol version the client speaks.
    pub protocol: u32,
    /// The robot's auth token.
    #[serde(deserialize_with = "strict::text")]
    pub token: String,
    /// Client software, e.g. `kairos-sdk/0.1.0`.
    #[serde(deserialize_with = "strict::text")]
    pub client: String,
}

/// S→C: the connection is authenticated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    /// Protocol version the server will speak on this connection.
    pub protocol: u32,
    /// Server software, e.g. `kairos/0.1.0`.
    #[serde(deserialize_with = "strict::text")]
    pub server: String,
    /// The robot name the token belongs to.
    #[serde(deserialize_with = "strict::text")]
    pub robot: String,
    /// What the served model expects and returns.
    pub model: ModelInfo,
    /// Size limits the server enforces.
    pub limits: Limits,
}

/// The served model's shapes, so a client can validate before sending.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelInfo {
    /// Model name.
    #[serde(deserialize_with = "strict::text")]
    pub name: String,
    /// Actions per chunk `N`.
    pub chunk_len: u32,
    /// Action dimension `D`.
    pub action_dim: u32,
    /// Expected state length.
    pub state_dim: u32,
    /// Flow-matching steps `K`.
    pub steps: u32,
    /// Most images per observation.
    pub max_images: u32,
    /// The model's camera names, in its order, when it matches images by name
    /// (`Image::camera`; a robot should name its cameras so); absent or empty: images are
    /// matched by position and their names are not read.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<String>,
}

/// C→S: a round request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Submit {
    /// Task id, chosen by the client; the first robot to use it owns it.
    pub task: u64,
    /// Round id: strictly increasing within a task. Resending the same id after a reconnect
    /// attaches to the round in progress (or returns its reply) instead of running it twice.
    pub round: u64,
    /// Client clock, µs, when this message was sent.
    pub sent_at_us: u64,
    /// The observation.
    pub observation: Observation,
    /// The execution phase running at send time; absent on a task's first round.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_exec: Option<LastExecInfo>,
    /// The horizon policy; absent = the server's default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizon: Option<HorizonSelection>,
    /// Remaining-work hint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub remaining: Option<RemainingHint>,
    /// How many times this round was sent before, on this or an earlier connection (0 on the
    /// first send). Informational: the server dedups by `round`, never by `attempt`.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub attempt: u32,
    /// The robot's control rate, Hz, when the client knows it. The server's idle clock waits
    /// for the chunk it answers to execute (`H / control_hz`), and on a task's first round there
    /// is no `last_exec` to take the rate from. `last_exec.control_hz` wins when both are sent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub control_hz: Option<f32>,
    /// Seed of the round's sampler noise, when the client wants to choose it (reproducible
    /// evaluation: `kairos bench horizon --live` sends the noise its in-process mode draws);
    /// absent = derived by the server from `task` and `round`. A resent round sends the same
    /// seed, so it reproduces its chunk either way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// The chunking strategy (docs/PROTOCOL.md §12); absent = the server's default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub chunking: Option<ChunkingSelection>,
}

fn is_zero(value: &u32) -> bool {
    *value == 0
}

/// S→C: send a fresher observation for this round before it is dispatched.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FetchObservation {
    /// The task.
    pub task: u64,
    /// The round.
    pub round: u64,
    /// How old the server judged the queued observation, µs.
    pub age_us: u64,
}

/// C→S: the fresher observation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FreshObservation {
    /// Client clock, µs, when this message was sent.
    pub sent_at_us: u64,
    /// The new observation.
    pub observation: Observation,
}

/// Server-side timing of one round, µs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// From arrival to dispatch.
    pub queue_us: u64,
    /// Re-fetching a stale observation (0 if none).
    pub refetch_us: u64,
    /// The forward pass, whole batch.
    pub inference_us: u64,
    /// From arrival to reply sent.
    pub total_us: u64,
    /// Requests in the batch this round ran in.
    pub batch_size: u32,
}

/// S→C: the round's actions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reply {
    /// The task.
    pub task: u64,
    /// The round.
    pub round: u64,
    /// Execution horizon `H`: actions the robot may execute before its next chunk is due.
    pub horizon: u32,
    /// Chunk length `N` the model generated (the reply carries `H` of them).
    pub chunk_len: u32,
    /// The first `H` actions, `f32` `[H, D]`.
    pub actions: Tensor,
    /// Name of the horizon policy that chose `H` (it can differ from the one requested if
    /// that one failed and the fallback answered).
    #[serde(deserialize_with = "strict::text")]
    pub policy: String,
    /// Server-side timing.
    pub timing: Timing,
    /// The index of `actions` the server predicts the robot executes when the reply arrives:
    /// the actions it executes between the observation's capture and the arrival (the
    /// predicted `d`, less any the robot would have run out of). Action `i` still belongs to
    /// `i` control steps after the capture, whatever the strategy (§12). Absent from older
    /// servers.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<u32>,
    /// The predicted `d`: control steps from the observation's capture to the reply's arrival.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub delay: Option<u32>,
    /// The chunking strategy that made the chunk (its wire name; text, so an older client
    /// reads a newer server's strategies).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "strict::opt_text"
    )]
    pub chunking: Option<String>,
}

/// C→S: the task is over.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EndTask {
    /// The task.
    pub task: u64,
    /// `done` or `failed`.
    #[serde(deserialize_with = "strict::name")]
    pub outcome: TaskOutcome,
    /// Client clock, µs, when this message was sent.
    pub sent_at_us: u64,
    /// The last execution phase, so the server can close the task's final E interval.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_exec: Option<LastExecInfo>,
}

/// How the robot says a task ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TaskOutcome {
    /// Finished.
    Done,
    /// Gave up.
    Failed,
}

/// One closed interval on the client's clock, µs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct IntervalUs {
    /// Start.
    pub start_us: u64,
    /// End.
    pub end_us: u64,
}

/// One round of a task's record, as the server reconstructed it (client clock, µs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RoundRecordWire {
    /// Round id.
    pub round: u64,
    /// Generation interval `G`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub generation: Option<IntervalUs>,
    /// Execution interval `E`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execution: Option<IntervalUs>,
    /// Horizon chosen.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizon: Option<u32>,
}

/// S→C: the task's record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskEnded {
    /// The task.
    pub task: u64,
    /// Rounds answered.
    pub rounds: u32,
    /// Σ W_j, µs.
    pub wait_us: u64,
    /// Σ |G_j|, µs.
    pub attained_service_us: u64,
    /// The most recent rounds (bounded by the server's history size).
    pub history: Vec<RoundRecordWire>,
}

/// Error codes on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The frame could not be parsed (truncated, bad kind, bad MessagePack).
    BadFrame,
    /// A field violates a size limit.
    TooLarge,
    /// The observation does not fit the model (shape, dtype, state length, image count).
    InvalidObservation,
    /// Another field is invalid (horizon parameters, exec info...).
    InvalidRequest,
    /// The protocol version is not supported.
    UnsupportedVersion,
    /// The token is unknown.
    Unauthorized,
    /// Reserved: the task belongs to another robot. Servers of this version answer
    /// `UnknownTask` instead, so that the answer does not reveal which task ids exist.
    Forbidden,
    /// The task is not open for this robot: unknown, ended, or another robot's.
    UnknownTask,
    /// The round id is not after the task's last one.
    RoundOutOfOrder,
    /// The horizon policy named is not loaded.
    UnknownPolicy,
    /// The server is at capacity; retry later.
    Overloaded,
    /// Generation failed.
    Internal,
    /// The server is shutting down.
    ShuttingDown,
    /// The request's frame arrived slower than the server's minimum upload rate; the server
    /// stopped reading the stream. Retryable: a faster link may succeed.
    TooSlow,
}

/// S→C: the request on this stream failed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorReply {
    /// Machine-readable code.
    #[serde(deserialize_with = "strict::name")]
    pub code: ErrorCode,
    /// Human-readable explanation.
    #[serde(deserialize_with = "strict::text")]
    pub message: String,
    /// Whether sending the same request again may succeed.
    pub retryable: bool,
    /// For `overloaded`: how long the client should wait before retrying, ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retry_after_ms: Option<u32>,
}

impl ErrorReply {
    /// An error with the code's default retryability ([`ErrorCode::is_retryable`]).
    pub fn new(code: ErrorCode, message: impl Into<String>) -> ErrorReply {
        ErrorReply {
            code,
            message: message.into(),
            retryable: code.is_retryable(),
            retry_after_ms: None,
        }
    }
}

impl ErrorCode {
    /// Whether the same request may succeed if sent again later: `overloaded`, `shutting_down`
    /// (another server or a restarted one may answer), `internal` (a failed generation) and
    /// `too_slow` (a faster link may deliver it).
    /// Every other code describes the request itself, which will fail the same way again.
    pub fn is_retryable(self) -> bool {
        matches!(
            self,
            ErrorCode::Overloaded
                | ErrorCode::ShuttingDown
                | ErrorCode::Internal
                | ErrorCode::TooSlow
        )
    }

    /// The code as it appears on the wire (`snake_case`).
    pub fn as_str(self) -> &'static str {
        match self {
            ErrorCode::BadFrame => "bad_frame",
            ErrorCode::TooLarge => "too_large",
            ErrorCode::InvalidObservation => "invalid_observation",
            ErrorCode::InvalidRequest => "invalid_request",
            ErrorCode::UnsupportedVersion => "unsupported_version",
            ErrorCode::Unauthorized => "unauthorized",
            ErrorCode::Forbidden => "forbidden",
            ErrorCode::UnknownTask => "unknown_task",
            ErrorCode::RoundOutOfOrder => "round_out_of_order",
            ErrorCode::UnknownPolicy => "unknown_policy",
            ErrorCode::Overloaded => "overloaded",
            ErrorCode::Internal => "internal",
            ErrorCode::ShuttingDown => "shutting_down",
            ErrorCode::TooSlow => "too_slow",
        }
    }
}

impl std::fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}
