//! `kairos bench chunking --live`: the delay is real and the server predicts `d` itself.
//!
//! A real server starts in this process ([`crate::fleet::LocalServer`]: TLS, the real scheduler
//! and driver) serving the task's policy on one engine instance whose every forward pass takes
//! at least `forward` ([`SlowForward`]: the bench policy samples in well under a millisecond,
//! a VLA on a GPU takes tens; the engine thread waits out the rest), profiled at start as
//! `kairos serve` profiles an engine. Many robots connect with the real client at once, so the
//! rounds queue and batch behind each other: the delay of a round is what the loaded server
//! makes it. Each robot runs its episodes in real
//! time, one action per control tick (`--live-hz`), with the SDK's [`ChunkExecutor`]: it sends
//! a request every `period` steps with its Last Exec Info (round, phase, remaining actions and
//! the previous round's actual `d`), keeps executing while the round is in flight, and applies
//! the chunk when it arrives, aligned by its own count or by the reply's `start`
//! ([`Alignment`]). The server predicts each round's `d` from that Last Exec Info, the engine
//! profile, its own reply time and the task's network time, plans the round with the robot's
//! strategy, and scores its prediction against the robot's next report.
//!
//! `sync` waits for each chunk standing still, then executes `period` actions of it.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_core::driver::DriverStats;
use kairos_engine::profile::{DEFAULT_MIN_GAIN, MeasureOptions, measure};
use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineError, ModelChunking, ModelSpec,
};
use kairos_sdk::client::{Client, ClientError, NoRefetch, RoundReply, RoundRequest, Task};
use kairos_sdk::protocol::{ChunkingSelection, ChunkingStrategy, PrefixSchedule, Reply};
use kairos_sdk::protocol::{HorizonSelection, Observation, TaskOutcome, Tensor};
use kairos_sdk::robot::{Alignment, ChunkExecutor};
use kairos_server::config::Config;
use kairos_server::pool::{EngineInstance, EnginePool, LocalEngine};

use super::episode::{Execution, Outcome, diverged, forecast, velocity_jump};
use crate::fleet::{self, LocalServer};
use crate::horizon_bench::env::{ACTION_DIM, Env, EnvConfig, OBS_DIM};
use crate::horizon_bench::noise_seed;
use crate::horizon_bench::served::HorizonFlowModel;

/// Why a live run failed.
#[derive(Debug, thiserror::Error)]
#[error("live: {0}")]
pub struct LiveError(pub String);

fn live(what: &str) -> impl FnOnce(String) -> LiveError + '_ {
    move |e| LiveError(format!("{what}: {e}"))
}

/// What a live run does.
#[derive(Clone, Debug)]
pub struct LivePlan {
    /// The policy's directory, served as `horizon-flow:DIR`.
    pub model_dir: PathBuf,
    /// The server's state (certificate, tokens); created if missing.
    pub data_dir: PathBuf,
    /// The task.
    pub env: EnvConfig,
    /// The executions compared.
    pub executions: Vec<Execution>,
    /// How the robots align arriving chunks (each execution runs once per alignment).
    pub alignments: Vec<Alignment>,
    /// Episodes per (execution, alignment); the same seeds for all.
    pub episodes: usize,
    /// First episode seed.
    pub seed: u64,
    /// Robots connected at once (the server's load).
    pub robots: usize,
    /// Control ticks per second of every robot.
    pub control_hz: f32,
    /// Steps between requests.
    pub period: u32,
    /// The least time of one forward pass of the served model.
    pub forward: Duration,
}

/// A model whose every forward pass takes at least `forward`: the engine thread sleeps out what
/// the inner model's generation did not take (an accelerator's latency, without its compute on
/// the CPU the robots and the server share). The chunks are the inner model's.
pub struct SlowForward {
    /// The model.
    pub inner: HorizonFlowModel,
    /// The least time of one `generate`.
    pub forward: Duration,
}

impl ActionModel for SlowForward {
    fn spec(&self) -> &ModelSpec {
        self.inner.spec()
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        let started = std::time::Instant::now();
        let chunks = self.inner.generate(batch)?;
        std::thread::sleep(self.forward.saturating_sub(started.elapsed()));
        Ok(chunks)
    }

    fn chunking(&self) -> ModelChunking {
        self.inner.chunking()
    }
}

/// One (execution, alignment)'s live results.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveResult {
    /// The execution.
    pub execution: Execution,
    /// The alignment.
    pub alignment: Alignment,
    /// Episodes run.
    pub episodes: usize,
    /// Episodes that succeeded.
    pub successes: usize,
    /// Σ switch and within-chunk jumps, as in-process.
    pub outcome: Outcome,
    /// Episodes in which a chunk diverged (an action beyond ±10).
    pub diverged: usize,
    /// Rounds whose robot executed the previous chunk when the reply came, and among them: the
    /// actual `d` summed, the predicted one summed, |predicted − actual| summed, and exact.
    pub rounds: u64,
    /// Σ actual `d`.
    pub actual_sum: u64,
    /// Σ |predicted − actual|.
    pub abs_error_sum: u64,
    /// Σ (predicted − actual).
    pub error_sum: i64,
    /// Rounds predicted exactly.
    pub exact: u64,
}

impl LiveResult {
    /// Successes / episodes.
    pub fn success_rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }
}

/// The whole live run: one result per (execution, alignment), and the server's own record.
#[derive(Clone, Debug)]
pub struct LiveReport {
    /// Per (execution, alignment), in plan order.
    pub results: Vec<LiveResult>,
    /// The server's totals at the end (its delay prediction histograms included).
    pub server: DriverStats,
}

/// One episode's record of its rounds' `d`.
#[derive(Clone, Copy, Debug, Default)]
struct Delays {
    rounds: u64,
    actual: u64,
    abs_error: u64,
    error: i64,
    exact: u64,
}

type Pending = tokio::task::JoinHandle<(Task, u64, Result<RoundReply, ClientError>)>;

/// Runs `plan`. Blocking: it runs its own tokio runtime.
pub fn run_live(plan: &LivePlan, on_episode: &(dyn Fn() + Sync)) -> Result<LiveReport, LiveError> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| LiveError(format!("starting the runtime: {e}")))?;
    runtime.block_on(run(plan, on_episode))
}

async fn start_server(plan: &LivePlan) -> Result<LocalServer, LiveError> {
    let (model_dir, forward) = (plan.model_dir.clone(), plan.forward);
    let pool = tokio::task::spawn_blocking(move || {
        let inner = HorizonFlowModel::load(&model_dir).map_err(|e| e.to_string())?;
        let model: Arc<dyn ActionModel> = Arc::new(SlowForward { inner, forward });
        let profile = measure(
            model.as_ref(),
            &MeasureOptions {
                batches: vec![1, 2, 4, 8],
                iterations: 3,
                device: format!("cpu, forward at least {} ms", forward.as_millis()),
                min_gain: DEFAULT_MIN_GAIN,
            },
            |_| {},
        )
        .map_err(|e| e.to_string())?;
        let engine: Arc<dyn EngineInstance> =
            Arc::new(LocalEngine::start("edge-0", model, profile));
        EnginePool::new(vec![engine]).map_err(|e| e.to_string())
    })
    .await
    .map_err(|e| live("loading the model")(e.to_string()))?
    .map_err(live("loading the model"))?;
    let config = Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        data_dir: plan.data_dir.clone(),
        ..Config::default()
    };
    LocalServer::start(&config, pool, Default::default())
        .await
        .map_err(|e| live("starting the server")(e.to_string()))
}

async fn run(plan: &LivePlan, on_episode: &(dyn Fn() + Sync)) -> Result<LiveReport, LiveError> {
    let server = start_server(plan).await?;
    let outcome = async {
        let config = server
            .generated_robot()
            .ok_or_else(|| LiveError("the server generated no robot token".into()))?;
        let clients = fleet::connect(&config, plan.robots.max(1))
            .await
            .map_err(|e| live("connecting")(e.to_string()))?;
        let combos: Vec<(Execution, Alignment)> = plan
            .executions
            .iter()
            .flat_map(|&e| plan.alignments.iter().map(move |&a| (e, a)))
            .collect();
        // Episodes interleave the combinations, so that load on the server (which the other
        // robots make) hits them alike.
        let jobs: Vec<(usize, u64)> = (0..plan.episodes as u64)
            .flat_map(|e| (0..combos.len()).map(move |c| (c, e)))
            .collect();
        let next = AtomicUsize::new(0);
        type Slot = Option<Result<(Outcome, Delays), LiveError>>;
        let slots: Mutex<Vec<Slot>> = Mutex::new((0..jobs.len()).map(|_| None).collect());
        let robot = |client: &Client| {
            let (jobs, next, slots, combos) = (&jobs, &next, &slots, &combos);
            let client = client.clone();
            async move {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(c, e)) = jobs.get(i) else { break };
                    let (execution, alignment) = combos[c];
                    let task = ((c as u64) << 32) | e;
                    let r = episode(&client, task, plan, execution, alignment, plan.seed + e).await;
                    if let Ok(mut slots) = slots.lock() {
                        slots[i] = Some(r);
                    }
                    on_episode();
                }
            }
        };
        futures::future::join_all(clients.iter().map(robot)).await;
        for client in &clients {
            client.close().await;
        }
        let slots = slots
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let mut results: Vec<LiveResult> = combos
            .iter()
            .map(|&(execution, alignment)| LiveResult {
                execution,
                alignment,
                episodes: 0,
                successes: 0,
                outcome: Outcome::default(),
                diverged: 0,
                rounds: 0,
                actual_sum: 0,
                abs_error_sum: 0,
                error_sum: 0,
                exact: 0,
            })
            .collect();
        for (slot, &(c, _)) in slots.into_iter().zip(&jobs) {
            let (o, d) = slot.ok_or_else(|| LiveError("an episode did not run".into()))??;
            let r = &mut results[c];
            r.episodes += 1;
            r.successes += usize::from(o.success);
            r.outcome.steps += o.steps;
            r.outcome.calls += o.calls;
            r.outcome.switch_jump += o.switch_jump;
            r.outcome.switches += o.switches;
            r.outcome.within_jump += o.within_jump;
            r.outcome.within += o.within;
            r.diverged += usize::from(o.diverged);
            r.rounds += d.rounds;
            r.actual_sum += d.actual;
            r.abs_error_sum += d.abs_error;
            r.error_sum += d.error;
            r.exact += d.exact;
        }
        Ok(results)
    }
    .await;
    let report = server.shutdown().await;
    Ok(LiveReport {
        results: outcome?,
        server: report.driver,
    })
}

fn wire_schedule(schedule: kairos_engine::PrefixSchedule) -> PrefixSchedule {
    match schedule {
        kairos_engine::PrefixSchedule::Zeros => PrefixSchedule::Zeros,
        kairos_engine::PrefixSchedule::Ones => PrefixSchedule::Ones,
        kairos_engine::PrefixSchedule::Linear => PrefixSchedule::Linear,
        kairos_engine::PrefixSchedule::Exp => PrefixSchedule::Exp,
    }
}

/// One episode in real time (module docs).
async fn episode(
    client: &Client,
    task: u64,
    plan: &LivePlan,
    execution: Execution,
    alignment: Alignment,
    seed: u64,
) -> Result<(Outcome, Delays), LiveError> {
    let mut env = Env::new(plan.env.clone(), seed);
    let tick = Duration::try_from_secs_f64(1.0 / f64::from(plan.control_hz))
        .map_err(|e| live("--live-hz")(format!("{}: {e}", plan.control_hz)))?;
    let mut exec = ChunkExecutor::new(plan.control_hz, 1.0).with_alignment(alignment);
    let mut out = Outcome::default();
    let mut delays = Delays::default();
    let mut handle = Some(client.task(task));
    let mut in_flight: Option<Pending> = None;
    // The reply being executed, for the committed actions a forecast rolls through.
    let mut current: Option<Reply> = None;
    let mut sync_left = 0u32;
    let mut previous: Option<(u64, [f32; ACTION_DIM])> = None;
    let mut last_capture: Option<u32> = None;
    let mut step = 0u32;
    let mut ticker = tokio::time::interval(tick);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let strategy = execution.strategy();
    let settings = execution.chunking(&Default::default());
    while !env.done() {
        ticker.tick().await;
        let now_us = client.now_us();
        // A reply that came in since the last tick is applied before this tick's action.
        if in_flight.as_ref().is_some_and(|p| p.is_finished())
            && let Some(pending) = in_flight.take()
        {
            let (task_handle, round, result) = pending
                .await
                .map_err(|e| live("joining a round")(e.to_string()))?;
            handle = Some(task_handle);
            let reply = result
                .map_err(|e| live(&format!("episode {seed}, round {round}"))(e.to_string()))?
                .reply;
            out.diverged |= diverged(&reply.actions.to_f32().unwrap_or_default());
            let actions: Vec<Vec<f32>> = reply
                .actions
                .to_f32()
                .map_err(|e| live("decoding the reply")(e.to_string()))?
                .chunks_exact(ACTION_DIM)
                .map(<[f32]>::to_vec)
                .collect();
            let applied = exec.reply_arrived_from(round, actions, reply.start);
            if let Some(last) = exec.last_exec(now_us)
                && let (Some(actual), Some(p)) = (last.delay, reply.delay)
                && applied.replaced.is_some()
            {
                let error = i64::from(p) - i64::from(actual);
                delays.rounds += 1;
                delays.actual += u64::from(actual);
                delays.error += error;
                delays.abs_error += error.unsigned_abs();
                delays.exact += u64::from(error == 0);
            }
            if execution == Execution::Sync {
                sync_left = plan.period;
            }
            current = Some(reply);
        }
        // This tick's action: the executor's, or standing still (sync while it waits, or a
        // robot that ran out).
        let from_executor = match execution {
            Execution::Sync if sync_left == 0 => None,
            _ => exec.next_action(now_us).map(|a| {
                let mut v = [0.0; ACTION_DIM];
                v.copy_from_slice(&a.action[..ACTION_DIM]);
                (v, a.round)
            }),
        };
        if execution == Execution::Sync && from_executor.is_some() {
            sync_left = sync_left.saturating_sub(1);
        }
        let action = match from_executor {
            Some((a, round)) => {
                if let Some((prev_round, prev)) = &previous {
                    let jump = velocity_jump(&a, prev);
                    if *prev_round == round {
                        out.within_jump += jump;
                        out.within += 1;
                    } else {
                        out.switch_jump += jump;
                        out.switches += 1;
                    }
                }
                previous = Some((round, a));
                a
            }
            None => {
                let a = [0.0, 0.0, previous.as_ref().map_or(-1.0, |p| p.1[2])];
                previous = Some((u64::MAX, a));
                a
            }
        };
        env.step(&action);
        // The next request goes out after this tick's action, as the SDK's runner sends it: the
        // observation is of the state that action left.
        let due = match execution {
            Execution::Sync => sync_left == 0,
            Execution::Async(_) | Execution::Rtc(_) => {
                last_capture.is_none_or(|at| step >= at + plan.period)
            }
        };
        if in_flight.is_none()
            && due
            && let Some(mut task_handle) = handle.take()
        {
            let round = task_handle.next_round();
            let last_exec = exec.request_sent(round, now_us);
            let obs: [f32; OBS_DIM] = env.observe();
            let mut chunking = ChunkingSelection::new(strategy);
            if let Execution::Rtc(_) = execution {
                chunking.schedule = Some(wire_schedule(settings.schedule));
                chunking.execution_horizon = Some(settings.execution_horizon);
            }
            if strategy == ChunkingStrategy::ArrivalState
                && let (Some(reply), Some(last)) = (&current, last_exec)
            {
                let actions = reply.actions.to_f32().unwrap_or_default();
                let rows = actions.len() / ACTION_DIM;
                let left = (last.actions_remaining as usize).min(rows);
                let rows_ahead = forecast(&env, &actions[(rows - left) * ACTION_DIM..]);
                if !rows_ahead.is_empty() {
                    let flat: Vec<f32> = rows_ahead.concat();
                    chunking.forecast =
                        Tensor::from_f32(vec![rows_ahead.len() as u32, OBS_DIM as u32], &flat).ok();
                }
            }
            let request = RoundRequest {
                observation: Observation {
                    captured_at_us: now_us,
                    state: Tensor::from_f32(vec![OBS_DIM as u32], &obs)
                        .map_err(|e| live("encoding the observation")(e.to_string()))?,
                    images: Vec::new(),
                    instruction: String::new(),
                },
                last_exec,
                horizon: Some(HorizonSelection {
                    policy: "static".into(),
                    // The whole chunk: the robot re-plans on its own schedule.
                    params: [("h".to_string(), 1024.0)].into(),
                    samples: 1,
                }),
                remaining: None,
                control_hz: Some(plan.control_hz),
                seed: Some(noise_seed(seed, out.calls)),
                chunking: Some(chunking),
            };
            out.calls += 1;
            last_capture = Some(step);
            in_flight = Some(tokio::spawn(async move {
                let result = task_handle.submit(request, &mut NoRefetch).await;
                (task_handle, round, result)
            }));
        }
        step += 1;
    }
    if let Some(pending) = in_flight.take() {
        let (task_handle, _, _) = pending
            .await
            .map_err(|e| live("joining a round")(e.to_string()))?;
        handle = Some(task_handle);
    }
    out.success = env.success();
    out.steps = env.steps();
    if let Some(task_handle) = handle {
        let outcome = if out.success {
            TaskOutcome::Done
        } else {
            TaskOutcome::Failed
        };
        task_handle
            .end(outcome, exec.last_exec(client.now_us()))
            .await
            .map_err(|e| live(&format!("ending episode {seed}"))(e.to_string()))?;
    }
    Ok((out, delays))
}
