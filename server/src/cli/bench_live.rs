//! `kairos bench live`: the simulator's online experiment, run for real.
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

mod robot;

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use kairos_engine::{EngineProfile, ProfilePoint};
use kairos_sdk::client::{Client, ClientConfig};
use kairos_sdk::tls::Fingerprint;
use kairos_sdk::trace::TraceSet;
use tokio::time::Instant;

pub use robot::{ReplayError, ReplayedTask, RoundOutcome, replay_task};

use crate::config::{Config, TokensFile};
use crate::pool::EnginePool;
use crate::pool::replay::replay_engine;
use crate::sim::experiment::{self, Experiment, Job, JobResult, Placement, Report, Variant};
use crate::sim::stats::summarize;
use crate::sim::{Load, SimNetwork};
use crate::transport::launch::{Policies, start};
use crate::workload::{Workload, generate};

/// `kairos bench live`
#[derive(Args, Debug, Clone)]
pub struct LiveArgs {
    /// Workload file (TOML): engines (the replay engine's latency profile), trace generator,
    /// default arrival rate.
    #[arg(long, short = 'w', default_value = "workloads/libero-smolvla.toml")]
    pub workload: PathBuf,
    /// Replay this trace file instead of generating traces from the workload.
    #[arg(long)]
    pub traces: Option<PathBuf>,
    /// Systems to run, comma-separated keys of the online experiment: fifo, autellix, kairos,
    /// kairos-static, fifo-dynamic, autellix-dynamic, srw, srw-hint.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "fifo,autellix,kairos,srw"
    )]
    pub variants: Vec<String>,
    /// Poisson arrival rate, tasks per second of the recording (default: the workload's middle
    /// rate, a moderate load).
    #[arg(long)]
    pub rate: Option<f64>,
    /// Tasks per run.
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub tasks: u64,
    /// Seed of arrivals and task picks (the simulator draws the same schedule from it).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seed of the trace generator.
    #[arg(long, default_value_t = 42)]
    pub trace_seed: u64,
    /// Run this many times faster than the recording (control rates and arrival rates x k,
    /// latencies / k, for both the live run and its simulation; reported times are scaled
    /// back).
    #[arg(long, default_value_t = 4.0)]
    pub time_scale: f64,
    /// Output directory for summary.md, live.csv, sim.csv and plots.
    #[arg(long, short = 'o', default_value = "kairos-live")]
    pub out: PathBuf,
    /// Skip the plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Replay against this running replay server instead of starting one (see `--serve`);
    /// it runs one system, the first of `--variants`, which must match the server's policy.
    #[arg(long, requires_all = ["pin", "token"])]
    pub server: Option<SocketAddr>,
    /// The remote server's certificate pin, `sha256:<64 hex>`.
    #[arg(long)]
    pub pin: Option<Fingerprint>,
    /// A robot token of the remote server.
    #[arg(long)]
    pub token: Option<String>,
    /// How the simulation models the robot link: `measured` (the live run's network + client
    /// overhead per round) or `free`.
    #[arg(long, value_enum, default_value_t = SimNetworkMode::Measured)]
    pub sim_network: SimNetworkMode,
    /// Only simulate the runs (what the live runs would be compared with), printing the table.
    #[arg(long, conflicts_with_all = ["server", "serve"])]
    pub sim_only: bool,
    /// Only serve: start the replay server for this workload on ADDR with the scheduler of the
    /// first of `--variants`, print how to connect, and wait for Ctrl-C.
    #[arg(long, conflicts_with = "server")]
    pub serve: Option<SocketAddr>,
}

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
    config.scheduler.stale_after = config.scheduler.stale_after.div_f64(k);
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
            latencies,
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
) -> anyhow::Result<crate::transport::launch::RunningServer> {
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
    start(&config, pool, Policies::default())
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
    let (addr, pin, token, server) = match target {
        Target::InProcess(dir) => {
            let server = start_replay_server(job, traces, "127.0.0.1:0".parse()?, dir).await?;
            let tokens = server
                .tokens_file
                .clone()
                .context("the replay server generated no robot token")?;
            let token = TokensFile::read(&tokens)?
                .token(crate::config::DEFAULT_ROBOT)
                .context("no default robot in the tokens file")?
                .to_string();
            let pin: Fingerprint = server.fingerprint.parse()?;
            (server.local_addr, pin, token, Some(server))
        }
        Target::Remote { addr, pin, token } => (*addr, *pin, token.clone(), None),
    };
    let mut client_config = ClientConfig::pinned(addr, pin, token);
    client_config.connect_timeout = Duration::from_secs(20);
    let clients = futures::future::try_join_all(schedule.iter().map(|_| {
        let config = client_config.clone();
        async move { Client::connect(config).await }
    }))
    .await
    .with_context(|| format!("connecting the robots to {addr}"))?;
    let model = clients
        .first()
        .context("no task to run")?
        .welcome()
        .await
        .context("connected but got no Welcome")?
        .model
        .clone();
    if model.name != crate::pool::replay::REPLAY_MODEL {
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
    let mut running = tokio::task::JoinSet::new();
    for (index, ((at, trace), client)) in schedule.iter().zip(&clients).enumerate() {
        let trace = (*trace).clone();
        let client = client.clone();
        let start_at = t0 + Duration::from_micros(at.as_micros());
        let hints = job.config.hints;
        let on_event = Arc::clone(&on_event);
        running.spawn(async move {
            tokio::time::sleep_until(start_at).await;
            let done = replay_task(&client, base | index as u64, &trace, hints, |_| {
                on_event(LiveEvent::Round)
            })
            .await;
            on_event(LiveEvent::TaskDone);
            (index, done)
        });
    }
    let mut tasks: Vec<Option<ReplayedTask>> = vec![None; schedule.len()];
    let mut failure = None;
    while let Some(joined) = running.join_next().await {
        let (index, done) = joined.context("a robot task panicked")?;
        match done {
            Ok(task) => tasks[index] = Some(task),
            Err(error) => {
                failure.get_or_insert(error);
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
        return Err(error).context("a replayed task failed");
    }
    Ok(LiveOutcome {
        tasks: tasks.into_iter().flatten().collect(),
        batches,
        wall,
    })
}

/// How the simulation a live run is compared with models the robot's link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum SimNetworkMode {
    /// The robot round trip is the live run's measured network + client overhead per round
    /// (round trip at the robot minus the server's own time): what loopback QUIC actually cost.
    #[default]
    Measured,
    /// A free link: zero round trip, unbounded uplink.
    Free,
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
        sim_job.config.network.robot_rtt = Duration::from_secs_f64(measured.network_us / 1e6);
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
) -> anyhow::Result<(Workload, TraceSet)> {
    let w = Workload::load(workload)?;
    let set = match traces {
        Some(path) => {
            let file =
                std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
            TraceSet::read(std::io::BufReader::new(file))
                .with_context(|| format!("reading {}", path.display()))?
        }
        None => generate::generate(&w, trace_seed)
            .with_context(|| format!("generating traces for `{}`", w.name))?,
    };
    Ok((w, set))
}

/// Runs `kairos bench live`.
pub fn run(args: LiveArgs) -> anyhow::Result<()> {
    let k = args.time_scale;
    if !(k.is_finite() && k > 0.0) {
        bail!("--time-scale must be a positive number");
    }
    let (w, set) = load(&args.workload, args.traces.as_deref(), args.trace_seed)?;
    let rate = match args.rate {
        Some(r) if r.is_finite() && r > 0.0 => r,
        Some(r) => bail!("--rate must be a positive number, got {r}"),
        None => w.experiments.rates[w.experiments.rates.len() / 2],
    };
    let variants = args
        .variants
        .iter()
        .map(|key| variant(key.trim()))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let first = variants.first().context("--variants is empty")?;
    let tasks = usize::try_from(args.tasks).context("--tasks")?;
    let scaled = scale_traces(&set, k);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;

    if let Some(listen) = args.serve {
        let job = live_job(&w, first, rate, tasks, args.seed, k);
        let data_dir = args.out.join("server-data");
        return runtime.block_on(async {
            let server = start_replay_server(&job, &scaled, listen, &data_dir).await?;
            let token = match &server.tokens_file {
                Some(path) => TokensFile::read(path)?
                    .token(crate::config::DEFAULT_ROBOT)
                    .unwrap_or_default()
                    .to_string(),
                None => String::new(),
            };
            println!(
                "trace-replay server for `{}` ({} scheduler, time scale {k}) on {}",
                w.name, first.label, server.local_addr
            );
            println!(
                "connect with: kairos bench live -w {} --variants {} --time-scale {k} --server {} --pin {} --token {token}",
                args.workload.display(),
                first.key,
                server.local_addr,
                server.fingerprint
            );
            tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
            server.shutdown().await;
            anyhow::Ok(())
        });
    }

    let runs: Vec<Variant> = match args.server {
        Some(_) => vec![first.clone()],
        None => variants,
    };
    println!(
        "live replay of `{}`: {} tasks at {rate} tasks/s (seed {}), time scale {k}, systems: {}",
        w.name,
        tasks,
        args.seed,
        runs.iter()
            .map(|v| v.label.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    );
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut rows = Vec::new();
    for v in &runs {
        let job = live_job(&w, v, rate, tasks, args.seed, k);
        if args.sim_only {
            let sim = simulate_scaled(&job, &scaled, k)?;
            println!(
                "{:<24} sim P25 {:.2} s, avg {:.2} s, P95 {:.2} s, {:.1} rounds/task, batch {:.2}, queue {:.0} ms, re-fetched {:.0}%",
                v.label,
                sim.summary.p25,
                sim.summary.mean,
                sim.summary.p95,
                sim.rounds_per_task,
                sim.mean_batch,
                sim.mean_queue_s * 1e3,
                sim.refetch_share * 100.0
            );
            continue;
        }
        let target = match (args.server, args.pin, &args.token) {
            (Some(addr), Some(pin), Some(token)) => Target::Remote {
                addr,
                pin,
                token: token.clone(),
            },
            _ => Target::InProcess(args.out.join("server-data")),
        };
        let bar = ProgressBar::new(tasks as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} {prefix:<24} [{elapsed_precise}] {bar:30} {pos}/{len} tasks, {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(v.label.clone());
        bar.set_message("connecting");
        bar.enable_steady_tick(Duration::from_millis(200));
        let rounds = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let (events_bar, events_rounds) = (bar.clone(), Arc::clone(&rounds));
        let outcome = runtime.block_on(run_live(&job, &scaled, &target, move |event| {
            use std::sync::atomic::Ordering;
            match event {
                LiveEvent::Connected => events_bar.set_message("running"),
                LiveEvent::Round => {
                    let n = events_rounds.fetch_add(1, Ordering::Relaxed) + 1;
                    events_bar.set_message(format!("{n} rounds"));
                }
                LiveEvent::TaskDone => events_bar.inc(1),
            }
        }))?;
        bar.finish_and_clear();
        let row = compare(job, &outcome, &scaled, k, args.sim_network)?;
        println!(
            "{:<24} live avg {:.2} s, sim avg {:.2} s ({:+.1}%), {:.1} s wall",
            v.label,
            row.live.summary.mean,
            row.sim.summary.mean,
            relative_diff(row.live.summary.mean, row.sim.summary.mean) * 100.0,
            row.measured.wall.as_secs_f64()
        );
        rows.push(row);
    }
    if args.sim_only {
        return Ok(());
    }
    write_outputs(&args, &w, rate, k, &rows)
}

fn write_outputs(
    args: &LiveArgs,
    w: &Workload,
    rate: f64,
    k: f64,
    rows: &[Comparison],
) -> anyhow::Result<()> {
    let workloads = [w.clone()];
    let jobs: Vec<Job> = rows.iter().map(|c| c.job.clone()).collect();
    let live: Vec<JobResult> = rows.iter().map(|c| c.live.clone()).collect();
    let sim: Vec<JobResult> = rows.iter().map(|c| c.sim.clone()).collect();
    let live_report = Report {
        workloads: &workloads,
        jobs: &jobs,
        results: &live,
    };
    let sim_report = Report {
        workloads: &workloads,
        jobs: &jobs,
        results: &sim,
    };
    let wall: f64 = rows.iter().map(|c| c.measured.wall.as_secs_f64()).sum();
    let network = match args.sim_network {
        SimNetworkMode::Measured => format!(
            "the robot round trip set to the live run's measured network + client overhead per round ({})",
            rows.iter()
                .map(|c| format!("{:.2} ms", c.sim_rtt.as_secs_f64() * 1e3))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        SimNetworkMode::Free => "a free network (zero round trip)".to_string(),
    };
    let mut summary = format!(
        "# Live replay vs simulation\n\nGenerated by `kairos bench live -w {}` ({} tasks at {rate} tasks/s, seed {}, trace seed {}, time scale {k}); {wall:.1} s of live runs. Times are in the recording's seconds (wall-clock x {k}) except the last three columns, which are wall-clock.\n\nLive: robots replay the traces over QUIC on loopback against the real server, whose engine is the trace-replay engine (the profiled latency of `{}`, the recorded chunks). Sim: the same schedule and inputs in virtual time, with {network}. Each cell is live (sim).\n\n",
        args.workload.display(),
        args.tasks,
        args.seed,
        args.trace_seed,
        w.engines.edge.device,
    );
    summary.push_str(&comparison_table(rows));
    summary.push_str("\n## Live, as `kairos bench sim` reports it\n");
    summary.push_str(&live_report.peak_table());
    std::fs::write(args.out.join("summary.md"), &summary)
        .with_context(|| format!("writing {}", args.out.join("summary.md").display()))?;
    std::fs::write(args.out.join("live.csv"), live_report.csv())
        .with_context(|| format!("writing {}", args.out.join("live.csv").display()))?;
    std::fs::write(args.out.join("sim.csv"), sim_report.csv())
        .with_context(|| format!("writing {}", args.out.join("sim.csv").display()))?;
    if !args.no_plots {
        super::bench::plot::all(&live_report, &args.out)?;
    }
    println!("\n{summary}");
    println!("Outputs in {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: LiveArgs,
    }

    fn parse(extra: &[&str]) -> Result<LiveArgs, clap::Error> {
        Cli::try_parse_from(std::iter::once("live").chain(extra.iter().copied())).map(|c| c.args)
    }

    fn workload() -> Workload {
        Workload::load(Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../workloads/libero-smolvla.toml"
        )))
        .unwrap()
    }

    #[test]
    fn arguments_parse_and_remote_runs_need_a_pin_and_token() {
        let args = parse(&["--variants", "fifo,kairos", "--tasks", "12"]).unwrap();
        assert_eq!(args.variants, ["fifo", "kairos"]);
        assert_eq!(args.sim_network, SimNetworkMode::Measured);
        assert!(parse(&["--server", "127.0.0.1:4433"]).is_err());
        assert!(parse(&["--tasks", "0"]).is_err());
        assert!(parse(&["--serve", "127.0.0.1:1", "--server", "127.0.0.1:2"]).is_err());
        assert!(variant("kairos").is_ok());
        let unknown = variant("lottery").unwrap_err().to_string();
        assert!(unknown.contains("fifo"), "{unknown}");
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
        assert_eq!(edge.latency(1), w.edge_profile().latency(1).div_f64(4.0));
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
