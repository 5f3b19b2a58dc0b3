//! The demo's workload: the fleet's tasks, and the sizing rule that picks how many robots start
//! and how far apart, from the engine profile measured at start.
//!
//! # Why the fleet is sized from the profile
//!
//! A scheduler only matters when requests wait for the engine: with an idle engine every order
//! is the same order. A fixed fleet contends a slow engine and leaves a fast one mostly idle,
//! where every scheduler and horizon comes out the same. So the demo sizes its fleet from the engine it measured, such that the baseline
//! (FIFO with the static horizon `H`) offers about [`DEFAULT_LOAD`] of what the engine can serve:
//! contended, with a queue that builds, on any machine.
//!
//! # The rule
//!
//! - **Capacity.** At its saturation batch `b*` (the profile's `max_batch`) the engine serves
//!   `μ = b* / L(b*)` requests per second, `L` the profiled latency.
//! - **Actions per round.** With asynchronous inference a robot does not ask once per `H`
//!   actions. It asks when it has executed `⌈trigger · e⌉` of the `e` actions it can execute of a
//!   chunk, and keeps executing while the round is generated; the new chunk's actions for those
//!   steps are then discarded (the SDK runner's rules, `kairos_sdk::robot`). [`round_cycle`]
//!   follows these rules to a steady state: from `H/2` actions per round when answers are
//!   instant to about `H/(2 − trigger)` when each answer arrives as the robot runs out (5 to
//!   6.7 for `H = 10`), so a robot sends `1.5–2×` as many requests as `actions / H`.
//! - **The rate the rule counts** is the one at which FIFO's robots ask when the queue delays
//!   each answer up to the moment its robot runs out of actions ([`sizing_cycle`]), or when the
//!   engine alone takes longer than that, the one at `L(b*)`. A faster answer makes the robots
//!   ask more often, so on an engine much faster than the robots' slack the fleet offers more
//!   than the target until the queue builds to about that slack: the queue builds on any
//!   engine, and FIFO's robots are on the edge of stalling. Counting the rate at `L(b*)`
//!   instead would let a fast engine absorb the fleet with a short queue, where the order of a
//!   few requests decides nothing.
//! - **Work per task.** A task of `n` actions (log-normal around `task_s · control_hz`, see
//!   [`fleet`]) takes `n / (actions per round)` rounds; [`mean_task_actions`] is the
//!   distribution's mean.
//! - **Arrivals.** Robots start as a Poisson process with mean gap `s`. In steady state the
//!   fleet offers `rounds per task / s` requests per second, so `s = rounds per task / (load · μ)`
//!   (the same as Little's law: `task time / s` robots at once, each asking once per cycle).
//! - **Fleet.** Enough robots to keep arriving for [`ARRIVAL_WINDOW_TASKS`] mean task times:
//!   `robots = ⌈window / s⌉`, i.e. that many times as many robots as run at once, at most
//!   [`MAX_ROBOTS`]. The window is counted in tasks, so a fast engine gets more robots, not a
//!   longer run.
//! - **Calibration.** The seed draws the fleet's tasks and gaps; with a few dozen robots they
//!   stray from their means, so the stagger is scaled such that this fleet's rounds over the
//!   span its robots arrive in are exactly the target load.
//!
//! `--robots` and `--stagger-s` each replace their own half of the rule; [`FleetSizing::load`]
//! is then what the fleet given offers. The dynamic horizon asks less often than the static one,
//! so under it the same fleet contends the engine less: that difference is what the demo shows.

use std::time::Duration;

use kairos_engine::EngineProfile;
use rand::{Rng, SeedableRng, rngs::StdRng};
use rand_distr::StandardNormal;

use super::DemoOptions;

/// The share of the engine's capacity the baseline fleet offers, by default.
pub const DEFAULT_LOAD: f64 = 0.9;
/// Robots keep starting for this many mean task times (a task's actions and its robot's waits
/// for chunks, every round taking the engine's latency at its saturation batch): long enough
/// for the queue to build, short enough for the four runs to take about a minute.
pub const ARRIVAL_WINDOW_TASKS: f64 = 3.5;
/// The largest fleet the rule picks (the command line's bound on `--robots`).
pub const MAX_ROBOTS: u32 = 1024;
/// The runner's trigger: the next request goes out when half of a chunk's executable actions
/// have run (LeRobot's `chunk_size_threshold`).
pub const TRIGGER: f64 = 0.5;
/// Spread of the task lengths: `σ` of their logarithm.
const TASK_SIGMA: f64 = 0.5;
/// Task lengths are clamped to this range, in median task lengths.
const TASK_RANGE: (f64, f64) = (0.25, 3.0);

/// One robot's task in the fleet.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FleetTask {
    /// When the robot starts, from the run's start.
    pub start: Duration,
    /// Actions the task takes.
    pub actions: u64,
}

/// Actions of a task whose standard-normal draw is `z`, for a median of `median` actions.
fn task_actions(median: f64, z: f64) -> u64 {
    let actions =
        (median * (TASK_SIGMA * z).exp()).clamp(TASK_RANGE.0 * median, TASK_RANGE.1 * median);
    (actions.round() as u64).max(1)
}

/// What the seed draws for each robot, in fleet order: its task's length in actions, and the gap
/// to the next robot's start in mean gaps (a standard exponential).
fn draws(args: &DemoOptions, robots: u32) -> Vec<(u64, f64)> {
    let mut rng = StdRng::seed_from_u64(args.seed);
    let median = args.task_s * args.control_hz;
    (0..robots)
        .map(|_| {
            let z: f64 = rng.sample(StandardNormal);
            let u: f64 = rng.random();
            (task_actions(median, z), -(1.0 - u).ln())
        })
        .collect()
}

/// The fleet every scheduler sees: `sizing.robots` robots with Poisson start times (mean gap
/// `sizing.stagger_s`) and log-normal task lengths (median `task_s` seconds of actions, `σ =
/// 0.5`, within 0.25x–3x), all from `args.seed`. The `i`-th task's length depends only on the
/// seed, not on the fleet's size or stagger.
pub fn fleet(args: &DemoOptions, sizing: &FleetSizing) -> Vec<FleetTask> {
    let mut at = 0.0f64;
    draws(args, sizing.robots)
        .into_iter()
        .map(|(actions, gap)| {
            let task = FleetTask {
                // `at` is a sum of finite, non-negative gaps; past the end of time it saturates.
                start: Duration::try_from_secs_f64(at).unwrap_or(Duration::MAX),
                actions,
            };
            at += gap * sizing.stagger_s;
            task
        })
        .collect()
}

/// The mean of [`fleet`]'s task lengths, in actions, for a median of `median` actions: the
/// clamped, rounded log-normal integrated over the normal density (Simpson's rule on `[-8, 8]`).
pub fn mean_task_actions(median: f64) -> f64 {
    const STEPS: usize = 4000;
    let (a, b) = (-8.0f64, 8.0f64);
    let h = (b - a) / STEPS as f64;
    let f = |z: f64| task_actions(median, z) as f64 * (-0.5 * z * z).exp();
    let inner: f64 = (1..STEPS)
        .map(|i| f(a + i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 })
        .sum();
    (f(a) + inner + f(b)) * h / 3.0 / (2.0 * std::f64::consts::PI).sqrt()
}

/// A robot's round in steady state, when every round trip takes the same time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoundCycle {
    /// Actions executed per round (task progress per request).
    pub actions: f64,
    /// Seconds from one request to the next (idle time included).
    pub seconds: f64,
}

/// The steady state of the runner's rules for a robot at `control_hz` executing `h` actions of
/// each chunk and asking at `trigger`, when every round trip takes `latency_s`: a chunk arrives
/// with the actions executed since its request discarded (`d`), the robot executes `⌈trigger ·
/// (h − d)⌉` of the rest and asks, then executes what is left while the round trip lasts, or
/// idles. Averaged over 64 rounds after 8 to settle (the map can alternate between two states).
pub fn round_cycle(h: u32, trigger: f64, control_hz: f64, latency_s: f64) -> RoundCycle {
    let h = f64::from(h.max(1));
    let during_round_trip = latency_s.max(0.0) * control_hz;
    let (mut discarded, mut actions, mut seconds) = (0.0f64, 0.0f64, 0.0f64);
    for round in 0..72 {
        let executable = (h - discarded).max(1.0);
        let to_trigger = (trigger.clamp(0.0, 1.0) * executable).ceil().max(1.0);
        let left = (executable - to_trigger).max(0.0);
        let executed = during_round_trip.min(left);
        if round >= 8 {
            actions += to_trigger + executed;
            seconds += to_trigger / control_hz + latency_s.max(0.0);
        }
        discarded = executed;
    }
    RoundCycle {
        actions: actions / 64.0,
        seconds: seconds / 64.0,
    }
}

/// The round the sizing rule counts for a robot executing `h` actions of each chunk, when the
/// engine alone takes `latency_s`: each answer arriving as the robot runs out of actions (the
/// slowest the robot asks without stalling), or at `latency_s` when that is later.
pub fn sizing_cycle(h: u32, trigger: f64, control_hz: f64, latency_s: f64) -> RoundCycle {
    // A round trip of a whole chunk's time outlasts whatever the robot has left.
    let dry = round_cycle(h, trigger, control_hz, f64::from(h.max(1)) / control_hz);
    let engine = round_cycle(h, trigger, control_hz, latency_s);
    RoundCycle {
        actions: dry.actions,
        seconds: (dry.actions / control_hz).max(engine.seconds),
    }
}

/// How the fleet was sized, and what it offers the engine.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FleetSizing {
    /// Robots in the fleet.
    pub robots: u32,
    /// Mean gap between robot starts, seconds (the Poisson process's; the fleet's own gaps,
    /// drawn from the seed, are what the calibration counts).
    pub stagger_s: f64,
    /// Whether `robots` came from the rule (not `--robots`).
    pub auto_robots: bool,
    /// Whether `stagger_s` came from the rule (not `--stagger-s`).
    pub auto_stagger: bool,
    /// The saturation batch `b*` the capacity is counted at.
    pub batch: u32,
    /// Requests per second the engine serves at `b*`.
    pub capacity_rps: f64,
    /// A baseline robot's round as the rule counts it ([`sizing_cycle`]).
    pub cycle: RoundCycle,
    /// Mean rounds per task of the fleet under the baseline.
    pub rounds_per_task: f64,
    /// Robots running at once in steady state (Little's law, at most `robots`).
    pub concurrent: f64,
    /// Requests per second the baseline fleet offers in steady state.
    pub offered_rps: f64,
    /// `offered_rps / capacity_rps`.
    pub load: f64,
}

/// The sizing rule of the module docs: `args.robots` / `args.stagger_s` where given, the rest
/// such that the baseline offers `args.load` of the engine's capacity at its saturation batch.
///
/// The stagger is calibrated on the fleet the seed draws rather than on the distribution: with
/// a few dozen robots, one seed's tasks and gaps can stray 20% from their means, and the rule
/// is about the fleet that runs. So `load` is exactly the target when both halves are sized,
/// counted as the rounds the fleet's tasks bring over the span its robots arrive in.
pub fn size_fleet(profile: &EngineProfile, args: &DemoOptions) -> FleetSizing {
    let batch = profile.max_batch.max(1);
    let latency_s = profile.latency(batch).as_secs_f64();
    // A profile of zero latency (none is measured so) would make the capacity infinite; a
    // microsecond keeps every ratio finite.
    let capacity_rps = f64::from(batch) / latency_s.max(1e-6);
    let cycle = sizing_cycle(args.static_h, TRIGGER, args.control_hz, latency_s);
    let actions_per_round = cycle.actions.max(1e-9);
    let per_robot_rps = 1.0 / cycle.seconds.max(1e-9);
    let target_rps = (args.load * capacity_rps).max(1e-9);
    // The fleet's size from the distribution's mean task: robots keep arriving for
    // `ARRIVAL_WINDOW_TASKS` mean task times, i.e. that many times as many robots as run at once.
    let mean_rounds = mean_task_actions(args.task_s * args.control_hz) / actions_per_round;
    let task_seconds = mean_rounds * cycle.seconds;
    let robots = match (args.robots, args.stagger_s) {
        (Some(n), _) => f64::from(n),
        // All at once: as many robots as offer the load together.
        (None, Some(s)) if s <= 0.0 => (target_rps / per_robot_rps).ceil(),
        (None, s) => {
            (ARRIVAL_WINDOW_TASKS * task_seconds / s.unwrap_or(mean_rounds / target_rps)).ceil()
        }
    }
    .clamp(1.0, f64::from(MAX_ROBOTS)) as u32;
    let drawn = draws(args, robots);
    let rounds_per_task = drawn
        .iter()
        .map(|&(actions, _)| actions as f64 / actions_per_round)
        .sum::<f64>()
        / f64::from(robots);
    // The span the robots arrive in, in mean gaps: `n` starts, `n − 1` gaps.
    let span_gaps: f64 = drawn[..drawn.len() - 1].iter().map(|&(_, gap)| gap).sum();
    let stagger_s = match args.stagger_s {
        Some(s) => s,
        // One robot has no span: the distribution's rule.
        None if robots < 2 => mean_rounds / target_rps,
        None => rounds_per_task * f64::from(robots - 1) / (span_gaps * target_rps),
    };
    let arrivals_per_s = if robots >= 2 && stagger_s > 0.0 {
        f64::from(robots - 1) / (span_gaps * stagger_s)
    } else if stagger_s > 0.0 {
        1.0 / stagger_s
    } else {
        f64::INFINITY
    };
    // Little's law, bounded by the fleet.
    let concurrent = (rounds_per_task * cycle.seconds * arrivals_per_s).min(f64::from(robots));
    let offered_rps = concurrent * per_robot_rps;
    FleetSizing {
        robots,
        stagger_s,
        auto_robots: args.robots.is_none(),
        auto_stagger: args.stagger_s.is_none(),
        batch,
        capacity_rps,
        cycle,
        rounds_per_task,
        concurrent,
        offered_rps,
        load: offered_rps / capacity_rps,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kairos_engine::ProfilePoint;

    /// A profile whose batch of `b` takes `base_ms · (1 + 0.5 (b − 1))`, saturating at 8.
    fn profile(base_ms: f64) -> EngineProfile {
        EngineProfile {
            model: "test".into(),
            device: "test".into(),
            points: [1, 2, 4, 8]
                .map(|b| ProfilePoint {
                    batch: b,
                    latency_ms: base_ms * (1.0 + 0.5 * f64::from(b - 1)),
                })
                .to_vec(),
            max_batch: 8,
        }
    }

    /// The fleet's offered load computed from the fleet itself: every task's rounds over the
    /// arrival span, against the capacity.
    fn realised_load(args: &DemoOptions, sizing: &FleetSizing) -> f64 {
        let tasks = fleet(args, sizing);
        let rounds: f64 = tasks
            .iter()
            .map(|t| t.actions as f64 / sizing.cycle.actions)
            .sum();
        let span = tasks.last().unwrap().start.as_secs_f64();
        // `n` arrivals over `n − 1` gaps: the rate is `(n − 1) / span`.
        let per_task = rounds / tasks.len() as f64;
        per_task * (tasks.len() - 1) as f64 / span / sizing.capacity_rps
    }

    #[test]
    fn the_auto_sized_fleet_offers_the_target_share_of_the_capacity() {
        let args = DemoOptions::default();
        let p = profile(20.0);
        let sizing = size_fleet(&p, &args);
        assert!(sizing.auto_robots && sizing.auto_stagger);
        assert!((sizing.load - DEFAULT_LOAD).abs() < 1e-9, "{sizing:?}");
        // Capacity at the saturation batch: 8 / 90 ms.
        assert!((sizing.capacity_rps - 8.0 / 0.090).abs() < 1e-6);
        // More robots than run at once: the arrivals reach a steady state.
        assert!(
            f64::from(sizing.robots) > 2.0 * sizing.concurrent,
            "{sizing:?}"
        );
        // The fleet drawn from the seed offers about the same load, however fast the engine.
        for base_ms in [1.0, 3.0, 10.0, 20.0, 60.0, 200.0] {
            for args in [args.clone(), args.clone().resolve_quick(Some("1".as_ref()))] {
                let sizing = size_fleet(&profile(base_ms), &args);
                let realised = realised_load(&args, &sizing);
                assert!(
                    (realised - DEFAULT_LOAD).abs() < 1e-6,
                    "{base_ms} ms: {realised} {sizing:?}"
                );
            }
        }
    }

    #[test]
    fn a_faster_engine_gets_more_robots_arriving_faster() {
        let args = DemoOptions::default();
        let slow = size_fleet(&profile(40.0), &args);
        let fast = size_fleet(&profile(10.0), &args);
        assert!(fast.robots > 2 * slow.robots, "{fast:?} vs {slow:?}");
        assert!(fast.stagger_s < slow.stagger_s / 2.0);
        assert!(fast.concurrent > 2.0 * slow.concurrent);
        for s in [slow, fast] {
            assert!((s.load - DEFAULT_LOAD).abs() < 0.01, "{s:?}");
        }
        // The arrival window is counted in tasks: as many times as many robots as run at once.
        for s in [slow, fast] {
            let ratio = f64::from(s.robots) / s.concurrent;
            assert!((ratio - ARRIVAL_WINDOW_TASKS).abs() < 0.5, "{ratio} {s:?}");
        }
    }

    #[test]
    fn the_target_load_scales_the_arrival_rate() {
        let p = profile(20.0);
        let half = size_fleet(
            &p,
            &DemoOptions {
                load: 0.45,
                ..DemoOptions::default()
            },
        );
        let full = size_fleet(&p, &DemoOptions::default());
        assert!((half.load - 0.45).abs() < 1e-9, "{half:?}");
        assert!(
            half.robots.abs_diff(full.robots / 2) <= 1,
            "{half:?} {full:?}"
        );
        assert!(half.stagger_s > 1.5 * full.stagger_s, "{half:?} {full:?}");
    }

    #[test]
    fn overrides_win_and_the_load_is_what_they_offer() {
        let p = profile(20.0);
        let auto = size_fleet(&p, &DemoOptions::default());
        let robots = size_fleet(
            &p,
            &DemoOptions {
                robots: Some(5),
                ..DemoOptions::default()
            },
        );
        assert_eq!(robots.robots, 5);
        assert!(!robots.auto_robots && robots.auto_stagger);
        assert!(robots.concurrent <= 5.0);
        assert!(robots.load < auto.load, "5 robots cannot offer 90%");
        let stagger = size_fleet(
            &p,
            &DemoOptions {
                stagger_s: Some(auto.stagger_s * 2.0),
                ..DemoOptions::default()
            },
        );
        assert!(stagger.auto_robots && !stagger.auto_stagger);
        assert_eq!(stagger.stagger_s, auto.stagger_s * 2.0);
        assert!(
            (stagger.load / auto.load - 0.5).abs() < 0.15,
            "twice the gap, about half the load: {stagger:?}"
        );
        let both = size_fleet(
            &p,
            &DemoOptions {
                robots: Some(3),
                stagger_s: Some(0.0),
                ..DemoOptions::default()
            },
        );
        assert_eq!((both.robots, both.stagger_s), (3, 0.0));
        assert_eq!(both.concurrent, 3.0);
        // All at once with the robots left to the rule: as many as offer the load.
        let burst = size_fleet(
            &p,
            &DemoOptions {
                stagger_s: Some(0.0),
                ..DemoOptions::default()
            },
        );
        assert!(
            burst.load >= DEFAULT_LOAD && burst.load < DEFAULT_LOAD * 1.2,
            "{burst:?}"
        );
    }

    #[test]
    fn a_round_executes_half_a_chunk_plus_what_runs_during_the_round_trip() {
        // No latency: ask at 5 of 10, the chunk arrives at once, nothing discarded.
        let instant = round_cycle(10, 0.5, 30.0, 0.0);
        assert_eq!(instant.actions, 5.0);
        assert!((instant.seconds - 5.0 / 30.0).abs() < 1e-12);
        // A round trip of 2 actions: 2 discarded, ask at ⌈4⌉ of 8, 2 more run meanwhile.
        let short = round_cycle(10, 0.5, 30.0, 2.0 / 30.0);
        assert!((short.actions - 6.0).abs() < 1e-9, "{short:?}");
        assert!(
            (short.seconds - short.actions / 30.0).abs() < 1e-9,
            "no idling"
        );
        // A round trip longer than what is left: the robot idles, progress is capped.
        let long = round_cycle(10, 0.5, 30.0, 1.0);
        assert!((6.0..=7.0).contains(&long.actions), "{long:?}");
        assert!(long.seconds > long.actions / 30.0 + 0.5, "it idles");
        // A longer horizon asks less often.
        assert!(
            round_cycle(40, 0.5, 30.0, 0.1).seconds > 2.5 * round_cycle(10, 0.5, 30.0, 0.1).seconds
        );
    }

    #[test]
    fn the_rule_counts_the_rate_of_robots_answered_as_they_run_out() {
        // An engine far faster than the robot's slack: the rate of a robot answered just in
        // time, slower than that of one answered at once.
        let fast = sizing_cycle(10, 0.5, 30.0, 0.01);
        let dry = round_cycle(10, 0.5, 30.0, 10.0);
        assert_eq!(fast.actions, dry.actions);
        assert!(
            (fast.seconds - dry.actions / 30.0).abs() < 1e-12,
            "no idling counted"
        );
        assert!(fast.seconds > round_cycle(10, 0.5, 30.0, 0.01).seconds);
        // An engine slower than the slack: its own latency sets the pace.
        let slow = sizing_cycle(10, 0.5, 30.0, 0.5);
        assert_eq!(slow, round_cycle(10, 0.5, 30.0, 0.5));
        assert!(slow.seconds > fast.seconds);
    }

    #[test]
    fn the_mean_task_length_matches_the_drawn_fleet() {
        let median = 90.0;
        let mean = mean_task_actions(median);
        // The log-normal mean, `median · e^{σ²/2}`, barely moved by the clamp.
        assert!(
            (mean / (median * (0.125f64).exp()) - 1.0).abs() < 0.01,
            "{mean}"
        );
        let args = DemoOptions::default();
        let many = FleetSizing {
            robots: 20_000,
            stagger_s: 0.0,
            ..size_fleet(&profile(20.0), &args)
        };
        let drawn = fleet(&args, &many);
        let sample = drawn.iter().map(|t| t.actions as f64).sum::<f64>() / drawn.len() as f64;
        assert!((sample / mean - 1.0).abs() < 0.02, "{sample} vs {mean}");
    }

    #[test]
    fn the_fleet_is_a_function_of_the_seed() {
        let args = DemoOptions::default();
        let sizing = size_fleet(&profile(20.0), &args);
        let a = fleet(&args, &sizing);
        assert_eq!(a, fleet(&args, &sizing));
        assert_eq!(a.len(), sizing.robots as usize);
        assert_eq!(a[0].start, Duration::ZERO);
        assert!(a.windows(2).all(|w| w[0].start <= w[1].start));
        let median = args.task_s * args.control_hz;
        assert!(a.iter().all(|t| {
            let x = t.actions as f64;
            x >= (0.25 * median).floor() && x <= (3.0 * median).ceil()
        }));
        let other = fleet(
            &DemoOptions {
                seed: 8,
                ..DemoOptions::default()
            },
            &sizing,
        );
        assert_ne!(a, other);
        // Task lengths do not depend on the fleet's size or stagger.
        let smaller = FleetSizing {
            robots: 5,
            stagger_s: 1.0,
            ..sizing
        };
        let b = fleet(&args, &smaller);
        assert!(b.iter().zip(&a).all(|(x, y)| x.actions == y.actions));
    }
}
