//! Wire messages → `Valid*` types, and every internal error → one wire error.
//!
//! Two layers of checks run on every request before it reaches the driver:
//! 1. the protocol's own ([`Validate`], in the SDK): sizes against [`Limits`], tensor byte
//!    lengths, a 1-D `f32` state, finite numbers, `control_hz > 0`;
//! 2. the served model's (here): state length, image count, raw image channels, the horizon
//!    policy (registered, parameters valid, samples within the limit), and client timestamps that
//!    are consistent with each other.
//!
//! Client timestamps are microseconds on the robot's own monotonic clock. Each message carries
//! `sent_at_us`; the server maps the robot's clock onto its own with an offset estimated per
//! connection by [`ClockEstimator`]: `offset = min(server_read − sent_at_us) − RTT/2` over the
//! connection's most recent first-attempt messages, where RTT is quinn's smoothed estimate.
//! `server_read − sent_at_us` is the true offset plus that message's one-way delay (network,
//! queueing, server scheduling); the minimum over a window picks the least delayed message, and
//! half the RTT stands in for its network delay. Robots need no clock synchronisation; the
//! mapping error is the least-delayed message's deviation from RTT/2 — tens of microseconds on
//! loopback, of the order of the jitter on Wi-Fi — and does not grow when the server is busy.
//! Re-sent rounds (after a reconnect) keep their first `sent_at_us`, so they never feed the
//! estimate. The window (32 messages) bounds the effect of clock drift between the two machines.
//!
//! [`RequestError`] is the one error type a connection task answers with; `From<&RequestError>
//! for ErrorReply` is the one place that picks wire codes.

use std::time::Duration;

use kairos_engine::image_features::{self, ImageLimits};
use kairos_engine::{
    ActionRequest, EngineError, ImageFormat, ImageInput, InputError, MAX_SAMPLES, ModelSpec,
};
use kairos_sdk::protocol::{
    DType, EndTask, ErrorCode, ErrorReply, FrameError, FreshObservation, Hello, ImagePayload,
    LastExecInfo, Limits, Observation, PROTOCOL_VERSION, Submit, TaskOutcome, Validate,
    ValidationError,
};

use crate::action::{ActionManager, PolicyLookupError, RoundPolicy};
use crate::pool::PoolError;
use crate::scheduler::{
    AdmitError, ExecReport, RemainingWork, RobotId, RoundSubmit, TaskEnd, TaskId,
};
use crate::time::{Timestamp, duration_micros};

/// Maps one robot's clock onto the server's, for one request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ClockMap {
    /// `server_us − client_us`.
    offset_us: i128,
}

impl ClockMap {
    /// The mapping implied by a request sent at `sent_at_us` (client clock) and read at
    /// `server_now`, over a connection whose round trip is `rtt`.
    pub fn new(server_now: Timestamp, sent_at_us: u64, rtt: Duration) -> ClockMap {
        let sent_on_server =
            i128::from(server_now.as_micros()) - i128::from(duration_micros(rtt) / 2);
        ClockMap {
            offset_us: sent_on_server - i128::from(sent_at_us),
        }
    }

    /// A client time on the server clock (clamped to the server's epoch).
    pub fn to_server(&self, client_us: u64) -> Timestamp {
        let server = i128::from(client_us) + self.offset_us;
        Timestamp::from_micros(u64::try_from(server.max(0)).unwrap_or(u64::MAX))
    }

    /// A server time on the client clock (clamped to the client's zero).
    pub fn to_client(&self, t: Timestamp) -> u64 {
        let client = i128::from(t.as_micros()) - self.offset_us;
        u64::try_from(client.max(0)).unwrap_or(u64::MAX)
    }
}

/// Estimates one connection's clock offset from the messages it sends (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct ClockEstimator {
    /// `server_read − sent_at` of the most recent first-attempt messages, µs.
    samples: std::collections::VecDeque<i128>,
}

impl ClockEstimator {
    /// Messages the estimate is the minimum over.
    pub const WINDOW: usize = 32;

    /// Records a message sent at `sent_at_us` (client clock) and read at `server_now`, and returns
    /// the mapping to use for it. `first_attempt` is false for a re-sent round, whose `sent_at_us`
    /// is its first send's: it is mapped with the current estimate and does not change it (unless
    /// there is none yet).
    pub fn observe(
        &mut self,
        server_now: Timestamp,
        sent_at_us: u64,
        rtt: Duration,
        first_attempt: bool,
    ) -> ClockMap {
        let sample = i128::from(server_now.as_micros()) - i128::from(sent_at_us);
        let half_rtt = i128::from(duration_micros(rtt) / 2);
        if first_attempt || self.samples.is_empty() {
            if self.samples.len() >= Self::WINDOW {
                self.samples.pop_front();
            }
            self.samples.push_back(sample);
        }
        let best = self.samples.iter().copied().min().unwrap_or(sample);
        ClockMap {
            offset_us: best - half_rtt,
        }
    }
}

/// An observation that fits the served model, on the server clock.
#[derive(Clone, Debug, PartialEq)]
pub struct ValidObservation {
    /// When it was captured.
    pub captured_at: Timestamp,
    /// The model input (`samples` and `seed` are set per round).
    pub request: ActionRequest,
}

/// A round request that passed every check.
#[derive(Debug)]
pub struct ValidSubmit {
    /// What the scheduler sees.
    pub round: RoundSubmit,
    /// The observation.
    pub observation: ValidObservation,
    /// The horizon policy, built.
    pub policy: RoundPolicy,
    /// Samples to draw.
    pub samples: usize,
    /// The robot's control frequency, if this request reported it.
    pub control_hz: Option<f32>,
    /// This request's clock mapping.
    pub clock: ClockMap,
}

/// An `EndTask` that passed every check.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValidEndTask {
    /// The task.
    pub task: TaskId,
    /// How it ended.
    pub end: TaskEnd,
    /// The final execution phase.
    pub exec: Option<ExecReport>,
    /// When the message was sent, on the server clock.
    pub sent_at: Timestamp,
    /// Its clock mapping.
    pub clock: ClockMap,
}

/// What a request is checked against.
pub struct Validator {
    /// The served model's shapes.
    pub spec: ModelSpec,
    /// The limits announced in `Welcome`.
    pub limits: Limits,
}

/// Every way a request can fail, from the first byte to the reply.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    /// The bytes are not a valid frame or message.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// A field breaks the protocol's limits or rules.
    #[error(transparent)]
    Protocol(#[from] ValidationError),
    /// The observation does not fit the served model.
    #[error("invalid observation: {field}: {reason}")]
    Observation {
        /// Which field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// Another field is inconsistent.
    #[error("invalid request: {field}: {reason}")]
    Invalid {
        /// Which field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A message of the wrong kind at this point of the exchange.
    #[error("unexpected {got} message, expected {expected}")]
    UnexpectedMessage {
        /// What the exchange needs here.
        expected: &'static str,
        /// What arrived.
        got: String,
    },
    /// The horizon policy is unknown or its parameters are invalid.
    #[error(transparent)]
    Policy(#[from] PolicyLookupError),
    /// The scheduler refused the request.
    #[error(transparent)]
    Admit(#[from] AdmitError),
    /// The client speaks no protocol version this server does.
    #[error("protocol version {0} is not supported (this server speaks {PROTOCOL_VERSION})")]
    UnsupportedVersion(u32),
    /// The token matches no configured robot.
    #[error("unknown token")]
    Unauthorized,
    /// A pending request was replaced by a newer round of its task.
    #[error("round {round} was superseded by round {by}")]
    Superseded {
        /// The replaced round.
        round: u64,
        /// The newer round.
        by: u64,
    },
    /// Generation failed.
    #[error(transparent)]
    Engine(#[from] PoolError),
    /// The horizon policy and its fallback both failed.
    #[error("{0}")]
    Internal(String),
    /// The server is draining.
    #[error("the server is shutting down")]
    ShuttingDown,
    /// The request's frame arrived slower than `[connections] min_upload_bytes_per_s`
    /// (the reason says how slow).
    #[error("{0}")]
    TooSlow(String),
}

impl RequestError {
    /// The wire code.
    pub fn code(&self) -> ErrorCode {
        match self {
            RequestError::Frame(e) => e.code(),
            RequestError::Protocol(e) => e.code(),
            RequestError::Observation { .. } => ErrorCode::InvalidObservation,
            RequestError::Invalid { .. } => ErrorCode::InvalidRequest,
            RequestError::UnexpectedMessage { .. } => ErrorCode::BadFrame,
            RequestError::Policy(PolicyLookupError::Unknown { .. }) => ErrorCode::UnknownPolicy,
            RequestError::Policy(PolicyLookupError::Params { .. }) => ErrorCode::InvalidRequest,
            RequestError::Admit(e) => match e {
                AdmitError::Overloaded { .. } => ErrorCode::Overloaded,
                // One answer for all three, so a robot cannot learn which ids other robots use.
                AdmitError::Forbidden { .. }
                | AdmitError::UnknownTask { .. }
                | AdmitError::TaskEnded { .. } => ErrorCode::UnknownTask,
                AdmitError::RoundOutOfOrder { .. } | AdmitError::RoundInProgress { .. } => {
                    ErrorCode::RoundOutOfOrder
                }
                AdmitError::InvalidExecInfo(_) => ErrorCode::InvalidRequest,
            },
            RequestError::UnsupportedVersion(_) => ErrorCode::UnsupportedVersion,
            RequestError::Unauthorized => ErrorCode::Unauthorized,
            RequestError::Superseded { .. } => ErrorCode::RoundOutOfOrder,
            // A request the model refused is the request's fault (defence in depth: validation
            // checks everything the engine would refuse); any other engine failure is ours.
            RequestError::Engine(PoolError::Engine {
                source: EngineError::InvalidInput(_),
                ..
            }) => ErrorCode::InvalidObservation,
            RequestError::Engine(_) | RequestError::Internal(_) => ErrorCode::Internal,
            RequestError::ShuttingDown => ErrorCode::ShuttingDown,
            RequestError::TooSlow(_) => ErrorCode::TooSlow,
        }
    }
}

/// How long an overloaded client is asked to wait before retrying.
pub const OVERLOADED_RETRY_AFTER_MS: u32 = 50;

/// The text of every refusal that concerns a task the robot may not use, whether the id is
/// unknown, ended, or another robot's: one text (and one code, `unknown_task`), so that the
/// answer does not tell a robot which task ids exist.
pub fn task_not_open_message(task: TaskId) -> String {
    format!(
        "task {} is not open for this robot (unknown, ended, or another robot's)",
        task.0
    )
}

impl From<&RequestError> for ErrorReply {
    fn from(error: &RequestError) -> ErrorReply {
        let message = match error {
            RequestError::Admit(
                AdmitError::Forbidden { task }
                | AdmitError::UnknownTask { task }
                | AdmitError::TaskEnded { task },
            ) => task_not_open_message(*task),
            other => other.to_string(),
        };
        let mut reply = ErrorReply::new(error.code(), message);
        if matches!(error, RequestError::Admit(AdmitError::Overloaded { .. })) {
            reply.retry_after_ms = Some(OVERLOADED_RETRY_AFTER_MS);
        }
        reply
    }
}

fn observation_error(field: impl Into<String>, reason: impl Into<String>) -> RequestError {
    RequestError::Observation {
        field: field.into(),
        reason: reason.into(),
    }
}

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> RequestError {
    RequestError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

/// The seed of a round's initial noise: a fixed mix of task and round, so a retried round
/// reproduces its chunk.
pub fn round_seed(task: u64, round: u64) -> u64 {
    fn splitmix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    splitmix(task ^ splitmix(round))
}

impl Validator {
    /// Checks `Hello`'s fields and version (the token is checked by the caller).
    pub fn hello(&self, hello: &Hello) -> Result<u32, RequestError> {
        hello.validate(&self.limits)?;
        if hello.protocol < PROTOCOL_VERSION {
            return Err(RequestError::UnsupportedVersion(hello.protocol));
        }
        Ok(PROTOCOL_VERSION)
    }

    /// Checks a round request and builds its horizon policy.
    pub fn submit(
        &self,
        submit: Submit,
        robot: RobotId,
        actions: &ActionManager,
        clock: ClockMap,
    ) -> Result<ValidSubmit, RequestError> {
        submit.validate(&self.limits)?;
        let observation = self.observation(submit.observation, submit.sent_at_us, &clock)?;
        let last_exec = submit
            .last_exec
            .map(|e| exec_report(&e, submit.sent_at_us, &clock))
            .transpose()?;
        let (policy, samples) = match &submit.horizon {
            Some(h) => (
                actions.build(Some(&h.policy), Some(&h.params))?,
                h.samples as usize,
            ),
            None => (actions.build(None, None)?, 1),
        };
        if samples > MAX_SAMPLES {
            return Err(invalid(
                "horizon.samples",
                format!("{samples}, the engine draws at most {MAX_SAMPLES}"),
            ));
        }
        let mut observation = observation;
        observation.request.samples = samples;
        // The client's own sampler seed when it sent one (reproducible evaluation), else the
        // fixed mix of task and round.
        observation.request.seed = submit
            .seed
            .unwrap_or_else(|| round_seed(submit.task, submit.round));
        Ok(ValidSubmit {
            round: RoundSubmit {
                task: TaskId(submit.task),
                robot,
                round: submit.round,
                sent_at: clock.to_server(submit.sent_at_us),
                obs_captured_at: observation.captured_at,
                last_exec,
                remaining: submit.remaining.map(|r| RemainingWork {
                    rounds: r.rounds,
                    seconds: r.seconds,
                }),
                control_hz: submit.control_hz,
            },
            observation,
            policy,
            samples,
            control_hz: submit.last_exec.map(|e| e.control_hz).or(submit.control_hz),
            clock,
        })
    }

    /// Checks a re-fetched observation. `samples` and `seed` are left for the caller to copy from
    /// the queued one.
    pub fn fresh(
        &self,
        fresh: FreshObservation,
        clock: ClockMap,
    ) -> Result<ValidObservation, RequestError> {
        fresh.validate(&self.limits)?;
        self.observation(fresh.observation, fresh.sent_at_us, &clock)
    }

    /// Checks an `EndTask`.
    pub fn end_task(&self, end: EndTask, clock: ClockMap) -> Result<ValidEndTask, RequestError> {
        end.validate(&self.limits)?;
        let exec = end
            .last_exec
            .map(|e| exec_report(&e, end.sent_at_us, &clock))
            .transpose()?;
        Ok(ValidEndTask {
            task: TaskId(end.task),
            end: match end.outcome {
                TaskOutcome::Done => TaskEnd::Done,
                TaskOutcome::Failed => TaskEnd::Failed,
            },
            exec,
            sent_at: clock.to_server(end.sent_at_us),
            clock,
        })
    }

    fn observation(
        &self,
        observation: Observation,
        sent_at_us: u64,
        clock: &ClockMap,
    ) -> Result<ValidObservation, RequestError> {
        let spec = &self.spec;
        if observation.captured_at_us > sent_at_us {
            return Err(invalid(
                "observation.captured_at_us",
                format!(
                    "captured at {} µs, after the message was sent at {sent_at_us} µs",
                    observation.captured_at_us
                ),
            ));
        }
        let state = observation
            .state
            .to_f32()
            .map_err(|e| observation_error("observation.state", e.to_string()))?;
        let mut images = Vec::with_capacity(observation.images.len());
        let mut cameras = Vec::with_capacity(observation.images.len());
        for (i, image) in observation.images.into_iter().enumerate() {
            images.push(image_input(i, image.payload)?);
            cameras.push(image.camera);
        }
        let request = ActionRequest {
            cameras,
            state,
            images,
            instruction: observation.instruction,
            samples: 1,
            seed: 0,
        };
        // Everything the engine would refuse, refused here with the field named, so that a bad
        // observation fails only its own round and never reaches a batch.
        spec.check_request(&request, &self.image_limits()).map_err(
            |InputError { field, reason }| {
                observation_error(format!("observation.{field}"), reason)
            },
        )?;
        Ok(ValidObservation {
            captured_at: clock.to_server(observation.captured_at_us),
            request,
        })
    }

    /// The image bounds of [`Limits`]: raw and encoded images alike, the latter checked from
    /// their headers.
    pub fn image_limits(&self) -> ImageLimits {
        ImageLimits {
            max_side: self.limits.max_tensor_dim as usize,
            max_pixels: self.limits.max_image_pixels as usize,
        }
    }

    /// Decodes a checked observation's JPEG and PNG images to pixels, on the bounded decode pool
    /// ([`decode_slots`]): off the async runtime, off the engine threads, and before the round is
    /// queued, so a file whose body is corrupt (its header passed [`Validator::submit`]) fails
    /// its own round with `invalid_observation` and engines never decode.
    pub async fn decode(
        &self,
        mut observation: ValidObservation,
    ) -> Result<ValidObservation, RequestError> {
        if !observation
            .request
            .images
            .iter()
            .any(|i| matches!(i, ImageInput::Encoded { .. }))
        {
            return Ok(observation);
        }
        let limits = self.image_limits();
        let images = std::mem::take(&mut observation.request.images);
        let _slot = decode_slots()
            .acquire()
            .await
            .map_err(|_| RequestError::ShuttingDown)?;
        let decoded = tokio::task::spawn_blocking(move || decode_images(&images, &limits))
            .await
            .map_err(|e| RequestError::Internal(format!("image decoding failed: {e}")))??;
        observation.request.images = decoded;
        Ok(observation)
    }

    /// [`Validator::decode`] for a round request.
    pub async fn decode_submit(
        &self,
        mut submit: ValidSubmit,
    ) -> Result<ValidSubmit, RequestError> {
        submit.observation = self.decode(submit.observation).await?;
        Ok(submit)
    }
}

/// Decodes an observation's JPEG and PNG images to pixels (raw ones are checked and kept), each
/// within `limits` from its header before any pixel is allocated. Blocking: the server calls it
/// on the decode pool ([`Validator::decode`]); the fuzz targets call it directly.
pub fn decode_images(
    images: &[ImageInput],
    limits: &ImageLimits,
) -> Result<Vec<ImageInput>, RequestError> {
    images
        .iter()
        .enumerate()
        .map(|(i, image)| {
            image_features::decode(image, limits)
                .map_err(|reason| observation_error(format!("observation.images[{i}]"), reason))
        })
        .collect()
}

/// The decode pool's bound: how many observations are decoded at once, process-wide. Waiting
/// rounds queue on the semaphore (no thread each); a permit's holder runs on tokio's blocking
/// pool. One pool per process, like the engine's kernel threads, sized to the cores (at most 4:
/// a capped image decodes in tens of milliseconds, and engines need the rest).
pub fn decode_slots() -> &'static tokio::sync::Semaphore {
    static SLOTS: std::sync::OnceLock<tokio::sync::Semaphore> = std::sync::OnceLock::new();
    SLOTS.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        tokio::sync::Semaphore::new(cores.clamp(1, 4))
    })
}

fn image_input(index: usize, payload: ImagePayload) -> Result<ImageInput, RequestError> {
    let field = format!("observation.images[{index}]");
    Ok(match payload {
        ImagePayload::Jpeg { data } => ImageInput::Encoded {
            format: ImageFormat::Jpeg,
            bytes: data,
        },
        ImagePayload::Png { data } => ImageInput::Encoded {
            format: ImageFormat::Png,
            bytes: data,
        },
        ImagePayload::Raw { tensor } => {
            // The protocol check guarantees rank 3 and a matching byte length.
            let [height, width, channels] = match tensor.shape.as_slice() {
                [h, w, c] => [*h as usize, *w as usize, *c as usize],
                other => {
                    return Err(observation_error(
                        format!("{field}.payload.tensor.shape"),
                        format!("expected [height, width, channels], got {other:?}"),
                    ));
                }
            };
            match tensor.dtype {
                DType::U8 => ImageInput::RawU8 {
                    height,
                    width,
                    channels,
                    data: tensor.data,
                },
                DType::F32 => ImageInput::RawF32 {
                    height,
                    width,
                    channels,
                    data: tensor.to_f32().map_err(|e| {
                        observation_error(format!("{field}.payload.tensor"), e.to_string())
                    })?,
                },
                other => {
                    return Err(observation_error(
                        format!("{field}.payload.tensor.dtype"),
                        format!("a raw image is u8 or f32, got {other:?}"),
                    ));
                }
            }
        }
    })
}

fn exec_report(
    info: &LastExecInfo,
    sent_at_us: u64,
    clock: &ClockMap,
) -> Result<ExecReport, RequestError> {
    if info.exec_started_at_us > sent_at_us {
        return Err(invalid(
            "last_exec.exec_started_at_us",
            format!(
                "execution started at {} µs, after the message was sent at {sent_at_us} µs",
                info.exec_started_at_us
            ),
        ));
    }
    Ok(ExecReport {
        started_at: clock.to_server(info.exec_started_at_us),
        actions_remaining: info.actions_remaining,
        control_hz: info.control_hz,
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use kairos_sdk::protocol::{HorizonSelection, Image, MAX_ROUND, Tensor};

    use super::*;
    use crate::registry::native_horizon_policies;

    fn validator() -> Validator {
        Validator {
            spec: ModelSpec {
                cameras: Vec::new(),
                camera_aliases: Default::default(),
                name: "m".into(),
                chunk_len: 8,
                action_dim: 2,
                state_dim: 3,
                steps: 4,
                max_images: 1,
            },
            limits: Limits::default(),
        }
    }

    fn actions() -> ActionManager {
        let natives = native_horizon_policies();
        ActionManager::new(natives.clone(), &natives, "threshold", BTreeMap::new()).unwrap()
    }

    fn submit() -> Submit {
        Submit {
            task: 5,
            round: 2,
            sent_at_us: 1_000_000,
            observation: Observation {
                captured_at_us: 990_000,
                state: Tensor::from_f32(vec![3], &[1.0, 2.0, 3.0]).unwrap(),
                images: Vec::new(),
                instruction: "pick".into(),
            },
            last_exec: Some(LastExecInfo {
                exec_started_at_us: 900_000,
                actions_remaining: 4,
                control_hz: 50.0,
            }),
            horizon: None,
            remaining: None,
            attempt: 0,
            control_hz: None,
            seed: None,
        }
    }

    fn check(s: Submit) -> Result<ValidSubmit, RequestError> {
        validator().submit(
            s,
            RobotId(1),
            &actions(),
            ClockMap::new(
                Timestamp::from_micros(5_000_000),
                1_000_000,
                Duration::from_micros(200),
            ),
        )
    }

    #[test]
    fn clock_map_subtracts_half_the_rtt_and_round_trips() {
        let clock = ClockMap::new(
            Timestamp::from_micros(5_000_000),
            1_000_000,
            Duration::from_micros(200),
        );
        assert_eq!(clock.to_server(1_000_000).as_micros(), 4_999_900);
        assert_eq!(clock.to_server(900_000).as_micros(), 4_899_900);
        assert_eq!(clock.to_client(Timestamp::from_micros(4_899_900)), 900_000);
        // A client clock far ahead of the server's epoch clamps instead of wrapping.
        let ahead = ClockMap::new(Timestamp::from_micros(10), u64::MAX / 2, Duration::ZERO);
        assert_eq!(ahead.to_server(0), Timestamp::ZERO);
    }

    #[test]
    fn clock_estimator_takes_the_least_delayed_message_and_ignores_resends() {
        let mut est = ClockEstimator::default();
        let rtt = Duration::from_micros(100);
        // True offset 1_000_000 µs; one-way delays 500, 80 and 3000 µs.
        let map = est.observe(Timestamp::from_micros(1_010_500), 10_000, rtt, true);
        assert_eq!(map.to_server(10_000).as_micros(), 1_010_450);
        let map = est.observe(Timestamp::from_micros(1_020_080), 20_000, rtt, true);
        assert_eq!(map.to_server(20_000).as_micros(), 1_020_030);
        let map = est.observe(Timestamp::from_micros(1_033_000), 30_000, rtt, true);
        assert_eq!(
            map.to_server(30_000).as_micros(),
            1_030_030,
            "a delayed message does not move the estimate"
        );
        // A round re-sent 2 s later with its first sent_at.
        let map = est.observe(Timestamp::from_micros(3_040_000), 40_000, rtt, false);
        assert_eq!(map.to_server(40_000).as_micros(), 1_040_030);
        for i in 0..ClockEstimator::WINDOW as u64 {
            est.observe(
                Timestamp::from_micros(1_100_000 + i * 10 + 200),
                100_000 + i * 10,
                rtt,
                true,
            );
        }
        let map = est.observe(Timestamp::from_micros(1_200_200), 200_000, rtt, true);
        assert_eq!(
            map.to_server(200_000).as_micros(),
            1_200_150,
            "old samples leave the window"
        );
    }

    #[test]
    fn a_good_submit_maps_onto_the_server_clock() {
        let v = check(submit()).unwrap();
        assert_eq!(v.round.task, TaskId(5));
        assert_eq!(v.round.robot, RobotId(1));
        assert_eq!(v.round.sent_at.as_micros(), 4_999_900);
        assert_eq!(v.round.obs_captured_at.as_micros(), 4_989_900);
        let exec = v.round.last_exec.unwrap();
        assert_eq!(exec.started_at.as_micros(), 4_899_900);
        assert_eq!(exec.actions_remaining, 4);
        assert_eq!(v.observation.request.state, vec![1.0, 2.0, 3.0]);
        assert_eq!(v.observation.request.seed, round_seed(5, 2));
        assert_ne!(round_seed(5, 2), round_seed(5, 3));
        // A client's own sampler seed wins over the derived one.
        let seeded = check(Submit {
            seed: Some(77),
            ..submit()
        })
        .unwrap();
        assert_eq!(seeded.observation.request.seed, 77);
        assert_eq!(v.samples, 1);
        assert_eq!(v.policy.policy.name(), "threshold");
        assert_eq!(v.control_hz, Some(50.0));
    }

    #[test]
    fn a_first_round_carries_its_control_rate_to_the_scheduler() {
        let mut s = submit();
        s.last_exec = None;
        s.control_hz = Some(0.4);
        let v = check(s).unwrap();
        assert_eq!(v.round.control_hz, Some(0.4));
        assert_eq!(v.control_hz, Some(0.4));
        // The execution report's rate wins when both are present.
        let mut s = submit();
        s.control_hz = Some(7.0);
        assert_eq!(check(s).unwrap().control_hz, Some(50.0));
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let mut s = submit();
            s.control_hz = Some(bad);
            assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz {bad}");
        }
    }

    fn code(s: Submit) -> ErrorCode {
        let err = check(s).unwrap_err();
        ErrorReply::from(&err).code
    }

    #[test]
    fn each_bad_field_gets_its_code() {
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![2], &[1.0, 2.0]).unwrap();
        assert_eq!(code(s), ErrorCode::InvalidObservation, "state too short");

        let mut s = submit();
        s.observation.state = Tensor::from_u8(vec![3], vec![1, 2, 3]).unwrap();
        assert_eq!(code(s), ErrorCode::InvalidObservation, "state dtype");

        let raw = |shape: Vec<u32>| Image {
            camera: "front".into(),
            payload: ImagePayload::Raw {
                tensor: Tensor::from_u8(
                    shape.clone(),
                    vec![0; shape.iter().product::<u32>() as usize],
                )
                .unwrap(),
            },
        };
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 3])];
        assert!(check(s).is_ok());
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 5])];
        assert_eq!(code(s), ErrorCode::InvalidObservation, "channels");
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 3]), {
            let mut i = raw(vec![2, 2, 3]);
            i.camera = "wrist".into();
            i
        }];
        assert_eq!(code(s), ErrorCode::InvalidObservation, "too many images");

        let mut s = submit();
        s.observation.images = vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Jpeg {
                data: vec![0; Limits::default().max_image_bytes as usize + 1],
            },
        }];
        assert_eq!(code(s), ErrorCode::TooLarge, "oversize image");

        let mut s = submit();
        s.last_exec.as_mut().unwrap().control_hz = 0.0;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz");
        let mut s = submit();
        s.last_exec.as_mut().unwrap().control_hz = f32::NAN;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz NaN");
        let mut s = submit();
        s.last_exec.as_mut().unwrap().exec_started_at_us = 2_000_000;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "exec in the future");
        let mut s = submit();
        s.observation.captured_at_us = 2_000_000;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "captured after sent");

        let selection = |policy: &str, params: &[(&str, f64)], samples: u32| HorizonSelection {
            policy: policy.into(),
            params: params.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            samples,
        };
        let mut s = submit();
        s.horizon = Some(selection("nope", &[], 1));
        assert_eq!(code(s), ErrorCode::UnknownPolicy);
        let mut s = submit();
        s.horizon = Some(selection("threshold", &[("t", -2.0)], 1));
        assert_eq!(code(s), ErrorCode::InvalidRequest, "bad param");
        let mut s = submit();
        s.horizon = Some(selection("threshold", &[], 1000));
        assert_eq!(code(s), ErrorCode::TooLarge, "samples over the limit");
        let mut s = submit();
        s.horizon = Some(selection("static", &[("h", 4.0)], 2));
        let v = check(s).unwrap();
        assert_eq!((v.samples, v.observation.request.samples), (2, 2));
        assert_eq!(v.policy.policy.name(), "static");
    }

    /// A 2x2 RGB PNG.
    const PNG_2X2: [u8; 73] = [
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44,
        0x52, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x02, 0x08, 0x02, 0x00, 0x00, 0x00, 0xfd,
        0xd4, 0x9a, 0x73, 0x00, 0x00, 0x00, 0x10, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x10,
        0x50, 0x30, 0x00, 0x22, 0x06, 0x08, 0x05, 0x00, 0x0a, 0x0e, 0x01, 0x81, 0x56, 0x33, 0xee,
        0xf3, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
    ];

    /// The head of a decompression bomb: a PNG header declaring 8192x8192 RGB (192 MiB of
    /// pixels) and the first 26 bytes of its data.
    const PNG_BOMB_HEAD: [u8; 83] = [
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44,
        0x52, 0x00, 0x00, 0x20, 0x00, 0x00, 0x00, 0x20, 0x00, 0x08, 0x02, 0x00, 0x00, 0x00, 0xfd,
        0xc8, 0x5d, 0x0e, 0x00, 0x00, 0x00, 0x1a, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0xed, 0xc1,
        0x01, 0x0d, 0x00, 0x00, 0x00, 0xc2, 0xa0, 0xf7, 0x4f, 0x6d, 0x0f, 0x07, 0x14, 0x00, 0x00,
        0x00, 0xf0, 0x6e, 0x10, 0x00, 0x00, 0x01, 0x4b, 0x9e, 0xa3, 0x3c, 0x00, 0x00, 0x00, 0x00,
        0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
    ];

    fn with_image(payload: ImagePayload) -> Submit {
        let mut s = submit();
        s.observation.images = vec![Image {
            camera: "front".into(),
            payload,
        }];
        s
    }

    /// The refusal's wire form: it must be `invalid_observation`, not retryable, and name
    /// `field`.
    fn refused(s: Submit, field: &str) -> String {
        let reply = ErrorReply::from(&check(s).unwrap_err());
        assert_eq!(
            reply.code,
            ErrorCode::InvalidObservation,
            "{}",
            reply.message
        );
        assert!(!reply.retryable);
        assert!(
            reply.message.contains(field),
            "{} names {field}",
            reply.message
        );
        reply.message
    }

    #[test]
    fn everything_the_engine_would_refuse_is_refused_before_the_queue() {
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![3], &[1.0, f32::NAN, 3.0]).unwrap();
        refused(s, "observation.state[1]");
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![3], &[f32::INFINITY, 0.0, 3.0]).unwrap();
        refused(s, "observation.state[0]");

        // Bytes that claim to be an image but are not one.
        refused(
            with_image(ImagePayload::Png {
                data: b"GIF89a, not a PNG".to_vec(),
            }),
            "observation.images[0]",
        );
        refused(
            with_image(ImagePayload::Jpeg {
                data: PNG_2X2.to_vec(),
            }),
            "observation.images[0]",
        );
        assert!(
            check(with_image(ImagePayload::Png {
                data: PNG_2X2.to_vec()
            }))
            .is_ok()
        );

        let raw_f32 = |shape: Vec<u32>, values: &[f32]| ImagePayload::Raw {
            tensor: Tensor::from_f32(shape, values).unwrap(),
        };
        refused(
            with_image(raw_f32(vec![1, 2, 1], &[0.5, f32::NAN])),
            "observation.images[0]",
        );
        assert!(check(with_image(raw_f32(vec![1, 2, 1], &[0.5, 1.0]))).is_ok());
        // No pixels: a 0-wide image.
        let message = refused(
            with_image(raw_f32(vec![4, 0, 3], &[])),
            "observation.images[0]",
        );
        assert!(message.contains("4x0"), "{message}");
    }

    #[test]
    fn a_decompression_bomb_is_refused_from_its_header() {
        let message = refused(
            with_image(ImagePayload::Png {
                data: PNG_BOMB_HEAD.to_vec(),
            }),
            "observation.images[0]",
        );
        assert!(message.contains("8192x8192"), "{message}");
        assert!(message.contains("over the limit"), "{message}");
        // The cap is the configured one: the 2x2 image passes at 4 pixels, not at 3.
        let mut v = validator();
        v.limits.max_image_pixels = 3;
        let small = with_image(ImagePayload::Png {
            data: PNG_2X2.to_vec(),
        });
        let clock = ClockMap::new(Timestamp::from_micros(5_000_000), 1_000_000, Duration::ZERO);
        let error = v.submit(small, RobotId(1), &actions(), clock).unwrap_err();
        assert_eq!(error.code(), ErrorCode::InvalidObservation);
        assert!(error.to_string().contains("4 pixels"), "{error}");
    }

    #[tokio::test]
    async fn decoding_turns_files_into_pixels_before_the_queue() {
        let v = validator();
        let valid = check(with_image(ImagePayload::Png {
            data: PNG_2X2.to_vec(),
        }))
        .unwrap();
        let decoded = v.decode_submit(valid).await.unwrap();
        assert_eq!(
            decoded.observation.request.images,
            vec![ImageInput::RawU8 {
                height: 2,
                width: 2,
                channels: 3,
                data: [0x10, 0x20, 0x30].repeat(4),
            }]
        );
        // A file whose header is fine but whose pixel data is cut off fails its own round here.
        let mut truncated = PNG_2X2.to_vec();
        truncated.truncate(50);
        let valid = check(with_image(ImagePayload::Png { data: truncated })).unwrap();
        let error = v.decode_submit(valid).await.unwrap_err();
        assert_eq!(error.code(), ErrorCode::InvalidObservation);
        assert!(
            error.to_string().contains("observation.images[0]"),
            "{error}"
        );
    }

    #[test]
    fn round_ids_are_bounded() {
        let mut s = submit();
        s.round = MAX_ROUND;
        assert!(check(s).is_ok());
        for round in [MAX_ROUND + 1, u64::MAX] {
            let mut s = submit();
            s.round = round;
            let reply = ErrorReply::from(&check(s).unwrap_err());
            assert_eq!(reply.code, ErrorCode::InvalidRequest);
            assert!(reply.message.contains("round"), "{}", reply.message);
        }
    }

    #[test]
    fn a_task_that_is_not_the_robots_gets_one_answer_whatever_the_reason() {
        let task = TaskId(42);
        let replies: Vec<ErrorReply> = [
            AdmitError::Forbidden { task },
            AdmitError::UnknownTask { task },
            AdmitError::TaskEnded { task },
        ]
        .into_iter()
        .map(|e| ErrorReply::from(&RequestError::from(e)))
        .collect();
        assert_eq!(replies[0].code, ErrorCode::UnknownTask);
        assert!(replies.iter().all(|r| *r == replies[0]), "{replies:?}");
    }

    #[test]
    fn an_engine_refusal_is_the_requests_fault_and_a_crash_is_ours() {
        let refused = RequestError::Engine(PoolError::Engine {
            engine: "e".into(),
            source: EngineError::InvalidInput("state[0]: NaN".into()),
        });
        assert_eq!(refused.code(), ErrorCode::InvalidObservation);
        assert!(!ErrorReply::from(&refused).retryable);
        let crashed = RequestError::Engine(PoolError::Panicked {
            engine: "e".into(),
            message: "bug".into(),
        });
        assert_eq!(crashed.code(), ErrorCode::Internal);
        assert!(ErrorReply::from(&crashed).retryable);
    }

    #[test]
    fn admit_errors_map_to_their_wire_codes() {
        let cases = [
            (AdmitError::Overloaded { pending: 3 }, ErrorCode::Overloaded),
            (
                AdmitError::Forbidden { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::UnknownTask { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::TaskEnded { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::RoundOutOfOrder { last: 3, got: 2 },
                ErrorCode::RoundOutOfOrder,
            ),
            (
                AdmitError::InvalidExecInfo("x".into()),
                ErrorCode::InvalidRequest,
            ),
        ];
        for (admit, expected) in cases {
            let reply = ErrorReply::from(&RequestError::from(admit));
            assert_eq!(reply.code, expected);
            assert_eq!(reply.retryable, expected == ErrorCode::Overloaded);
        }
        let overloaded =
            ErrorReply::from(&RequestError::from(AdmitError::Overloaded { pending: 1 }));
        assert_eq!(overloaded.retry_after_ms, Some(OVERLOADED_RETRY_AFTER_MS));
        assert_eq!(
            ErrorReply::from(&RequestError::Unauthorized).code,
            ErrorCode::Unauthorized
        );
    }

    #[test]
    fn hello_requires_a_supported_version() {
        let v = validator();
        let hello = |protocol| Hello {
            protocol,
            token: "t".into(),
            client: "c".into(),
        };
        assert_eq!(v.hello(&hello(1)).unwrap(), 1);
        assert_eq!(
            v.hello(&hello(7)).unwrap(),
            1,
            "newer clients speak v1 to us"
        );
        assert!(matches!(
            v.hello(&hello(0)),
            Err(RequestError::UnsupportedVersion(0))
        ));
    }
}
