//! The driver's running totals, histograms and latency summaries: the facts the core reports
//! as data ([`DriverReport`]), which the server exports to Prometheus. Each fact is counted here
//! once.

use std::collections::VecDeque;
use std::time::Duration;

use kairos_protocol::Timing;

use crate::error::LossReason;
use crate::scheduler::Tier;
use crate::stats::quantile;

/// Running totals of the driver.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DriverStats {
    /// Rounds accepted by the scheduler.
    pub accepted: u64,
    /// Rounds refused (any reason).
    pub refused: u64,
    /// Re-sent rounds attached to the request already carrying them.
    pub attached: u64,
    /// Re-sent rounds answered from the reply cache.
    pub cached_replies: u64,
    /// Replies generated and sent.
    pub replies: u64,
    /// Rounds whose generation failed.
    pub failed: u64,
    /// Pending requests removed because every stream waiting for them went away.
    pub cancelled: u64,
    /// Pending requests replaced by a newer round of their task.
    pub superseded: u64,
    /// `FetchObservation`s asked of a round's stream.
    pub refetch_asked: u64,
    /// Fresh observations received in time and used.
    pub refetch_used: u64,
    /// Batches run.
    pub batches: u64,
    /// Tasks ended (explicitly or by expiry).
    pub tasks_ended: u64,
    /// Rounds put back in the queue after their batch was lost with a remote engine, by reason.
    pub redispatched: RedispatchCounts,
    /// Rounds of lost batches failed (retryable) instead: out of attempts or of time.
    pub redispatch_given_up: u64,
    /// Rounds answered after their robot ran out of actions (`E.end` of its previous round).
    pub deadline_misses: u64,
    /// Server-side latency of answered rounds, from the `Submit` read to the reply, seconds.
    pub round_latency: Histogram,
    /// Requests per batch given to an engine instance.
    pub batch_size: Histogram,
    /// Horizons of answered rounds: the actions each reply asked its robot to execute.
    pub horizon: Histogram,
    /// Rounds per chunking strategy applied, and those that fell back to `skip`.
    pub chunking: crate::chunking::StrategyCounts,
    /// The predicted `d` of answered rounds, control steps.
    pub delay_predicted: Histogram,
    /// |predicted − actual| `d`, control steps, of rounds whose robot said what it was (its
    /// next Last Exec Info).
    pub delay_error: Histogram,
    /// Σ (predicted − actual) `d` over the same rounds: the prediction's bias, with
    /// `delay_error`'s count.
    pub delay_error_signed: i64,
    /// Server-added latency of recent replies: `timing.total − timing.inference` (queueing
    /// behind other batches included).
    pub overhead: LatencySummary,
    /// The part of `overhead` that is the server's own work, without waiting for an engine or a
    /// re-fetched observation: from the `Submit` frame read to the scheduler accepting it
    /// (validation, the driver's queue), plus from dispatch to the reply handed to the stream
    /// (batch start, engine hand-off, horizon policy, trim, driver), less the forward pass.
    pub processing: LatencySummary,
}

/// A cumulative histogram over fixed upper bounds, as Prometheus exports one: `counts[i]` is the
/// number of observations `<= bounds[i]`'s bucket alone; values above the last bound count only
/// in `count` (the `+Inf` bucket).
#[derive(Clone, Debug, PartialEq)]
pub struct Histogram {
    bounds: Vec<f64>,
    counts: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Histogram {
    /// Buckets at `start`, `start·factor`, … (`len` bounds), Prometheus's exponential buckets.
    pub fn exponential(start: f64, factor: f64, len: usize) -> Histogram {
        let bounds: Vec<f64> = std::iter::successors(Some(start), |b| Some(b * factor))
            .take(len)
            .collect();
        Histogram {
            counts: vec![0; bounds.len()],
            bounds,
            sum: 0.0,
            count: 0,
        }
    }

    /// Round latency: 1 ms .. ~16 s (a forward pass, ms to a second, plus queueing).
    pub fn round_latency() -> Histogram {
        Histogram::exponential(0.001, 2.0, 15)
    }

    /// Batch size: 1 .. 512 requests.
    pub fn batch_size() -> Histogram {
        Histogram::exponential(1.0, 2.0, 10)
    }

    /// Horizon, actions per reply: every count up to 8, then coarser up to 64, with a bound at
    /// 50 so that SmolVLA's and π0's whole chunk has a bucket of its own.
    pub fn horizon() -> Histogram {
        Histogram::with_bounds(&[
            1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 16.0, 20.0, 25.0, 32.0, 40.0, 49.0,
            50.0, 64.0,
        ])
    }

    /// Buckets at the given upper bounds (ascending).
    pub fn with_bounds(bounds: &[f64]) -> Histogram {
        Histogram {
            bounds: bounds.to_vec(),
            counts: vec![0; bounds.len()],
            sum: 0.0,
            count: 0,
        }
    }

    /// A delay in control steps: 0 .. 64.
    pub fn delay_steps() -> Histogram {
        Histogram::with_bounds(&[0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 32.0, 64.0])
    }

    /// A delay's absolute prediction error in control steps: 0 .. 16.
    pub fn delay_error() -> Histogram {
        Histogram::with_bounds(&[0.0, 1.0, 2.0, 3.0, 4.0, 8.0, 16.0])
    }

    /// Counts `value` (a non-finite value counts in `count` and the `+Inf` bucket only).
    pub fn observe(&mut self, value: f64) {
        self.count += 1;
        if !value.is_finite() {
            return;
        }
        self.sum += value;
        if let Some(i) = self.bounds.iter().position(|&b| value <= b) {
            self.counts[i] += 1;
        }
    }

    /// Observations so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Sum of the finite observations.
    pub fn sum(&self) -> f64 {
        self.sum
    }

    /// `(upper bound, observations in this bucket alone)`, `+Inf` last: the form Prometheus
    /// encoders take.
    pub fn buckets(&self) -> Vec<(f64, u64)> {
        let finite: u64 = self.counts.iter().sum();
        let mut out: Vec<(f64, u64)> = self
            .bounds
            .iter()
            .copied()
            .zip(self.counts.iter().copied())
            .collect();
        out.push((f64::INFINITY, self.count.saturating_sub(finite)));
        out
    }

    /// `(upper bound, observations <= bound)` per bucket, cumulative, `+Inf` last.
    pub fn cumulative(&self) -> Vec<(f64, u64)> {
        let mut total = 0;
        let mut out: Vec<(f64, u64)> = self
            .bounds
            .iter()
            .zip(&self.counts)
            .map(|(&b, &c)| {
                total += c;
                (b, total)
            })
            .collect();
        out.push((f64::INFINITY, self.count));
        out
    }
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram::exponential(1.0, 2.0, 0)
    }
}

/// Where an engine instance stands, as the report shows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EngineState {
    /// In the pool: batches may be placed on it.
    Ready,
    /// Left the pool but still runs its last batch (a draining worker).
    Draining,
}

impl EngineState {
    /// The label, `snake_case`.
    pub fn as_str(self) -> &'static str {
        match self {
            EngineState::Ready => "ready",
            EngineState::Draining => "draining",
        }
    }
}

/// One engine instance in a [`DriverReport`]. Instances that left the pool and run nothing are
/// not reported.
#[derive(Clone, Debug, PartialEq)]
pub struct EngineReport {
    /// Its name (`edge-0.1`, a worker's id).
    pub name: String,
    /// Edge or cloud.
    pub tier: Tier,
    /// Ready or draining.
    pub state: EngineState,
    /// Whether a batch runs on it now.
    pub busy: bool,
    /// Time it spent running forward passes since it joined.
    pub busy_time: Duration,
    /// The measured round trip of a remote worker (`None` for a local instance).
    pub rtt: Option<Duration>,
}

/// Everything the core reports about itself: its totals, the queue and the engines. The shell
/// publishes one after every event; the metrics exporter reads the latest.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DriverReport {
    /// Running totals and histograms (the latency summaries are left empty: they sort the
    /// recent replies, see `DriverCore::stats`).
    pub stats: DriverStats,
    /// Rounds waiting for dispatch.
    pub queue_depth: usize,
    /// Rounds in batches that have not finished.
    pub running: usize,
    /// Open tasks.
    pub open_tasks: usize,
    /// The engine instances.
    pub engines: Vec<EngineReport>,
}

/// Re-dispatched rounds by [`LossReason`] (the `kairos_redispatch_total{reason}` counter).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RedispatchCounts {
    /// The worker's connection closed or timed out.
    pub connection_lost: u64,
    /// The batch's stream was reset or ended without an answer.
    pub stream_reset: u64,
    /// The worker answered the batch unusably.
    pub invalid_answer: u64,
    /// The batch's deadline passed.
    pub deadline: u64,
    /// The engine had left before the batch was sent.
    pub gone: u64,
}

impl RedispatchCounts {
    /// Counts one round.
    pub fn count(&mut self, reason: LossReason) {
        *self.get_mut(reason) += 1;
    }

    /// The count for `reason`.
    pub fn get(&self, reason: LossReason) -> u64 {
        match reason {
            LossReason::ConnectionLost => self.connection_lost,
            LossReason::StreamReset => self.stream_reset,
            LossReason::InvalidAnswer => self.invalid_answer,
            LossReason::Deadline => self.deadline,
            LossReason::Gone => self.gone,
        }
    }

    fn get_mut(&mut self, reason: LossReason) -> &mut u64 {
        match reason {
            LossReason::ConnectionLost => &mut self.connection_lost,
            LossReason::StreamReset => &mut self.stream_reset,
            LossReason::InvalidAnswer => &mut self.invalid_answer,
            LossReason::Deadline => &mut self.deadline,
            LossReason::Gone => &mut self.gone,
        }
    }

    /// All reasons together.
    pub fn total(&self) -> u64 {
        LossReason::ALL.iter().map(|&r| self.get(r)).sum()
    }
}

/// Percentiles of a latency over the most recent [`RECENT_LATENCIES`] replies, µs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LatencySummary {
    /// Replies summarised.
    pub count: u64,
    /// Median.
    pub p50_us: u64,
    /// 99th percentile (the project's one percentile, [`crate::stats::quantile`]).
    pub p99_us: u64,
    /// Largest.
    pub max_us: u64,
}

/// Replies the latency summaries cover.
pub const RECENT_LATENCIES: usize = 1 << 16;

impl LatencySummary {
    /// Percentiles of `values` by [`crate::stats::quantile`] (linear interpolation), rounded to
    /// the microsecond.
    pub fn of(values: impl Iterator<Item = u64>) -> LatencySummary {
        let mut sorted: Vec<f64> = values.map(|v| v as f64).collect();
        sorted.sort_by(f64::total_cmp);
        let Some(&max) = sorted.last() else {
            return LatencySummary::default();
        };
        let at = |q: f64| quantile(&sorted, q).round() as u64;
        LatencySummary {
            count: sorted.len() as u64,
            p50_us: at(0.50),
            p99_us: at(0.99),
            max_us: max as u64,
        }
    }
}

/// The latest [`RECENT_LATENCIES`] values of server-added latency.
#[derive(Debug, Default)]
pub(super) struct RecentLatencies {
    /// `(overhead, processing)` per reply, µs.
    values: VecDeque<(u64, u64)>,
}

impl RecentLatencies {
    pub(super) fn record(&mut self, timing: &Timing, processing_us: u64) {
        if self.values.len() >= RECENT_LATENCIES {
            self.values.pop_front();
        }
        let overhead = timing.total_us.saturating_sub(timing.inference_us);
        self.values.push_back((overhead, processing_us));
    }

    pub(super) fn summaries(&self) -> (LatencySummary, LatencySummary) {
        (
            LatencySummary::of(self.values.iter().map(|v| v.0)),
            LatencySummary::of(self.values.iter().map(|v| v.1)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_summary_uses_the_one_percentile() {
        // 1..=200: the median lies halfway between 100 and 101, p99 at 198.01 (NumPy's default).
        let s = LatencySummary::of((1..=200).rev());
        assert_eq!(
            (s.count, s.p50_us, s.p99_us, s.max_us),
            (200, 101, 198, 200)
        );
        assert_eq!(
            LatencySummary::of(std::iter::empty()),
            LatencySummary::default()
        );
    }
}
