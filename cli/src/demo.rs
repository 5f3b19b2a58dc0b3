//! `kairos demo`: runs [`kairos_bench::demo`] with progress bars and prints its summary.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use anyhow::bail;
use indicatif::{ProgressBar, ProgressStyle};

use kairos_bench::demo::{
    DEFAULT_LOAD, DemoEvent, DemoOptions, DemoProgress, FleetSizing, FleetTask, Horizons,
    QUICK_ENV, RunResult, SchedulerRun, execute,
};
use kairos_server::pool::BuildEvent;

/// Which horizon policy each scheduler's robots ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum HorizonsArg {
    /// As in the paper's comparison: FIFO and Autellix a static `H`, the others the threshold
    /// policy (the dynamic horizon).
    Paper,
    /// Every scheduler with the threshold policy: only the scheduling differs.
    Dynamic,
    /// Every scheduler with the static `H`.
    Static,
}

impl From<HorizonsArg> for Horizons {
    fn from(arg: HorizonsArg) -> Horizons {
        match arg {
            HorizonsArg::Paper => Horizons::Paper,
            HorizonsArg::Dynamic => Horizons::Dynamic,
            HorizonsArg::Static => Horizons::Static,
        }
    }
}

/// Run the server and a fleet of simulated robots in one process, once per scheduler, and
/// compare.
#[derive(clap::Args, Debug, Clone)]
pub struct DemoArgs {
    /// Robots in the fleet: each runs one task over its own QUIC connection. Default: sized from
    /// the engine's profile so that FIFO's fleet offers `--load` of the engine's capacity.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub robots: Option<u32>,
    /// Median task length, seconds of execution (log-normal, σ = 0.5, within 0.25x–3x).
    #[arg(long, default_value_t = 3.0, value_parser = parse_positive)]
    pub task_s: f64,
    /// Mean gap between robot starts (Poisson arrivals), seconds. Default: sized from the
    /// engine's profile, like `--robots`.
    #[arg(long, value_parser = parse_non_negative)]
    pub stagger_s: Option<f64>,
    /// The share of the engine's capacity (at its saturation batch) that the fleet offers under
    /// FIFO with the static H, when `--robots` / `--stagger-s` are sized from the profile.
    #[arg(long, default_value_t = DEFAULT_LOAD, value_parser = parse_positive)]
    pub load: f64,
    /// Schedulers to compare, comma-separated priority policies (`fifo`, `plas` = Autellix,
    /// `kairos`, `srw`, or any `name:key=value` spec the server accepts).
    #[arg(long, value_delimiter = ',', default_value = "fifo,plas,kairos,srw")]
    pub schedulers: Vec<String>,
    /// Horizon policy per scheduler.
    #[arg(long, value_enum, default_value_t = HorizonsArg::Paper)]
    pub horizons: HorizonsArg,
    /// The static horizon `H`.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..))]
    pub static_h: u32,
    /// Threshold `t` of the dynamic horizon (paper §3.1).
    #[arg(long, default_value_t = 0.4, value_parser = parse_non_negative)]
    pub threshold: f64,
    /// `H_min` of the dynamic horizon.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    pub h_min: u32,
    /// Robot control frequency, actions per second.
    #[arg(long, default_value_t = 30.0, value_parser = parse_positive)]
    pub control_hz: f64,
    /// Largest batch measured when profiling the engine at start.
    #[arg(long, default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub profile_max_batch: u32,
    /// Seed of the fleet (start times, task lengths).
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, short = 'o', default_value = "kairos-demo")]
    pub out: PathBuf,
    /// Skip the plot.
    #[arg(long)]
    pub no_plot: bool,
    /// A short run of the same code path, sized the same way, for CI and smoke tests: tasks of
    /// 1 s, the engine profiled up to batch 4. Also set by the environment variable
    /// `KAIROS_DEMO_QUICK=1`, so that the README's command runs verbatim in CI. Overrides
    /// `--task-s` and `--profile-max-batch`.
    #[arg(long)]
    pub quick: bool,
}

impl From<DemoArgs> for DemoOptions {
    fn from(args: DemoArgs) -> DemoOptions {
        DemoOptions {
            robots: args.robots,
            task_s: args.task_s,
            stagger_s: args.stagger_s,
            load: args.load,
            schedulers: args.schedulers,
            horizons: args.horizons.into(),
            static_h: args.static_h,
            threshold: args.threshold,
            h_min: args.h_min,
            control_hz: args.control_hz,
            profile_max_batch: args.profile_max_batch,
            seed: args.seed,
            out: args.out,
            no_plot: args.no_plot,
            quick: args.quick,
        }
    }
}

fn parse_positive(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got {text:?}")),
    }
}

fn parse_non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("expected a number >= 0, got {text:?}")),
    }
}

/// Progress bars for the engine's profiling and each scheduler's run, and a line per run.
struct Terminal {
    /// The bar in use: the engine's, then each run's.
    bar: Mutex<ProgressBar>,
    /// Rounds answered in the current run.
    rounds: AtomicU64,
}

impl Terminal {
    fn new() -> Terminal {
        Terminal {
            bar: Mutex::new(bar(
                0,
                "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}",
            )),
            rounds: AtomicU64::new(0),
        }
    }

    fn bar(&self) -> ProgressBar {
        // A bar is a handle; a poisoned lock still holds a usable one.
        self.bar
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

fn bar(len: u64, template: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(template).unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.enable_steady_tick(Duration::from_millis(150));
    bar
}

impl DemoProgress for Terminal {
    fn engine(&self, event: &BuildEvent) {
        let bar = self.bar();
        match event {
            BuildEvent::Loading { model, .. } => bar.set_message(format!("loading {model}")),
            BuildEvent::Measured {
                batch, done, total, ..
            } => {
                bar.set_length(*total as u64);
                bar.set_position(*done as u64);
                bar.set_message(format!("profiling the engine: batch {batch}"));
            }
            BuildEvent::Ready { .. } => {}
        }
    }

    fn ready(
        &self,
        engine: &str,
        sizing: &FleetSizing,
        fleet: &[FleetTask],
        runs: &[SchedulerRun],
        args: &DemoOptions,
    ) {
        self.bar().finish_and_clear();
        println!("engine: {engine}");
        let seconds = |actions: Option<u64>| actions.unwrap_or(0) as f64 / args.control_hz;
        println!(
            "fleet: {} robots{}, about {:.1} at once, offering {:.0}% of the engine's {:.1} requests/s under FIFO with H={}",
            fleet.len(),
            if sizing.auto_robots && sizing.auto_stagger {
                " (sized from the profile)"
            } else {
                ""
            },
            sizing.concurrent,
            sizing.load * 100.0,
            sizing.capacity_rps,
            args.static_h,
        );
        println!(
            "       tasks of {:.1}–{:.1} s at {} Hz, starts over {:.1} s; schedulers: {}{}",
            seconds(fleet.iter().map(|t| t.actions).min()),
            seconds(fleet.iter().map(|t| t.actions).max()),
            args.control_hz,
            fleet.last().map_or(0.0, |t| t.start.as_secs_f64()),
            runs.iter()
                .map(|r| r.label.as_str())
                .collect::<Vec<_>>()
                .join(" | "),
            if args.quick { " (quick run)" } else { "" }
        );
    }

    fn run_started(&self, run: &SchedulerRun, robots: usize) {
        let next = bar(
            robots as u64,
            "{spinner} {prefix:<26} [{elapsed_precise}] {bar:30} {pos}/{len} tasks, {msg}",
        );
        next.set_prefix(run.label.clone());
        next.set_message("connecting");
        self.rounds.store(0, Ordering::Relaxed);
        *self.bar.lock().unwrap_or_else(PoisonError::into_inner) = next;
    }

    fn event(&self, event: DemoEvent) {
        let bar = self.bar();
        match event {
            DemoEvent::Round => {
                let n = self.rounds.fetch_add(1, Ordering::Relaxed) + 1;
                bar.set_message(format!("{n} rounds"));
            }
            DemoEvent::TaskDone => bar.inc(1),
        }
    }

    fn run_finished(&self, result: &RunResult) {
        self.bar().finish_and_clear();
        let m = result.summary();
        println!(
            "{:<26} avg {:.2} s, P95 {:.2} s, {} rounds, mean H {:.1}, engine busy {:.0}% ({:.1} s)",
            result.run.label,
            m.mean,
            m.p95,
            result.round_count(),
            result.mean_horizon(),
            result.engine_busy() * 100.0,
            result.wall.as_secs_f64()
        );
        for failure in &result.failures {
            eprintln!("  {failure}");
        }
    }
}

/// Runs `kairos demo`.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let args = DemoOptions::from(args).resolve_quick(std::env::var_os(QUICK_ENV).as_deref());
    let report = execute(&args, Arc::new(Terminal::new()))?;
    println!("\n{}", report.summary);
    if let Some(plot) = &report.plot {
        println!("plot: {}", plot.display());
    }
    println!("summary: {}", args.out.join("summary.md").display());
    if report.results.iter().any(|r| !r.failures.is_empty()) {
        bail!("some robots failed (listed above)");
    }
    Ok(())
}
