//! `kairos bench`: evaluation tools. `sim` replays workloads through the real scheduler in
//! virtual time and reproduces the paper's experiments (tables, CSV, plots) and the scale
//! experiment; `traces` turns a workload file into a trace file.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use kairos_sdk::trace::TraceSet;

use kairos_bench::sim::experiment::{self, Experiment, Job, JobResult, Plan, Report, Variant};
use kairos_bench::sim::plugins::{UserPlugins, load_user_plugins, plugin_cache_dir};
use kairos_bench::sim::scale::{DEFAULT_ROBOTS_PER_WORKER, ScalePlan};
use kairos_bench::workload::generate::{self, DYNAMIC, STATIC};
use kairos_bench::workload::{self, Workload};
use kairos_core::scheduler::PolicySpec;

/// `kairos bench ...`
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// What to run.
    #[command(subcommand)]
    pub command: BenchCommand,
}

/// The bench subcommands.
#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// Simulate workloads against the real scheduler in virtual time (paper §5 experiments).
    Sim(Box<SimArgs>),
    /// Generate a trace file from a workload file.
    Traces(TracesArgs),
    /// Find the arrival rate at which a policy's average latency reaches a multiple of its
    /// unloaded value (how the shipped workloads' peak rates were placed).
    Calibrate(CalibrateArgs),
    /// Replay the same traces live: simulated robots over QUIC against a real server with the
    /// trace-replay engine, side by side with the simulation.
    Live(Box<super::bench_live::LiveArgs>),
    /// Judge horizon policies in closed loop: task success against mean executed horizon on a
    /// seeded control task with a trained flow-matching policy (pareto.csv, summary.md, plot).
    Horizon(Box<super::bench_horizon::HorizonArgs>),
    /// Judge what a robot does with a chunk that arrives D control steps after its observation
    /// (every server chunking strategy and synchronous execution, in closed loop on the horizon
    /// bench's tasks; results.csv, summary.md, plot).
    Chunking(Box<super::bench_chunking::ChunkingArgs>),
}

/// `kairos bench calibrate`
#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// Workload files (default: every `*.toml` in `workloads/`).
    #[arg(long = "workload", short = 'w')]
    pub workloads: Vec<PathBuf>,
    /// Priority policy (replays the dynamic-horizon traces).
    #[arg(long, default_value = "kairos")]
    pub policy: String,
    /// Target: average latency = factor x unloaded average.
    #[arg(long, default_value_t = 1.5)]
    pub factor: f64,
    /// Seed of arrivals and task picks.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seed of the trace generator.
    #[arg(long, default_value_t = 42)]
    pub trace_seed: u64,
}

/// `kairos bench sim`
#[derive(Args, Debug)]
pub struct SimArgs {
    /// Workload files (TOML). Default: every `*.toml` in `workloads/`.
    #[arg(long = "workload", short = 'w')]
    pub workloads: Vec<PathBuf>,
    /// Replay this trace file instead of generating traces (needs exactly one --workload, which
    /// supplies the engines, network and experiment list).
    #[arg(long)]
    pub traces: Option<PathBuf>,
    /// Experiments to run, comma-separated: online, fleet, hybrid, buckets, intra, refetch; also
    /// scale (thousands of robots, see --scale-robots) and load-horizon (the load-aware horizon
    /// against static and threshold), which are not in the default list.
    #[arg(
        long,
        short = 'e',
        value_delimiter = ',',
        default_value = "online,fleet,hybrid,buckets,intra,refetch"
    )]
    pub experiments: Vec<String>,
    /// Extra priority policy to compare in the online experiment, e.g. `srw:starve=0.3`
    /// (replays the dynamic-horizon traces). Repeatable.
    #[arg(long = "policy")]
    pub policies: Vec<String>,
    /// Robots send the remaining-work hint in the runs of the --policy policies.
    #[arg(long)]
    pub hints: bool,
    /// Users' plugins to compare with the built-in systems.
    #[command(flatten)]
    pub plugins: UserPluginArgs,
    /// Seed of arrivals and task picks.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seed of the trace generator.
    #[arg(long, default_value_t = 42)]
    pub trace_seed: u64,
    /// Multiply every run's task count (e.g. 0.25 for a quick look; not the scale experiment's).
    #[arg(long, default_value_t = 1.0)]
    pub task_scale: f64,
    /// Fleet sizes of the scale experiment, comma-separated (one task per robot).
    #[arg(long, value_delimiter = ',', default_value = "1000,2000,5000,10000")]
    pub scale_robots: Vec<usize>,
    /// Robots per engine instance in the scale experiment: each fleet size gets
    /// ceil(robots / this) workers.
    #[arg(long, default_value_t = DEFAULT_ROBOTS_PER_WORKER)]
    pub robots_per_worker: usize,
    /// Worker threads (default: available cores; 1 when the scale experiment runs, so that its
    /// timings are not shared with another run).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Output directory for summary.md, results.csv and plots.
    #[arg(long, short = 'o', default_value = "kairos-eval")]
    pub out: PathBuf,
    /// Skip the plots.
    #[arg(long)]
    pub no_plots: bool,
}

/// `kairos bench traces`
#[derive(Args, Debug)]
pub struct TracesArgs {
    /// The workload file.
    pub workload: PathBuf,
    /// Generator seed.
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Output trace file (JSON Lines).
    #[arg(long, short = 'o')]
    pub out: PathBuf,
}

/// Runs `kairos bench`.
pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    match args.command {
        BenchCommand::Sim(a) => run_sim(*a),
        BenchCommand::Traces(a) => run_traces(a),
        BenchCommand::Calibrate(a) => run_calibrate(a),
        BenchCommand::Live(a) => super::bench_live::run(*a),
        BenchCommand::Horizon(a) => super::bench_horizon::run(*a),
        BenchCommand::Chunking(a) => super::bench_chunking::run(*a),
    }
}

fn run_calibrate(a: CalibrateArgs) -> anyhow::Result<()> {
    if !(a.factor.is_finite() && a.factor > 1.0) {
        bail!("--factor must be a number > 1");
    }
    let files = if a.workloads.is_empty() {
        default_workloads()?
    } else {
        a.workloads.clone()
    };
    let spec: PolicySpec = a.policy.parse()?;
    kairos_core::scheduler::build_policy(&spec)?;
    let variant = Variant::new(&spec.to_string(), &spec.to_string(), spec, DYNAMIC);
    for f in &files {
        let w = Workload::load(f)?;
        let set = generate::generate(&w, a.trace_seed)
            .with_context(|| format!("generating traces for `{}`", w.name))?;
        let edge = w.edge_profile();
        let per_s = f64::from(edge.max_batch) / edge.latency(edge.max_batch).as_secs_f64();
        let rounds = set.variant(DYNAMIC).map(|t| t.rounds.len()).sum::<usize>() as f64
            / set.variant(DYNAMIC).count().max(1) as f64;
        let saturation = per_s / rounds.max(1e-9);
        let rate = experiment::calibrate_rate(
            &w,
            &set,
            &variant,
            a.factor,
            (saturation * 0.05, saturation * 4.0),
            14,
            a.seed,
        )?;
        println!(
            "{:<22} {} reaches {}x its unloaded average latency at {rate:.3} tasks/s ({:.2}x the dynamic-horizon saturation estimate {saturation:.3})",
            w.title,
            variant.label,
            a.factor,
            rate / saturation
        );
    }
    Ok(())
}

fn run_traces(a: TracesArgs) -> anyhow::Result<()> {
    let w = Workload::load(&a.workload)?;
    let set = workload::generate(&w, a.seed)
        .with_context(|| format!("generating traces for `{}`", w.name))?;
    let file =
        std::fs::File::create(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    set.write(std::io::BufWriter::new(file))
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "wrote {} tasks ({} per setting) of `{}` to {}",
        set.tasks.len(),
        w.tasks.pool,
        w.name,
        a.out.display()
    );
    Ok(())
}

/// The shipped workload files, sorted.
fn default_workloads() -> anyhow::Result<Vec<PathBuf>> {
    let dir = Path::new("workloads");
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| {
            format!(
                "no --workload given and cannot read {} (run from the repository root)",
                dir.display()
            )
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("no *.toml workload files in {}", dir.display());
    }
    Ok(files)
}

/// One line per workload: what the traces ask of the GPU, for reading the results.
fn describe(w: &Workload, set: &TraceSet) -> String {
    let rounds = |setting: &str| {
        let (n, r) = set
            .variant(setting)
            .fold((0usize, 0usize), |(n, r), t| (n + 1, r + t.rounds.len()));
        r as f64 / n.max(1) as f64
    };
    let exec: f64 = set
        .variant(STATIC)
        .map(|t| t.execution_seconds())
        .sum::<f64>()
        / set.variant(STATIC).count().max(1) as f64;
    let edge = w.edge_profile();
    let per_s = f64::from(edge.max_batch) / edge.latency(edge.max_batch).as_secs_f64();
    let (static_r, dynamic_r) = (rounds(STATIC), rounds(DYNAMIC));
    format!(
        "{:<22} mean task {:>5.1} s | rounds/task static {:>5.1}, dynamic {:>5.1} | edge {:.0} req/s at batch {} → saturates at {:.2} tasks/s static, {:.2} dynamic | rates {:?}",
        w.title,
        exec,
        static_r,
        dynamic_r,
        per_s,
        edge.max_batch,
        per_s / static_r.max(1e-9),
        per_s / dynamic_r.max(1e-9),
        w.experiments.rates
    )
}

fn run_sim(a: SimArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let files = if a.workloads.is_empty() {
        default_workloads()?
    } else {
        a.workloads.clone()
    };
    if a.traces.is_some() && files.len() != 1 {
        bail!("--traces needs exactly one --workload (it supplies engines, network and rates)");
    }
    if !(a.task_scale.is_finite() && a.task_scale > 0.0) {
        bail!("--task-scale must be a positive number");
    }
    if a.robots_per_worker == 0 || a.scale_robots.contains(&0) {
        bail!("--robots-per-worker and every --scale-robots size must be at least 1");
    }
    let mut experiments = Vec::new();
    for name in &a.experiments {
        let e = Experiment::parse(name.trim()).with_context(|| {
            format!("unknown experiment `{name}` (expected online, fleet, hybrid, buckets, intra, refetch, scale, load-horizon)")
        })?;
        if !experiments.contains(&e) {
            experiments.push(e);
        }
    }
    let mut extra = Vec::new();
    for p in &a.policies {
        let spec: PolicySpec = p.parse()?;
        kairos_core::scheduler::build_policy(&spec)?;
        let mut v = Variant::new(&format!("extra:{spec}"), &spec.to_string(), spec, DYNAMIC);
        v.hints = a.hints;
        v.user = true;
        extra.push(v);
    }

    let user = a.plugins.load()?;
    if a.traces.is_some() && !a.plugins.horizon_plugins.is_empty() {
        bail!(
            "--horizon-plugin needs generated traces (a recorded trace file has no rounds chosen by the plugin)"
        );
    }
    extra.extend(user.variants(a.plugins.plugin_refetch));

    let mut workloads = Vec::new();
    let mut traces = Vec::new();
    for f in &files {
        let w = Workload::load(f)?;
        let set = match &a.traces {
            Some(path) => {
                let file = std::fs::File::open(path)
                    .with_context(|| format!("opening {}", path.display()))?;
                TraceSet::read(std::io::BufReader::new(file))
                    .with_context(|| format!("reading {}", path.display()))?
            }
            None => {
                let mut settings = generate::settings(&w).to_vec();
                settings.extend(user.horizon_settings());
                let (horizons, _) = user.policies.with_natives();
                generate::generate_settings(&w, a.trace_seed, &settings, &horizons)
                    .with_context(|| format!("generating traces for `{}`", w.name))?
            }
        };
        println!("{}", describe(&w, &set));
        workloads.push(w);
        traces.push(set);
    }

    let jobs: Vec<Job> = experiment::plan(
        &workloads,
        &Plan {
            experiments,
            seed: a.seed,
            extra,
            task_scale: a.task_scale,
            policies: user.policies.clone(),
            scale: ScalePlan {
                robots: a.scale_robots.clone(),
                robots_per_worker: a.robots_per_worker,
            },
        },
    );
    // A recorded trace set may hold only some settings (a robot records the one it ran); drop the
    // runs that would replay a missing one, and say so.
    let jobs: Vec<Job> = if a.traces.is_some() {
        let available: Vec<String> = traces.iter().flat_map(|t| t.settings()).collect();
        let (keep, drop): (Vec<Job>, Vec<Job>) = jobs
            .into_iter()
            .partition(|j| available.contains(&j.variant.setting));
        if !drop.is_empty() {
            println!(
                "skipping {} runs whose horizon setting is not in the trace file (it has: {})",
                drop.len(),
                available.join(", ")
            );
        }
        keep
    } else {
        jobs
    };
    if jobs.is_empty() {
        bail!("nothing to run");
    }
    let timed = jobs.iter().any(|j| j.experiment == Experiment::Scale);
    let threads = a
        .threads
        .unwrap_or_else(|| {
            if timed {
                1
            } else {
                std::thread::available_parallelism().map_or(1, |n| n.get())
            }
        })
        .max(1);
    let bar = ProgressBar::new(jobs.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} runs, eta {eta} {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let on_done = |job: &Job| {
        bar.set_message(format!(
            "{} {}",
            workloads[job.workload].name,
            job.experiment.name()
        ));
        bar.inc(1);
    };
    let sim_started = Instant::now();
    let results = experiment::run_jobs(&jobs, &traces, threads, &on_done);
    bar.finish_and_clear();
    let sim_elapsed = sim_started.elapsed();
    let mut ok: Vec<JobResult> = Vec::with_capacity(results.len());
    for (job, r) in jobs.iter().zip(results) {
        let r = r.with_context(|| {
            format!(
                "{} / {} / {} at {}",
                workloads[job.workload].name,
                job.experiment.name(),
                job.variant.key,
                job.x
            )
        })?;
        ok.push(r);
    }
    let report = Report {
        workloads: &workloads,
        jobs: &jobs,
        results: &ok,
    };

    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let summary = summary_markdown(&report, &a, threads);
    write(&a.out.join("summary.md"), &summary)?;
    write(&a.out.join("results.csv"), &report.csv())?;
    if timed {
        write(&a.out.join("scale.csv"), &report.scale_csv())?;
    }
    if !a.no_plots {
        kairos_bench::plot::all(&report, &a.out)?;
    }
    println!("{summary}");
    println!(
        "{} runs on {threads} thread(s): simulation {:.1} s, total {:.1} s. Outputs in {}",
        jobs.len(),
        sim_elapsed.as_secs_f64(),
        started.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

fn summary_markdown(report: &Report<'_>, a: &SimArgs, threads: usize) -> String {
    let mut s = String::new();
    let has = |e: Experiment| report.jobs.iter().any(|j| j.experiment == e);
    s.push_str(&format!(
        "# Simulation results\n\nGenerated by `kairos bench sim` (seed {}, trace seed {}, task scale {}; {} runs). Deterministic: the same command gives the same file.\n",
        a.seed,
        a.trace_seed,
        a.task_scale,
        report.jobs.len(),
    ));
    let users: Vec<&Variant> = {
        let mut seen: Vec<&Variant> = Vec::new();
        for j in report.jobs.iter().filter(|j| j.variant.user) {
            if !seen.iter().any(|v| v.key == j.variant.key) {
                seen.push(&j.variant);
            }
        }
        seen
    };
    if !users.is_empty() {
        s.push_str("\nUser policies in the online experiment (rows of their own below):\n\n");
        for v in users {
            s.push_str(&format!(
                "- {} (`{}`): priority `{}`, horizon setting `{}`, re-fetch {}\n",
                v.label,
                v.key,
                v.policy,
                v.setting,
                if v.refetch { "on" } else { "off" }
            ));
        }
    }
    if has(Experiment::Online) {
        s.push_str("\n## Latency reduction at the highest arrival rate vs FIFO\n\n");
        s.push_str(&report.reduction_table("fifo"));
        s.push_str("\n## Latency reduction at the highest arrival rate vs Autellix\n\n");
        s.push_str(&report.reduction_table("autellix"));
        s.push_str("\n## End-to-end latency at the highest arrival rate\n");
        s.push_str(&report.peak_table());
        s.push_str("\n## Online: average (P95) end-to-end latency in seconds by arrival rate\n");
        s.push_str(&report.sweep_table(Experiment::Online, "tasks/s"));
    }
    if has(Experiment::Fleet) {
        s.push_str("\n## Offline fleet: average (P95) latency in seconds by fleet size\n");
        s.push_str(&report.sweep_table(Experiment::Fleet, "robots"));
    }
    if has(Experiment::Hybrid) {
        s.push_str("\n## Hybrid edge + cloud: average (P95) latency in seconds by arrival rate\n");
        s.push_str(&report.sweep_table(Experiment::Hybrid, "tasks/s"));
    }
    if has(Experiment::Buckets) {
        s.push_str("\n## Ablation: wait-ratio bucket count at the highest rate, average (P95) s\n");
        s.push_str(&report.sweep_table(Experiment::Buckets, "tasks/s"));
    }
    if has(Experiment::Intra) {
        s.push_str("\n## Ablation: intra-bucket order at the highest rate, average (P95) s\n");
        s.push_str(&report.sweep_table(Experiment::Intra, "tasks/s"));
    }
    if has(Experiment::LoadHorizon) {
        s.push_str("\n## Load-aware horizon: Kairos by arrival rate, average (P95) latency in seconds · mean H · actions per task past the threshold's cut\n");
        s.push_str(&report.load_horizon_table());
    }
    if has(Experiment::Refetch) {
        s.push_str("\n## Ablation: each system's re-fetch setting flipped, at the highest rate\n");
        s.push_str(&report.refetch_table());
    }
    if has(Experiment::Scale) {
        s.push_str(&format!(
            "\n## Scale: one scheduler, {} robots per engine instance (Kairos, dynamic horizon)\n\nDecision and scheduler times are wall-clock, measured around the scheduler's calls on this machine ({} thread(s)); everything else is virtual time and deterministic.\n",
            a.robots_per_worker, threads
        ));
        s.push_str(&report.scale_table());
    }
    s
}

/// Users' plugins in `kairos bench sim` and `kairos bench live`: loaded into the same policy
/// registries as the built-ins and compared beside them.
#[derive(Debug, Clone, clap::Args)]
pub struct UserPluginArgs {
    /// A priority-policy plugin (`.wasm` component) to compare with the built-in schedulers:
    /// systems `F.wasm` (static-horizon traces) and `F.wasm + dyn. horizon`. Repeatable.
    #[arg(long = "priority-plugin", value_name = "F.wasm")]
    pub priority_plugins: Vec<PathBuf>,
    /// A horizon-policy plugin (`.wasm` component): every task is also recorded with it choosing
    /// the horizon, and Algorithm 1 replays that (system `Kairos + F.wasm`, beside `Kairos` with
    /// the native threshold rule). Repeatable.
    #[arg(long = "horizon-plugin", value_name = "F.wasm")]
    pub horizon_plugins: Vec<PathBuf>,
    /// A parameter handed to every plugin, `name=value` (repeatable).
    #[arg(long = "param", value_parser = super::parse_param)]
    pub params: Vec<(String, f64)>,
    /// The priority plugins' runs re-fetch stale observations (as Algorithm 1 does; off by
    /// default, as for the baseline schedulers, so a plugin's system shows its ordering alone).
    #[arg(long)]
    pub plugin_refetch: bool,
    /// Precompiled plugin code cache (default: the user's cache directory).
    #[arg(long, value_name = "DIR")]
    pub plugin_cache: Option<PathBuf>,
}

impl UserPluginArgs {
    /// Loads and checks every plugin named.
    pub fn load(&self) -> anyhow::Result<UserPlugins> {
        Ok(load_user_plugins(
            &self.priority_plugins,
            &self.horizon_plugins,
            &self.params.iter().cloned().collect(),
            &plugin_cache_dir(self.plugin_cache.clone()),
        )?)
    }
}
