//! FIFO: first come, first served by request arrival (the vLLM/SGLang default the paper compares
//! against).
//!
//! Exact semantics (what a plugin twin must reproduce): sort the pending requests by
//! `(arrived_at, request)` ascending — arrival time in microseconds, ties broken by the smaller
//! `RequestId`. Nothing about the task is consulted.

use super::policy::{PendingView, PolicyError, PriorityPolicy};
use crate::time::Timestamp;

/// First come, first served.
#[derive(Clone, Copy, Debug, Default)]
pub struct Fifo;

impl PriorityPolicy for Fifo {
    fn name(&self) -> &str {
        "fifo"
    }

    fn order(
        &mut self,
        _now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        order.extend(0..pending.len());
        order.sort_unstable_by_key(|&i| (pending[i].arrived_at, pending[i].request));
        Ok(())
    }
}
