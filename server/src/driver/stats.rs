//! The driver's running totals and latency summaries.

use std::collections::VecDeque;

use kairos_sdk::protocol::Timing;

use crate::pool::LossReason;
use crate::stats::quantile;

/// Running totals of the driver.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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
    /// Server-added latency of recent replies: `timing.total − timing.inference` (queueing
    /// behind other batches included).
    pub overhead: LatencySummary,
    /// The part of `overhead` that is the server's own work, without waiting for an engine or a
    /// re-fetched observation: from the `Submit` frame read to the scheduler accepting it
    /// (validation, the driver's queue), plus from dispatch to the reply handed to the stream
    /// (batch start, engine hand-off, horizon policy, trim, driver), less the forward pass.
    pub processing: LatencySummary,
}

/// Re-dispatched rounds by [`LossReason`] (the `kairos_redispatch_total{reason}` counter).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RedispatchCounts {
    /// The worker's connection closed or timed out.
    pub connection_lost: u64,
    /// The batch's stream was reset or answered unusably.
    pub stream_reset: u64,
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
            LossReason::Deadline => self.deadline,
            LossReason::Gone => self.gone,
        }
    }

    fn get_mut(&mut self, reason: LossReason) -> &mut u64 {
        match reason {
            LossReason::ConnectionLost => &mut self.connection_lost,
            LossReason::StreamReset => &mut self.stream_reset,
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
