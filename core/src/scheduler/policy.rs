//! Priority policies: the order in which pending round requests are dispatched.
//!
//! A [`PriorityPolicy`] sees every pending request once per scheduling decision, with the
//! per-task lifecycle summary the scheduler keeps, and returns a dispatch order. Batching,
//! placement, skip counters and stale-observation re-fetch stay in the scheduler (Algorithm 1
//! phase 3 and the skip update), so a policy — native or WASM — only decides priority.

use std::time::Duration;

use super::{RequestId, TaskId};
use crate::time::Timestamp;

/// The client's own estimate of the work its task has left, when it sends one.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RemainingWork {
    /// Estimated rounds left, this one included.
    pub rounds: Option<u32>,
    /// Estimated seconds of execution left.
    pub seconds: Option<f32>,
}

/// One pending request as a policy sees it: the request plus its task's lifecycle summary.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PendingView {
    /// The request.
    pub request: RequestId,
    /// Its task.
    pub task: TaskId,
    /// Round index within the task (0 = the task's first request).
    pub round_index: u64,
    /// When the request reached the scheduler.
    pub arrived_at: Timestamp,
    /// When the task's first request reached the scheduler (`t_start` in Eq. 1).
    pub task_started_at: Timestamp,
    /// Consecutive scheduling decisions that passed this request over.
    pub skipped: u32,
    /// Σ_j W_j: the task's wait so far by the dominant-phase rule (paper Fig. "wait_time"),
    /// including the wait accrued in the round still open. See `lifecycle`.
    pub wait: Duration,
    /// Σ_j |G_j|: generation time the task has received (Autellix's attained service), counting
    /// every finished generation of the task, answered or not.
    pub attained_service: Duration,
    /// Σ time the task's requests spent queued before their forward pass started, including this
    /// request's wait so far: the execution-unaware waiting time Autellix's anti-starvation uses.
    pub queued: Duration,
    /// |E_last|: duration of the task's most recent execution phase, if any.
    pub last_exec: Option<Duration>,
    /// `E_last.end` as the robot reported it with this request (send time + remaining actions /
    /// control frequency): when the robot runs out of actions unless this request is answered.
    /// `None` before the task's first execution report (its robot has nothing to execute).
    pub exec_ends_at: Option<Timestamp>,
    /// |G_last|: duration of the task's most recent generation phase, if any.
    pub last_gen: Option<Duration>,
    /// Rounds of this task already answered.
    pub rounds_completed: u32,
    /// The client's remaining-work hint, if it sent one.
    pub remaining: Option<RemainingWork>,
}

impl PendingView {
    /// Eq. 1: `wait / (now - t_start)`, in `[0, 1]` (0 for a task that started at `now`).
    ///
    /// Exactly: both durations in whole microseconds, converted to `f64` and divided once, then
    /// clamped (see [`crate::lifecycle::wait_ratio_micros`]); plugins reproduce it bit for bit.
    pub fn wait_ratio(&self, now: Timestamp) -> f64 {
        crate::lifecycle::wait_ratio_micros(self.wait, now.saturating_since(self.task_started_at))
    }
}

/// Why a policy gave no usable order.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolicyError {
    /// The order is not a permutation of the pending indices.
    #[error("invalid order: {0}")]
    InvalidOrder(String),
    /// The policy failed (a trap, a timeout, an error returned by a plugin).
    #[error("policy failed: {0}")]
    Failed(String),
}

/// A rule that orders pending requests for dispatch, most urgent first.
pub trait PriorityPolicy: Send {
    /// A short stable name (`fifo`, `plas`, `kairos`, a plugin's name).
    fn name(&self) -> &str;

    /// Fill `order` with every index of `pending` exactly once, most urgent first.
    /// `order` arrives empty; its capacity is reused between calls.
    fn order(
        &mut self,
        now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError>;

    /// Told when a task ends, for policies that learn from finished tasks. Default: ignore.
    fn task_finished(&mut self, _summary: &FinishedTask) {}
}

/// What a policy may learn from a task that ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FinishedTask {
    /// The task.
    pub task: TaskId,
    /// Rounds it took.
    pub rounds: u32,
    /// From its first request to the end of its last execution.
    pub latency: Duration,
    /// Σ |G_j|.
    pub attained_service: Duration,
    /// Σ W_j.
    pub wait: Duration,
}

/// Fills `order` with the indices of `pending` sorted ascending by `key`, reusing `scratch`
/// between calls. End every key with the request id: keys are then unique, the order is total,
/// and it does not depend on the sort algorithm (what plugin twins rely on).
pub fn order_by_key<K: Ord>(
    pending: &[PendingView],
    order: &mut Vec<usize>,
    scratch: &mut Vec<(K, usize)>,
    mut key: impl FnMut(&PendingView) -> K,
) {
    order_by_indexed_key(pending, order, scratch, |_, v| key(v));
}

/// [`order_by_key`] for keys that also read per-index data kept beside `pending` (a plugin's
/// sort-key lists): `key` gets each request's index in `pending` with its view.
pub fn order_by_indexed_key<K: Ord>(
    pending: &[PendingView],
    order: &mut Vec<usize>,
    scratch: &mut Vec<(K, usize)>,
    mut key: impl FnMut(usize, &PendingView) -> K,
) {
    scratch.clear();
    scratch.extend(pending.iter().enumerate().map(|(i, v)| (key(i, v), i)));
    scratch.sort_unstable();
    order.extend(scratch.iter().map(|&(_, i)| i));
}

/// Checks that `order` is a permutation of `0..len`: nothing omitted, nothing repeated.
pub fn validate_order(len: usize, order: &[usize]) -> Result<(), PolicyError> {
    if order.len() != len {
        return Err(PolicyError::InvalidOrder(format!(
            "{} indices for {len} pending requests",
            order.len()
        )));
    }
    let mut seen = vec![false; len];
    for &i in order {
        match seen.get_mut(i) {
            None => {
                return Err(PolicyError::InvalidOrder(format!(
                    "index {i} out of range 0..{len}"
                )));
            }
            Some(true) => return Err(PolicyError::InvalidOrder(format!("index {i} repeated"))),
            Some(s) => *s = true,
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_order_rejects_omissions_duplicates_and_out_of_range() {
        assert!(validate_order(3, &[2, 0, 1]).is_ok());
        assert!(validate_order(0, &[]).is_ok());
        assert!(validate_order(3, &[0, 1]).is_err());
        assert!(validate_order(3, &[0, 1, 1]).is_err());
        assert!(validate_order(3, &[0, 1, 3]).is_err());
    }
}
