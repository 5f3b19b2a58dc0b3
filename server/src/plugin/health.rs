//! Failure accounting for one plugin: counts, log-once, quarantine.
//!
//! Every failed call is counted by kind. The first failure of each kind is logged at `warn`
//! with the plugin's name and the reason; later ones only at `debug`, so a plugin failing on
//! every call cannot flood the log.
//!
//! **Quarantine is per robot first.** A horizon decision belongs to one robot's round, and one
//! robot's inputs (its chunks, its parameters) can make a plugin trap that serves every other
//! robot well. So each robot has its own streak: after `quarantine_after` consecutive failures
//! on its rounds, that robot's decisions are answered by the fallback for `probation` of its
//! decisions, then one is a probe call; a failed probe doubles its probation (up to
//! [`MAX_PROBATION`]), a success ends its quarantine. The other robots keep the plugin.
//!
//! **Globally when several robots fail.** Once `quarantine_robots` robots are in quarantine at
//! the same time, the plugin itself is broken (a bad version, a hang under load) and each
//! robot paying its own `quarantine_after` failures, each up to a deadline, would cost
//! everyone: the plugin is then quarantined for every decision in the same way (sit out,
//! probe, double), on top of the robots' own. Decisions that belong to no robot (a priority
//! plugin's, which orders everyone's rounds, or callers that do not say) count towards the
//! plugin-wide record directly, as before. Loading a new version of the file ends every
//! quarantine.
//!
//! Quarantine is counted in decisions rather than seconds so that a simulation replaying a
//! trace in virtual time behaves exactly like the live server. The table of robots holds only
//! robots with failures, and robots are those the configuration allows: it is bounded.

use std::collections::HashMap;
use std::time::Duration;

use kairos_core::scheduler::RobotId;

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
    /// Times the plugin was put in quarantine, for every robot or for one.
    pub quarantines: u64,
    /// Whether it is in quarantine for every robot now.
    pub quarantined: bool,
    /// Robots for which it is in quarantine now.
    pub quarantined_robots: usize,
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

/// One quarantine record: a streak of failures and, while quarantined, the decisions left to
/// sit out (`Some(0)`: the next decision is a probe).
#[derive(Clone, Copy, Debug)]
struct Streak {
    consecutive_failures: u32,
    sitting_out: Option<u32>,
    probation: u32,
}

impl Streak {
    fn new(probation: u32) -> Streak {
        Streak {
            consecutive_failures: 0,
            sitting_out: None,
            probation,
        }
    }

    /// Whether to call the plugin; counts one decision sat out if not.
    fn admit(&mut self) -> bool {
        match &mut self.sitting_out {
            Some(0) | None => true,
            Some(left) => {
                *left -= 1;
                false
            }
        }
    }

    /// A failure; returns whether it (re)entered quarantine.
    fn failed(&mut self, quarantine_after: u32) -> bool {
        self.consecutive_failures = self.consecutive_failures.saturating_add(1);
        let probe_failed = self.sitting_out == Some(0);
        if probe_failed {
            self.probation = self.probation.saturating_mul(2).clamp(1, MAX_PROBATION);
        }
        if probe_failed || self.consecutive_failures == quarantine_after {
            self.sitting_out = Some(self.probation);
            return true;
        }
        false
    }

    /// Enters quarantine now (the plugin-wide record, when enough robots are in theirs).
    fn quarantine(&mut self) {
        if self.sitting_out.is_none() {
            self.sitting_out = Some(self.probation);
        }
    }

    /// A success: the streak ends; returns whether a quarantine was lifted.
    fn succeeded(&mut self, base_probation: u32) -> bool {
        self.consecutive_failures = 0;
        let lifted = self.sitting_out.take().is_some();
        if lifted {
            self.probation = base_probation;
        }
        lifted
    }

    fn quarantined(&self) -> bool {
        self.sitting_out.is_some()
    }
}

/// Health of one plugin. Owned by its wrapper; no clock, no I/O besides logging.
#[derive(Debug)]
pub struct Health {
    name: String,
    quarantine_after: u32,
    quarantine_robots: usize,
    base_probation: u32,
    /// The plugin-wide record.
    all: Streak,
    /// Robots with failures in their current streak, or in quarantine.
    robots: HashMap<RobotId, Streak>,
    failures: [u64; FailureKind::ALL.len()],
    logged: [bool; FailureKind::ALL.len()],
    stats: PluginStats,
    /// `stats.fallbacks`, exported (`PluginOptions::fallback_counter`).
    exported_fallbacks: Option<prometheus_client::metrics::counter::Counter>,
    /// Whether it is quarantined for every robot, exported (`PluginOptions::quarantine_gauge`).
    exported_quarantine: Option<prometheus_client::metrics::gauge::Gauge>,
}

impl Health {
    /// A healthy plugin called `name`.
    pub fn new(name: impl Into<String>, options: &PluginOptions) -> Self {
        Health {
            name: name.into(),
            quarantine_after: options.quarantine_after.max(1),
            quarantine_robots: usize::try_from(options.quarantine_robots.max(1))
                .unwrap_or(usize::MAX),
            base_probation: options.probation,
            all: Streak::new(options.probation),
            robots: HashMap::new(),
            failures: [0; FailureKind::ALL.len()],
            logged: [false; FailureKind::ALL.len()],
            stats: PluginStats::default(),
            exported_fallbacks: options.fallback_counter.clone(),
            exported_quarantine: options.quarantine_gauge.clone(),
        }
    }

    /// Whether to call the plugin for this decision of `robot` (`None`: a decision of no one
    /// robot). Counts the decision; a `false` means it is quarantined, for every robot or for
    /// this one, and the caller answers with the fallback (and must not call `failed`).
    pub fn admit(&mut self, robot: Option<RobotId>) -> bool {
        self.stats.decisions += 1;
        let admitted = match (self.all.sitting_out, robot) {
            // Quarantined for everyone, or everyone's probe: the robot's own record waits.
            (Some(_), _) | (None, None) => self.all.admit(),
            (None, Some(robot)) => self.robots.get_mut(&robot).is_none_or(Streak::admit),
        };
        if !admitted {
            self.count(FailureKind::Quarantined);
            self.fell_back();
        }
        admitted
    }

    fn fell_back(&mut self) {
        self.stats.fallbacks += 1;
        if let Some(counter) = &self.exported_fallbacks {
            counter.inc();
        }
    }

    /// The plugin answered `robot`'s decision validly.
    pub fn succeeded(&mut self, robot: Option<RobotId>, elapsed: Duration, peak_memory: usize) {
        self.stats.answered += 1;
        self.stats.max_call = self.stats.max_call.max(elapsed);
        self.stats.peak_memory = self.stats.peak_memory.max(peak_memory);
        if let Some(robot) = robot
            && let Some(mut streak) = self.robots.remove(&robot)
            && streak.succeeded(self.base_probation)
        {
            tracing::info!(plugin = %self.name, robot = robot.0,
                "plugin answered the robot again; its quarantine lifted");
        }
        // A success on any robot's round shows the plugin works: the plugin-wide streak ends.
        if self.all.succeeded(self.base_probation) {
            tracing::info!(plugin = %self.name, "plugin answered again; quarantine lifted");
            self.export_quarantine();
        }
    }

    /// The plugin failed `robot`'s decision; the caller answers with the fallback.
    pub fn failed(&mut self, robot: Option<RobotId>, kind: FailureKind, message: &str) {
        self.fell_back();
        self.record_failure(robot, kind, message);
    }

    /// A call that is not a decision (`task-finished`) failed: counted, logged and quarantined
    /// like a decision's failure of no one robot, but there was no answer to fall back for.
    /// Its successes do not reset the failure streak: a plugin that fails every decision stays
    /// quarantined.
    pub fn notice_failed(&mut self, kind: FailureKind, message: &str) {
        self.record_failure(None, kind, message);
    }

    /// Whether the plugin is quarantined for every robot now (sitting out, or waiting for its
    /// probe).
    pub fn quarantined(&self) -> bool {
        self.all.quarantined()
    }

    fn record_failure(&mut self, robot: Option<RobotId>, kind: FailureKind, message: &str) {
        self.count(kind);
        if !std::mem::replace(&mut self.logged[kind.index()], true) {
            tracing::warn!(plugin = %self.name, failure = %kind, %message,
                "plugin failed; a decision uses the fallback policy (further failures of this kind are counted, not logged)");
        } else {
            tracing::debug!(plugin = %self.name, failure = %kind, %message, "plugin failed again");
        }
        let everyone_probed = self.all.sitting_out == Some(0);
        let Some(robot) = robot.filter(|_| !everyone_probed) else {
            // A decision of no robot, or the plugin-wide probe: the plugin-wide record.
            if self.all.failed(self.quarantine_after) {
                self.entered_quarantine(None);
            }
            return;
        };
        let streak = self
            .robots
            .entry(robot)
            .or_insert_with(|| Streak::new(self.base_probation));
        if !streak.failed(self.quarantine_after) {
            return;
        }
        self.entered_quarantine(Some(robot));
        let quarantined_robots = self.robots.values().filter(|s| s.quarantined()).count();
        if quarantined_robots >= self.quarantine_robots && !self.all.quarantined() {
            self.all.quarantine();
            self.entered_quarantine(None);
        }
    }

    fn entered_quarantine(&mut self, robot: Option<RobotId>) {
        self.stats.quarantines += 1;
        match robot {
            Some(robot) => {
                let streak = self.robots.get(&robot).copied();
                tracing::warn!(plugin = %self.name, robot = robot.0,
                    consecutive_failures = streak.map_or(0, |s| s.consecutive_failures),
                    sit_out_decisions = streak.and_then(|s| s.sitting_out),
                    "plugin quarantined for one robot: the fallback policy answers that robot until it is probed again or the file changes");
            }
            None => {
                self.export_quarantine();
                tracing::warn!(plugin = %self.name,
                consecutive_failures = self.all.consecutive_failures,
                sit_out_decisions = self.all.sitting_out,
                quarantined_robots = self.robots.values().filter(|s| s.quarantined()).count(),
                "plugin quarantined: the fallback policy answers every robot until it is probed again or its file changes");
            }
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
        self.all = Streak::new(self.base_probation);
        self.robots.clear();
        self.logged = [false; FailureKind::ALL.len()];
        self.export_quarantine();
    }

    fn export_quarantine(&self) {
        if let Some(gauge) = &self.exported_quarantine {
            gauge.set(i64::from(self.all.quarantined()));
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
        stats.quarantined = self.all.quarantined();
        stats.quarantined_robots = self.robots.values().filter(|s| s.quarantined()).count();
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
        assert!(h.admit(None));
        h.failed(None, FailureKind::Trap, "x");
        assert!(h.admit(None));
        h.succeeded(None, Duration::ZERO, 0);
        // A success in between resets the streak.
        assert!(h.admit(None));
        h.failed(None, FailureKind::Trap, "x");
        assert!(!h.stats().quarantined);
        assert!(h.admit(None));
        h.failed(None, FailureKind::Timeout, "x");
        assert!(h.stats().quarantined);
        assert_eq!(quarantined.get(), 1, "the quarantine is exported");
        assert_eq!(h.stats().quarantines, 1);
        // Sits out 3 decisions, then is probed.
        assert!((0..3).all(|_| !h.admit(None)));
        assert!(h.admit(None));
        h.failed(None, FailureKind::Trap, "x");
        // The failed probe doubles the probation to 6.
        assert!((0..6).all(|_| !h.admit(None)));
        assert!(h.admit(None));
        h.succeeded(None, Duration::ZERO, 0);
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
        assert!(h.admit(None));
        h.failed(None, FailureKind::Trap, "x");
        assert!(!h.admit(None));
        h.reloaded();
        assert!(h.admit(None));
        assert_eq!(h.stats().reloads, 1);
    }

    #[test]
    fn one_robots_failures_quarantine_the_plugin_for_that_robot_only() {
        let mut h = Health::new("p", &options(3, 4));
        let (a, b) = (Some(RobotId(0)), Some(RobotId(1)));
        for _ in 0..3 {
            assert!(h.admit(a));
            h.failed(a, FailureKind::Trap, "x");
        }
        let stats = h.stats();
        assert_eq!((stats.quarantined, stats.quarantined_robots), (false, 1));
        // `b` keeps the plugin on every decision; `a` sits out its own 4, then is probed.
        for _ in 0..4 {
            assert!(!h.admit(a));
            assert!(h.admit(b));
            h.succeeded(b, Duration::ZERO, 0);
        }
        assert!(h.admit(a), "a's probe");
        h.failed(a, FailureKind::Trap, "x");
        // Its failed probe doubles its probation; `b` is still served.
        assert!((0..8).all(|_| !h.admit(a)));
        assert!(h.admit(b));
        h.succeeded(b, Duration::ZERO, 0);
        assert!(h.admit(a));
        h.succeeded(a, Duration::ZERO, 0);
        let stats = h.stats();
        assert_eq!((stats.quarantined, stats.quarantined_robots), (false, 0));
        assert_eq!(stats.failures_of(FailureKind::Quarantined), 12);
        assert_eq!(stats.quarantines, 2);
    }

    #[test]
    fn failures_on_several_robots_quarantine_the_plugin_for_everyone() {
        let mut h = Health::new(
            "p",
            &PluginOptions {
                quarantine_robots: 2,
                ..options(2, 3)
            },
        );
        let robots: Vec<Option<RobotId>> = (0..3).map(|i| Some(RobotId(i))).collect();
        for robot in &robots[..2] {
            for _ in 0..2 {
                assert!(h.admit(*robot));
                h.failed(*robot, FailureKind::Timeout, "x");
            }
        }
        // Two robots in quarantine: a third that never failed sits out too.
        assert!(h.stats().quarantined);
        assert!((0..3).all(|_| !h.admit(robots[2])));
        // The plugin-wide probe goes to whoever decides next; its failure doubles the
        // plugin-wide probation.
        assert!(h.admit(robots[2]));
        h.failed(robots[2], FailureKind::Timeout, "x");
        assert!((0..6).all(|_| !h.admit(robots[2])));
        assert!(h.admit(robots[2]));
        h.succeeded(robots[2], Duration::ZERO, 0);
        // Lifted for everyone; the two robots are still in their own quarantine.
        let stats = h.stats();
        assert_eq!((stats.quarantined, stats.quarantined_robots), (false, 2));
        assert!(h.admit(robots[2]));
        assert!(!h.admit(robots[0]));
        // Decisions of no robot (a priority plugin's) use the plugin-wide record alone.
        assert!(h.admit(None));
        h.reloaded();
        let stats = h.stats();
        assert_eq!((stats.quarantined, stats.quarantined_robots), (false, 0));
        assert!(h.admit(robots[0]));
    }
}
