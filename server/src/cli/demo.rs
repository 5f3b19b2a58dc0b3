//! `kairos demo`: runs [`crate::demo`] with progress bars and prints its summary.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use anyhow::bail;
use indicatif::{ProgressBar, ProgressStyle};

use crate::demo::{
    DemoArgs, DemoEvent, DemoProgress, FleetTask, QUICK_ENV, RunResult, SchedulerRun, execute,
};
use crate::pool::BuildEvent;

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

    fn ready(&self, engine: &str, fleet: &[FleetTask], runs: &[SchedulerRun], args: &DemoArgs) {
        self.bar().finish_and_clear();
        println!("engine: {engine}");
        let seconds = |actions: Option<u64>| actions.unwrap_or(0) as f64 / args.control_hz;
        println!(
            "fleet: {} robots, tasks of {:.1}–{:.1} s at {} Hz, starts over {:.1} s; schedulers: {}{}",
            fleet.len(),
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
            "{:<26} avg {:.2} s, P95 {:.2} s, {} rounds, mean H {:.1} ({:.1} s)",
            result.run.label,
            m.mean,
            m.p95,
            result.round_count(),
            result.mean_horizon(),
            result.wall.as_secs_f64()
        );
        for failure in &result.failures {
            eprintln!("  {failure}");
        }
    }
}

/// Runs `kairos demo`.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let args = args.resolve_quick(std::env::var_os(QUICK_ENV).as_deref());
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
