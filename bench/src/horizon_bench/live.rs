//! `kairos bench horizon --live`: the same episodes with the policy served over loopback QUIC.
//!
//! A real server starts in this process ([`crate::fleet::LocalServer`], as `kairos serve` runs
//! it: TLS, the generated robot's token read from its data directory, the real scheduler and
//! driver) with the bench's flow-matching policy as its engine model (`horizon-flow:DIR`, on
//! [`kairos_server::pool::LocalEngine`] threads) and the run's plugins in its registries. Each episode is
//! one task of a robot that connects with the real client: every round sends the observation and
//! names the policy under test (`HorizonSelection`: name, parameters, samples); the server samples
//! the chunk, its horizon code chooses `H` (falling back as in `serve`), and the reply's `H`
//! actions go to the SDK's [`ChunkExecutor`].
//!
//! The environment's time is virtual and does not advance while a round is in flight
//! (synchronous inference, `trigger = 1`, as in-process), and each round carries the sampler
//! seed the in-process run draws ([`super::noise_seed`], `Submit.seed`): the same episode seed
//! therefore gives the same chunks, horizons and outcome in both modes, which is what the test
//! `bench_horizon::live_and_in_process_episodes_agree` checks. What `--live` adds is the wire:
//! encoding, TLS, batching across robots, the driver's bookkeeping and the horizon policy on
//! the server's blocking pool. The robots report no `last_exec`: its times would be on the
//! virtual clock, not the client's.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use kairos_sdk::client::{Client, NoRefetch, RoundRequest};
use kairos_sdk::protocol::{HorizonSelection, Observation, TaskOutcome, Tensor};
use kairos_sdk::robot::ChunkExecutor;

use super::env::{ACTION_DIM, Env, EnvConfig, OBS_DIM};
use super::served::{HORIZON_FLOW_MODEL, HORIZON_FLOW_PREFIX};
use super::{BenchError, BenchPlan, Episode, FALLBACK_POLICY, PointResult, PolicyPoint};
use crate::fleet::{self, LocalServer};
use kairos_core::registry::Policies;
use kairos_server::config::{Config, EngineConfig, HorizonSection};
use kairos_server::pool::build_pool;

fn live(what: &str) -> impl FnOnce(String) -> BenchError + '_ {
    move |e| BenchError::Live(format!("{what}: {e}"))
}

/// Where and what the loopback server serves.
#[derive(Clone, Debug)]
pub struct LiveSetup {
    /// The policy's directory, served as `horizon-flow:DIR`.
    pub model_dir: PathBuf,
    /// The server's state (certificate, tokens); created if missing.
    pub data_dir: PathBuf,
    /// Plugins to load into the server's registries beside the natives.
    pub policies: Policies,
}

/// Runs `plan` as [`super::run_bench`] does, but through a server on loopback QUIC: one engine
/// instance and one robot connection per thread of `plan`, each robot running its share of the
/// episodes one after another. Blocking: it runs its own small tokio runtime.
/// Also returns how many rounds the server answered with another policy than the one asked
/// for (its fallback, after the policy under test failed).
pub fn run_live_bench(
    setup: &LiveSetup,
    plan: &BenchPlan,
    on_episode: &(dyn Fn() + Sync),
) -> Result<(Vec<PointResult>, usize), BenchError> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| BenchError::Live(format!("starting the runtime: {e}")))?;
    let fallbacks = AtomicUsize::new(0);
    let slots = runtime.block_on(run_slots(setup, plan, &fallbacks, on_episode))?;
    Ok((super::gather(plan, slots)?, fallbacks.into_inner()))
}

/// Starts the server (engine threads loaded and profiled off the runtime).
async fn start_server(setup: &LiveSetup, instances: u32) -> Result<LocalServer, BenchError> {
    let engines = vec![EngineConfig {
        model: format!("{HORIZON_FLOW_PREFIX}{}", setup.model_dir.display()),
        instances,
        ..EngineConfig::default()
    }];
    let pool = {
        let engines = engines.clone();
        tokio::task::spawn_blocking(move || {
            build_pool(&engines, &super::served::schemes(), |_| {}).map_err(|e| e.to_string())
        })
        .await
        .map_err(|e| live("loading the model")(e.to_string()))?
        .map_err(live("loading the model"))?
    };
    let config = Config {
        listen: SocketAddr::from(([127, 0, 0, 1], 0)),
        data_dir: setup.data_dir.clone(),
        engines,
        horizon: HorizonSection {
            policy: FALLBACK_POLICY.to_string(),
            params: Default::default(),
        },
        ..Config::default()
    };
    LocalServer::start(&config, pool, setup.policies.clone())
        .await
        .map_err(|e| live("starting the server")(e.to_string()))
}

type Slots = Vec<Option<Result<Episode, BenchError>>>;

async fn run_slots(
    setup: &LiveSetup,
    plan: &BenchPlan,
    fallbacks: &AtomicUsize,
    on_episode: &(dyn Fn() + Sync),
) -> Result<Slots, BenchError> {
    let robots = plan.threads.max(1);
    let server = start_server(setup, u32::try_from(robots).unwrap_or(u32::MAX)).await?;
    let run = async {
        let config = server
            .generated_robot()
            .ok_or_else(|| BenchError::Live("the server generated no robot token".into()))?;
        let clients = fleet::connect(&config, robots)
            .await
            .map_err(|e| live("connecting")(e.to_string()))?;
        let model = fleet::served_model(&clients)
            .await
            .map_err(|e| live("connecting")(e.to_string()))?;
        if model.name != HORIZON_FLOW_MODEL {
            return Err(BenchError::Live(format!(
                "the server serves `{}`, not `{HORIZON_FLOW_MODEL}`",
                model.name
            )));
        }
        let jobs = super::plan_jobs(plan);
        let next = AtomicUsize::new(0);
        let slots: Mutex<Slots> = Mutex::new((0..jobs.len()).map(|_| None).collect());
        // The robots run concurrently on this task (their rounds wait on the network; the model
        // and the horizon policies run on the server's threads, not here).
        let robot = |client: &Client| {
            let (jobs, next, slots) = (&jobs, &next, &slots);
            let client = client.clone();
            async move {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(p, e)) = jobs.get(i) else { break };
                    // Task ids are unique in the run; the noise follows the episode seed.
                    let task = ((p as u64) << 32) | e;
                    let r = run_live_episode(
                        &client,
                        task,
                        &plan.points[p],
                        &plan.env,
                        plan.seed + e,
                        fallbacks,
                    )
                    .await;
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
        Ok(slots
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner()))
    }
    .await;
    server.shutdown().await;
    run
}

/// Episode `seed` of `point` as task `task`: [`super::run_episode`]'s loop with the round sent
/// over the wire instead of sampled and chosen in-process. Rounds the server answered with its
/// fallback policy are counted in `fallbacks`.
pub async fn run_live_episode(
    client: &Client,
    task: u64,
    point: &PolicyPoint,
    env_cfg: &EnvConfig,
    seed: u64,
    fallbacks: &AtomicUsize,
) -> Result<Episode, BenchError> {
    let mut handle = client.task(task);
    let mut env = Env::new(env_cfg.clone(), seed);
    let hz = env_cfg.control_hz;
    let period_us = (1e6 / f64::from(hz)).round() as u64;
    let mut exec = ChunkExecutor::new(hz, 1.0);
    let mut out = Episode::default();
    let mut now_us = 0u64;
    let samples = u32::try_from(point.samples).map_err(|_| {
        BenchError::Live(format!("{} samples per request is too many", point.samples))
    })?;
    while !env.done() {
        if exec.wants_request() {
            let round = handle.next_round();
            exec.request_sent(round, now_us);
            let obs: [f32; OBS_DIM] = env.observe();
            let state = Tensor::from_f32(vec![OBS_DIM as u32], &obs)
                .map_err(|e| live("encoding the observation")(e.to_string()))?;
            let request = RoundRequest {
                observation: Observation {
                    captured_at_us: client.now_us(),
                    state,
                    images: Vec::new(),
                    instruction: String::new(),
                },
                last_exec: None,
                horizon: Some(HorizonSelection {
                    policy: point.name.clone(),
                    params: point.params.clone(),
                    samples,
                }),
                remaining: None,
                control_hz: Some(hz),
                seed: Some(super::noise_seed(seed, out.calls)),
                chunking: None,
            };
            let reply = handle
                .submit(request, &mut NoRefetch)
                .await
                .map_err(|e| live(&format!("episode {seed}, round {round}"))(e.to_string()))?
                .reply;
            let flat = reply
                .actions
                .to_f32()
                .map_err(|e| live("decoding the reply")(e.to_string()))?;
            if reply.policy != point.name {
                fallbacks.fetch_add(1, Ordering::Relaxed);
            }
            let h = reply.horizon as usize;
            if h == 0 || flat.len() != h * ACTION_DIM {
                return Err(BenchError::Live(format!(
                    "episode {seed}, round {round}: H = {h} with {} action values",
                    flat.len()
                )));
            }
            let actions: Vec<Vec<f32>> =
                flat.chunks_exact(ACTION_DIM).map(<[f32]>::to_vec).collect();
            exec.reply_arrived(round, actions);
            out.calls += 1;
            out.horizon_sum += h as u64;
        }
        let step = exec.next_action(now_us).ok_or(BenchError::NoAction(seed))?;
        env.step(step.action);
        now_us += period_us;
    }
    out.success = env.success();
    out.steps = env.steps();
    let outcome = if out.success {
        TaskOutcome::Done
    } else {
        TaskOutcome::Failed
    };
    handle
        .end(outcome, None)
        .await
        .map_err(|e| live(&format!("ending episode {seed}"))(e.to_string()))?;
    Ok(out)
}

/// A fresh data directory for the loopback server under the system's temporary directory
/// (removed by the caller when the run ends).
pub fn scratch_data_dir() -> PathBuf {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    std::env::temp_dir().join(format!(
        "kairos-horizon-live-{}-{nanos}",
        std::process::id()
    ))
}

/// Removes a directory made by [`scratch_data_dir`], ignoring one already gone.
pub fn remove_scratch(dir: &Path) {
    let _ = std::fs::remove_dir_all(dir);
}
