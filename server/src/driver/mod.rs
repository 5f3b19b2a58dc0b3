//! The driver: the pure state machine of `kairos_core::driver` ([`DriverCore`]) behind a thin
//! shell ([`shell`]) that runs it on a thread of its own and carries out its effects.
//!
//! The core takes events with `now` as an argument and returns [`core::Effect`]s: answers for
//! the streams waiting for a round, re-fetch asks, batches to run, the next timer. It keeps
//! what the scheduler does not: observations and horizon policies of pending rounds, the streams
//! waiting for each round, each open task's last reply (so a round re-sent after a reconnect gets
//! the same answer instead of a second generation) and clock mapping (to show G/E records on the
//! robot's clock), snapshots of ended tasks, and statistics.
//!
//! The shell runs the core on an OS thread of its own, like the engines, because the core calls
//! the priority policy (on every decision and when a task ends), and a policy may be a plugin
//! that blocks up to its deadline. Connection tasks reach it through a [`DriverHandle`] (an mpsc
//! of commands, each with a oneshot for its answer); nothing else touches the scheduler, so
//! there is no lock around it. On the tokio runtime the shell only waits: for re-fetched
//! observations (up to the re-fetch deadline), for an engine's answer, for the next timer. Each
//! batch's horizon policies run on tokio's blocking pool after the engine has answered; the
//! engine instance is reported idle (`G.end`) before they run, so it takes the next batch
//! meanwhile. No policy runs on a tokio worker thread. docs/ARCHITECTURE.md says why this
//! split, with the measurement.
//!
//! Time is read from [`Clock`](crate::clock::Clock), that is tokio's clock, so tests run the
//! driver in virtual time.
//!
//! Shutdown: once the shutdown signal is set (or every handle is dropped) new rounds are
//! refused with `shutting_down`; rounds already accepted are still run and answered, and the
//! task returned by [`spawn`] completes when none is left.
//!
//! A driver that dies (a panic in the core or in a policy it calls) cannot be restarted in
//! place: its state may be half-updated. Its handles answer `DriverGone` from then on,
//! [`DriverHandle::ended`] says why, and `kairos_driver_alive` turns 0; the server built on it
//! turns unready and stops (`transport::launch`).

mod shell;
#[cfg(test)]
mod tests;

use std::time::Duration;

pub use kairos_core::driver::{
    DriverCore, DriverReport, DriverStats, LatencySummary, RECENT_LATENCIES, Redispatch,
    RedispatchCounts, RedispatchRule, RoundAnswer, TaskSnapshot, WaiterId,
};
use kairos_core::round::ValidObservation;
use tokio::sync::oneshot;

pub use self::shell::EngineView;
pub use self::shell::{DriverEnd, DriverGone, DriverHandle, PendingRound, spawn};

/// A request from the driver to a round's connection task: send `FetchObservation` and return
/// the validated `FreshObservation`. Dropping `reply` means "no fresh observation".
#[derive(Debug)]
pub struct RefetchAsk {
    /// How old the queued observation is.
    pub age: Duration,
    /// Where the fresh observation goes.
    pub reply: oneshot::Sender<ValidObservation>,
}

/// Tunables of the driver.
#[derive(Clone, Debug)]
pub struct DriverConfig {
    /// How long to wait for a re-fetched observation.
    pub refetch_timeout: Duration,
    /// Ended tasks whose snapshot is kept (for `snapshot` after the end).
    pub ended_snapshots: usize,
    /// Capacity of the command channel.
    pub queue: usize,
    /// What happens to rounds lost with a remote engine.
    pub redispatch: RedispatchRule,
    /// Where the core exports its facts (`/metrics`); the default is a registry nobody serves.
    pub metrics: crate::metrics::Metrics,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig {
            refetch_timeout: Duration::from_millis(50),
            ended_snapshots: 4096,
            queue: 8192,
            redispatch: RedispatchRule::default(),
            metrics: crate::metrics::Metrics::new(),
        }
    }
}
