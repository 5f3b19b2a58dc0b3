//! The demo (`kairos demo`): the whole system in one process, in about a minute, with nothing to
//! set up. This module runs it and writes its outputs; `cli::demo` shows its progress.
//!
//! For each scheduler in turn (FIFO, Autellix, Kairos, and SRW, the better policy of
//! docs/EVALUATION.md) it starts the real server on `127.0.0.1:0` — QUIC with TLS 1.3, the driver,
//! the scheduler, the action manager — whose engine is the engine crate's built-in flow head
//! running real forward passes (profiled once at start, like `kairos serve` does), and a fleet
//! of simulated robots, one QUIC connection each, that start at Poisson-staggered times and each
//! run one task with the SDK's [`RobotRunner`]: actions execute in real time at the control
//! frequency while the next chunk is generated, and the server's horizon policy decides how much
//! of each chunk runs. Every scheduler sees the same fleet: the same start times and task
//! lengths (from `--seed`).
//!
//! **The fleet contends the engine on any machine.** Its size and stagger come from the profile
//! measured at start ([`workload`]): under FIFO with the static horizon the fleet offers about 90%
//! of what the engine serves at its saturation batch, so requests queue and the order matters,
//! whether a forward pass takes 13 ms or 130 ms. A fixed fleet could not do that: one that
//! contends a slow machine's engine leaves a fast one's mostly idle, and there every scheduler and
//! horizon comes out the same.
//!
//! **What it shows.** Horizons follow the paper's comparison by default (`--horizons paper`): the
//! baselines (FIFO, Autellix) execute a static `H`, Kairos and SRW the §3.1 threshold policy on
//! the chunk's diffusion updates. The dynamic horizon executes more of each chunk, so the same
//! work needs fewer rounds, the contended engine is relieved, and robots stop waiting: that is
//! most of Kairos's gain, as in the paper. Between schedulers with the same horizon the
//! differences are smaller, for two reasons the demo does not hide. With a static `H` every
//! request goes out with the same slack (the half chunk its robot still has to execute), so
//! arrival order is deadline order and FIFO is already close to the best order for idle robots;
//! a scheduler gains there only through what FIFO ignores, such as a task's remaining length, and
//! loses by serving a request with slack before one whose robot is dry. Under the dynamic horizon
//! the same fleet no longer
//! contends the engine enough for the order to matter. The summary says which differences are
//! within noise ([`comparison`]) and how fast the engine ran in each run (a shared machine's
//! other work shows there). `--horizons dynamic` gives every scheduler the threshold policy,
//! which isolates the schedulers.
//!
//! It leads with a short result (Kairos's average task latency against FIFO's, and the engine's
//! busy share under each), then a per-scheduler table (average / P25 / P95 task latency, the
//! difference from FIFO with its interval, rounds, mean horizon, server queueing, batch size,
//! engine busy share), a few sentences reading it, and a PNG plot. Everything it writes goes
//! under `--out` (default `./kairos-demo/`): the server's state (certificate, token),
//! `summary.md`, `demo.png`/`.svg`.
//!
//! The fleet runs through [`crate::fleet`], like `kairos robot` and `kairos bench live`.

pub mod comparison;
pub mod summary;
pub mod workload;

use std::collections::BTreeMap;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use kairos_sdk::protocol::{HorizonSelection, Observation};
use kairos_sdk::robot::{
    Robot, RobotError, RobotRunner, RunnerConfig, RunnerEvent, SimulatedRobot, TaskSummary,
};
use tokio::time::Instant;

use crate::fleet::{self, LocalServer};
use kairos_core::scheduler::PolicySpec;
use kairos_core::stats::{Summary, summarize};
use kairos_engine::EngineProfile;
use kairos_server::config::{Config, EngineConfig};
use kairos_server::pool::{BuildEvent, EnginePool, ModelSchemes, build_pool};
use kairos_server::transport::launch::{Policies, ServerReport};

pub use summary::{headline, reading, summary_table};
pub use workload::{DEFAULT_LOAD, FleetSizing, FleetTask, fleet, size_fleet};

/// Which horizon policy each scheduler's robots ask for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Horizons {
    /// As in the paper's comparison: FIFO and Autellix a static `H`, the others the threshold
    /// policy (the dynamic horizon).
    #[default]
    Paper,
    /// Every scheduler with the threshold policy: only the scheduling differs.
    Dynamic,
    /// Every scheduler with the static `H`.
    Static,
}

/// What the demo runs: the fleet, the schedulers compared, the horizons, where it writes.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Robots in the fleet: each runs one task over its own QUIC connection. `None`: sized from
    /// the engine's profile ([`size_fleet`]).
    pub robots: Option<u32>,
    /// Median task length, seconds of execution (log-normal, σ = 0.5, within 0.25x–3x).
    pub task_s: f64,
    /// Mean gap between robot starts (Poisson arrivals), seconds. `None`: sized from the
    /// engine's profile.
    pub stagger_s: Option<f64>,
    /// The share of the engine's capacity the baseline fleet (FIFO, static `H`) offers when
    /// the fleet is sized from the profile.
    pub load: f64,
    /// Schedulers to compare, comma-separated priority policies (`fifo`, `plas` = Autellix,
    /// `kairos`, `srw`, or any `name:key=value` spec the server accepts).
    pub schedulers: Vec<String>,
    /// Horizon policy per scheduler.
    pub horizons: Horizons,
    /// The static horizon `H`.
    pub static_h: u32,
    /// Threshold `t` of the dynamic horizon (paper §3.1).
    pub threshold: f64,
    /// `H_min` of the dynamic horizon.
    pub h_min: u32,
    /// Robot control frequency, actions per second.
    pub control_hz: f64,
    /// Largest batch measured when profiling the engine at start.
    pub profile_max_batch: u32,
    /// Seed of the fleet (start times, task lengths).
    pub seed: u64,
    /// Output directory.
    pub out: PathBuf,
    /// Skip the plot.
    pub no_plot: bool,
    /// A short run of the same code path, sized the same way, for CI and smoke tests: tasks of
    /// 1 s, the engine profiled up to batch 4. Also set by the environment variable
    /// `KAIROS_DEMO_QUICK=1`, so that the README's command runs verbatim in CI. Overrides
    /// `--task-s` and `--profile-max-batch`.
    pub quick: bool,
}

/// The environment variable that turns on [`DemoOptions::quick`].
pub const QUICK_ENV: &str = "KAIROS_DEMO_QUICK";

impl DemoOptions {
    /// `self` with the quick run's settings if `--quick` is given or `KAIROS_DEMO_QUICK` is `1`
    /// in `env` (the process environment, for the caller to pass).
    pub fn resolve_quick(mut self, env: Option<&std::ffi::OsStr>) -> DemoOptions {
        self.quick |= env.is_some_and(|v| v == "1");
        if self.quick {
            self.task_s = 1.0;
            self.profile_max_batch = 4;
        }
        self
    }
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions {
            robots: None,
            task_s: 3.0,
            stagger_s: None,
            load: DEFAULT_LOAD,
            schedulers: ["fifo", "plas", "kairos", "srw"].map(String::from).to_vec(),
            horizons: Horizons::Paper,
            static_h: 10,
            threshold: 0.4,
            h_min: 5,
            control_hz: 30.0,
            profile_max_batch: 16,
            seed: 7,
            out: PathBuf::from("kairos-demo"),
            no_plot: false,
            quick: false,
        }
    }
}

/// One scheduler's configuration in the comparison.
#[derive(Clone, Debug, PartialEq)]
pub struct SchedulerRun {
    /// Colour key for the plot (`fifo`, `autellix`, `kairos`, `srw`, other).
    pub key: String,
    /// Label.
    pub label: String,
    /// The server's priority policy.
    pub policy: PolicySpec,
    /// The horizon policy the robots ask for.
    pub horizon: HorizonSelection,
}

impl SchedulerRun {
    /// Whether the robots ask for the dynamic (threshold) horizon.
    pub fn dynamic(&self) -> bool {
        self.horizon.policy == "threshold"
    }
}

/// The runs `args` asks for, in order.
pub fn scheduler_runs(args: &DemoOptions) -> anyhow::Result<Vec<SchedulerRun>> {
    if args.schedulers.is_empty() {
        bail!("--schedulers is empty");
    }
    let static_h = HorizonSelection {
        policy: "static".into(),
        params: BTreeMap::from([("h".to_string(), f64::from(args.static_h))]),
        samples: 1,
    };
    let dynamic = HorizonSelection {
        policy: "threshold".into(),
        params: BTreeMap::from([
            ("t".to_string(), args.threshold),
            ("h_min".to_string(), f64::from(args.h_min)),
        ]),
        samples: 1,
    };
    args.schedulers
        .iter()
        .map(|text| {
            let policy: PolicySpec = text.trim().parse()?;
            kairos_core::scheduler::build_policy(&policy)?;
            let (key, name) = match policy.name.as_str() {
                "fifo" => ("fifo", "FIFO"),
                "plas" => ("autellix", "Autellix"),
                "kairos" => ("kairos", "Kairos"),
                "srw" => ("srw", "SRW (ours)"),
                other => (other, other),
            };
            let baseline = matches!(key, "fifo" | "autellix");
            let horizon = match args.horizons {
                Horizons::Paper if baseline => static_h.clone(),
                Horizons::Paper | Horizons::Dynamic => dynamic.clone(),
                Horizons::Static => static_h.clone(),
            };
            let label = if policy.params.is_empty() {
                name.to_string()
            } else {
                format!("{name} ({policy})")
            };
            let label = match horizon.policy.as_str() {
                "static" => format!("{label}, H={}", args.static_h),
                _ => format!("{label}, dyn. H"),
            };
            Ok(SchedulerRun {
                key: key.to_string(),
                label,
                policy,
                horizon,
            })
        })
        .collect()
}

/// A [`SimulatedRobot`] whose task is done after a fixed number of actions.
struct FleetRobot {
    inner: SimulatedRobot,
    actions: u64,
}

impl Robot for FleetRobot {
    fn get_obs(
        &mut self,
        now_us: u64,
    ) -> impl Future<Output = Result<Observation, RobotError>> + Send {
        self.inner.get_obs(now_us)
    }

    fn send_act(&mut self, action: &[f32]) -> impl Future<Output = Result<(), RobotError>> + Send {
        self.inner.send_act(action)
    }

    fn task_done(&self) -> bool {
        self.inner.executed() >= self.actions
    }
}

/// One scheduler's run.
#[derive(Clone, Debug)]
pub struct RunResult {
    /// What ran.
    pub run: SchedulerRun,
    /// Every finished task, in fleet order.
    pub tasks: Vec<TaskSummary>,
    /// Tasks that failed, with why.
    pub failures: Vec<String>,
    /// The server's counters.
    pub server: ServerReport,
    /// Wall-clock time of the run.
    pub wall: Duration,
}

impl RunResult {
    /// Task latencies (first request → last action), seconds.
    pub fn latencies(&self) -> Vec<f64> {
        self.tasks
            .iter()
            .map(|t| t.latency_us() as f64 / 1e6)
            .collect()
    }

    /// `(task id, latency in seconds)` of every finished task, for paired comparisons.
    pub fn task_latencies(&self) -> Vec<(u64, f64)> {
        self.tasks
            .iter()
            .map(|t| (t.task, t.latency_us() as f64 / 1e6))
            .collect()
    }

    /// P25 / mean / P95 of the task latencies.
    pub fn summary(&self) -> Summary {
        summarize(&self.latencies())
    }

    fn rounds(&self) -> impl Iterator<Item = &kairos_sdk::robot::RoundRecord> {
        self.tasks.iter().flat_map(|t| &t.rounds)
    }

    /// Answered rounds.
    pub fn round_count(&self) -> usize {
        self.rounds().count()
    }

    /// Mean horizon `H` the server chose.
    pub fn mean_horizon(&self) -> f64 {
        mean(self.rounds().map(|r| f64::from(r.horizon)))
    }

    /// Mean server queueing per round (arrival → dispatch), ms.
    pub fn mean_queue_ms(&self) -> f64 {
        mean(self.rounds().map(|r| r.timing.queue_us as f64 / 1e3))
    }

    /// Mean batch size, over batches.
    pub fn mean_batch(&self) -> f64 {
        let batches = self.server.driver.batches.max(1) as f64;
        self.server.driver.replies as f64 / batches
    }

    /// Share of the run's wall-clock time the engine spent generating.
    pub fn engine_busy(&self) -> f64 {
        let busy_us: f64 = self
            .rounds()
            .map(|r| r.timing.inference_us as f64 / f64::from(r.timing.batch_size.max(1)))
            .sum();
        busy_us / 1e6 / self.wall.as_secs_f64().max(1e-9)
    }

    /// How fast the engine ran during the run against its profile: the forward passes' total
    /// time over what the profile predicts for the same batches (1.0: as profiled; 1.3: 30%
    /// slower, e.g. a machine busier than when it was profiled). Per batch, not per round.
    pub fn engine_pace(&self, profile: &EngineProfile) -> f64 {
        let (ran, profiled) = self.rounds().fold((0.0, 0.0), |(ran, profiled), r| {
            let batch = r.timing.batch_size.max(1);
            (
                ran + r.timing.inference_us as f64 / 1e6 / f64::from(batch),
                profiled + profile.latency(batch).as_secs_f64() / f64::from(batch),
            )
        });
        if profiled > 0.0 { ran / profiled } else { 0.0 }
    }

    /// Mean time a robot sat idle waiting for actions, per task, seconds.
    pub fn mean_idle_s(&self) -> f64 {
        mean(self.tasks.iter().map(|t| t.idle_us as f64 / 1e6))
    }
}

pub(crate) fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// Progress of a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DemoEvent {
    /// A round was answered.
    Round,
    /// A robot finished its task (or failed).
    TaskDone,
}

/// What [`execute`] reports while it works, for a progress display. Every method has a no-op
/// default; `()` reports nothing.
pub trait DemoProgress: Send + Sync {
    /// Loading or profiling the engine.
    fn engine(&self, _event: &BuildEvent) {}
    /// The engine is ready (`engine` describes it), the fleet is sized, and the runs are about
    /// to start.
    fn ready(
        &self,
        _engine: &str,
        _sizing: &FleetSizing,
        _fleet: &[FleetTask],
        _runs: &[SchedulerRun],
        _args: &DemoOptions,
    ) {
    }
    /// A scheduler's run starts.
    fn run_started(&self, _run: &SchedulerRun, _robots: usize) {}
    /// A round was answered or a task finished, from the robots' tasks.
    fn event(&self, _event: DemoEvent) {}
    /// A scheduler's run ended.
    fn run_finished(&self, _result: &RunResult) {}
}

impl DemoProgress for () {}

/// Runs the fleet against a fresh server with `run`'s scheduler on `pool`, keeping the server's
/// state in `data_dir`.
pub async fn run_fleet(
    pool: EnginePool,
    fleet: &[FleetTask],
    run: &SchedulerRun,
    control_hz: f64,
    data_dir: &Path,
    on_event: impl Fn(DemoEvent) + Send + Sync + 'static,
) -> anyhow::Result<RunResult> {
    let mut config = Config {
        listen: "127.0.0.1:0".parse()?,
        data_dir: data_dir.to_path_buf(),
        ..Config::default()
    };
    config.scheduler.policy = run.policy.clone();
    let server = LocalServer::start(&config, pool, Policies::default()).await?;
    let client_config = server
        .generated_robot()
        .context("the server generated no robot token")?;
    let clients = fleet::connect(&client_config, fleet.len()).await?;
    let model = fleet::served_model(&clients).await?;
    let runner = RobotRunner::new(RunnerConfig {
        control_hz: control_hz as f32,
        trigger: workload::TRIGGER as f32,
        // The task ends on its action count (`FleetRobot::task_done`); a round budget this large
        // also keeps the runner from sending a remaining-rounds hint it cannot know.
        rounds: u64::MAX,
        horizon: Some(run.horizon.clone()),
        ..RunnerConfig::default()
    });

    let on_event = Arc::new(on_event);
    let cameras = model.max_images.min(2) as usize;
    let state_dim = model.state_dim as usize;
    // A little lead so that the first robots do not start late while the others are spawned.
    let t0 = Instant::now() + Duration::from_millis(100);
    let starts: Vec<Duration> = fleet.iter().map(|task| task.start).collect();
    let outcomes = fleet::run_from(t0, &starts, |index| {
        let (runner, client, on_event) = (
            runner.clone(),
            clients[index].clone(),
            Arc::clone(&on_event),
        );
        let actions = fleet[index].actions;
        async move {
            let mut robot = FleetRobot {
                inner: SimulatedRobot::new(state_dim, cameras, 64, 64),
                actions,
            };
            let summary = runner
                .run(&mut robot, client.task(index as u64), |event| {
                    if let RunnerEvent::ReplyReceived { .. } = event {
                        on_event(DemoEvent::Round);
                    }
                })
                .await;
            on_event(DemoEvent::TaskDone);
            summary
        }
    })
    .await;
    let mut tasks = Vec::with_capacity(fleet.len());
    let mut failures = Vec::new();
    for (index, outcome) in outcomes.into_iter().enumerate() {
        match outcome {
            Ok(Ok(summary)) => tasks.push(summary),
            Ok(Err(error)) => failures.push(format!("robot {index}: {error}")),
            Err(error) => failures.push(format!("robot {index} panicked: {error}")),
        }
    }
    let wall = t0.elapsed();
    for client in &clients {
        client.close().await;
    }
    let server = server.shutdown().await;
    Ok(RunResult {
        run: run.clone(),
        tasks,
        failures,
        server,
        wall,
    })
}

/// What a demo produced.
#[derive(Clone, Debug)]
pub struct DemoReport {
    /// Per scheduler, in order.
    pub results: Vec<RunResult>,
    /// The engine's profile line.
    pub engine: String,
    /// How the fleet was sized.
    pub sizing: FleetSizing,
    /// `summary.md`'s text.
    pub summary: String,
    /// The plot, if drawn.
    pub plot: Option<PathBuf>,
}

/// The profile in one line: model, device, and latency per measured batch.
fn describe(profile: &EngineProfile) -> String {
    format!(
        "{} on {}, batches up to {} ({})",
        profile.model,
        profile.device,
        profile.max_batch,
        profile
            .points
            .iter()
            .map(|p| format!("{}: {:.1} ms", p.batch, p.latency_ms))
            .collect::<Vec<_>>()
            .join(", ")
    )
}

/// Runs the demo, writes `summary.md` and the plot under `args.out`, and returns its report.
/// Blocking: it profiles the engine, sizes the fleet from the profile, and runs its own tokio
/// runtime.
pub fn execute(args: &DemoOptions, progress: Arc<dyn DemoProgress>) -> anyhow::Result<DemoReport> {
    let runs = scheduler_runs(args)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let engine_config = EngineConfig {
        profile_max_batch: args.profile_max_batch,
        ..EngineConfig::default()
    };
    let mut profile = None;
    let pool = build_pool(&[engine_config], &ModelSchemes::new(), |event| {
        if let BuildEvent::Ready { profile: p, .. } = &event {
            profile = Some(p.clone());
        }
        progress.engine(&event);
    })
    .context("starting the engine")?;
    let profile = profile.context("the engine reported no profile")?;
    let engine = describe(&profile);
    let sizing = size_fleet(&profile, args);
    let fleet = fleet(args, &sizing);
    progress.ready(&engine, &sizing, &fleet, &runs, args);

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let mut results = Vec::new();
    for run in &runs {
        progress.run_started(run, fleet.len());
        let events = Arc::clone(&progress);
        let result = runtime.block_on(run_fleet(
            pool.clone(),
            &fleet,
            run,
            args.control_hz,
            &args.out.join("server-data"),
            move |event| events.event(event),
        ))?;
        progress.run_finished(&result);
        results.push(result);
    }

    let mut summary = format!("# kairos demo\n\n{}\n\n", headline(&results, &profile));
    summary.push_str(&summary_table(&results, &profile));
    summary.push('\n');
    summary.push_str(&format!(
        "One process: the real server (QUIC + TLS 1.3 on loopback, scheduler, action manager) with the built-in flow head doing real forward passes ({engine}), and {} simulated robots, one connection each, starting as a Poisson process, each running one task of {:.1}–{:.1} s of actions at {} Hz with asynchronous inference. Every scheduler sees the same fleet (seed {}). Latency = first request to last action; engine busy = the share of the run's time the engine spent generating. {}\n\n",
        fleet.len(),
        fleet.iter().map(|t| t.actions).min().unwrap_or(0) as f64 / args.control_hz,
        fleet.iter().map(|t| t.actions).max().unwrap_or(0) as f64 / args.control_hz,
        args.control_hz,
        args.seed,
        summary::sizing_sentence(&sizing, args.static_h),
    ));
    summary.push_str(&reading(&results, &profile));
    summary.push('\n');
    let plot = if args.no_plot {
        None
    } else {
        let latencies: Vec<Vec<f64>> = results.iter().map(RunResult::latencies).collect();
        let summaries: Vec<Summary> = results.iter().map(RunResult::summary).collect();
        let systems: Vec<crate::plot::Compared<'_>> = results
            .iter()
            .zip(&latencies)
            .zip(&summaries)
            .map(|((r, l), m)| crate::plot::Compared {
                key: &r.run.key,
                label: &r.run.label,
                summary: m,
                latencies: l,
            })
            .collect();
        Some(crate::plot::comparison(
            &args.out,
            "demo",
            &format!(
                "{} robots, {:.0}% offered load under FIFO, real flow head",
                fleet.len(),
                sizing.load * 100.0
            ),
            &systems,
        )?)
    };
    std::fs::write(args.out.join("summary.md"), &summary)
        .with_context(|| format!("writing {}", args.out.join("summary.md").display()))?;
    Ok(DemoReport {
        results,
        engine,
        sizing,
        summary,
        plot,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quick_mode_comes_from_the_flag_or_the_environment() {
        let full = DemoOptions::default();
        assert!(!full.clone().resolve_quick(None).quick);
        let off = full.clone().resolve_quick(Some(std::ffi::OsStr::new("0")));
        assert!(!off.quick, "only `1` turns it on");
        assert_eq!(off.task_s, full.task_s);
        let quick = full.clone().resolve_quick(Some(std::ffi::OsStr::new("1")));
        assert!(quick.quick);
        assert_eq!((quick.task_s, quick.profile_max_batch), (1.0, 4));
        let flag = DemoOptions {
            quick: true,
            ..DemoOptions::default()
        }
        .resolve_quick(None);
        assert_eq!(flag.task_s, 1.0);
        assert_eq!(
            (quick.robots, quick.stagger_s, quick.load),
            (None, None, full.load),
            "the quick run is sized by the same rule"
        );
        assert_eq!(
            (quick.schedulers, quick.seed),
            (full.schedulers, full.seed),
            "the same schedulers and fleet seed"
        );
    }

    #[test]
    fn the_paper_setup_gives_the_baselines_the_static_horizon() {
        let runs = scheduler_runs(&DemoOptions::default()).unwrap();
        let summary: Vec<(&str, bool)> =
            runs.iter().map(|r| (r.key.as_str(), r.dynamic())).collect();
        assert_eq!(
            summary,
            [
                ("fifo", false),
                ("autellix", false),
                ("kairos", true),
                ("srw", true)
            ]
        );
        assert_eq!(runs[0].horizon.params["h"], 10.0);
        assert_eq!(runs[2].horizon.params["t"], 0.4);
        let all_static = scheduler_runs(&DemoOptions {
            horizons: Horizons::Static,
            ..DemoOptions::default()
        })
        .unwrap();
        assert!(all_static.iter().all(|r| !r.dynamic()));
    }
}
