//! [`Removal`]: how the scheduler removes a worker, once. Its registration task (heartbeats,
//! the registration stream) and its [`RemoteEngine`](super::RemoteEngine) (batches) can both
//! find it unusable, even at the same moment; the first reason closes the connection with its
//! close code and is counted in `kairos_worker_removed_total{reason}`, later ones are not. A
//! removal for an unusable answer also bars the worker from registering again for a while
//! ([`super::readmission`]).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use kairos_sdk::client::close_code;
use kairos_sdk::protocol::worker::close_code as worker_close;
use quinn::{Connection, VarInt};

use super::readmission::Readmission;
use crate::metrics::{Metrics, WorkerRemoval};

/// Longest close reason sent (QUIC carries it in one packet).
const MAX_CLOSE_REASON: usize = 200;

/// The close code a worker removed for `reason` is told.
pub fn close_code_of(reason: WorkerRemoval) -> u32 {
    match reason {
        WorkerRemoval::InvalidRegistration => worker_close::REFUSED,
        WorkerRemoval::Deadline => worker_close::DEADLINE,
        WorkerRemoval::InvalidAnswer | WorkerRemoval::StreamFailed => worker_close::BATCH_LOST,
        WorkerRemoval::Silent => worker_close::SILENT,
        WorkerRemoval::ProtocolError | WorkerRemoval::ConnectionLost => close_code::PROTOCOL_ERROR,
    }
}

/// `text` cut to at most `max` bytes, on a character boundary.
pub fn truncated(text: &str, max: usize) -> &str {
    let mut cut = text.len().min(max);
    while !text.is_char_boundary(cut) {
        cut -= 1;
    }
    &text[..cut]
}

/// One registered worker's removal: see the module docs. Cheap to clone.
#[derive(Clone)]
pub struct Removal {
    connection: Connection,
    metrics: Metrics,
    done: Arc<AtomicBool>,
    /// Where a removal for an unusable answer bars the worker, under its `worker_id`.
    readmission: Option<(Arc<Readmission>, Arc<str>)>,
}

impl Removal {
    /// The removal of the worker on `connection`, counted in `metrics`.
    pub fn new(connection: Connection, metrics: Metrics) -> Removal {
        Removal {
            connection,
            metrics,
            done: Arc::new(AtomicBool::new(false)),
            readmission: None,
        }
    }

    /// A removal for an unusable answer also bars the worker `worker_id` (from this
    /// connection's address) in `readmission`.
    pub fn barring(mut self, readmission: Arc<Readmission>, worker_id: &str) -> Removal {
        self.readmission = Some((readmission, Arc::from(worker_id)));
        self
    }

    /// Removes the worker for `reason`: closes its connection with the reason's code and
    /// `detail`, and counts it. Returns whether this call removed it (false: it was already
    /// removed, or it left on its own).
    pub fn remove(&self, reason: WorkerRemoval, detail: &str) -> bool {
        if self.done.swap(true, Ordering::AcqRel) {
            return false;
        }
        // Barred before the connection closes: a worker that reconnects on seeing the close
        // finds the bar in place.
        if reason == WorkerRemoval::InvalidAnswer
            && let Some((readmission, worker_id)) = &self.readmission
        {
            readmission.bar(
                worker_id,
                self.connection.remote_address().ip(),
                tokio::time::Instant::now(),
            );
        }
        self.connection.close(
            VarInt::from_u32(close_code_of(reason)),
            truncated(detail, MAX_CLOSE_REASON).as_bytes(),
        );
        self.metrics.record_worker_removed(reason);
        tracing::warn!(reason = reason.as_str(), %detail, remote = %self.connection.remote_address(),
            "worker removed");
        true
    }

    /// The worker left on its own terms (it drained, or the scheduler is stopping): nothing is
    /// counted, and a later [`Removal::remove`] does nothing. Returns whether it had not been
    /// removed before.
    pub fn left(&self) -> bool {
        !self.done.swap(true, Ordering::AcqRel)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn close_reasons_are_cut_on_a_character_boundary() {
        assert_eq!(truncated("héllo", 2), "h");
        assert_eq!(truncated("héllo", 3), "hé");
        assert_eq!(truncated("short", 200), "short");
        assert_eq!(truncated("", 0), "");
    }

    #[test]
    fn every_reason_has_a_worker_close_code() {
        let codes: Vec<u32> = WorkerRemoval::ALL.into_iter().map(close_code_of).collect();
        assert_eq!(
            codes,
            [
                0x20,
                0x22,
                0x21,
                0x22,
                0x23,
                close_code::PROTOCOL_ERROR,
                close_code::PROTOCOL_ERROR
            ]
        );
    }
}
