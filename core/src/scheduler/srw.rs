//! SRW, slack-aware shortest remaining work: a priority policy that lowers average end-to-end
//! latency below Algorithm 1's without making the tail worse (docs/EVALUATION.md, "A better
//! priority policy").
//!
//! Two observations drive it.
//!
//! 1. **A request is only needed when its robot runs dry.** With asynchronous inference a robot
//!    sends round `i` while it still executes chunk `i − 1`, and reports when that chunk ends
//!    (Last Exec Info: `E_{i−1}.end`, the request's *deadline*). Serving a request before its
//!    deadline gains nothing — the chunk would wait on the robot — while a robot past its deadline
//!    is stalled and its task's latency grows one-for-one. So requests past their deadline
//!    (*due*) go first, and the rest in earliest-deadline order. Algorithm 1 sees the deadline only
//!    indirectly, through the wait ratio, and FIFO not at all; in simulation this alone is most of
//!    SRW's gain.
//! 2. **Among stalled robots, finishing tasks empties the system fastest.** When more robots are
//!    stalled than a batch holds, each one served removes one stalled robot for a chunk, and
//!    serving a task close to its end removes it for good: shortest remaining processing time first
//!    minimises mean response time (Schrage 1968), with processing counted in rounds. The remaining
//!    work comes from the client's hint (`RemainingWork`) when it sends one, and otherwise from a
//!    Gittins index learned online from the round counts of finished tasks (`task_finished`; no
//!    oracle) — the optimal non-anticipating rule for mean response time in the M/G/1 queue
//!    (Gittins 1989; Scully & Harchol-Balter 2018), which reduces to SRPT when sizes are known.
//!
//! Anti-starvation: a due request's urgency is divided by `1 − w`, where `w` is its task's wait
//! ratio (paper Eq. 1, the signal Algorithm 1 buckets). A long task that keeps losing accumulates
//! wait, `w → 1`, and its urgency grows without bound until it is served. A task's first request
//! has waited its whole life (`w = 1`), so a newly arrived robot is served promptly.
//!
//! Exact semantics (for a plugin twin), with `now` the decision time:
//! 1. Deadline `d` = [`PendingView::exec_ends_at`], or `arrived_at` when absent (a robot with no
//!    chunk yet is dry already). With `slack = 0` every request counts as due.
//! 2. Due iff `d <= now`. Due requests come before all others.
//! 3. Work urgency `u` (higher first): with `hints = 1` and a hint, `1 / max(1, rounds)`, or with
//!    only seconds in the hint and a known `|E_last|` (seconds), `1 / max(1, seconds / |E_last|)`;
//!    otherwise, once `warmup` tasks have finished, the Gittins index `G(rounds_completed)` of
//!    [`GittinsIndex`]; otherwise 0.
//! 4. Due requests, with `due_order = work` (default): by `u / max(1 − w, 0.01)` descending (`w` =
//!    [`PendingView::wait_ratio`], `f64`); with `due_order = deadline`: by `d` ascending.
//!    Requests not due: by `d` ascending.
//! 5. Remaining ties: `arrived_at` ascending, then `RequestId` ascending.
//!
//! Parameters: `hints` (1 = use client hints, 0 = ignore them; default 1), `warmup` (finished
//! tasks before the learned index is used; default 20), `slack` (1 = deadline-aware, 0 = treat
//! every request as due, the ablation without observation 1; default 1), `due_order` (`work` or
//! `deadline`, the ablation without observation 2; default `work`).

use super::policy::{FinishedTask, PendingView, PolicyError, PriorityPolicy, order_by_key};
use crate::time::Timestamp;

/// Default number of finished tasks before the learned index is used.
pub const DEFAULT_WARMUP: u32 = 20;
/// The smallest `1 − w` the aging divides by: bounds the boost of a fully starved request so
/// that remaining work still orders such requests among themselves.
pub const MIN_UNWAITED: f64 = 0.01;

/// How due requests are ordered among themselves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DueOrder {
    /// Remaining-work urgency aged by the wait ratio (the policy proper).
    Work,
    /// Earliest deadline first (ablation: deadline awareness only).
    Deadline,
}

/// SRW configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SrwConfig {
    /// Use the client's remaining-work hint when present.
    pub hints: bool,
    /// Finished tasks needed before the learned index replaces "no information".
    pub warmup: u32,
    /// Deadline-aware: requests whose robot is not yet dry wait (ablation switch).
    pub slack: bool,
    /// Order among due requests.
    pub due_order: DueOrder,
}

impl Default for SrwConfig {
    fn default() -> Self {
        SrwConfig {
            hints: true,
            warmup: DEFAULT_WARMUP,
            slack: true,
            due_order: DueOrder::Work,
        }
    }
}

/// The Gittins index over task round counts, learned from finished tasks.
///
/// For a task that has completed `a` rounds and the empirical distribution of round counts `S`,
/// `G(a) = max_{Δ ≥ 1} P(S − a ≤ Δ | S > a) / E[min(S − a, Δ) | S > a]`: the best ratio of
/// completion probability to rounds invested over any look-ahead `Δ`. Ages at or beyond the
/// longest task seen use the index of the last age with survivors. Computed over the
/// counts in `f64`; rebuilt when the number of observed tasks has grown by 1/16 since the last
/// rebuild (an O(n²) pass over round counts, n the longest task).
#[derive(Clone, Debug, Default)]
pub struct GittinsIndex {
    /// `counts[n]`: finished tasks that took `n` rounds.
    counts: Vec<u64>,
    observed: u64,
    index: Vec<f64>,
    built_at: u64,
}

impl GittinsIndex {
    /// Records a finished task's round count (0 is ignored).
    pub fn observe(&mut self, rounds: u32) {
        if rounds == 0 {
            return;
        }
        let n = rounds as usize;
        if self.counts.len() <= n {
            self.counts.resize(n + 1, 0);
        }
        self.counts[n] += 1;
        self.observed += 1;
    }

    /// Tasks observed.
    pub fn observed(&self) -> u64 {
        self.observed
    }

    fn rebuild(&mut self) {
        let len = self.counts.len();
        // survivors[a] = tasks with more than `a` rounds.
        let mut survivors = vec![0u64; len + 1];
        for a in (0..len).rev() {
            survivors[a] = survivors[a + 1] + self.counts.get(a + 1).copied().unwrap_or(0);
        }
        self.index.clear();
        let mut last = 0.0;
        for a in 0..len {
            let alive = survivors[a];
            if alive == 0 {
                self.index.push(last);
                continue;
            }
            let mut best = 0.0f64;
            let mut invested = 0u64;
            for delta in 1..=(len - a) {
                invested += survivors[a + delta - 1];
                let finished = alive - survivors[a + delta];
                best = best.max(finished as f64 / invested as f64);
            }
            last = best;
            self.index.push(best);
        }
        self.built_at = self.observed;
    }

    /// `G(age)` for a task that has completed `age` rounds (0 before any observation).
    pub fn get(&mut self, age: u32) -> f64 {
        if self.observed > self.built_at + self.built_at / 16 {
            self.rebuild();
        }
        match self.index.len() {
            0 => 0.0,
            n => self.index[(age as usize).min(n - 1)],
        }
    }
}

/// Slack-aware shortest remaining work first.
#[derive(Clone, Debug, Default)]
pub struct Srw {
    config: SrwConfig,
    gittins: GittinsIndex,
    scratch: Vec<((bool, u64, Timestamp, u64), usize)>,
}

impl Srw {
    /// An SRW policy; `config` is assumed valid (the registry validates it).
    pub fn new(config: SrwConfig) -> Self {
        Srw {
            config,
            gittins: GittinsIndex::default(),
            scratch: Vec::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &SrwConfig {
        &self.config
    }

    /// The client's hint as a round count, if usable.
    pub fn hinted_rounds(view: &PendingView) -> Option<f64> {
        let hint = view.remaining?;
        if let Some(r) = hint.rounds {
            return Some(f64::from(r).max(1.0));
        }
        let secs = f64::from(hint.seconds?);
        let exec = view.last_exec?.as_secs_f64();
        (secs.is_finite() && secs >= 0.0 && exec > 0.0).then(|| (secs / exec).max(1.0))
    }

    /// Step 3: the work urgency of a request (higher: less work left).
    pub fn urgency(&mut self, view: &PendingView) -> f64 {
        if self.config.hints
            && let Some(rounds) = Self::hinted_rounds(view)
        {
            return 1.0 / rounds;
        }
        if self.gittins.observed() >= u64::from(self.config.warmup) {
            return self.gittins.get(view.rounds_completed);
        }
        0.0
    }
}

impl PriorityPolicy for Srw {
    fn name(&self) -> &str {
        "srw"
    }

    fn order(
        &mut self,
        now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        let mut scratch = std::mem::take(&mut self.scratch);
        order_by_key(pending, order, &mut scratch, |view| {
            let deadline = view.exec_ends_at.unwrap_or(view.arrived_at);
            let due = !self.config.slack || deadline <= now;
            // Ascending keys: due first; then the primary key, which is either the deadline in
            // microseconds or, for due requests ordered by work, the complement of the score's
            // bits (for finite scores >= 0 the bit pattern orders like the number).
            let primary = match (due, self.config.due_order) {
                (true, DueOrder::Work) => {
                    let unwaited = (1.0 - view.wait_ratio(now)).max(MIN_UNWAITED);
                    let score = self.urgency(view) / unwaited;
                    let score = if score.is_finite() && score > 0.0 {
                        score
                    } else {
                        0.0
                    };
                    u64::MAX - score.to_bits()
                }
                _ => deadline.as_micros(),
            };
            (!due, primary, view.arrived_at, view.request.0)
        });
        self.scratch = scratch;
        Ok(())
    }

    fn task_finished(&mut self, summary: &FinishedTask) {
        self.gittins.observe(summary.rounds);
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;
    use crate::scheduler::{RemainingWork, RequestId, TaskId};

    fn ms(v: u64) -> Timestamp {
        Timestamp::from_micros(v * 1000)
    }

    fn view(request: u64, exec_ends_ms: Option<u64>, rounds_left: Option<u32>) -> PendingView {
        PendingView {
            request: RequestId(request),
            task: TaskId(request),
            round_index: 3,
            arrived_at: ms(900 + request),
            task_started_at: ms(0),
            skipped: 0,
            wait: Duration::ZERO,
            attained_service: Duration::from_millis(300),
            queued: Duration::ZERO,
            last_exec: Some(Duration::from_millis(500)),
            exec_ends_at: exec_ends_ms.map(ms),
            last_gen: Some(Duration::from_millis(100)),
            rounds_completed: 3,
            remaining: rounds_left.map(|r| RemainingWork {
                rounds: Some(r),
                seconds: None,
            }),
        }
    }

    fn order(p: &mut Srw, now_ms: u64, views: &[PendingView]) -> Vec<u64> {
        let mut o = Vec::new();
        p.order(ms(now_ms), views, &mut o).unwrap();
        crate::scheduler::validate_order(views.len(), &o).unwrap();
        o.iter().map(|&i| views[i].request.0).collect()
    }

    #[test]
    fn due_requests_first_then_earliest_deadline() {
        let mut p = Srw::new(SrwConfig::default());
        let views = [
            view(1, Some(1500), Some(2)),  // not due, late deadline, little work
            view(2, Some(1200), Some(50)), // not due, earlier deadline
            view(3, Some(900), Some(40)),  // due
            view(4, Some(950), Some(10)),  // due, less work
        ];
        assert_eq!(order(&mut p, 1000, &views), vec![4, 3, 2, 1]);
        // Ablations: without slack everything is due and ordered by work; deadline-only is EDF.
        let mut no_slack = Srw::new(SrwConfig {
            slack: false,
            ..SrwConfig::default()
        });
        assert_eq!(order(&mut no_slack, 1000, &views), vec![1, 4, 3, 2]);
        let mut edf = Srw::new(SrwConfig {
            due_order: DueOrder::Deadline,
            ..SrwConfig::default()
        });
        assert_eq!(order(&mut edf, 1000, &views), vec![3, 4, 2, 1]);
    }

    #[test]
    fn waiting_ages_a_long_task_past_shorter_ones() {
        let mut p = Srw::new(SrwConfig::default());
        let mut long = view(1, Some(500), Some(40));
        let short = view(2, Some(500), Some(10));
        // At wait ratio 0 the short task wins; at 0.8 the long one (40 x 0.2 = 8 < 10) does.
        assert_eq!(order(&mut p, 1000, &[long, short]), vec![2, 1]);
        long.wait = Duration::from_millis(800);
        assert_eq!(order(&mut p, 1000, &[long, short]), vec![1, 2]);
    }

    #[test]
    fn hints_can_be_ignored_and_seconds_convert_with_the_last_execution() {
        let mut v = view(1, None, None);
        v.remaining = Some(RemainingWork {
            rounds: None,
            seconds: Some(5.0),
        });
        assert_eq!(Srw::hinted_rounds(&v), Some(10.0));
        let mut p = Srw::new(SrwConfig {
            hints: false,
            ..SrwConfig::default()
        });
        assert_eq!(p.urgency(&v), 0.0, "no hint use and no finished tasks yet");
    }

    #[test]
    fn gittins_index_matches_a_hand_computed_distribution() {
        // Half the tasks take 2 rounds, half take 10.
        let mut g = GittinsIndex::default();
        for _ in 0..10 {
            g.observe(2);
            g.observe(10);
        }
        // Age 0: best look-ahead is Δ = 2: P(done) = 1/2, E[min(S, 2)] = 2 -> 0.25.
        assert!((g.get(0) - 0.25).abs() < 1e-12, "{}", g.get(0));
        // Age 1: Δ = 1 finishes half of the survivors in 1 round -> 0.5.
        assert!((g.get(1) - 0.5).abs() < 1e-12);
        // Age 2: only 10-round tasks survive, 8 rounds left -> 1/8.
        assert!((g.get(2) - 0.125).abs() < 1e-12);
        // Age 9: one round left -> 1; beyond the longest task: the last age's index.
        assert!((g.get(9) - 1.0).abs() < 1e-12);
        assert!((g.get(50) - 1.0).abs() < 1e-12);
    }
}
