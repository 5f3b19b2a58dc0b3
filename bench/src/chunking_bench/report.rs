//! The chunking bench's outputs: `results.csv` (one row per cell), the markdown tables of
//! `summary.md`, and the verdict per task the issue asks for.

use std::fmt::Write as _;

use super::episode::Execution;
use super::{CellResult, Cost};

/// `results.csv`: one row per cell.
pub fn results_csv(results: &[CellResult]) -> String {
    let mut s = String::from(
        "task,delay,period,execution,episodes,successes,success_rate,ci_low,ci_high,switch_jump,within_jump,calls_per_episode,sampling_us,diverged\n",
    );
    for r in results {
        let (lo, hi) = r.ci();
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.2},{:.1},{}",
            r.cell.task,
            r.cell.delay,
            r.cell.period,
            r.cell.execution.name(),
            r.episodes,
            r.successes,
            r.success_rate(),
            lo,
            hi,
            r.switch_jump,
            r.within_jump,
            r.calls_per_episode,
            r.sampling_us,
            r.diverged
        );
    }
    s
}

fn pct(x: f64) -> String {
    format!("{:.1}", 100.0 * x)
}

/// The cell of `task`, `delay`, `period` and `execution`, if it ran.
pub fn find<'a>(
    results: &'a [CellResult],
    task: &str,
    delay: u32,
    period: u32,
    execution: Execution,
) -> Option<&'a CellResult> {
    results.iter().find(|r| {
        r.cell.task == task
            && r.cell.delay == delay
            && r.cell.period == period
            && r.cell.execution == execution
    })
}

/// Which of the two periods a cell belongs to: `short` is `max(2, D)`, `quarter` `max(N/4, D)`.
fn period_of(delay: u32, chunk_len: usize, quarter: bool) -> u32 {
    let periods = super::periods(delay, chunk_len);
    if quarter {
        *periods.last().unwrap_or(&delay)
    } else {
        periods[0]
    }
}

/// The success table of one task: executions down, delays across, each cell `success [CI]`.
pub fn success_table(
    results: &[CellResult],
    task: &str,
    delays: &[u32],
    chunk_len: usize,
    quarter: bool,
) -> String {
    let mut s = String::from("| execution |");
    for d in delays {
        let _ = write!(
            s,
            " D = {d} (every {}) |",
            period_of(*d, chunk_len, quarter)
        );
    }
    s.push_str("\n|---|");
    for _ in delays {
        s.push_str("---|");
    }
    s.push('\n');
    for execution in Execution::all() {
        let _ = write!(s, "| {} |", execution.name());
        for &d in delays {
            match find(
                results,
                task,
                d,
                period_of(d, chunk_len, quarter),
                execution,
            ) {
                Some(r) => {
                    let (lo, hi) = r.ci();
                    let _ = write!(s, " {} ({}–{}) |", pct(r.success_rate()), pct(lo), pct(hi));
                }
                None => s.push_str(" – |"),
            }
        }
        s.push('\n');
    }
    s
}

/// The smoothness table of one task at `delay` (short period): the mean jump of the velocity
/// command at chunk switches and within chunks, and the sampling time per chunk.
pub fn jump_table(results: &[CellResult], task: &str, delay: u32, chunk_len: usize) -> String {
    let period = period_of(delay, chunk_len, false);
    let mut s = String::from(
        "| execution | jump at switches | jump within chunks | ratio | chunks / episode | sampling µs / chunk | diverged episodes |\n|---|---|---|---|---|---|---|\n",
    );
    for execution in Execution::all() {
        if let Some(r) = find(results, task, delay, period, execution) {
            let _ = writeln!(
                s,
                "| {} | {:.3} | {:.3} | {:.2} | {:.1} | {:.0} | {} |",
                execution.name(),
                r.switch_jump,
                r.within_jump,
                r.switch_jump / r.within_jump.max(1e-9),
                r.calls_per_episode,
                r.sampling_us,
                r.diverged
            );
        }
    }
    s
}

/// The cost table: each guidance mode's sampling time against plain sampling.
pub fn cost_table(costs: &[Cost]) -> String {
    let mut s =
        String::from("| sampling | median µs / chunk | relative to plain |\n|---|---|---|\n");
    for c in costs {
        let _ = writeln!(
            s,
            "| {} | {:.0} | {:.2}× |",
            c.name, c.median_us, c.relative
        );
    }
    s
}

/// The verdict on one task for the `default` strategy: at `D = 2` (short period)
/// success within 3 points of `D = 0`, and at least 10 points above `skip` where `skip` loses
/// (falls more than 3 points from `D = 0`); and whether `rtc` beats both `skip` and
/// `arrival_state` in any cell (success strictly higher than both, and whether its interval
/// clears theirs).
pub fn verdict(
    results: &[CellResult],
    task: &str,
    default: Execution,
    delays: &[u32],
    chunk_len: usize,
) -> String {
    let mut s = String::new();
    let at = |d: u32, e: Execution| {
        find(results, task, d, period_of(d, chunk_len, false), e).map(|r| r.success_rate())
    };
    if let (Some(d0), Some(d2), Some(skip0), Some(skip2)) = (
        at(0, default),
        at(2, default),
        at(
            0,
            Execution::Async(kairos_sdk::protocol::ChunkingStrategy::Skip),
        ),
        at(
            2,
            Execution::Async(kairos_sdk::protocol::ChunkingStrategy::Skip),
        ),
    ) {
        let within = d0 - d2 <= 0.03;
        let skip_loses = skip0 - skip2 > 0.03;
        let margin = d2 - skip2;
        let _ = writeln!(
            s,
            "- `{}` at D = 2: {}% against {}% at D = 0 ({}: goal within 3 points); `skip` at \
             D = 2: {}% ({} from {}% at D = 0){}.",
            default.name(),
            pct(d2),
            pct(d0),
            if within { "met" } else { "not met" },
            pct(skip2),
            if skip_loses { "loses" } else { "does not lose" },
            pct(skip0),
            if skip_loses {
                format!(
                    "; `{}` is {:+.1} points above it (goal ≥ 10: {})",
                    default.name(),
                    100.0 * margin,
                    if margin >= 0.10 { "met" } else { "not met" }
                )
            } else {
                String::new()
            }
        );
    }
    let skip = Execution::Async(kairos_sdk::protocol::ChunkingStrategy::Skip);
    let arrival = Execution::Async(kairos_sdk::protocol::ChunkingStrategy::ArrivalState);
    let rtcs = Execution::all()
        .into_iter()
        .filter(|e| e.strategy().as_str().starts_with("rtc"));
    for rtc in rtcs {
        let mut wins = Vec::new();
        for &d in delays {
            for period in super::periods(d, chunk_len) {
                let get = |e| find(results, task, d, period, e);
                if let (Some(r), Some(k), Some(a)) = (get(rtc), get(skip), get(arrival))
                    && r.success_rate() > k.success_rate()
                    && r.success_rate() > a.success_rate()
                {
                    let clear = r.ci().0 > k.ci().1 && r.ci().0 > a.ci().1;
                    wins.push(format!(
                        "D = {d} every {period}: {}% vs {}% / {}%{}",
                        pct(r.success_rate()),
                        pct(k.success_rate()),
                        pct(a.success_rate()),
                        if clear {
                            ", intervals clear"
                        } else {
                            ", intervals overlap"
                        }
                    ));
                }
            }
        }
        if wins.is_empty() {
            let _ = writeln!(
                s,
                "- `{}` beats both `skip` and `arrival_state`: nowhere.",
                rtc.name()
            );
        } else {
            let _ = writeln!(
                s,
                "- `{}` beats both `skip` and `arrival_state` (skip / arrival_state): {}.",
                rtc.name(),
                wins.join("; ")
            );
        }
    }
    s
}
