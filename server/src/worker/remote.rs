//! A remote engine worker (`kairos worker`) behind [`EngineInstance`]: each batch is one QUIC
//! stream of the worker's connection (`RunBatch` → `Chunks`, worker protocol `kairos-worker/1`,
//! `kairos_sdk::protocol::worker`), bounded by a deadline.
//!
//! The future a batch returns only waits on the network; the worker runs the model on its own
//! engine thread. A batch that cannot be answered because the worker is gone, its stream was
//! reset, its deadline passed, or it was answered with anything unusable (a count that is not
//! the batch's, a chunk of the wrong shape, a value that is not finite, text over the
//! protocol's limits) ends as [`PoolError::Lost`]: the worker is removed (its connection closed,
//! the reason counted, [`Removal`]) and the driver runs the batch's rounds again elsewhere.
//! Nothing a worker sent reaches a robot before it passed these checks. Errors the worker's
//! engine reports for single requests are ordinary per-request errors and are not retried.
//!

use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{ActionRequest, EngineProfile, ModelSpec};
use kairos_sdk::protocol::worker::{Chunks, RunBatch, WORKER_MAX_FRAME, WorkResult, WorkerMessage};
use kairos_sdk::protocol::{Limits, ReadFrameError, Validate, read_frame, write_body};
use quinn::{Connection, ConnectionError, ReadError, WriteError};

use super::removal::Removal;
use super::wire::{chunk_from_wire, request_to_wire};
use crate::config::WorkersConfig;
use crate::metrics::WorkerRemoval;
use crate::pool::{BatchChunks, BatchLabel, EngineInstance, PoolError, check_output};
use kairos_core::error::LossReason;
use kairos_core::scheduler::Tier;
use kairos_core::sync::lock;

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
        // Both terms are durations already, so `next` is finite and in range; keep the old
        // estimate rather than panic should that ever not hold.
        self.value = Duration::try_from_secs_f64(next.max(0.0)).unwrap_or(self.value);
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
    /// Removes the worker (once) when a batch shows it unusable.
    removal: Removal,
    link: Arc<Mutex<Link>>,
    workers: WorkersConfig,
}

impl RemoteEngine {
    /// The worker on `connection`, registered as `name` with its spec, profile (its `max_batch`
    /// already capped to the worker's) and tier (`None`: `auto`, classified by
    /// [`tier_from_rtt`] against `workers.cloud_rtt()`, first from QUIC's estimate). Its round
    /// trip starts at QUIC's estimate. A batch that is lost, or answered with anything but a
    /// valid `Chunks`, removes the worker through `removal`.
    pub fn new(
        name: String,
        spec: ModelSpec,
        profile: EngineProfile,
        tier: Option<Tier>,
        connection: Connection,
        removal: Removal,
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
            removal,
            link: Arc::new(Mutex::new(Link { rtt, tier })),
            workers,
        }
    }

    fn link(&self) -> Link {
        *lock(&self.link)
    }
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
        let removal = self.removal.clone();
        let link = self.link.clone();
        let cloud_rtt = self.auto_tier.then(|| self.workers.cloud_rtt());
        async move {
            let lost = |reason: LossReason, detail: String| {
                removal.remove(removal_for(reason), &detail);
                PoolError::Lost {
                    engine: name.clone(),
                    reason,
                    detail,
                }
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
                Ok(Err((reason, detail))) => return Err(lost(reason, detail)),
                Err(_) => {
                    let detail = format!("no answer within the deadline of {deadline:?}");
                    return Err(lost(LossReason::Deadline, detail));
                }
            };
            // Everything in the answer is checked before any of it is used: the protocol's
            // rules, then the batch's counts, shapes and values.
            let results = chunks
                .validate(&Limits::default())
                .map_err(|error| error.to_string())
                .and_then(|()| chunks_from_wire(&name, &spec, &batch, chunks.results));
            let results = match results {
                Ok(results) => results,
                Err(detail) => return Err(lost(LossReason::InvalidAnswer, detail)),
            };
            let compute = Duration::from_micros(chunks.compute_us);
            {
                let mut link = lock(&link);
                link.rtt.observe(sent.elapsed(), compute);
                if let Some(threshold) = cloud_rtt {
                    link.tier = tier_from_rtt(Some(link.tier), link.rtt.get(), threshold);
                }
            }
            Ok(results)
        }
        .boxed()
    }
}

/// How a worker that lost a batch this way is removed.
fn removal_for(reason: LossReason) -> WorkerRemoval {
    match reason {
        LossReason::ConnectionLost | LossReason::Gone => WorkerRemoval::ConnectionLost,
        LossReason::StreamReset => WorkerRemoval::StreamFailed,
        LossReason::InvalidAnswer => WorkerRemoval::InvalidAnswer,
        LossReason::Deadline => WorkerRemoval::Deadline,
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
        Err(error) => return Err((LossReason::InvalidAnswer, error.to_string())),
    };
    match WorkerMessage::decode(&frame) {
        Ok(WorkerMessage::Chunks(chunks))
            if chunks.batch_id == run.batch_id && chunks.attempt == run.attempt =>
        {
            Ok(chunks)
        }
        Ok(other) => Err((
            LossReason::InvalidAnswer,
            format!(
                "expected the Chunks of batch {} attempt {}, got {}",
                run.batch_id,
                run.attempt,
                other.kind()
            ),
        )),
        Err(error) => Err((LossReason::InvalidAnswer, error.to_string())),
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

/// The worker's answers as the pool's per-request results, checked against the batch: one
/// result per request, each chunk of the request's exact shape with finite values (an error
/// text is the request's own answer, not retried). Any violation makes the whole answer
/// unusable: the reason.
fn chunks_from_wire(
    name: &str,
    spec: &ModelSpec,
    batch: &[ActionRequest],
    results: Vec<WorkResult>,
) -> Result<BatchChunks, String> {
    if results.len() != batch.len() {
        return Err(format!(
            "{} results for {} requests",
            results.len(),
            batch.len()
        ));
    }
    let mut out = Vec::with_capacity(results.len());
    for (i, (result, request)) in results.into_iter().zip(batch).enumerate() {
        let entry = match (result.chunk, result.error) {
            (Some(chunk), None) => {
                let chunk = chunk_from_wire(spec, request.samples.max(1), &chunk)
                    .map_err(|reason| format!("result {i}: {reason}"))?;
                check_output(
                    name,
                    spec,
                    std::slice::from_ref(request),
                    std::slice::from_ref(&chunk),
                )
                .map_err(|error| format!("result {i}: {error}"))?;
                Ok(chunk)
            }
            (None, Some(message)) => Err(PoolError::Remote {
                engine: name.to_string(),
                message,
            }),
            _ => return Err(format!("result {i} has neither or both of chunk and error")),
        };
        out.push(entry);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::wire::{chunk_to_wire, request_from_wire};
    use super::*;
    use crate::pool::test_model::{LinearFlow, request};
    use kairos_engine::{ActionModel, ImageFormat, ImageInput};
    use kairos_sdk::protocol::Tensor;
    use kairos_sdk::protocol::worker::WorkChunk;

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
        guided.guidance = Some(kairos_engine::Guidance {
            mode: kairos_engine::GuidanceMode::Inpaint,
            prefix: vec![0.5; 6],
            delay: 2,
            execution_horizon: 3,
            schedule: kairos_engine::PrefixSchedule::Exp,
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
        // A worker that answers a wrong shape, a value that is not finite or the wrong number
        // of results is caught before the action manager sees anything of it.
        let answer = |chunk: WorkChunk| {
            vec![WorkResult {
                chunk: Some(chunk),
                error: None,
            }]
        };
        let unusable = |results: Vec<WorkResult>| {
            chunks_from_wire("w", &model.spec, std::slice::from_ref(&req), results)
                .map(|_| ())
                .unwrap_err()
        };
        let short = WorkChunk {
            actions: Tensor::from_f32(vec![1], &[0.0]).unwrap(),
            ..wire.clone()
        };
        assert!(unusable(answer(short)).contains("shape"));
        let flat = WorkChunk {
            actions: Tensor::from_f32(vec![chunk.actions.len() as u32], &chunk.actions).unwrap(),
            ..wire.clone()
        };
        assert!(unusable(answer(flat)).contains("shape"));
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            for tensor in 0..3 {
                let mut values = chunk.clone();
                match tensor {
                    0 => values.actions[3] = bad,
                    1 => values.updates[5] = bad,
                    _ => values.noise[0] = bad,
                }
                let reason = unusable(answer(chunk_to_wire(&values).unwrap()));
                assert!(reason.contains("not a finite number"), "{reason}");
            }
        }
        let mut two = answer(wire.clone());
        two.push(two[0].clone());
        assert!(unusable(two).contains("2 results for 1 requests"));
        assert!(unusable(Vec::new()).contains("0 results"));
        // An engine error for one request stays that request's, not retried.
        let results = vec![WorkResult {
            chunk: None,
            error: Some("state[0] is NaN".into()),
        }];
        let answered =
            chunks_from_wire("w", &model.spec, std::slice::from_ref(&req), results).unwrap();
        assert!(matches!(answered[0], Err(PoolError::Remote { .. })));
    }
}
