//! Kairos: Algorithm 1 phases 1–2 of the paper (§3.2), the execution-aware priority.
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit):
//! 1. Wait ratio `w` = [`PendingView::wait_ratio`]: `Σ W_j / (now − t_start)` over whole
//!    microseconds as `f64`, clamped to `[0, 1]` (0 when `now = t_start`).
//! 2. With `B` buckets: `b = min(B−1, floor(w·B))` (`f64` product, then floor). If
//!    `skipped ≥ A`: `b = min(B−1, b + floor(skipped / A))` (integer division).
//! 3. Buckets are served from `B−1` down to 0. Within a bucket, with `intra = longest-exec`
//!    (default), by `ê = |E_last| · (1 + skipped)` descending, a product of whole microseconds
//!    saturating at `2^64 − 1` (584,000 years: only absurd inputs saturate, and they then tie;
//!    a `u64` is what a WIT 0.2.0 sort key holds) (`|E_last| = 0` when the task has no reported
//!    execution yet); with
//!    `intra = fifo` this key is skipped (the paper's intra-bucket ablation).
//! 4. Remaining ties: `arrived_at` ascending, then `RequestId` ascending.
//! 5. `B = ∞` (`buckets=inf`): the paper's "prioritise by absolute wait ratio" ablation. The
//!    bucket is replaced by `w` itself (descending; for `w ≥ 0` the order of `f64::to_bits` is the
//!    numeric order), then steps 3–4. Bucket promotion by aging has width `1/B → 0` in this limit,
//!    so it does nothing; the `(1 + skipped)` factor still breaks ties.
//!
//! Defaults: `B = 10` (paper); `A = 4`. The paper leaves `A` open. A request's own wait ratio
//! already rises while it waits (the open round counts), by about one bucket per
//! `life / (B · G)` decisions for a task alive for `life` with generations of `G`; for a task
//! 30 s old and 0.3 s generations that is one bucket per 10 decisions. `A = 4` makes aging about
//! twice as fast as that for mature tasks — a backstop for long-lived tasks whose ratio barely
//! moves — while a young task (life below `A·B·G` = 12 s) still moves faster by its own ratio.
//!
//! Starvation: after `A·(B−1)` skips a request is in the top bucket whatever its ratio. Inside it
//! the `(1 + skipped)` factor bounds how often others pass it, but only if `|E_last| > 0`: a
//! request with no reported execution has `ê = 0` forever and can be passed by every top-bucket
//! request with an execution phase. docs/SCHEDULER.md derives the bound and this caveat.

use std::cmp::Reverse;

use super::RequestId;
use super::policy::{PendingView, PolicyError, PriorityPolicy, order_by_key};
use crate::time::{Timestamp, duration_micros};

/// Default number of wait-ratio buckets `B` (paper §3.2).
pub const DEFAULT_BUCKETS: u32 = 10;
/// Default aging interval `A`.
pub const DEFAULT_AGING: u32 = 4;

/// Order inside a bucket.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IntraBucket {
    /// `|E_last| · (1 + skipped)` descending (the paper's choice).
    LongestExecFirst,
    /// Arrival order (the paper's ablation baseline, Fig. "microbenchmark-intra-bin").
    Fifo,
}

/// Kairos configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KairosConfig {
    /// Buckets `B` (≥ 1); `None` is `∞`.
    pub buckets: Option<u32>,
    /// Aging interval `A` (≥ 1).
    pub aging: u32,
    /// Order inside a bucket.
    pub intra: IntraBucket,
}

impl Default for KairosConfig {
    fn default() -> Self {
        KairosConfig {
            buckets: Some(DEFAULT_BUCKETS),
            aging: DEFAULT_AGING,
            intra: IntraBucket::LongestExecFirst,
        }
    }
}

/// Sort key: priority (bucket or ratio bits) and `ê`, both descending, then arrival and id.
type Key = (Reverse<u64>, Reverse<u64>, Timestamp, RequestId);

/// Algorithm 1, phases 1–2.
#[derive(Clone, Debug)]
pub struct Kairos {
    config: KairosConfig,
    scratch: Vec<(Key, usize)>,
}

impl Kairos {
    /// A Kairos policy; `config` is assumed valid (see [`super::registry`] for validation).
    pub fn new(config: KairosConfig) -> Self {
        Kairos {
            config,
            scratch: Vec::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &KairosConfig {
        &self.config
    }

    /// Phase 1 for one request: its bucket (or, for `B = ∞`, its ratio's bits).
    pub fn priority(&self, now: Timestamp, view: &PendingView) -> u64 {
        let w = view.wait_ratio(now);
        match self.config.buckets {
            None => w.to_bits(),
            Some(buckets) => {
                let top = u64::from(buckets.max(1) - 1);
                let mut bucket = ((w * f64::from(buckets)).floor() as u64).min(top);
                let aging = self.config.aging.max(1);
                if view.skipped >= aging {
                    bucket = (bucket + u64::from(view.skipped / aging)).min(top);
                }
                bucket
            }
        }
    }

    /// Phase 2's key `ê = |E_last| · (1 + skipped)` in microseconds, saturating.
    pub fn estimated_exec(view: &PendingView) -> u64 {
        let exec = view.last_exec.map(duration_micros).unwrap_or(0);
        exec.saturating_mul(1 + u64::from(view.skipped))
    }
}

impl PriorityPolicy for Kairos {
    fn name(&self) -> &str {
        "kairos"
    }

    fn order(
        &mut self,
        now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        let mut scratch = std::mem::take(&mut self.scratch);
        order_by_key(pending, order, &mut scratch, |v| {
            let exec = match self.config.intra {
                IntraBucket::LongestExecFirst => Kairos::estimated_exec(v),
                IntraBucket::Fifo => 0,
            };
            (
                Reverse(self.priority(now, v)),
                Reverse(exec),
                v.arrived_at,
                v.request,
            )
        });
        self.scratch = scratch;
        Ok(())
    }
}
