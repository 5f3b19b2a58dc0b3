//! A remote engine worker (`kairos worker`) behind [`EngineInstance`]: each batch is one QUIC
//! stream of the worker's connection (`RunBatch` → `Chunks`, worker protocol `kairos-worker/1`,
//! `kairos_sdk::protocol::worker`), bounded by a deadline.
//!
//! The future a batch returns only waits on the network; the worker runs the model on its own
//! engine thread. A batch that cannot be answered because the worker is gone, its stream was
//! reset, or its deadline passed ends as [`PoolError::Lost`]: the connection is closed (the
//! worker leaves the pool) and the driver runs the batch's rounds again elsewhere. Errors the
//! worker's engine reports for single requests are ordinary per-request errors and are not
//! retried.
//!
//! Also here, shared by both ends: the conversions between engine types and their wire forms.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{
    ActionChunk, ActionRequest, EngineProfile, Guidance, GuidanceMode, ImageFormat, ImageInput,
    ModelSpec, PrefixSchedule, ProfilePoint,
};
use kairos_sdk::protocol::worker::{
    Chunks, ProfilePointWire, ProfileWire, RunBatch, WORKER_MAX_FRAME, WorkChunk, WorkGuidance,
    WorkRequest, WorkResult, WorkerMessage, close_code as worker_close,
};
use kairos_sdk::protocol::{
    ChunkingStrategy, DType, Image, ImagePayload, Limits, ModelInfo,
    PrefixSchedule as WirePrefixSchedule, ReadFrameError, Tensor, read_frame, write_body,
};
use quinn::{Connection, ConnectionError, ReadError, VarInt, WriteError};

use super::{BatchChunks, BatchLabel, EngineInstance, PoolError, check_output};
use crate::config::WorkersConfig;
use kairos_core::error::LossReason;
use kairos_core::scheduler::Tier;

/// A moving average of a worker's round trip: end-to-end batch time minus the compute time the
/// worker reports, so payload transfer counts. Seeded from QUIC's smoothed RTT. Pure.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RttEstimate {
    value: Duration,
    samples: u64,
}

impl RttEstimate {
    /// Weight of a new sample.
    pub const ALPHA: f64 = 0.25;

    /// Starts at `seed` (QUIC's estimate at registration).
    pub fn new(seed: Duration) -> RttEstimate {
        RttEstimate {
            value: seed,
            samples: 0,
        }
    }

    /// One batch took `end_to_end` and the worker computed for `compute`.
    pub fn observe(&mut self, end_to_end: Duration, compute: Duration) {
        let sample = end_to_end.saturating_sub(compute).as_secs_f64();
        let current = self.value.as_secs_f64();
        let next = current + Self::ALPHA * (sample - current);
        self.value = Duration::from_secs_f64(next.max(0.0));
        self.samples += 1;
    }

    /// The estimate.
    pub fn get(&self) -> Duration {
        self.value
    }

    /// Batch samples folded in.
    pub fn samples(&self) -> u64 {
        self.samples
    }
}

/// How far past the threshold ([`WorkersConfig::cloud_rtt_ms`]) a worker's round trip must move
/// before [`tier_from_rtt`] re-classifies it, as a fraction of the threshold: an edge worker
/// becomes cloud above `threshold × (1 + HYSTERESIS)` and a cloud worker edge again below
/// `threshold × (1 − HYSTERESIS)`, so an average that wanders around the threshold does not
/// flip placement at every batch.
pub const TIER_HYSTERESIS: f64 = 0.25;

/// The tier of a worker that registered as `auto`, from its measured round trip `rtt` against
/// the `threshold`: first (`current` is `None`, at registration) cloud iff `rtt >= threshold`,
/// then with [`TIER_HYSTERESIS`] around it. Pure.
pub fn tier_from_rtt(current: Option<Tier>, rtt: Duration, threshold: Duration) -> Tier {
    let rtt = rtt.as_secs_f64();
    let threshold = threshold.as_secs_f64();
    match current {
        None if rtt >= threshold => Tier::Cloud,
        None => Tier::Edge,
        Some(Tier::Edge) if rtt > threshold * (1.0 + TIER_HYSTERESIS) => Tier::Cloud,
        Some(Tier::Cloud) if rtt < threshold * (1.0 - TIER_HYSTERESIS) => Tier::Edge,
        Some(tier) => tier,
    }
}

/// What the scheduler knows of a worker's link: its round trip and, for an `auto` worker, the
/// tier that round trip gives.
#[derive(Clone, Copy, Debug)]
struct Link {
    rtt: RttEstimate,
    tier: Tier,
}

/// A registered worker, as one engine instance of the pool.
pub struct RemoteEngine {
    name: String,
    spec: ModelSpec,
    profile: EngineProfile,
    /// Whether the tier follows the measured round trip (the worker registered as `auto`).
    auto_tier: bool,
    connection: Connection,
    link: Arc<Mutex<Link>>,
    workers: WorkersConfig,
}

impl RemoteEngine {
    /// The worker on `connection`, registered as `name` with its spec, profile (its `max_batch`
    /// already capped to the worker's) and tier (`None`: `auto`, classified by
    /// [`tier_from_rtt`] against `workers.cloud_rtt()`, first from QUIC's estimate). Its round
    /// trip starts at QUIC's estimate.
    pub fn new(
        name: String,
        spec: ModelSpec,
        profile: EngineProfile,
        tier: Option<Tier>,
        connection: Connection,
        workers: WorkersConfig,
    ) -> RemoteEngine {
        let rtt = RttEstimate::new(connection.rtt());
        let auto_tier = tier.is_none();
        let tier = tier.unwrap_or_else(|| tier_from_rtt(None, rtt.get(), workers.cloud_rtt()));
        RemoteEngine {
            name,
            spec,
            profile,
            auto_tier,
            connection,
            link: Arc::new(Mutex::new(Link { rtt, tier })),
            workers,
        }
    }

    fn link(&self) -> Link {
        *lock(&self.link)
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl EngineInstance for RemoteEngine {
    fn name(&self) -> &str {
        &self.name
    }

    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn profile(&self) -> &EngineProfile {
        &self.profile
    }

    fn tier(&self) -> Tier {
        self.link().tier
    }

    fn rtt(&self) -> Duration {
        self.link().rtt.get()
    }

    fn can_lose_batches(&self) -> bool {
        true
    }

    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        self.run_labeled(
            BatchLabel {
                batch: kairos_core::scheduler::BatchId(u64::MAX),
                attempt: 0,
            },
            batch,
        )
    }

    fn run_labeled(
        &self,
        label: BatchLabel,
        batch: Vec<ActionRequest>,
    ) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        let n = u32::try_from(batch.len()).unwrap_or(u32::MAX);
        let expected = self.profile.latency(n).saturating_add(self.rtt());
        let deadline = self.workers.batch_deadline(expected);
        let name = self.name.clone();
        let spec = self.spec.clone();
        let connection = self.connection.clone();
        let link = self.link.clone();
        let cloud_rtt = self.auto_tier.then(|| self.workers.cloud_rtt());
        async move {
            let lost = |reason: LossReason, detail: String| PoolError::Lost {
                engine: name.clone(),
                reason,
                detail,
            };
            let requests = batch
                .iter()
                .map(request_to_wire)
                .collect::<Result<Vec<_>, String>>()
                .map_err(|reason| PoolError::BadOutput {
                    engine: name.clone(),
                    reason: format!("cannot encode the batch: {reason}"),
                })?;
            let run = RunBatch {
                batch_id: label.batch.0,
                attempt: label.attempt,
                deadline_ms: u32::try_from(deadline.as_millis()).unwrap_or(u32::MAX),
                requests,
            };
            let sent = tokio::time::Instant::now();
            let exchange = exchange(&connection, &run);
            let chunks = match tokio::time::timeout(deadline, exchange).await {
                Ok(Ok(chunks)) => chunks,
                Ok(Err((reason, detail))) => {
                    connection.close(
                        VarInt::from_u32(worker_close::BATCH_LOST),
                        detail.as_bytes(),
                    );
                    return Err(lost(reason, detail));
                }
                Err(_) => {
                    let detail = format!("no answer within the deadline of {deadline:?}");
                    connection.close(VarInt::from_u32(worker_close::DEADLINE), detail.as_bytes());
                    return Err(lost(LossReason::Deadline, detail));
                }
            };
            let compute = Duration::from_micros(chunks.compute_us);
            {
                let mut link = lock(&link);
                link.rtt.observe(sent.elapsed(), compute);
                if let Some(threshold) = cloud_rtt {
                    link.tier = tier_from_rtt(Some(link.tier), link.rtt.get(), threshold);
                }
            }
            chunks_from_wire(&name, &spec, &batch, chunks.results)
        }
        .boxed()
    }
}

/// One batch stream: `RunBatch` out, one `Chunks` for the same `(batch_id, attempt)` back.
async fn exchange(connection: &Connection, run: &RunBatch) -> Result<Chunks, (LossReason, String)> {
    let (mut send, mut recv) = connection.open_bi().await.map_err(connection_error)?;
    write_body(&mut send, run, WORKER_MAX_FRAME)
        .await
        .map_err(|error| match error {
            kairos_sdk::protocol::WriteFrameError::Write(error) => write_error(error),
            other => (LossReason::StreamReset, other.to_string()),
        })?;
    let _ = send.finish();
    let limits = Limits {
        max_frame: WORKER_MAX_FRAME,
        ..Limits::default()
    };
    let frame = match read_frame(&mut recv, &limits).await {
        Ok(Some(frame)) => frame,
        Ok(None) => {
            return Err((
                LossReason::StreamReset,
                "the worker finished the stream without an answer".into(),
            ));
        }
        Err(ReadFrameError::Read(error)) => return Err(read_error(error)),
        Err(error) => return Err((LossReason::StreamReset, error.to_string())),
    };
    match WorkerMessage::decode(&frame) {
        Ok(WorkerMessage::Chunks(chunks))
            if chunks.batch_id == run.batch_id && chunks.attempt == run.attempt =>
        {
            Ok(chunks)
        }
        Ok(other) => Err((
            LossReason::StreamReset,
            format!("expected the Chunks of this batch, got {other:?}")
                .chars()
                .take(200)
                .collect(),
        )),
        Err(error) => Err((LossReason::StreamReset, error.to_string())),
    }
}

fn connection_error(error: ConnectionError) -> (LossReason, String) {
    (LossReason::ConnectionLost, error.to_string())
}

fn read_error(error: ReadError) -> (LossReason, String) {
    match error {
        ReadError::ConnectionLost(error) => connection_error(error),
        other => (LossReason::StreamReset, other.to_string()),
    }
}

fn write_error(error: WriteError) -> (LossReason, String) {
    match error {
        WriteError::ConnectionLost(error) => connection_error(error),
        other => (LossReason::StreamReset, other.to_string()),
    }
}

/// The worker's answers as the pool's per-request results, checked against the batch.
fn chunks_from_wire(
    name: &str,
    spec: &ModelSpec,
    batch: &[ActionRequest],
    results: Vec<WorkResult>,
) -> Result<BatchChunks, PoolError> {
    let bad = |reason: String| PoolError::BadOutput {
        engine: name.to_string(),
        reason,
    };
    if results.len() != batch.len() {
        return Err(bad(format!(
            "{} results for {} requests",
            results.len(),
            batch.len()
        )));
    }
    let mut out = Vec::with_capacity(results.len());
    for (i, (result, request)) in results.into_iter().zip(batch).enumerate() {
        let entry = match (result.chunk, result.error) {
            (Some(chunk), None) => {
                let chunk = chunk_from_wire(spec, request.samples.max(1), &chunk)
                    .map_err(|reason| bad(format!("result {i}: {reason}")))?;
                check_output(
                    name,
                    spec,
                    std::slice::from_ref(request),
                    std::slice::from_ref(&chunk),
                )?;
                Ok(chunk)
            }
            (None, Some(message)) => Err(PoolError::Remote {
                engine: name.to_string(),
                message,
            }),
            _ => {
                return Err(bad(format!(
                    "result {i} has neither or both of chunk and error"
                )));
            }
        };
        out.push(entry);
    }
    Ok(out)
}

fn usize_u32(value: usize) -> u32 {
    u32::try_from(value).unwrap_or(u32::MAX)
}

/// A model request in its wire form (a request without camera names names its images
/// `camera0`, `camera1`, ... by position).
pub fn request_to_wire(request: &ActionRequest) -> Result<WorkRequest, String> {
    let state = Tensor::from_f32(vec![usize_u32(request.state.len())], &request.state)
        .map_err(|e| e.to_string())?;
    let images = request
        .images
        .iter()
        .enumerate()
        .map(|(i, image)| {
            let payload = match image {
                ImageInput::Encoded {
                    format: ImageFormat::Jpeg,
                    bytes,
                } => ImagePayload::Jpeg {
                    data: bytes.clone(),
                },
                ImageInput::Encoded {
                    format: ImageFormat::Png,
                    bytes,
                } => ImagePayload::Png {
                    data: bytes.clone(),
                },
                ImageInput::RawU8 {
                    height,
                    width,
                    channels,
                    data,
                } => ImagePayload::Raw {
                    tensor: Tensor::from_u8(
                        vec![usize_u32(*height), usize_u32(*width), usize_u32(*channels)],
                        data.clone(),
                    )
                    .map_err(|e| e.to_string())?,
                },
                ImageInput::RawF32 {
                    height,
                    width,
                    channels,
                    data,
                } => ImagePayload::Raw {
                    tensor: Tensor::from_f32(
                        vec![usize_u32(*height), usize_u32(*width), usize_u32(*channels)],
                        data,
                    )
                    .map_err(|e| e.to_string())?,
                },
            };
            Ok(Image {
                camera: request
                    .cameras
                    .get(i)
                    .cloned()
                    .unwrap_or_else(|| format!("camera{i}")),
                payload,
            })
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok(WorkRequest {
        state,
        images,
        instruction: request.instruction.clone(),
        samples: usize_u32(request.samples),
        seed: request.seed,
        guidance: request
            .guidance
            .as_ref()
            .map(guidance_to_wire)
            .transpose()?,
    })
}

fn guidance_to_wire(guidance: &Guidance) -> Result<WorkGuidance, String> {
    Ok(WorkGuidance {
        mode: match guidance.mode {
            GuidanceMode::Rtc => ChunkingStrategy::Rtc,
            GuidanceMode::RtcVjp => ChunkingStrategy::RtcVjp,
            GuidanceMode::Inpaint => ChunkingStrategy::Inpaint,
        },
        prefix: Tensor::from_f32(vec![usize_u32(guidance.prefix.len())], &guidance.prefix)
            .map_err(|e| e.to_string())?,
        delay: usize_u32(guidance.delay),
        execution_horizon: usize_u32(guidance.execution_horizon),
        schedule: match guidance.schedule {
            PrefixSchedule::Zeros => WirePrefixSchedule::Zeros,
            PrefixSchedule::Ones => WirePrefixSchedule::Ones,
            PrefixSchedule::Linear => WirePrefixSchedule::Linear,
            PrefixSchedule::Exp => WirePrefixSchedule::Exp,
        },
        max_guidance_weight: guidance.max_guidance_weight,
    })
}

fn guidance_from_wire(guidance: WorkGuidance) -> Result<Guidance, String> {
    let mode = match guidance.mode {
        ChunkingStrategy::Rtc => GuidanceMode::Rtc,
        ChunkingStrategy::RtcVjp => GuidanceMode::RtcVjp,
        ChunkingStrategy::Inpaint => GuidanceMode::Inpaint,
        other => return Err(format!("`{other}` is not a guidance mode")),
    };
    if guidance.prefix.shape.len() != 1 {
        return Err(format!(
            "a guidance prefix is flat [rows × action_dim], got shape {:?}",
            guidance.prefix.shape
        ));
    }
    Ok(Guidance {
        mode,
        prefix: guidance.prefix.to_f32().map_err(|e| e.to_string())?,
        delay: guidance.delay as usize,
        execution_horizon: guidance.execution_horizon as usize,
        schedule: kairos_core::chunking::engine_schedule(guidance.schedule),
        max_guidance_weight: guidance.max_guidance_weight,
    })
}

/// A wire request as a model request (the worker's side). Shapes are checked; the model's own
/// `check_request` still refuses what it cannot serve, one request at a time.
pub fn request_from_wire(request: WorkRequest) -> Result<ActionRequest, String> {
    let state = request.state.to_f32().map_err(|e| e.to_string())?;
    let cameras = request.images.iter().map(|i| i.camera.clone()).collect();
    let images = request
        .images
        .into_iter()
        .map(|image| match image.payload {
            ImagePayload::Jpeg { data } => Ok(ImageInput::Encoded {
                format: ImageFormat::Jpeg,
                bytes: data,
            }),
            ImagePayload::Png { data } => Ok(ImageInput::Encoded {
                format: ImageFormat::Png,
                bytes: data,
            }),
            ImagePayload::Raw { tensor } => {
                tensor.check_len().map_err(|e| e.to_string())?;
                let [height, width, channels] = tensor.shape[..] else {
                    return Err(format!("raw image of shape {:?}", tensor.shape));
                };
                let (height, width, channels) =
                    (height as usize, width as usize, channels as usize);
                match tensor.dtype {
                    DType::U8 => Ok(ImageInput::RawU8 {
                        height,
                        width,
                        channels,
                        data: tensor.data,
                    }),
                    _ => Ok(ImageInput::RawF32 {
                        height,
                        width,
                        channels,
                        data: tensor.to_f32().map_err(|e| e.to_string())?,
                    }),
                }
            }
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok(ActionRequest {
        cameras,
        state,
        images,
        instruction: request.instruction,
        samples: request.samples as usize,
        seed: request.seed,
        guidance: request.guidance.map(guidance_from_wire).transpose()?,
    })
}

/// A generated chunk in its wire form.
pub fn chunk_to_wire(chunk: &ActionChunk) -> Result<WorkChunk, String> {
    let (s, k, n, d) = (
        usize_u32(chunk.samples),
        usize_u32(chunk.steps),
        usize_u32(chunk.chunk_len),
        usize_u32(chunk.action_dim),
    );
    let tensor = |shape: Vec<u32>, values: &[f32]| {
        Tensor::from_f32(shape, values).map_err(|e| e.to_string())
    };
    Ok(WorkChunk {
        actions: tensor(vec![s, n, d], &chunk.actions)?,
        updates: tensor(vec![s, k, n, d], &chunk.updates)?,
        noise: tensor(vec![s, n, d], &chunk.noise)?,
    })
}

/// A wire chunk as the engine's, for a request of `samples` samples of a `spec` model.
pub fn chunk_from_wire(
    spec: &ModelSpec,
    samples: usize,
    chunk: &WorkChunk,
) -> Result<ActionChunk, String> {
    let values = |t: &Tensor| {
        if t.dtype != DType::F32 {
            return Err(format!("{:?} tensor where f32 is expected", t.dtype));
        }
        t.to_f32().map_err(|e| e.to_string())
    };
    Ok(ActionChunk {
        samples,
        steps: spec.steps,
        chunk_len: spec.chunk_len,
        action_dim: spec.action_dim,
        actions: values(&chunk.actions)?,
        updates: values(&chunk.updates)?,
        noise: values(&chunk.noise)?,
    })
}

/// A profile in its wire form.
pub fn profile_to_wire(profile: &EngineProfile) -> ProfileWire {
    ProfileWire {
        model: profile.model.clone(),
        device: profile.device.clone(),
        points: profile
            .points
            .iter()
            .map(|p| ProfilePointWire {
                batch: p.batch,
                latency_ms: p.latency_ms,
            })
            .collect(),
        max_batch: profile.max_batch,
    }
}

/// A wire profile as the engine's; refused when it has no usable point.
pub fn profile_from_wire(profile: ProfileWire) -> Result<EngineProfile, String> {
    let mut points: Vec<ProfilePoint> = profile
        .points
        .iter()
        .map(|p| ProfilePoint {
            batch: p.batch,
            latency_ms: p.latency_ms,
        })
        .collect();
    if points.is_empty()
        || points
            .iter()
            .any(|p| p.batch == 0 || !(p.latency_ms.is_finite() && p.latency_ms >= 0.0))
    {
        return Err("the profile needs points with batch >= 1 and a finite latency >= 0".into());
    }
    points.sort_by_key(|p| p.batch);
    Ok(EngineProfile {
        model: profile.model,
        device: profile.device,
        points,
        max_batch: profile.max_batch.max(1),
    })
}

/// A model's shapes as the wire's `ModelInfo`.
pub fn model_info(spec: &ModelSpec) -> ModelInfo {
    ModelInfo {
        name: spec.name.clone(),
        chunk_len: usize_u32(spec.chunk_len),
        action_dim: usize_u32(spec.action_dim),
        state_dim: usize_u32(spec.state_dim),
        steps: usize_u32(spec.steps),
        max_images: usize_u32(spec.max_images),
        cameras: spec.cameras.clone(),
    }
}

/// The wire's `ModelInfo` as a model spec.
pub fn model_spec(info: &ModelInfo) -> ModelSpec {
    ModelSpec {
        cameras: info.cameras.clone(),
        camera_aliases: Default::default(),
        name: info.name.clone(),
        chunk_len: info.chunk_len as usize,
        action_dim: info.action_dim as usize,
        state_dim: info.state_dim as usize,
        steps: info.steps as usize,
        max_images: info.max_images as usize,
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_model::{LinearFlow, request};
    use super::*;
    use kairos_engine::ActionModel;

    #[test]
    fn rtt_is_a_moving_average_of_end_to_end_less_compute() {
        let mut rtt = RttEstimate::new(Duration::from_millis(1));
        // 30 ms end to end of which 10 ms compute: a 20 ms sample moves a quarter of the way.
        rtt.observe(Duration::from_millis(30), Duration::from_millis(10));
        let after_one = rtt.get().as_secs_f64() * 1e3;
        assert!((after_one - 5.75).abs() < 1e-6, "{after_one}");
        for _ in 0..60 {
            rtt.observe(Duration::from_millis(30), Duration::from_millis(10));
        }
        let settled = rtt.get().as_secs_f64() * 1e3;
        assert!((settled - 20.0).abs() < 1e-3, "{settled}");
        assert_eq!(rtt.samples(), 61);
        // A worker that reports more compute than the whole trip took adds a zero sample.
        rtt.observe(Duration::from_millis(5), Duration::from_millis(9));
        assert!(rtt.get() < Duration::from_millis(20));
    }

    #[test]
    fn auto_tier_follows_the_round_trip_with_hysteresis() {
        let ms = Duration::from_millis;
        let threshold = ms(20);
        // At registration: the threshold itself is cloud.
        assert_eq!(tier_from_rtt(None, ms(19), threshold), Tier::Edge);
        assert_eq!(tier_from_rtt(None, ms(20), threshold), Tier::Cloud);
        // An edge worker stays edge up to 25 % above the threshold, then turns cloud.
        assert_eq!(
            tier_from_rtt(Some(Tier::Edge), ms(24), threshold),
            Tier::Edge
        );
        assert_eq!(
            tier_from_rtt(Some(Tier::Edge), ms(25), threshold),
            Tier::Edge
        );
        assert_eq!(
            tier_from_rtt(Some(Tier::Edge), ms(26), threshold),
            Tier::Cloud
        );
        // A cloud worker stays cloud down to 25 % below it, then turns edge.
        assert_eq!(
            tier_from_rtt(Some(Tier::Cloud), ms(16), threshold),
            Tier::Cloud
        );
        assert_eq!(
            tier_from_rtt(Some(Tier::Cloud), ms(15), threshold),
            Tier::Cloud
        );
        assert_eq!(
            tier_from_rtt(Some(Tier::Cloud), ms(14), threshold),
            Tier::Edge
        );
        // An average that wanders inside the band never flips it.
        let mut rtt = RttEstimate::new(ms(30));
        let mut tier = tier_from_rtt(None, rtt.get(), threshold);
        let mut flips = 0;
        for i in 0..200 {
            let sample = if i % 2 == 0 { ms(17) } else { ms(23) };
            rtt.observe(sample, Duration::ZERO);
            let next = tier_from_rtt(Some(tier), rtt.get(), threshold);
            flips += u32::from(next != tier);
            tier = next;
        }
        assert_eq!(flips, 0, "{rtt:?}");
        assert_eq!(tier, Tier::Cloud);
        // A link that really got shorter moves it once.
        for _ in 0..40 {
            rtt.observe(ms(2), Duration::ZERO);
            let next = tier_from_rtt(Some(tier), rtt.get(), threshold);
            flips += u32::from(next != tier);
            tier = next;
        }
        assert_eq!((tier, flips), (Tier::Edge, 1));
    }

    #[test]
    fn requests_and_chunks_survive_the_wire() {
        let model = LinearFlow::new();
        let mut req = request(0.5, 7);
        req.images = vec![
            ImageInput::RawU8 {
                height: 1,
                width: 2,
                channels: 3,
                data: vec![1, 2, 3, 4, 5, 6],
            },
            ImageInput::Encoded {
                format: ImageFormat::Png,
                bytes: vec![9, 9],
            },
        ];
        req.samples = 2;
        // A request without camera names (built in-process) travels with positional ones.
        let back = request_from_wire(request_to_wire(&req).unwrap()).unwrap();
        assert_eq!(back.cameras, ["camera0", "camera1"]);
        assert_eq!(
            ActionRequest {
                cameras: Vec::new(),
                ..back
            },
            req
        );
        // A robot's names (every validated request has them) travel as they are.
        req.cameras = vec!["top".into(), "observation.images.wrist".into()];
        let back = request_from_wire(request_to_wire(&req).unwrap()).unwrap();
        assert_eq!(back, req);
        // So does a request's guidance.
        let mut guided = req.clone();
        guided.guidance = Some(Guidance {
            mode: GuidanceMode::Inpaint,
            prefix: vec![0.5; 6],
            delay: 2,
            execution_horizon: 3,
            schedule: PrefixSchedule::Exp,
            max_guidance_weight: 4.0,
        });
        let back = request_from_wire(request_to_wire(&guided).unwrap()).unwrap();
        assert_eq!(back, guided);
        let chunk = model
            .generate(std::slice::from_ref(&req))
            .unwrap()
            .remove(0);
        let wire = chunk_to_wire(&chunk).unwrap();
        assert_eq!(chunk_from_wire(&model.spec, 2, &wire).unwrap(), chunk);
        // A worker that answers a wrong shape is caught before the action manager sees it.
        let results = vec![WorkResult {
            chunk: Some(WorkChunk {
                actions: Tensor::from_f32(vec![1], &[0.0]).unwrap(),
                ..wire
            }),
            error: None,
        }];
        assert!(matches!(
            chunks_from_wire("w", &model.spec, std::slice::from_ref(&req), results),
            Err(PoolError::BadOutput { .. })
        ));
        // An engine error for one request stays that request's, not retried.
        let results = vec![WorkResult {
            chunk: None,
            error: Some("state[0] is NaN".into()),
        }];
        let answered =
            chunks_from_wire("w", &model.spec, std::slice::from_ref(&req), results).unwrap();
        assert!(matches!(answered[0], Err(PoolError::Remote { .. })));
    }

    #[test]
    fn profiles_and_specs_round_trip_and_empty_profiles_are_refused() {
        let profile = EngineProfile {
            model: "m".into(),
            device: "cpu".into(),
            points: vec![
                ProfilePoint {
                    batch: 1,
                    latency_ms: 2.0,
                },
                ProfilePoint {
                    batch: 4,
                    latency_ms: 5.0,
                },
            ],
            max_batch: 4,
        };
        assert_eq!(
            profile_from_wire(profile_to_wire(&profile)).unwrap(),
            profile
        );
        let mut empty = profile_to_wire(&profile);
        empty.points.clear();
        assert!(profile_from_wire(empty).is_err());
        let spec = LinearFlow::new().spec;
        assert_eq!(model_spec(&model_info(&spec)), spec);
    }
}
