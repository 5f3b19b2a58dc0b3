//! Live replay (`kairos bench live`): the simulator's online experiment, run for real. This
//! module runs it and compares it with the simulation; `cli::bench_live` parses and prints.
//!
//! The same trace set `kairos bench sim` replays in virtual time is replayed by simulated robots
//! over real QUIC (TLS 1.3, one connection per robot) against the real server — transport,
//! driver, scheduler, action manager and horizon policies — whose engine is the trace-replay
//! engine (`pool::replay`): each batch takes the workload's *profiled* generation time for its
//! size and answers the chunk the trace recorded (paper §5.1's methodology). Robots issue every
//! request at the recorded action index, and tasks arrive as the Poisson process the simulator
//! draws for the same seed ([`crate::sim::online_schedule`]): same tasks, same instants.
//!
//! Every run is also simulated with exactly the same inputs, so the output is a side-by-side of
//! simulated and measured latency — the check that the simulator's numbers describe the real
//! system.
//!
//! **Time scale.** `--time-scale k` runs `k` times faster than the recording: control
//! frequencies and arrival rates are multiplied by `k`, profiled latencies and the scheduler's
//! staleness limit divided by `k` ([`scale_workload`], [`scale_traces`]). The simulation gets the
//! same scaled inputs, and every reported time is multiplied back by `k`, so tables read in the
//! recording's seconds. Only what does not scale — the loopback network, OS and tokio timer
//! jitter — is magnified by `k`, which is why `k` is kept modest (default 4).
//!
//! The network is loopback: the simulation it is compared with models the robot link as free
//! (zero round trip, unbounded uplink); the measured network + client overhead per round is
//! printed alongside.
//!
//! The robots run through [`crate::fleet`], like `kairos demo` and `kairos robot`.

mod robot;

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use kairos_engine::{EngineProfile, ProfilePoint};
use kairos_sdk::client::ClientConfig;
use kairos_sdk::tls::Fingerprint;
use kairos_sdk::trace::TraceSet;
use tokio::time::Instant;

pub use robot::{ReplayError, ReplayedTask, RoundOutcome, replay_task};

use crate::fleet::{self, LocalServer};
use crate::sim::experiment::{self, Experiment, Job, JobResult, Placement, Variant};
use crate::sim::plugins::UserPlugins;
use crate::sim::{Load, SimNetwork};
use crate::workload::{Workload, generate};
use kairos_core::stats::summarize;
use kairos_server::config::Config;
use kairos_server::pool::EnginePool;
use kairos_server::pool::replay::replay_engine;
use kairos_server::transport::launch::Policies;

/// Multiplies control frequencies by `k` and divides recorded latencies by `k`.
pub fn scale_traces(set: &TraceSet, k: f64) -> TraceSet {
    let mut scaled = set.clone();
    let shrink = |us: u64| (us as f64 / k).round() as u64;
    for task in &mut scaled.tasks {
        task.control_hz = (f64::from(task.control_hz) * k) as f32;
        for round in &mut task.rounds {
            round.gen_latency_us = shrink(round.gen_latency_us);
            round.round_trip_us = round.round_trip_us.map(shrink);
        }
    }
    scaled
}

/// Divides every latency of `profile` by `k`.
pub fn scale_profile(profile: &EngineProfile, k: f64) -> EngineProfile {
    EngineProfile {
        points: profile
            .points
            .iter()
            .map(|p| ProfilePoint {
                batch: p.batch,
                latency_ms: p.latency_ms / k,
            })
            .collect(),
        ..profile.clone()
    }
}

/// `w` run `k` times faster: control frequency and arrival rates x k, engine latencies and
/// network round trips / k.
pub fn scale_workload(w: &Workload, k: f64) -> Workload {
    let mut s = w.clone();
    s.robot.control_hz = (f64::from(s.robot.control_hz) * k) as f32;
    for spec in [&mut s.engines.edge, &mut s.engines.cloud] {
        for point in &mut spec.points {
            point[1] /= k;
        }
    }
    s.network.robot_rtt_ms /= k;
    s.network.wan_rtt_ms /= k;
    for rates in [&mut s.experiments.rates, &mut s.experiments.hybrid_rates] {
        for r in rates.iter_mut() {
            *r *= k;
        }
    }
    s
}

/// The robot link on loopback, as the simulation models it: free.
pub const LOOPBACK: SimNetwork = SimNetwork {
    robot_rtt: Duration::ZERO,
    robot_uplink_mbps: 1e12,
    wan_mbps: 1e12,
};

/// A live run of one system: the (scaled) simulation job that describes it. `w` is the
/// unscaled workload; `rate` in tasks per second of the recording.
pub fn live_job(
    w: &Workload,
    variant: &Variant,
    rate: f64,
    tasks: usize,
    seed: u64,
    k: f64,
) -> Job {
    let scaled = scale_workload(w, k);
    let mut config = experiment::config(
        &scaled,
        variant,
        Load::Poisson {
            rate: rate * k,
            tasks,
        },
        seed,
    );
    config.network = LOOPBACK;
    config.scheduler.stale_after =
        Duration::try_from_secs_f64(config.scheduler.stale_after.as_secs_f64() / k)
            .unwrap_or(config.scheduler.stale_after);
    Job {
        workload: 0,
        experiment: Experiment::Online,
        x: rate,
        variant: variant.clone(),
        config,
    }
}

/// The online experiment's system with key `key`.
pub fn variant(key: &str) -> anyhow::Result<Variant> {
    let all = experiment::online_variants();
    let keys: Vec<String> = all.iter().map(|v| v.key.clone()).collect();
    all.into_iter().find(|v| v.key == key).with_context(|| {
        format!(
            "unknown system `{key}` (expected one of {})",
            keys.join(", ")
        )
    })
}

/// Where a live run's robots connect.
#[derive(Clone, Debug)]
pub enum Target {
    /// Start a replay server in this process on `127.0.0.1:0`, keeping its state (certificate,
    /// tokens) in this directory.
    InProcess(PathBuf),
    /// A replay server already running.
    Remote {
        /// Its address.
        addr: SocketAddr,
        /// Its certificate pin.
        pin: Fingerprint,
        /// A robot token.
        token: String,
    },
}

/// What a live run measured, in wall-clock (scaled) time.
#[derive(Clone, Debug)]
pub struct LiveOutcome {
    /// Every task, in schedule order.
    pub tasks: Vec<ReplayedTask>,
    /// Batches the server ran (`None` for a remote server: then estimated from the replies).
    pub batches: Option<u64>,
    /// Wall-clock time of the run.
    pub wall: Duration,
}

impl LiveOutcome {
    /// The outcome as the simulator reports a job, times multiplied by `k` (back to the
    /// recording's seconds).
    pub fn job_result(&self, k: f64) -> JobResult {
        let rounds: Vec<&RoundOutcome> = self.tasks.iter().flat_map(|t| &t.rounds).collect();
        let requests = rounds.len().max(1) as f64;
        let latencies: Vec<f64> = self
            .tasks
            .iter()
            .map(|t| t.latency.as_secs_f64() * k)
            .collect();
        // Σ 1/b over requests counts each batch of b requests once.
        let batches = self.batches.map_or_else(
            || {
                rounds
                    .iter()
                    .map(|r| 1.0 / f64::from(r.batch_size.max(1)))
                    .sum::<f64>()
            },
            |b| b as f64,
        );
        JobResult {
            summary: summarize(&latencies),
            rounds_per_task: rounds.len() as f64 / self.tasks.len().max(1) as f64,
            mean_batch: if batches > 0.0 {
                rounds.len() as f64 / batches
            } else {
                0.0
            },
            refetch_share: rounds.iter().filter(|r| r.refetches > 0).count() as f64 / requests,
            cloud_share: 0.0,
            mean_queue_s: rounds.iter().map(|r| r.queue_us as f64).sum::<f64>() / requests / 1e6
                * k,
            events: 0,
            mean_horizon: None,
            beyond_cut_per_task: None,
            latencies,
            scale: None,
        }
    }

    /// Mean per round of the measured generation time minus `profile`'s latency for the
    /// round's batch size, µs of wall-clock time: how late the engine thread woke up.
    pub fn engine_overshoot_us(&self, profile: &EngineProfile) -> f64 {
        let rounds: Vec<&RoundOutcome> = self.tasks.iter().flat_map(|t| &t.rounds).collect();
        rounds
            .iter()
            .map(|r| r.inference_us as f64 - profile.latency(r.batch_size).as_secs_f64() * 1e6)
            .sum::<f64>()
            / rounds.len().max(1) as f64
    }

    /// Mean per round of the round trip the robot saw minus the server's own time: loopback
    /// network, QUIC and client overhead, µs of wall-clock time.
    pub fn network_overhead_us(&self) -> f64 {
        let rounds: Vec<&RoundOutcome> = self.tasks.iter().flat_map(|t| &t.rounds).collect();
        rounds
            .iter()
            .map(|r| r.round_trip_us.saturating_sub(r.server_total_us) as f64)
            .sum::<f64>()
            / rounds.len().max(1) as f64
    }
}

/// Progress of a live run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LiveEvent {
    /// Every robot is connected; the clock starts.
    Connected,
    /// A round was answered.
    Round,
    /// A task finished.
    TaskDone,
}

/// Starts the trace-replay server for `job` (its scaled edge profile, its policy and scheduler
/// settings) on `listen`, keeping state in `data_dir`.
pub async fn start_replay_server(
    job: &Job,
    traces: &TraceSet,
    listen: SocketAddr,
    data_dir: &Path,
) -> anyhow::Result<LocalServer> {
    if job.variant.placement != Placement::Edge {
        bail!(
            "live replay runs one edge engine; `{}` is not edge-only",
            job.variant.key
        );
    }
    let chunk_len = traces
        .variant(&job.config.setting)
        .map(|t| t.chunk_len)
        .max()
        .context("the trace set has no task under the run's setting")?;
    if traces
        .variant(&job.config.setting)
        .any(|t| t.chunk_len != chunk_len)
    {
        bail!("live replay needs one chunk length across the trace set");
    }
    let engine = job
        .config
        .engines
        .first()
        .context("the job has no engine")?;
    let pool = EnginePool::new(vec![replay_engine(
        "edge-0 (trace replay)",
        chunk_len as usize,
        engine.profile.clone(),
    )?])?;
    let mut config = Config {
        listen,
        data_dir: data_dir.to_path_buf(),
        ..Config::default()
    };
    config.scheduler.policy = job.config.policy.clone();
    config.scheduler.refetch = Some(job.config.scheduler.refetch);
    config.scheduler.stale_after_ms =
        u64::try_from(job.config.scheduler.stale_after.as_millis()).unwrap_or(u64::MAX);
    config.scheduler.max_pending = job.config.scheduler.max_pending;
    config.scheduler.history_rounds = job.config.scheduler.history_rounds;
    // The job's plugins, registered as `kairos bench sim` registers them: the server resolves
    // the robots' horizon policy and its scheduler's priority policy in the same registries.
    let policies: Policies = job.config.policies.clone();
    LocalServer::start(&config, pool, policies)
        .await
        .context("starting the replay server")
}

/// Replays `job`'s schedule over `traces` (both scaled) against `target`, one QUIC connection
/// per robot. Every robot connects first; then each starts its task at its arrival time.
pub async fn run_live(
    job: &Job,
    traces: &TraceSet,
    target: &Target,
    on_event: impl Fn(LiveEvent) + Send + Sync + 'static,
) -> anyhow::Result<LiveOutcome> {
    let schedule = crate::sim::online_schedule(traces, &job.config)?;
    let (client_config, server) = match target {
        Target::InProcess(dir) => {
            let server = start_replay_server(job, traces, "127.0.0.1:0".parse()?, dir).await?;
            let config = server
                .generated_robot()
                .context("the replay server generated no robot token")?;
            (config, Some(server))
        }
        Target::Remote { addr, pin, token } => {
            let mut config = ClientConfig::pinned(*addr, *pin, token.clone());
            config.connect_timeout = fleet::CONNECT_TIMEOUT;
            (config, None)
        }
    };
    let addr = client_config.server;
    let clients = fleet::connect(&client_config, schedule.len())
        .await
        .with_context(|| format!("connecting the robots to {addr}"))?;
    let model = fleet::served_model(&clients).await?;
    if model.name != kairos_server::pool::replay::REPLAY_MODEL {
        bail!(
            "{addr} serves `{}`, not the trace-replay engine (start one with `kairos bench live --serve`)",
            model.name
        );
    }
    on_event(LiveEvent::Connected);

    let on_event = Arc::new(on_event);
    let base: u64 = u64::from(rand::random::<u32>()) << 32;
    // A little lead so that the first arrivals are not late while tasks are spawned.
    let t0 = Instant::now() + Duration::from_millis(100);
    let starts: Vec<Duration> = schedule
        .iter()
        .map(|(at, _)| Duration::from_micros(at.as_micros()))
        .collect();
    let hints = job.config.hints;
    let outcomes = fleet::run_from(t0, &starts, |index| {
        let trace = kairos_sdk::trace::TaskTrace::clone(schedule[index].1);
        let (client, on_event) = (clients[index].clone(), Arc::clone(&on_event));
        async move {
            let done = replay_task(&client, base | index as u64, &trace, hints, |_| {
                on_event(LiveEvent::Round)
            })
            .await;
            on_event(LiveEvent::TaskDone);
            done
        }
    })
    .await;
    let mut tasks = Vec::with_capacity(schedule.len());
    let mut failure: Option<anyhow::Error> = None;
    for outcome in outcomes {
        match outcome {
            Ok(Ok(task)) => tasks.push(task),
            Ok(Err(error)) => {
                failure.get_or_insert_with(|| {
                    anyhow::Error::new(error).context("a replayed task failed")
                });
            }
            Err(error) => {
                failure.get_or_insert_with(|| {
                    anyhow::Error::new(error).context("a robot task panicked")
                });
            }
        }
    }
    let wall = t0.elapsed();
    for client in &clients {
        client.close().await;
    }
    let batches = match server {
        Some(server) => Some(server.shutdown().await.driver.batches),
        None => None,
    };
    if let Some(error) = failure {
        return Err(error);
    }
    Ok(LiveOutcome {
        tasks,
        batches,
        wall,
    })
}

/// How the simulation a live run is compared with models the robot's link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SimNetworkMode {
    /// The robot round trip is the live run's measured network + client overhead per round
    /// (round trip at the robot minus the server's own time): what loopback QUIC actually cost.
    #[default]
    Measured,
    /// A free link: zero round trip, unbounded uplink.
    Free,
}

impl std::str::FromStr for SimNetworkMode {
    type Err = String;

    /// `measured` or `free`.
    fn from_str(text: &str) -> Result<SimNetworkMode, String> {
        match text {
            "measured" => Ok(SimNetworkMode::Measured),
            "free" => Ok(SimNetworkMode::Free),
            other => Err(format!("`{other}` is not a network mode (measured, free)")),
        }
    }
}

/// What a live run measured besides latencies, wall-clock.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Measured {
    /// Duration of the run.
    pub wall: Duration,
    /// Mean network + client overhead per round, µs.
    pub network_us: f64,
    /// Mean wait for re-fetched observations, over re-fetched rounds, µs.
    pub refetch_us: f64,
    /// Mean generation time beyond the profile, µs.
    pub engine_overshoot_us: f64,
}

/// One system's live and simulated results.
#[derive(Clone, Debug)]
pub struct Comparison {
    /// The job (scaled).
    pub job: Job,
    /// Measured, in the recording's seconds.
    pub live: JobResult,
    /// Simulated with the same inputs, in the recording's seconds.
    pub sim: JobResult,
    /// The robot round trip the simulation used, wall-clock.
    pub sim_rtt: Duration,
    /// The live run's overheads.
    pub measured: Measured,
}

/// Simulates `job` on `traces` (both scaled) with the network `mode` describes, and pairs it
/// with the live `outcome`; every time is scaled back by `k`.
pub fn compare(
    job: Job,
    outcome: &LiveOutcome,
    traces: &TraceSet,
    k: f64,
    mode: SimNetworkMode,
) -> anyhow::Result<Comparison> {
    let rounds: Vec<&RoundOutcome> = outcome.tasks.iter().flat_map(|t| &t.rounds).collect();
    let refetched: Vec<f64> = rounds
        .iter()
        .filter(|r| r.refetches > 0)
        .map(|r| r.refetch_us as f64)
        .collect();
    let profile = job
        .config
        .engines
        .first()
        .map(|e| e.profile.clone())
        .context("the job has no engine")?;
    let measured = Measured {
        wall: outcome.wall,
        network_us: outcome.network_overhead_us(),
        refetch_us: refetched.iter().sum::<f64>() / refetched.len().max(1) as f64,
        engine_overshoot_us: outcome.engine_overshoot_us(&profile),
    };
    let mut sim_job = job.clone();
    if mode == SimNetworkMode::Measured {
        sim_job.config.network.robot_rtt =
            Duration::try_from_secs_f64(measured.network_us / 1e6).unwrap_or(Duration::ZERO);
    }
    let sim = simulate_scaled(&sim_job, traces, k)?;
    Ok(Comparison {
        live: outcome.job_result(k),
        sim,
        sim_rtt: sim_job.config.network.robot_rtt,
        measured,
        job,
    })
}

/// Simulates `job` on `traces` (both scaled) and scales the result's times back by `k`.
pub fn simulate_scaled(job: &Job, traces: &TraceSet, k: f64) -> anyhow::Result<JobResult> {
    let r = experiment::run_job(job, traces)?;
    let latencies: Vec<f64> = r.latencies.iter().map(|l| l * k).collect();
    Ok(JobResult {
        summary: summarize(&latencies),
        latencies,
        mean_queue_s: r.mean_queue_s * k,
        ..r
    })
}

/// The side-by-side table: per system, live and simulated P25 / average / P95 and their
/// difference, the run's shape (rounds, batch, queueing, re-fetches), and the live overheads the
/// simulation does not see (wall-clock ms).
pub fn comparison_table(rows: &[Comparison]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| System | P25 live (sim) s | avg live (sim) s | avg diff | P95 live (sim) s | rounds/task | batch | queue ms | re-fetched | net + client ms | re-fetch wait ms | engine late ms |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|---|");
    for c in rows {
        let (l, m) = (&c.live, &c.sim);
        let _ = writeln!(
            s,
            "| {} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:+.1}% | {:.2} ({:.2}) | {:.1} ({:.1}) | {:.2} ({:.2}) | {:.0} ({:.0}) | {:.0}% ({:.0}%) | {:.2} | {:.2} | {:.2} |",
            c.job.variant.label,
            l.summary.p25,
            m.summary.p25,
            l.summary.mean,
            m.summary.mean,
            relative_diff(l.summary.mean, m.summary.mean) * 100.0,
            l.summary.p95,
            m.summary.p95,
            l.rounds_per_task,
            m.rounds_per_task,
            l.mean_batch,
            m.mean_batch,
            l.mean_queue_s * 1e3,
            m.mean_queue_s * 1e3,
            l.refetch_share * 100.0,
            m.refetch_share * 100.0,
            c.measured.network_us / 1e3,
            c.measured.refetch_us / 1e3,
            c.measured.engine_overshoot_us / 1e3,
        );
    }
    s
}

/// `(live − sim) / sim`.
pub fn relative_diff(live: f64, sim: f64) -> f64 {
    if sim == 0.0 { 0.0 } else { (live - sim) / sim }
}

/// Loads the workload and its traces (generated, or read from `traces`).
pub fn load(
    workload: &Path,
    traces: Option<&Path>,
    trace_seed: u64,
    plugins: &UserPlugins,
) -> anyhow::Result<(Workload, TraceSet)> {
    let w = Workload::load(workload)?;
    if traces.is_some() && !plugins.horizon_settings().is_empty() {
        bail!(
            "--horizon-plugin needs generated traces (a recorded trace file has no rounds chosen by the plugin)"
        );
    }
    let set = match traces {
        Some(path) => {
            let file =
                std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
            TraceSet::read(std::io::BufReader::new(file))
                .with_context(|| format!("reading {}", path.display()))?
        }
        None => {
            // The workload's settings, plus one per horizon plugin (as `kairos bench sim`).
            let mut settings = generate::settings(&w).to_vec();
            settings.extend(plugins.horizon_settings());
            let (horizons, _) = plugins.policies.with_natives();
            generate::generate_settings(&w, trace_seed, &settings, &horizons)
                .with_context(|| format!("generating traces for `{}`", w.name))?
        }
    };
    Ok((w, set))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn workload() -> Workload {
        Workload::load(Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../workloads/libero-smolvla.toml"
        )))
        .unwrap()
    }

    #[test]
    fn the_simulation_does_not_depend_on_the_time_scale() {
        // Scaling time is what makes live runs short; the simulation of a scaled run, scaled
        // back, must be the unscaled simulation (up to µs rounding), or the side-by-side would
        // compare different systems.
        let w = workload();
        let set = generate::generate(&w, 42).unwrap();
        for key in ["fifo", "kairos"] {
            let v = variant(key).unwrap();
            let at = |k: f64| {
                let job = live_job(&w, &v, 5.0, 30, 3, k);
                simulate_scaled(&job, &scale_traces(&set, k), k).unwrap()
            };
            let (one, four) = (at(1.0), at(4.0));
            assert_eq!(one.summary.n, 30);
            assert!(
                (four.summary.mean / one.summary.mean - 1.0).abs() < 0.005,
                "{key}: {} vs {}",
                four.summary.mean,
                one.summary.mean
            );
            assert!((four.rounds_per_task / one.rounds_per_task - 1.0).abs() < 0.01);
        }
    }

    #[test]
    fn a_live_job_is_the_scaled_online_run_on_loopback() {
        let w = workload();
        let job = live_job(&w, &variant("kairos").unwrap(), 5.0, 30, 3, 4.0);
        assert_eq!(
            job.config.load,
            Load::Poisson {
                rate: 20.0,
                tasks: 30
            }
        );
        assert_eq!(job.config.network, LOOPBACK);
        assert_eq!(job.config.scheduler.stale_after, Duration::from_millis(25));
        let edge = &job.config.engines[0].profile;
        assert_eq!(edge.latency(1), w.edge_profile().latency(1) / 4);
        assert_eq!(job.x, 5.0, "reported at the recording's rate");
        let set = generate::generate(&w, 42).unwrap();
        let scaled = scale_traces(&set, 4.0);
        assert_eq!(scaled.tasks[0].control_hz, set.tasks[0].control_hz * 4.0);
        assert_eq!(scaled.tasks[0].rounds, {
            let mut r = set.tasks[0].rounds.clone();
            for round in &mut r {
                round.gen_latency_us = (round.gen_latency_us as f64 / 4.0).round() as u64;
                round.round_trip_us = round
                    .round_trip_us
                    .map(|us| (us as f64 / 4.0).round() as u64);
            }
            r
        });
    }
}
