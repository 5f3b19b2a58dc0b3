//! FIFO: first come, first served by request arrival (the vLLM/SGLang default the paper compares
//! against).
//!
//! Exact semantics (what a plugin twin must reproduce): sort the pending requests by
//! `(arrived_at, request)` ascending — arrival time in microseconds, ties broken by the smaller
//! `RequestId`. Nothing about the task is consulted.

use super::RequestId;
use super::policy::{PendingView, PolicyError, PriorityPolicy, order_by_key};
use crate::time::Timestamp;

/// First come, first served.
#[derive(Clone, Debug, Default)]
pub struct Fifo {
    scratch: Vec<((Timestamp, RequestId), usize)>,
}

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
        order_by_key(pending, order, &mut self.scratch, |v| {
            (v.arrived_at, v.request)
        });
        Ok(())
    }
}
