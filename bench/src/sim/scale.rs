//! The scale experiment (issue #15): one scheduler serving thousands of robots on a hundred
//! engine instances (workers), in virtual time.
//!
//! Each run is an offline fleet ([`super::Load::Fleet`]): `robots` robots, each working through
//! one task of the workload, powering up within the first second, served by
//! `robots / robots_per_worker` edge instances of the workload's edge profile, scheduled by
//! Algorithm 1 (Kairos, dynamic horizon, re-fetch on). The number of workers grows with the fleet,
//! so every size puts the same load on each worker and what changes from 1k to 10k robots is the
//! size of the problem the one scheduler solves: how many requests are pending at a decision and
//! how many engine instances it places on.
//!
//! The simulation is the ordinary one; [`super::simulate_timed`] reads a real clock around every
//! call into the scheduler, so the decision cost reported here is the scheduler's own, not the
//! simulator's. The timings depend on the machine and its load; everything else is a function of
//! the inputs.

use std::fmt::Write as _;

use super::stats::{Summary, summarize};
use super::{SchedulerTiming, SimResult};

/// Fleet sizes of the sweep.
pub const DEFAULT_ROBOTS: [usize; 4] = [1_000, 2_000, 5_000, 10_000];

/// Robots per engine instance: the 10,000 robots on 100 workers.
pub const DEFAULT_ROBOTS_PER_WORKER: usize = 100;

/// What the scale experiment runs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScalePlan {
    /// Fleet sizes, one run each.
    pub robots: Vec<usize>,
    /// Robots per engine instance; the instance count is `ceil(robots / robots_per_worker)`.
    pub robots_per_worker: usize,
}

impl Default for ScalePlan {
    fn default() -> Self {
        ScalePlan {
            robots: DEFAULT_ROBOTS.to_vec(),
            robots_per_worker: DEFAULT_ROBOTS_PER_WORKER,
        }
    }
}

impl ScalePlan {
    /// Engine instances serving `robots` robots (at least one).
    pub fn workers(&self, robots: usize) -> usize {
        robots.div_ceil(self.robots_per_worker.max(1)).max(1)
    }
}

/// What one scale run measured. "CPU" is the simulating thread's CPU time, "wall" the real
/// clock: on a shared machine wall time also counts waiting for a core.
#[derive(Clone, Debug, PartialEq)]
pub struct ScaleStats {
    /// Robots (one task each).
    pub robots: usize,
    /// Engine instances.
    pub workers: usize,
    /// Tasks completed.
    pub tasks: usize,
    /// Round requests submitted.
    pub rounds: u64,
    /// Round requests answered (the scheduler's count).
    pub answered: u64,
    /// Batches run.
    pub batches: u64,
    /// Scheduling decisions made.
    pub decisions: u64,
    /// Requests pending at a decision, mean.
    pub mean_pending: f64,
    /// Requests pending at a decision, most.
    pub max_pending: usize,
    /// Virtual time of the run, seconds.
    pub makespan_s: f64,
    /// Wall time of one decision (`poll_dispatch` that decided), microseconds.
    pub decision_us: Summary,
    /// CPU time of one decision, microseconds (all NaN without a thread CPU clock).
    pub decision_cpu_us: Summary,
    /// Decision CPU time (wall where there is no CPU clock) per batch dispatched, microseconds.
    pub decision_per_batch_us: f64,
    /// Wall time of every call into the scheduler, seconds.
    pub scheduler_s: f64,
    /// Wall time of the whole simulation loop, seconds.
    pub run_s: f64,
    /// CPU time of the whole simulation loop, seconds (0 without a thread CPU clock).
    pub run_cpu_s: f64,
    /// Events the simulator processed.
    pub events: u64,
}

impl ScaleStats {
    /// The statistics of a run of `robots` robots on `workers` instances.
    pub fn new(robots: usize, workers: usize, r: &SimResult, t: &SchedulerTiming) -> Self {
        let micros = |v: &[f64]| -> Vec<f64> { v.iter().map(|s| s * 1e6).collect() };
        let per_decision = if t.decisions_cpu.len() == t.decisions.len() {
            &t.decisions_cpu
        } else {
            &t.decisions
        };
        ScaleStats {
            robots,
            workers,
            tasks: r.tasks.len(),
            rounds: r.requests,
            answered: r.scheduler.answered,
            batches: r.batches,
            decisions: t.decisions.len() as u64,
            mean_pending: t.decision_pending as f64 / t.decisions.len().max(1) as f64,
            max_pending: t.max_pending,
            makespan_s: r.makespan_s,
            decision_us: summarize(&micros(&t.decisions)),
            decision_cpu_us: summarize(&micros(&t.decisions_cpu)),
            decision_per_batch_us: per_decision.iter().sum::<f64>() * 1e6
                / t.decision_batches.max(1) as f64,
            scheduler_s: t.scheduler_s(),
            run_s: t.run_s,
            run_cpu_s: t.run_cpu_s,
            events: r.events,
        }
    }

    /// Rounds served per virtual second.
    pub fn rounds_per_virtual_s(&self) -> f64 {
        self.answered as f64 / self.makespan_s.max(f64::MIN_POSITIVE)
    }

    /// The scheduler's share of the simulation loop's wall time (waiting for a core inflates
    /// both sides alike, so the share holds on a loaded machine).
    pub fn scheduler_share(&self) -> f64 {
        self.scheduler_s / self.run_s.max(f64::MIN_POSITIVE)
    }

    /// The simulation loop's time, seconds: CPU time where measured, else wall.
    pub fn loop_s(&self) -> f64 {
        if self.run_cpu_s > 0.0 {
            self.run_cpu_s
        } else {
            self.run_s
        }
    }

    /// The scheduler's time, seconds: its share of the loop's CPU time where measured (its own
    /// calls are timed on the wall clock, too short to read the CPU clock around each), else its
    /// wall time.
    pub fn scheduler_cpu_s(&self) -> f64 {
        self.scheduler_share() * self.loop_s()
    }

    /// Scheduler seconds per virtual second: the share of one core one scheduler needs to keep up
    /// with this fleet in real time.
    pub fn scheduler_per_virtual_s(&self) -> f64 {
        self.scheduler_cpu_s() / self.makespan_s.max(f64::MIN_POSITIVE)
    }

    /// Scheduler microseconds per round served.
    pub fn scheduler_per_round_us(&self) -> f64 {
        self.scheduler_cpu_s() * 1e6 / self.answered.max(1) as f64
    }

    /// Simulation seconds (CPU where measured) per virtual second.
    pub fn sim_per_virtual_s(&self) -> f64 {
        self.loop_s() / self.makespan_s.max(f64::MIN_POSITIVE)
    }
}

/// The CSV header of [`csv_row`].
pub const CSV_HEADER: &str = "workload,robots,workers,tasks,rounds,answered,batches,decisions,mean_pending,max_pending,makespan_s,rounds_per_virtual_s,decision_cpu_mean_us,decision_cpu_p50_us,decision_cpu_p99_us,decision_cpu_max_us,decision_wall_mean_us,decision_wall_p50_us,decision_wall_p99_us,decision_wall_max_us,decision_per_batch_us,scheduler_share,scheduler_per_round_us,scheduler_per_virtual_s,run_cpu_s,run_wall_s,sim_per_virtual_s,events";

/// One run as a CSV row (see [`CSV_HEADER`]).
pub fn csv_row(workload: &str, s: &ScaleStats) -> String {
    let (c, d) = (&s.decision_cpu_us, &s.decision_us);
    format!(
        "{workload},{},{},{},{},{},{},{},{:.1},{},{:.3},{:.1},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.2},{:.4},{:.3},{:.5},{:.3},{:.3},{:.5},{}",
        s.robots,
        s.workers,
        s.tasks,
        s.rounds,
        s.answered,
        s.batches,
        s.decisions,
        s.mean_pending,
        s.max_pending,
        s.makespan_s,
        s.rounds_per_virtual_s(),
        c.mean,
        c.p50,
        c.p99,
        c.max,
        d.mean,
        d.p50,
        d.p99,
        d.max,
        s.decision_per_batch_us,
        s.scheduler_share(),
        s.scheduler_per_round_us(),
        s.scheduler_per_virtual_s(),
        s.run_cpu_s,
        s.run_s,
        s.sim_per_virtual_s(),
        s.events,
    )
}

fn growth(value: f64, first: Option<f64>) -> String {
    match first {
        Some(f) if f > 0.0 => format!("{:.1}x", value / f),
        _ => "–".into(),
    }
}

/// The markdown table of one workload's runs, smallest fleet first, with the growth of the
/// decision cost and of the throughput against the first row.
pub fn table(runs: &[&ScaleStats]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| robots | workers | rounds | batches | pending at decision, mean (max) | virtual s | rounds / virtual s | decision CPU µs, mean (p50, p99) | decision wall µs, mean (p50, p99) | decision µs / batch | scheduler µs / round | scheduler s / virtual s | sim s / virtual s | growth: decision µs, rounds / virtual s |"
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let first = runs.first();
    for r in runs {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {:.0} ({}) | {:.1} | {:.0} | {:.1} ({:.1}, {:.1}) | {:.1} ({:.1}, {:.1}) | {:.1} | {:.2} | {:.4} | {:.4} | {}, {} |",
            r.robots,
            r.workers,
            r.rounds,
            r.batches,
            r.mean_pending,
            r.max_pending,
            r.makespan_s,
            r.rounds_per_virtual_s(),
            r.decision_cpu_us.mean,
            r.decision_cpu_us.p50,
            r.decision_cpu_us.p99,
            r.decision_us.mean,
            r.decision_us.p50,
            r.decision_us.p99,
            r.decision_per_batch_us,
            r.scheduler_per_round_us(),
            r.scheduler_per_virtual_s(),
            r.sim_per_virtual_s(),
            growth(
                r.decision_per_batch_us,
                first.map(|f| f.decision_per_batch_us)
            ),
            growth(
                r.rounds_per_virtual_s(),
                first.map(|f| f.rounds_per_virtual_s())
            ),
        );
    }
    s
}
