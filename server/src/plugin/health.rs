//! Failure accounting for one plugin: counts, log-once, quarantine.
//!
//! Every failed call is counted by kind. The first failure of each kind is logged at `warn`
//! with the plugin's name and the reason; later ones only at `debug`, so a plugin failing on
//! every call cannot flood the log. After `quarantine_after` consecutive failures the plugin is
//! quarantined: it sits out `probation` decisions (answered by the fallback), then gets one
//! probe call; a failed probe doubles the probation (up to [`MAX_PROBATION`]), a success
//! ends the quarantine. Loading a new version of the file ends it too.
//!
//! Quarantine is counted in decisions rather than seconds so that a simulation replaying a
//! trace in virtual time behaves exactly like the live server.

use std::time::Duration;

use super::{MAX_PROBATION, PluginOptions};

/// Why a call did not produce a usable answer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FailureKind {
    /// Interrupted at its deadline.
    Timeout,
    /// Tried to grow memory (or a table) beyond its cap.
    OverLimit,
    /// Ran out of fuel.
    OutOfFuel,
    /// Trapped (unreachable, out-of-bounds access, a host call it may not make, ...).
    Trap,
    /// Could not be instantiated (its start code trapped, timed out or hit a limit).
    Instantiate,
    /// Answered something invalid (a horizon outside `[h_min, h_max]`, an order that is
    /// not a permutation).
    InvalidAnswer,
    /// Returned an error (`result::err`) instead of an answer.
    Refused,
    /// Quarantined: not called at all.
    Quarantined,
    /// The worker thread running the call did not answer in time (stuck in a host call, which
    /// an epoch deadline cannot interrupt); it was abandoned and replaced.
    Stuck,
}

impl FailureKind {
    const ALL: [FailureKind; 9] = [
        FailureKind::Timeout,
        FailureKind::OverLimit,
        FailureKind::OutOfFuel,
        FailureKind::Trap,
        FailureKind::Instantiate,
        FailureKind::InvalidAnswer,
        FailureKind::Refused,
        FailureKind::Quarantined,
        FailureKind::Stuck,
    ];

    fn index(self) -> usize {
        self as usize
    }
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FailureKind::Timeout => "timeout",
            FailureKind::OverLimit => "over limit",
            FailureKind::OutOfFuel => "out of fuel",
            FailureKind::Trap => "trap",
            FailureKind::Instantiate => "instantiation failed",
            FailureKind::InvalidAnswer => "invalid answer",
            FailureKind::Refused => "refused",
            FailureKind::Quarantined => "quarantined",
            FailureKind::Stuck => "worker thread stuck",
        })
    }
}

/// Counters of one plugin since it was loaded.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct PluginStats {
    /// Decisions asked of the wrapper.
    pub decisions: u64,
    /// Decisions the plugin answered validly.
    pub answered: u64,
    /// Decisions answered by the fallback policy instead.
    pub fallbacks: u64,
    /// Failures by kind (`Quarantined` counts decisions skipped while quarantined).
    pub failures: Vec<(FailureKind, u64)>,
    /// Times the plugin was put in quarantine.
    pub quarantines: u64,
    /// Whether it is in quarantine now.
    pub quarantined: bool,
    /// New versions of the file swapped in.
    pub reloads: u64,
    /// Longest successful call.
    pub max_call: Duration,
    /// Largest linear memory any of its instances had, in bytes.
    pub peak_memory: usize,
}

impl PluginStats {
    /// Failures of `kind` so far.
    pub fn failures_of(&self, kind: FailureKind) -> u64 {
        self.failures
            .iter()
            .find(|(k, _)| *k == kind)
            .map_or(0, |(_, n)| *n)
    }
}

/// Health of one plugin. Owned by its wrapper; no clock, no I/O besides logging.
#[derive(Debug)]
pub struct Health {
    name: String,
    quarantine_after: u32,
    base_probation: u32,
    consecutive_failures: u32,
    /// Decisions left to sit out; `Some` while quarantined.
    sitting_out: Option<u32>,
    probation: u32,
    failures: [u64; FailureKind::ALL.len()],
    logged: [bool; FailureKind::ALL.len()],
    stats: PluginStats,
    /// `stats.fallbacks`, exported (`PluginOptions::fallback_counter`).
    exported_fallbacks: Option<prometheus_client::metrics::counter::Counter>,
    /// Whether it is quarantined, exported (`PluginOptions::quarantine_gauge`).
    exported_quarantine: Option<prometheus_client::metrics::gauge::Gauge>,
}

impl Health {
    /// A healthy plugin called `name`.
    pub fn new(name: impl Into<String>, options: &PluginOptions) -> Self {
        Health {
            name: name.into(),
            quarantine_after: options.quarantine_after.max(1),
            base_probation: options.probation,
            consecutive_failures: 0,
            sitting_out: None,
            probation: options.probation,
            failures: [0; FailureKind::ALL.len()],
            logged: [false; FailureKind::ALL.len()],
            stats: PluginStats::default(),
            exported_fallbacks: options.fallback_counter.clone(),
            exported_quarantine: options.quarantine_gauge.clone(),
        }
    }

    /// Whether to call the plugin for this decision. Counts the decision; a `false` means it
    /// is quarantined and the caller answers with the fallback (and must not call `failed`).
    pub fn admit(&mut self) -> bool {
        self.stats.decisions += 1;
        match &mut self.sitting_out {
            Some(0) | None => true,
            Some(left) => {
                *left -= 1;
                self.count(FailureKind::Quarantined);
                self.fell_back();
                false
            }
        }
    }

    fn fell_back(&mut self) {
        self.stats.fallbacks += 1;
        if let Some(counter) = &self.exported_fallbacks {
            counter.inc();
        }
    }

    /// The plugin answered validly.
    pub fn succeeded(&mut self, elapsed: Duration, peak_memory: usize) {
        self.stats.answered += 1;
        self.stats.max_call = self.stats.max_call.max(elapsed);
        self.stats.peak_memory = self.stats.peak_memory.max(peak_memory);
        self.consecutive_failures = 0;
        if self.sitting_out.take().is_some() {
            tracing::info!(plugin = %self.name, "plugin answered again; quarantine lifted");
            self.probation = self.base_probation;
            self.export_quarantine();
        }
    }

    /// The plugin failed this decision; the caller answers with the fallback.
    pub fn failed(&mut self, kind: FailureKind, message: &str) {
        self.fell_back();
        self.record_failure(kind, message);
    }

    /// A call that is not a decision (`task-finished`) failed: counted, logged and quarantined
    /// like a decision's failure, but there was no answer to fall back for. Its successes do
    /// not reset the failure streak: a plugin that fails every decision stays quarantined.
    pub fn notice_failed(&mut self, kind: FailureKind, message: &str) {
        self.record_failure(kind, message);
    }

    /// Whether the plugin is quarantined now (sitting out, or waiting for its probe).
    pub fn quarantined(&self) -> bool {
        self.sitting_out.is_some()
    }

    fn record_failure(&mut self, kind: FailureKind, message: &str) {
        self.count(kind);
        if !std::mem::replace(&mut self.logged[kind.index()], true) {
            tracing::warn!(plugin = %self.name, failure = %kind, %message,
                "plugin failed; a decision uses the fallback policy (further failures of this kind are counted, not logged)");
        } else {
            tracing::debug!(plugin = %self.name, failure = %kind, %message, "plugin failed again");
        }
        self.consecutive_failures = self.consecutive_failures.saturating_add(1);
        let probe_failed = self.sitting_out == Some(0);
        if probe_failed {
            self.probation = self.probation.saturating_mul(2).clamp(1, MAX_PROBATION);
        }
        if probe_failed || self.consecutive_failures == self.quarantine_after {
            self.sitting_out = Some(self.probation);
            self.stats.quarantines += 1;
            tracing::warn!(plugin = %self.name, consecutive_failures = self.consecutive_failures,
                sit_out_decisions = self.probation, "plugin quarantined: the fallback policy answers until it is probed again or its file changes");
            self.export_quarantine();
        }
    }

    /// The plugin declined to decide (a `horizon-error`); its answer is passed on, like a
    /// native policy's error, and does not count towards quarantine.
    pub fn refused(&mut self, message: &str) {
        self.count(FailureKind::Refused);
        if !std::mem::replace(&mut self.logged[FailureKind::Refused.index()], true) {
            tracing::info!(plugin = %self.name, %message, "plugin declined a decision (further refusals are counted, not logged)");
        }
    }

    /// A new version of the plugin was loaded: forget its predecessor's failures.
    pub fn reloaded(&mut self) {
        self.stats.reloads += 1;
        self.consecutive_failures = 0;
        self.sitting_out = None;
        self.probation = self.base_probation;
        self.logged = [false; FailureKind::ALL.len()];
        self.export_quarantine();
    }

    fn export_quarantine(&self) {
        if let Some(gauge) = &self.exported_quarantine {
            gauge.set(i64::from(self.sitting_out.is_some()));
        }
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> PluginStats {
        let mut stats = self.stats.clone();
        stats.failures = FailureKind::ALL
            .iter()
            .zip(self.failures)
            .filter(|(_, n)| *n > 0)
            .map(|(k, n)| (*k, n))
            .collect();
        stats.quarantined = self.sitting_out.is_some();
        stats
    }

    fn count(&mut self, kind: FailureKind) {
        self.failures[kind.index()] += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(after: u32, probation: u32) -> PluginOptions {
        PluginOptions {
            quarantine_after: after,
            probation,
            ..PluginOptions::horizon()
        }
    }

    #[test]
    fn quarantine_starts_after_consecutive_failures_and_doubles_on_failed_probes() {
        let exported = prometheus_client::metrics::counter::Counter::default();
        let quarantined = prometheus_client::metrics::gauge::Gauge::<i64>::default();
        let mut h = Health::new(
            "p",
            &PluginOptions {
                fallback_counter: Some(exported.clone()),
                quarantine_gauge: Some(quarantined.clone()),
                ..options(2, 3)
            },
        );
        assert!(h.admit());
        h.failed(FailureKind::Trap, "x");
        assert!(h.admit());
        h.succeeded(Duration::ZERO, 0);
        // A success in between resets the streak.
        assert!(h.admit());
        h.failed(FailureKind::Trap, "x");
        assert!(!h.stats().quarantined);
        assert!(h.admit());
        h.failed(FailureKind::Timeout, "x");
        assert!(h.stats().quarantined);
        assert_eq!(quarantined.get(), 1, "the quarantine is exported");
        assert_eq!(h.stats().quarantines, 1);
        // Sits out 3 decisions, then is probed.
        assert!((0..3).all(|_| !h.admit()));
        assert!(h.admit());
        h.failed(FailureKind::Trap, "x");
        // The failed probe doubles the probation to 6.
        assert!((0..6).all(|_| !h.admit()));
        assert!(h.admit());
        h.succeeded(Duration::ZERO, 0);
        assert!(!h.stats().quarantined);
        assert_eq!(quarantined.get(), 0, "and so is its end");
        let stats = h.stats();
        assert_eq!(stats.failures_of(FailureKind::Quarantined), 9);
        assert_eq!(stats.failures_of(FailureKind::Trap), 3);
        assert_eq!(stats.failures_of(FailureKind::Timeout), 1);
        assert_eq!(stats.fallbacks, 13);
        assert_eq!(exported.get(), 13, "every fallback is exported");
        assert_eq!(stats.answered, 2);
        assert_eq!(stats.decisions, 15);
    }

    #[test]
    fn reload_lifts_quarantine() {
        let mut h = Health::new("p", &options(1, 100));
        assert!(h.admit());
        h.failed(FailureKind::Trap, "x");
        assert!(!h.admit());
        h.reloaded();
        assert!(h.admit());
        assert_eq!(h.stats().reloads, 1);
    }
}
