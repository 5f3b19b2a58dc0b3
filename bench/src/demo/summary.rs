//! The demo's summary: a short result first, then the per-scheduler table, then a few sentences
//! reading it.

use std::fmt::Write as _;

use kairos_engine::EngineProfile;

use super::comparison::{Comparison, RESAMPLES, compare};
use super::workload::FleetSizing;
use super::{RunResult, mean};

/// `other`'s average task latency against `base`'s, paired by task.
pub fn compare_runs(base: &RunResult, other: &RunResult) -> Option<Comparison> {
    compare(&base.task_latencies(), &other.task_latencies())
}

/// The run the others are compared with: FIFO's, else the first.
fn baseline(results: &[RunResult]) -> Option<&RunResult> {
    results
        .iter()
        .find(|r| r.run.key == "fifo")
        .or_else(|| results.first())
}

/// "12.3% below" / "4.0% above", from a relative change.
fn below_or_above(change: f64) -> String {
    if change <= 0.0 {
        format!("{:.1}% below", -change * 100.0)
    } else {
        format!("{:.1}% above", change * 100.0)
    }
}

/// The interval of a comparison, in percent of the baseline's mean.
fn interval(c: &Comparison) -> String {
    format!(
        "95% interval {:+.1}% to {:+.1}%",
        c.low * 100.0,
        c.high * 100.0
    )
}

/// Paces further apart than this (slower / faster) mean the machine's speed changed between
/// runs.
const PACE_SPREAD: f64 = 1.15;

/// When the engine ran at clearly different paces in two runs: a clause saying so, since the
/// interval covers the fleet's tasks, not the machine's other load.
fn pace_note(base: &RunResult, other: &RunResult, profile: &EngineProfile) -> Option<String> {
    let (a, b) = (base.engine_pace(profile), other.engine_pace(profile));
    (a.min(b) > 0.0 && a.max(b) / a.min(b) > PACE_SPREAD).then(|| {
        format!(
            "but the engine ran at {a:.2}× its profiled latency under {} and {b:.2}× under {}, so part of the difference is the machine, which the interval does not cover",
            base.run.label, other.run.label
        )
    })
}

/// The short result the summary leads with: Kairos's average task latency against FIFO's (or,
/// without those two, the best run's against the first), whether that is more than noise, and
/// the engine's busy share under each.
pub fn headline(results: &[RunResult], profile: &EngineProfile) -> String {
    let Some(base) = baseline(results) else {
        return String::new();
    };
    let avg = |r: &RunResult| r.summary().mean;
    let ours = results
        .iter()
        .find(|r| r.run.key == "kairos" && r.run.label != base.run.label)
        .or_else(|| {
            results
                .iter()
                .filter(|r| r.run.label != base.run.label)
                .min_by(|a, b| avg(a).total_cmp(&avg(b)))
        });
    let Some(ours) = ours else {
        return format!(
            "**{}: average task latency {:.2} s; engine busy {:.0}%.**",
            base.run.label,
            avg(base),
            base.engine_busy() * 100.0
        );
    };
    let mut busy = format!(
        "engine busy {:.0}% under {}, {:.0}% under {}",
        base.engine_busy() * 100.0,
        base.run.label,
        ours.engine_busy() * 100.0,
        ours.run.label
    );
    if let Some(note) = pace_note(base, ours, profile) {
        busy = format!("{busy}; {note}");
    }
    match compare_runs(base, ours) {
        Some(c) if c.within_noise() => format!(
            "**{} and {}: average task latency within noise** ({:.2} s vs {:.2} s, {:+.1}%, {}); {busy}.",
            ours.run.label,
            base.run.label,
            avg(ours),
            avg(base),
            c.change * 100.0,
            interval(&c)
        ),
        Some(c) => format!(
            "**{}: average task latency {} {}** ({:.2} s vs {:.2} s, {}); {busy}.",
            ours.run.label,
            below_or_above(c.change),
            base.run.label,
            avg(ours),
            avg(base),
            interval(&c)
        ),
        None => format!(
            "**{}: average task latency {:.2} s, {}: {:.2} s** (no task finished under both); {busy}.",
            ours.run.label,
            avg(ours),
            base.run.label,
            avg(base)
        ),
    }
}

/// The per-scheduler table; `profile` is what the engine's pace is measured against.
pub fn summary_table(results: &[RunResult], profile: &EngineProfile) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "| Scheduler | tasks | avg (s) | P25 (s) | P95 (s) | avg vs FIFO (95% interval) | rounds | rounds/task | mean H | queue (ms) | batch | engine busy | engine pace | idle/task (s) |"
    );
    let _ = writeln!(
        s,
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    let base = baseline(results);
    for r in results {
        let m = r.summary();
        let vs = match base.filter(|b| b.run.label != r.run.label) {
            Some(b) => match compare_runs(b, r) {
                Some(c) => format!(
                    "{:+.1}% ({:+.1}…{:+.1}){}",
                    c.change * 100.0,
                    c.low * 100.0,
                    c.high * 100.0,
                    if c.within_noise() { ", noise" } else { "" }
                ),
                None => "–".to_string(),
            },
            None => "–".to_string(),
        };
        let _ = writeln!(
            s,
            "| {} | {} | {:.2} | {:.2} | {:.2} | {} | {} | {:.1} | {:.1} | {:.0} | {:.2} | {:.0}% | {:.2}× | {:.2} |",
            r.run.label,
            r.tasks.len(),
            m.mean,
            m.p25,
            m.p95,
            vs,
            r.round_count(),
            r.round_count() as f64 / r.tasks.len().max(1) as f64,
            r.mean_horizon(),
            r.mean_queue_ms(),
            r.mean_batch(),
            r.engine_busy() * 100.0,
            r.engine_pace(profile),
            r.mean_idle_s(),
        );
    }
    s
}

/// How the fleet was sized, in a sentence.
pub fn sizing_sentence(sizing: &FleetSizing, static_h: u32) -> String {
    let robots = if sizing.auto_robots {
        format!("{} robots", sizing.robots)
    } else {
        format!("{} robots (--robots)", sizing.robots)
    };
    let stagger = if sizing.auto_stagger {
        format!("one every {:.2} s on average", sizing.stagger_s)
    } else {
        format!(
            "one every {:.2} s on average (--stagger-s)",
            sizing.stagger_s
        )
    };
    format!(
        "Fleet sized from the engine's profile: at its saturation batch of {} the engine serves {:.1} requests/s; FIFO's robots with H={static_h} ask every {:.0} ms ({:.1} actions per round) when each answer arrives as the robot runs out of actions, so {robots}, {stagger}, about {:.1} at once, offer {:.0}% of that (more while answers come sooner, so the queue builds).",
        sizing.batch,
        sizing.capacity_rps,
        sizing.cycle.seconds * 1e3,
        sizing.cycle.actions,
        sizing.concurrent,
        sizing.load * 100.0,
    )
}

/// A few sentences reading the table: how much of the gain is the horizon and how much the
/// scheduler, which differences are within noise, whether requests queued, and whether the
/// engine ran at the same pace in every run.
pub fn reading(results: &[RunResult], profile: &EngineProfile) -> String {
    let mut s = String::new();
    let rounds_per_task = |rs: &[&RunResult]| {
        mean(
            rs.iter()
                .map(|r| r.round_count() as f64 / r.tasks.len().max(1) as f64),
        )
    };
    let (dynamic, fixed): (Vec<&RunResult>, Vec<&RunResult>) =
        results.iter().partition(|r| r.run.dynamic());
    if !dynamic.is_empty() && !fixed.is_empty() {
        let (rd, rf) = (rounds_per_task(&dynamic), rounds_per_task(&fixed));
        let _ = write!(
            s,
            "The horizon: the dynamic horizon executed {:.1} actions per chunk on average against the static {:.0}, so its tasks needed {:.1} rounds instead of {:.1} ({:.0}% fewer requests for the same work) and the engine was busy {:.0}% of the time instead of {:.0}%; in the paper, too, the dynamic horizon carries most of the gain. ",
            mean(dynamic.iter().map(|r| r.mean_horizon())),
            mean(fixed.iter().map(|r| r.mean_horizon())),
            rd,
            rf,
            if rf > 0.0 {
                (rf - rd) / rf * 100.0
            } else {
                0.0
            },
            mean(dynamic.iter().map(|r| r.engine_busy())) * 100.0,
            mean(fixed.iter().map(|r| r.engine_busy())) * 100.0,
        );
    }
    for group in [&fixed, &dynamic] {
        let Some((first, others)) = group.split_first() else {
            continue;
        };
        for other in others {
            let Some(c) = compare_runs(first, other) else {
                continue;
            };
            let _ = write!(
                s,
                "Same horizon, another scheduler: {}'s average task latency is {} {}'s ({}): {}{}. ",
                other.run.label,
                below_or_above(c.change),
                first.run.label,
                interval(&c),
                if c.within_noise() {
                    "within noise"
                } else {
                    "more than noise"
                },
                pace_note(first, other, profile)
                    .map(|note| format!(", {note}"))
                    .unwrap_or_default(),
            );
        }
    }
    if let Some(base) = baseline(results) {
        let worst = results
            .iter()
            .map(RunResult::mean_queue_ms)
            .fold(0.0, f64::max);
        if worst < 20.0 {
            let _ = write!(
                s,
                "Requests waited at most {worst:.0} ms on average for the engine, so the order a scheduler picks matters little; raise --load or --robots, or lower --stagger-s, to contend it harder. "
            );
        } else {
            let _ = write!(
                s,
                "Under {} requests waited {:.0} ms on average for the engine{}: they queued, and the scheduler's order decided who waited. ",
                base.run.label,
                base.mean_queue_ms(),
                if worst > base.mean_queue_ms() {
                    format!(" (up to {worst:.0} ms in another run)")
                } else {
                    String::new()
                },
            );
        }
    }
    let _ = write!(
        s,
        "Noise: a difference is within noise when the 95% interval of the relative difference of mean task latency contains zero; the interval comes from {RESAMPLES} bootstrap resamples of the fleet's tasks, each task paired with itself under the other scheduler. "
    );
    let paces: Vec<f64> = results.iter().map(|r| r.engine_pace(profile)).collect();
    let (slowest, fastest) = paces.iter().fold((0.0f64, f64::INFINITY), |(hi, lo), &p| {
        (hi.max(p), lo.min(p))
    });
    if fastest > 0.0 && slowest / fastest > PACE_SPREAD {
        let _ = write!(
            s,
            "The engine ran at {fastest:.2}–{slowest:.2}× its profiled latency across the runs (engine pace): the machine was busier during some runs than during others. "
        );
    }
    if !dynamic.is_empty() {
        let _ = write!(
            s,
            "The flow head's weights are random (nothing is downloaded), so the threshold policy reads an untrained model's diffusion updates: its H shows the mechanism, not a tuned accuracy/efficiency trade-off."
        );
    }
    s
}
