//! One replayed task: a robot that replays a recorded trace against a server over real QUIC.
//!
//! The robot follows the SDK's execution rules exactly — it *is* the SDK's sans-IO
//! [`ChunkExecutor`] (alignment, discarding, Last Exec Info) driven by the tokio clock — and the
//! replay trigger of docs/TRACES.md, the one the simulator's robots follow:
//!
//! - round `i` goes out once the robot has started `issued_at_action[i]` actions and holds the
//!   reply to round `i − 1`, immediately if it is already past that index, and at the latest when
//!   its chunk runs out (paper §5.1, "at the recorded action index");
//! - no request goes out once the chunks received cover the task's `total_actions`; past the last
//!   recorded round (only if replay drifted) the last round is repeated when the robot runs dry;
//! - the task ends when its last action starts; its latency is from the first request's send to
//!   that tick.
//!
//! Each request carries the round's recorded confidence as its state (what the trace-replay
//! engine turns back into the chunk, `pool::replay`), one blank frame of the recorded observation
//! size, and the trace's horizon setting (the recorded `H` as `static` for a round recorded
//! without confidence). A server re-fetch is answered with a new capture of the same round, and
//! the chunk stays aligned where the request went out: the replay engine answers with the
//! recorded chunk, meant for the recorded steps, so the replayed work is the recording's (as in
//! the simulator, `sim` module doc).

use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::client::{Client, ClientError, RoundReply, RoundRequest};
use kairos_sdk::protocol::{
    FetchObservation, HorizonSelection, Image, ImagePayload, LastExecInfo, Observation,
    RemainingHint, TaskOutcome, Tensor,
};
use kairos_sdk::robot::ChunkExecutor;
use kairos_sdk::trace::{RoundTrace, TaskTrace};
use tokio::time::Instant;

use kairos_server::pool::replay::replay_state;

use kairos_core::sync::lock;

/// Why a replayed task failed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// A round failed (connection, server error).
    #[error("task {task}, round {round}: {source}")]
    Round {
        /// Trace task id.
        task: u64,
        /// Round id.
        round: u64,
        /// The client's error.
        source: ClientError,
    },
    /// The reply does not fit the trace (wrong chunk length, malformed actions).
    #[error("task {task}, round {round}: {reason}")]
    BadReply {
        /// Trace task id.
        task: u64,
        /// Round id.
        round: u64,
        /// What is wrong.
        reason: String,
    },
    /// The round's task panicked.
    #[error("round task failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// One answered round, as the robot saw it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundOutcome {
    /// `H` the server chose.
    pub horizon: u32,
    /// Request sent → reply received, µs (client clock).
    pub round_trip_us: u64,
    /// The server's timing: arrival → dispatch.
    pub queue_us: u64,
    /// The server's timing: waiting for the re-fetched observations of the round's batch.
    pub refetch_us: u64,
    /// The server's timing: the batch's generation.
    pub inference_us: u64,
    /// The server's timing: arrival → reply sent.
    pub server_total_us: u64,
    /// Requests in the batch.
    pub batch_size: u32,
    /// Fresh observations sent for the round (server re-fetches).
    pub refetches: u32,
}

/// A finished replayed task.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayedTask {
    /// Trace task id.
    pub trace_task: u64,
    /// When its first request was sent.
    pub started_at: Instant,
    /// First request sent → last action started (the paper's end-to-end latency).
    pub latency: Duration,
    /// Every answered round, in order.
    pub rounds: Vec<RoundOutcome>,
}

/// What a request needs from the trace.
struct Requests {
    trace: TaskTrace,
    frame: Image,
    hints: bool,
}

impl Requests {
    /// Round `i` of the trace; past the end the last one is repeated.
    fn round(&self, i: usize) -> &RoundTrace {
        let rounds = &self.trace.rounds;
        &rounds[i.min(rounds.len().saturating_sub(1))]
    }

    fn observation(&self, i: usize, now_us: u64) -> Observation {
        let n = self.trace.chunk_len as usize;
        let state = replay_state(self.round(i), n);
        Observation {
            captured_at_us: now_us,
            // A 1-D tensor of `chunk_len` f32: the shape always matches the data.
            state: Tensor::from_f32(vec![self.trace.chunk_len], &state).unwrap_or_else(|_| {
                Tensor {
                    dtype: kairos_sdk::protocol::DType::F32,
                    shape: vec![0],
                    data: Vec::new(),
                }
            }),
            images: vec![self.frame.clone()],
            instruction: String::new(),
        }
    }

    fn request(&self, i: usize, now_us: u64, last_exec: Option<LastExecInfo>) -> RoundRequest {
        let round = self.round(i);
        let horizon = if round.confidence.is_some() {
            HorizonSelection {
                policy: self.trace.horizon.policy.clone(),
                params: self.trace.horizon.params.clone(),
                samples: 1,
            }
        } else {
            HorizonSelection {
                policy: "static".into(),
                params: [("h".to_string(), f64::from(round.horizon))].into(),
                samples: 1,
            }
        };
        let left = self.trace.rounds.len().saturating_sub(i).max(1);
        RoundRequest {
            observation: self.observation(i, now_us),
            last_exec,
            horizon: Some(horizon),
            remaining: self.hints.then(|| RemainingHint {
                rounds: u32::try_from(left).ok(),
                seconds: None,
            }),
            control_hz: Some(self.trace.control_hz),
            seed: None,
            chunking: None,
        }
    }
}

/// A blank single-channel camera frame of about `bytes` bytes (rows of 256 pixels).
fn blank_frame(bytes: u32) -> Image {
    const WIDTH: u32 = 256;
    let rows = bytes.div_ceil(WIDTH).max(1);
    let data = vec![0u8; (rows * WIDTH) as usize];
    Image {
        camera: "replay".into(),
        payload: ImagePayload::Raw {
            tensor: Tensor::from_u8(vec![rows, WIDTH, 1], data).unwrap_or_else(|_| Tensor {
                dtype: kairos_sdk::protocol::DType::U8,
                shape: vec![1, 1, 1],
                data: vec![0],
            }),
        },
    }
}

type InFlight =
    tokio::task::JoinHandle<(kairos_sdk::client::Task, Result<RoundReply, ClientError>)>;

async fn sleep_until_some(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// Replays `trace` as task `task_id` over `client`, starting now. `hints` sends the
/// remaining-work hint (rounds left in the trace); `on_round` sees every answered round.
pub async fn replay_task(
    client: &Client,
    task_id: u64,
    trace: &TaskTrace,
    hints: bool,
    mut on_round: impl FnMut(&RoundOutcome),
) -> Result<ReplayedTask, ReplayError> {
    let clock = client.clock();
    let total = u64::from(trace.total_actions);
    let period = kairos_sdk::robot::runner::control_period(trace.control_hz);
    // Shared with the re-fetch answer, which recaptures the observation inside the round. A
    // poisoned lock means a panic elsewhere in this task, which fails the task anyway.
    let executor = Arc::new(Mutex::new(ChunkExecutor::new(trace.control_hz, 0.5)));
    let requests = Arc::new(Requests {
        trace: trace.clone(),
        frame: blank_frame(trace.rounds.first().map_or(0, |r| r.obs_bytes)),
        hints,
    });

    let mut task = Some(client.task(task_id));
    let mut in_flight: Option<(usize, InFlight)> = None;
    let mut sent = 0usize;
    let mut next_tick: Option<Instant> = None;
    let mut started_at: Option<Instant> = None;
    let mut rounds = Vec::with_capacity(trace.rounds.len());

    let finished_at = loop {
        // Send the next round if it is due.
        let due = {
            let e = lock(&executor);
            let covered = e.executed_total() + e.remaining() as u64;
            let index = u64::from(requests.round(sent).issued_at_action);
            in_flight.is_none()
                && covered < total
                && (e.executed_total() >= index || e.remaining() == 0)
        };
        if due && let Some(mut round_task) = task.take() {
            let now = Instant::now();
            let now_us = clock.to_us(now);
            started_at.get_or_insert(now);
            let last_exec = lock(&executor).request_sent(round_task.next_round(), now_us);
            let request = requests.request(sent, now_us, last_exec);
            let index = sent;
            sent += 1;
            let source_requests = Arc::clone(&requests);
            let round_clock = clock;
            in_flight = Some((
                index,
                tokio::spawn(async move {
                    let mut refetch = move |_: &FetchObservation| {
                        Some(source_requests.observation(index, round_clock.now_us()))
                    };
                    let result = round_task.submit(request, &mut refetch).await;
                    (round_task, result)
                }),
            ));
        }

        tokio::select! {
            joined = async {
                match in_flight.as_mut() {
                    Some((_, handle)) => handle.await,
                    None => std::future::pending().await,
                }
            } => {
                in_flight = None;
                let (round_task, result) = joined?;
                let round = round_task.next_round().saturating_sub(1);
                task = Some(round_task);
                let reply = result.map_err(|source| ReplayError::Round {
                    task: trace.task,
                    round,
                    source,
                })?;
                let outcome = apply_reply(trace, round, &reply, &executor)?;
                on_round(&outcome);
                rounds.push(outcome);
                if next_tick.is_none() {
                    // An idle robot starts the new chunk's first action at once.
                    next_tick = Some(Instant::now());
                }
            }
            () = sleep_until_some(next_tick) => {
                let tick = next_tick.unwrap_or_else(Instant::now);
                let mut e = lock(&executor);
                if e.next_action(clock.to_us(tick)).is_none() {
                    next_tick = None;
                    continue;
                }
                if e.executed_total() >= total {
                    break tick;
                }
                next_tick = Some(tick + period);
            }
        }
    };

    // A round still in flight is abandoned (its stream is cancelled, so the server drops it),
    // as the simulator cancels it; then the task ends with its last chunk fully executed.
    if let Some((_, handle)) = in_flight.take() {
        handle.abort();
    }
    let next_round = task.as_ref().map_or(sent as u64, |t| t.next_round());
    let last_exec = lock(&executor)
        .last_exec(clock.to_us(finished_at))
        .map(|info| LastExecInfo {
            actions_remaining: 0,
            ..info
        });
    let ending = task.unwrap_or_else(|| client.task_from(task_id, next_round));
    ending
        .end(TaskOutcome::Done, last_exec)
        .await
        .map_err(|source| ReplayError::Round {
            task: trace.task,
            round: next_round,
            source,
        })?;
    let started_at = started_at.unwrap_or(finished_at);
    Ok(ReplayedTask {
        trace_task: trace.task,
        started_at,
        latency: finished_at.saturating_duration_since(started_at),
        rounds,
    })
}

/// Aligns a reply's chunk on the robot's timeline and records the round.
fn apply_reply(
    trace: &TaskTrace,
    round: u64,
    reply: &RoundReply,
    executor: &Mutex<ChunkExecutor>,
) -> Result<RoundOutcome, ReplayError> {
    let bad = |reason: String| ReplayError::BadReply {
        task: trace.task,
        round,
        reason,
    };
    let r = &reply.reply;
    if r.chunk_len != trace.chunk_len {
        return Err(bad(format!(
            "the server generates chunks of {} actions, the trace has {}",
            r.chunk_len, trace.chunk_len
        )));
    }
    let values = r.actions.to_f32().map_err(|e| bad(e.to_string()))?;
    let horizon = r.horizon as usize;
    if horizon == 0 || values.len() % horizon != 0 {
        return Err(bad(format!(
            "{} action values for a horizon of {horizon}",
            values.len()
        )));
    }
    let actions: Vec<Vec<f32>> = values
        .chunks(values.len() / horizon)
        .map(<[f32]>::to_vec)
        .collect();
    lock(executor).reply_arrived(round, actions);
    Ok(RoundOutcome {
        horizon: r.horizon,
        round_trip_us: reply.received_at_us.saturating_sub(reply.sent_at_us),
        queue_us: r.timing.queue_us,
        refetch_us: r.timing.refetch_us,
        inference_us: r.timing.inference_us,
        server_total_us: r.timing.total_us,
        batch_size: r.timing.batch_size,
        refetches: reply.refetches,
    })
}
