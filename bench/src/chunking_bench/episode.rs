//! One closed-loop episode with a delay of `D` control steps between an observation's capture
//! and its chunk's arrival, during which the robot keeps executing.
//!
//! The robot side is the SDK's real [`ChunkExecutor`] (its alignment: the actions executed since
//! the capture are skipped); the server side is the real planning code
//! ([`kairos_core::chunking::plan_round`], [`RoundPlan::finish`]) with the server's prediction
//! replaced by the exact `d` (in-process, the delay is known; `--live` has the server predict
//! it). Inference takes no virtual time. The first chunk of an episode is planned before the
//! clock starts (the robot waits for it, as at the start of any task); from then on a request
//! goes out every `period` steps, and its chunk arrives `delay` steps later.
//!
//! `sync` is synchronous execution: the robot stands still (zero velocity, gripper held) for the
//! `delay` steps of each inference, then executes `period` actions of the chunk from its first.

use std::time::{Duration, Instant};

use kairos_core::chunking::{
    ChunkingDefaults, DelayPrediction, PreviousChunk, RoundChunking, plan_round,
};
use kairos_core::time::Timestamp;
use kairos_engine::{ActionSpace, PrefixSchedule};
use kairos_sdk::protocol::{ChunkingStrategy, DType, Reply, Tensor, Timing};
use kairos_sdk::robot::ChunkExecutor;

use crate::horizon_bench::env::{ACTION_DIM, Env, EnvConfig, OBS_DIM};
use crate::horizon_bench::model::{FlowPolicy, ModelError};
use crate::horizon_bench::noise_seed;

/// Real-time chunking with other settings than the server's defaults.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct RtcSettings {
    /// The name in tables and CSVs.
    pub name: &'static str,
    /// The prefix schedule.
    pub schedule: PrefixSchedule,
    /// Previous actions that guide the chunk.
    pub execution_horizon: u32,
}

/// The real-time chunking variants the bench runs beside the server's defaults (LeRobot's:
/// `linear`, execution horizon 10): guidance on the committed actions only (`zeros`), and the
/// `exp` schedule over a horizon of 4, about LeRobot's 10 of 50 at this bench's chunk of 16.
pub const RTC_VARIANTS: [RtcSettings; 2] = [
    RtcSettings {
        name: "rtc_zeros",
        schedule: PrefixSchedule::Zeros,
        execution_horizon: 10,
    },
    RtcSettings {
        name: "rtc_exp4",
        schedule: PrefixSchedule::Exp,
        execution_horizon: 4,
    },
];

/// How the robot runs: synchronously, or asynchronously with a server chunking strategy.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Execution {
    /// The robot waits for every chunk (`delay` idle steps per inference).
    Sync,
    /// The robot keeps executing; the server applies this strategy with its default settings.
    Async(ChunkingStrategy),
    /// The robot keeps executing; the server applies `rtc` with these settings.
    Rtc(RtcSettings),
}

impl Execution {
    /// Every execution the bench compares, synchronous first, then the strategies, then the
    /// real-time chunking variants.
    pub fn all() -> Vec<Execution> {
        std::iter::once(Execution::Sync)
            .chain(ChunkingStrategy::ALL.into_iter().map(Execution::Async))
            .chain(RTC_VARIANTS.into_iter().map(Execution::Rtc))
            .collect()
    }

    /// The name in tables and CSVs: `sync`, the strategy's wire name, or the variant's.
    pub fn name(self) -> &'static str {
        match self {
            Execution::Sync => "sync",
            Execution::Async(s) => s.as_str(),
            Execution::Rtc(r) => r.name,
        }
    }

    /// The execution named `name`.
    pub fn parse(name: &str) -> Option<Execution> {
        Execution::all().into_iter().find(|e| e.name() == name)
    }

    /// The strategy the server applies (`skip` for `sync`, whose robot idles while it waits).
    pub fn strategy(self) -> ChunkingStrategy {
        match self {
            Execution::Sync => ChunkingStrategy::Skip,
            Execution::Async(s) => s,
            Execution::Rtc(_) => ChunkingStrategy::Rtc,
        }
    }

    /// The round's chunking with the server's `defaults` where the execution sets nothing.
    pub fn chunking(self, defaults: &ChunkingDefaults) -> RoundChunking {
        let mut chunking = RoundChunking::with_defaults(self.strategy(), defaults);
        if let Execution::Rtc(r) = self {
            chunking.schedule = r.schedule;
            chunking.execution_horizon = r.execution_horizon;
        }
        chunking
    }
}

/// One episode's outcome.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Outcome {
    /// Whether the task succeeded.
    pub success: bool,
    /// Control steps taken.
    pub steps: u32,
    /// Chunks requested.
    pub calls: u32,
    /// Σ ‖a_t − a_{t−1}‖ (velocity command) over steps whose action is the first of a newly
    /// applied chunk, and how many there were.
    pub switch_jump: f64,
    /// Switch steps.
    pub switches: u32,
    /// The same over consecutive actions of one chunk.
    pub within_jump: f64,
    /// Within-chunk steps.
    pub within: u32,
    /// Whether a chunk's sampling diverged: an action value beyond ±10 (the task's commands are
    /// in [−1, 1]; the environment clamps what it executes).
    pub diverged: bool,
    /// Wall time spent sampling chunks.
    pub sampling: Duration,
}

/// The robot's own forecast of its state after each of the `committed` actions (`[n][D]`):
/// its episode copied without future randomness (no actuation noise, pushes or turns; the goal
/// keeps its observed velocity) and stepped through them. What `arrival_state` is given as the
/// client's predictor.
pub fn forecast(env: &Env, committed: &[f32]) -> Vec<Vec<f32>> {
    let mut copy = env.without_randomness();
    committed
        .chunks_exact(ACTION_DIM)
        .map(|a| {
            copy.step(a);
            copy.observe().to_vec()
        })
        .collect()
}

/// The change of the velocity command the robot executes (the environment clamps commands to
/// [−1, 1] and executes a non-finite one as 0) between two actions.
pub fn velocity_jump(a: &[f32], b: &[f32]) -> f64 {
    let executed = |v: f32| {
        if v.is_finite() {
            v.clamp(-1.0, 1.0)
        } else {
            0.0
        }
    };
    let dx = f64::from(executed(a[0]) - executed(b[0]));
    let dy = f64::from(executed(a[1]) - executed(b[1]));
    (dx * dx + dy * dy).sqrt()
}

/// Whether a chunk's actions left the task's range by far (a diverged sampler).
pub fn diverged(actions: &[f32]) -> bool {
    actions.iter().any(|v| !v.is_finite() || v.abs() > 10.0)
}

/// The action of a robot standing still: zero velocity, the gripper as it was.
fn idle_action(previous: Option<&[f32]>) -> [f32; ACTION_DIM] {
    [0.0, 0.0, previous.map_or(-1.0, |a| a[2])]
}

/// What one episode runs with.
#[derive(Clone, Debug)]
pub struct EpisodeSpec<'a> {
    /// The task.
    pub env: &'a EnvConfig,
    /// Steps from capture to arrival.
    pub delay: u32,
    /// Steps between requests (at least `delay`, at least 1).
    pub period: u32,
    /// Synchronous, or the strategy.
    pub execution: Execution,
    /// The server's real-time chunking settings.
    pub defaults: &'a ChunkingDefaults,
}

/// Runs episode `seed` (module docs).
pub fn run_episode(
    model: &FlowPolicy,
    spec: &EpisodeSpec<'_>,
    seed: u64,
) -> Result<Outcome, ModelError> {
    match spec.execution {
        Execution::Sync => run_sync(model, spec, seed),
        execution => run_async(model, spec, execution, seed),
    }
}

/// A chunk as the server answers it: its whole `N` actions (horizon `N`).
fn reply_of(round: u64, actions: &[f32], chunk_len: usize) -> Reply {
    let rows = (actions.len() / ACTION_DIM) as u32;
    Reply {
        task: 0,
        round,
        horizon: rows,
        chunk_len: chunk_len as u32,
        actions: Tensor {
            dtype: DType::F32,
            shape: vec![rows, ACTION_DIM as u32],
            data: actions.iter().flat_map(|v| v.to_le_bytes()).collect(),
        },
        policy: "static".into(),
        timing: Timing::default(),
        start: None,
        delay: None,
        chunking: None,
    }
}

fn rows_of(values: &[f32]) -> Vec<Vec<f32>> {
    values
        .chunks_exact(ACTION_DIM)
        .map(<[f32]>::to_vec)
        .collect()
}

fn run_async(
    model: &FlowPolicy,
    spec: &EpisodeSpec<'_>,
    execution: Execution,
    seed: u64,
) -> Result<Outcome, ModelError> {
    let strategy = execution.strategy();
    let mut env = Env::new(spec.env.clone(), seed);
    let chunk_len = model.config().chunk_len;
    let period_us = (1e6 / f64::from(spec.env.control_hz)).round() as u64;
    let mut exec = ChunkExecutor::new(spec.env.control_hz, 1.0);
    let mut out = Outcome::default();
    // The last reply (what the robot executes) and the chunk in flight with its arrival step.
    let mut last_reply: Option<Reply> = None;
    let mut in_flight: Option<(u64, u32, Reply)> = None;
    let mut last_capture = 0u32;
    let mut previous: Option<(u64, [f32; ACTION_DIM])> = None;
    let mut step = 0u32;
    let request = |env: &Env,
                   exec: &mut ChunkExecutor,
                   last_reply: &Option<Reply>,
                   out: &mut Outcome,
                   step: u32|
     -> Result<Reply, ModelError> {
        let round = u64::from(out.calls);
        let now_us = u64::from(step) * period_us;
        exec.request_sent(round, now_us);
        let remaining = exec.remaining() as u32;
        // In-process the delay is exact: the server's prediction is `delay` steps, of which the
        // robot spends what it has left executing.
        let prediction = DelayPrediction {
            arrival: Timestamp::ZERO,
            delay: spec.delay,
            start: spec.delay.min(remaining),
            remaining_at_capture: remaining,
        };
        let obs = env.observe();
        let previous_actions = last_reply.as_ref().and_then(|r| r.actions.to_f32().ok());
        let mut chunking = execution.chunking(spec.defaults);
        if strategy == ChunkingStrategy::ArrivalState
            && let Some(actions) = &previous_actions
        {
            let rows = actions.len() / ACTION_DIM;
            let committed = &actions[(rows - remaining as usize) * ACTION_DIM..];
            chunking.forecast = Some(forecast(env, committed));
        }
        let (plan, input) = plan_round(
            &chunking,
            prediction,
            previous_actions.as_ref().map(|actions| PreviousChunk {
                actions,
                action_dim: ACTION_DIM,
            }),
            &obs,
            &ActionSpace::Unspecified,
            ACTION_DIM,
        );
        let state: [f32; OBS_DIM] = match &input.state {
            Some(s) => s.as_slice().try_into().unwrap_or(obs),
            None => obs,
        };
        let started = Instant::now();
        let chunk = model.sample_guided(
            &state,
            1,
            noise_seed(seed, out.calls),
            input.guidance.as_ref(),
        )?;
        out.sampling += started.elapsed();
        out.calls += 1;
        out.diverged |= diverged(chunk.sample_actions(0));
        let mut reply = reply_of(round, chunk.sample_actions(0), chunk_len);
        plan.finish(&mut reply);
        Ok(reply)
    };
    // The first chunk: planned before the clock starts.
    let first = request(&env, &mut exec, &last_reply, &mut out, 0)?;
    let actions = rows_of(&first.actions.to_f32().unwrap_or_default());
    exec.reply_arrived_from(first.round, actions, first.start);
    last_reply = Some(first);
    let arrive = |in_flight: &mut Option<(u64, u32, Reply)>,
                  exec: &mut ChunkExecutor,
                  last_reply: &mut Option<Reply>,
                  step: u32| {
        if in_flight.as_ref().is_some_and(|(_, at, _)| *at <= step)
            && let Some((round, _, reply)) = in_flight.take()
        {
            let actions = rows_of(&reply.actions.to_f32().unwrap_or_default());
            exec.reply_arrived_from(round, actions, reply.start);
            *last_reply = Some(reply);
        }
    };
    while !env.done() {
        let now_us = u64::from(step) * period_us;
        // A chunk due now arrives before this step's action; a request due now goes out after
        // it (so a chunk with no delay is there for this very step).
        arrive(&mut in_flight, &mut exec, &mut last_reply, step);
        if in_flight.is_none() && step >= last_capture + spec.period {
            let reply = request(&env, &mut exec, &last_reply, &mut out, step)?;
            last_capture = step;
            in_flight = Some((reply.round, step + spec.delay, reply));
            arrive(&mut in_flight, &mut exec, &mut last_reply, step);
        }
        let action: ([f32; ACTION_DIM], Option<u64>) = match exec.next_action(now_us) {
            Some(a) => {
                let mut v = [0.0; ACTION_DIM];
                v.copy_from_slice(&a.action[..ACTION_DIM]);
                (v, Some(a.round))
            }
            None => (idle_action(previous.as_ref().map(|p| &p.1[..])), None),
        };
        if let (Some((prev_round, prev)), Some(round)) = (&previous, action.1) {
            let jump = velocity_jump(&action.0, prev);
            if *prev_round == round {
                out.within_jump += jump;
                out.within += 1;
            } else {
                out.switch_jump += jump;
                out.switches += 1;
            }
        }
        env.step(&action.0);
        previous = Some((action.1.unwrap_or(u64::MAX), action.0));
        step += 1;
    }
    out.success = env.success();
    out.steps = env.steps();
    Ok(out)
}

fn run_sync(model: &FlowPolicy, spec: &EpisodeSpec<'_>, seed: u64) -> Result<Outcome, ModelError> {
    let mut env = Env::new(spec.env.clone(), seed);
    let mut out = Outcome::default();
    let mut previous: Option<(u64, [f32; ACTION_DIM])> = None;
    let mut first = true;
    while !env.done() {
        let obs = env.observe();
        let started = Instant::now();
        let chunk = model.sample(&obs, 1, noise_seed(seed, out.calls))?;
        out.sampling += started.elapsed();
        out.diverged |= diverged(chunk.sample_actions(0));
        let round = u64::from(out.calls);
        out.calls += 1;
        // The robot stands still while the chunk is generated (not before the first: the task
        // starts when its first chunk is there, as in the asynchronous runs).
        if !first {
            for _ in 0..spec.delay {
                if env.done() {
                    break;
                }
                let idle = idle_action(previous.as_ref().map(|p| &p.1[..]));
                env.step(&idle);
                previous = Some((u64::MAX, idle));
            }
        }
        first = false;
        for action in chunk
            .sample_actions(0)
            .chunks_exact(ACTION_DIM)
            .take(spec.period as usize)
        {
            if env.done() {
                break;
            }
            let mut a = [0.0; ACTION_DIM];
            a.copy_from_slice(action);
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
            env.step(&a);
            previous = Some((round, a));
        }
    }
    out.success = env.success();
    out.steps = env.steps();
    Ok(out)
}
