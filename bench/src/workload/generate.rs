//! Workload → trace set: synthetic tasks "recorded" in isolation, deterministically per seed.
//!
//! Each task is a trajectory of `T` actions (log-normal length) cut into phases; each phase has
//! a ratio `ρ` drawn from the workload's `ratio_cdf`, the factor by which the threshold policy's
//! horizon exceeds the static one while the robot is in that phase (paper Fig. "horizon_cdf").
//! The task is then run alone — one robot, an idle edge engine at batch 1, the workload's network
//! — once per horizon setting, with the robot following the shared execution rule
//! ([`crate::sim::robot`]) and the SDK's trigger rule, and the real horizon policies choosing `H`
//! from the per-round confidence vector. What the robot saw is the trace.
//!
//! The two settings of one task share its trajectory, so replaying them compares the same work
//! under different horizons, as the paper's ablations require.

use std::collections::BTreeMap;
use std::time::Duration;

use kairos_sdk::trace::{
    HorizonSetting, RoundTrace, TaskTrace, TraceHeader, TraceSet, TraceSource,
};
use rand::{Rng, SeedableRng, rngs::StdRng};
use rand_distr::StandardNormal;

use super::{Workload, inverse_cdf};
use crate::sim::horizon::{ReplayHorizon, ReplayHorizonError, confidence_for_target};
use crate::sim::robot::{Accepted, Execution};
use kairos_core::registry::HorizonRegistry;
use kairos_core::time::{Timestamp, duration_micros};

/// Setting label of the baselines' static horizon.
pub const STATIC: &str = "static";
/// Setting label of Kairos's threshold (dynamic) horizon.
pub const DYNAMIC: &str = "dynamic";

/// Why a trace set could not be generated.
#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    /// A horizon policy failed on a generated chunk.
    #[error("task {task}: a horizon policy failed")]
    Horizon {
        /// The task.
        task: u64,
        /// The failure.
        source: ReplayHorizonError,
    },
    /// The isolated run did not finish (a bug in the generator or an absurd workload).
    #[error("task {task}: isolated run did not finish within {rounds} rounds")]
    Runaway {
        /// The task.
        task: u64,
        /// Rounds tried.
        rounds: usize,
    },
    /// The generated trace is invalid.
    #[error(transparent)]
    Trace(#[from] kairos_sdk::trace::TraceError),
}

/// The two horizon settings of a workload, as trace settings.
pub fn settings(w: &Workload) -> [(String, HorizonSetting); 2] {
    [
        (
            STATIC.to_string(),
            HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), f64::from(w.horizon.static_h))]),
            },
        ),
        (
            DYNAMIC.to_string(),
            HorizonSetting {
                policy: "threshold".into(),
                params: BTreeMap::from([
                    ("t".to_string(), w.horizon.threshold),
                    ("h_min".to_string(), f64::from(w.horizon.h_min)),
                ]),
            },
        ),
    ]
}

/// A task's ground truth before recording: its length and its phases.
#[derive(Clone, Debug, PartialEq)]
struct Trajectory {
    total_actions: u32,
    /// `(first step, ratio)`, sorted by step, the first at step 0.
    phases: Vec<(u32, f64)>,
}

impl Trajectory {
    fn ratio_at(&self, step: u32) -> f64 {
        let i = self.phases.partition_point(|&(s, _)| s <= step);
        self.phases[i.saturating_sub(1)].1
    }
}

/// SplitMix64: independent, well-mixed seeds per task from one run seed.
fn task_seed(seed: u64, task: u64) -> u64 {
    let mut z = seed ^ task.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn trajectory(w: &Workload, rng: &mut StdRng) -> Trajectory {
    let hz = f64::from(w.robot.control_hz);
    let z: f64 = rng.sample(StandardNormal);
    let secs = (w.tasks.median_s * (w.tasks.sigma * z).exp()).clamp(w.tasks.min_s, w.tasks.max_s);
    let total_actions = ((secs * hz).round() as u32).max(1);
    let mut phases = Vec::new();
    let mut step = 0u32;
    // `ratio_cdf` is per round, as in the paper's figure, but phases are drawn per unit of
    // time and a phase with ratio ρ holds 1/ρ as many rounds per second: draw length-biased
    // (accept ρ with probability ρ/ρ_max) so that the rounds follow the CDF.
    let max_ratio = w.horizon.ratio_cdf.last().map_or(1.0, |p| p[0]);
    while step < total_actions {
        let ratio = loop {
            let r = inverse_cdf(&w.horizon.ratio_cdf, rng.random::<f64>());
            if rng.random::<f64>() * max_ratio <= r {
                break r;
            }
        };
        phases.push((step, ratio));
        let u: f64 = rng.random::<f64>();
        let len = -(1.0 - u).ln() * w.horizon.phase_mean_s * hz;
        step = step.saturating_add((len.round() as u32).max(1));
    }
    Trajectory {
        total_actions,
        phases,
    }
}

/// The horizon the threshold policy should pick at `step`: the static one scaled by the phase's
/// ratio, within `[h_min, chunk_len]`.
fn target_horizon(w: &Workload, traj: &Trajectory, step: u32) -> u32 {
    let h = (f64::from(w.horizon.static_h) * traj.ratio_at(step)).round() as u32;
    h.clamp(w.horizon.h_min, w.robot.chunk_len)
}

/// Bytes/s → time to push `bytes`.
pub(crate) fn transfer_time(bytes: u32, mbps: f64) -> Duration {
    // A workload's bandwidth is checked positive and finite; anything else saturates.
    Duration::try_from_secs_f64(f64::from(bytes) * 8.0 / (mbps * 1e6)).unwrap_or(Duration::MAX)
}

/// When the reply to a request sent at `sent` reaches the robot in isolation: half the round
/// trip up plus the observation on the uplink, the forward pass at batch 1 on an idle edge engine,
/// half the round trip back. Added up in the order the simulator adds them (each sum rounds to
/// whole microseconds), so that replaying a task alone reproduces its recording exactly.
pub fn isolated_reply_at(w: &Workload, sent: Timestamp) -> Timestamp {
    let one_way = w.robot_rtt() / 2;
    sent + one_way
        + transfer_time(w.robot.obs_bytes, w.network.robot_uplink_mbps)
        + w.edge_profile().latency(1)
        + one_way
}

/// Actions of a chunk with `executable` actions to start before the next request goes out: the
/// SDK's `ChunkExecutor` trigger point, `ceil(trigger · executable)` computed in `f32` as there.
pub fn trigger_point(executable: u32, trigger_fraction: f64) -> u32 {
    ((trigger_fraction as f32) * executable as f32).ceil() as u32
}

fn record(
    w: &Workload,
    task: u64,
    traj: &Trajectory,
    label: &str,
    setting: &HorizonSetting,
    horizons: &HorizonRegistry,
) -> Result<TaskTrace, GenerateError> {
    let n = w.robot.chunk_len;
    let hz = w.robot.control_hz;
    let generation = w.edge_profile().latency(1);
    let mut horizon = ReplayHorizon::with_registry(setting, horizons)
        .map_err(|source| GenerateError::Horizon { task, source })?;
    let dynamic = setting.policy != "static";
    let mut exec = Execution::new(hz);
    let mut rounds: Vec<RoundTrace> = Vec::new();
    // Step from which each round's chunk ran (None: dropped as stale).
    let mut ran_from: Vec<Option<u32>> = Vec::new();
    let mut now = Timestamp::ZERO;
    let max_rounds = traj.total_actions as usize + 2;
    loop {
        if rounds.len() > max_rounds {
            return Err(GenerateError::Runaway {
                task,
                rounds: rounds.len(),
            });
        }
        let obs_step = exec.started_at(now);
        let reply_at = isolated_reply_at(w, now);
        let target = target_horizon(w, traj, obs_step);
        let mut round = RoundTrace {
            aligned_at_action: None,
            issued_at_action: obs_step,
            horizon: 0,
            executed: 0,
            gen_latency_us: duration_micros(generation),
            round_trip_us: Some(duration_micros(reply_at.saturating_since(now))),
            obs_bytes: w.robot.obs_bytes,
            confidence: Some(confidence_for_target(target, w.horizon.threshold, n)),
        };
        round.horizon = horizon
            .choose(&round, rounds.len() as u64, n, hz)
            .map_err(|source| GenerateError::Horizon { task, source })?;
        if !dynamic {
            round.confidence = None;
        }
        let accepted = exec.accept(reply_at, obs_step, round.horizon);
        ran_from.push(match accepted {
            Accepted::Used { from_step, .. } => Some(from_step),
            Accepted::Stale => None,
        });
        rounds.push(round);
        if exec.until() >= traj.total_actions {
            break;
        }
        // The SDK trigger: once `ceil(trigger · executable)` actions of the new chunk have
        // started (at once for a stale chunk). Never before the chunk arrived.
        now = match accepted {
            Accepted::Used { from_step, .. } => {
                let executable = exec.until() - from_step;
                let count = from_step + trigger_point(executable, w.robot.trigger_fraction);
                exec.reaches(count).map_or(reply_at, |t| t.max(reply_at))
            }
            Accepted::Stale => reply_at,
        };
    }
    // Executed actions per chunk: from where it took over to where the next used one did.
    let mut end = traj.total_actions;
    for (round, from) in rounds.iter_mut().zip(&ran_from).rev() {
        if let Some(from) = *from {
            round.executed = end.saturating_sub(from).min(round.horizon);
            end = from;
        }
    }
    let trace = TaskTrace {
        task,
        label: Some(label.to_string()),
        setting: String::new(),
        horizon: setting.clone(),
        control_hz: hz,
        chunk_len: n,
        total_actions: traj.total_actions,
        rounds,
    };
    Ok(trace)
}

/// Generates `w.tasks.pool` tasks, each recorded under both settings (static first), with
/// `seed`. Same workload and seed, same trace set.
pub fn generate(w: &Workload, seed: u64) -> Result<TraceSet, GenerateError> {
    generate_settings(w, seed, &settings(w), &HorizonRegistry::natives())
}

/// Generates `w.tasks.pool` tasks, each recorded under every one of `settings` (in order), whose
/// horizon policies are resolved in `horizons`: [`generate`] with other settings, e.g. a user's
/// horizon plugin beside the workload's two (`kairos bench sim --horizon-plugin`). A task's
/// ground truth depends on the seed only, so its recording under a setting is the same whatever
/// other settings are generated beside it.
pub fn generate_settings(
    w: &Workload,
    seed: u64,
    settings: &[(String, HorizonSetting)],
    horizons: &HorizonRegistry,
) -> Result<TraceSet, GenerateError> {
    let mut header = TraceHeader::new(TraceSource::Generated);
    header.workload = Some(w.name.clone());
    header.seed = Some(seed);
    let mut tasks = Vec::with_capacity(w.tasks.pool * settings.len());
    for task in 0..w.tasks.pool as u64 {
        let mut rng = StdRng::seed_from_u64(task_seed(seed, task));
        let traj = trajectory(w, &mut rng);
        let label = format!("{}/{task}", w.name);
        for (name, setting) in settings {
            let mut t = record(w, task, &traj, &label, setting, horizons)?;
            t.setting = name.clone();
            t.validate()?;
            tasks.push(t);
        }
    }
    Ok(TraceSet { header, tasks })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::workload::tests_support::tiny;

    #[test]
    fn same_seed_same_traces_other_seed_other_traces() {
        let w = tiny();
        let a = generate(&w, 7).unwrap();
        let b = generate(&w, 7).unwrap();
        let c = generate(&w, 8).unwrap();
        assert_eq!(a, b);
        assert_ne!(a.tasks, c.tasks);
        assert_eq!(a.tasks.len(), 2 * w.tasks.pool);
    }

    #[test]
    fn both_settings_of_a_task_share_its_length_and_dynamic_needs_fewer_rounds() {
        let w = tiny();
        let set = generate(&w, 1).unwrap();
        let (mut static_rounds, mut dynamic_rounds) = (0, 0);
        for pair in set.tasks.chunks(2) {
            assert_eq!(pair[0].task, pair[1].task);
            assert_eq!(pair[0].setting, STATIC);
            assert_eq!(pair[1].setting, DYNAMIC);
            assert_eq!(pair[0].total_actions, pair[1].total_actions);
            assert!(
                pair[0]
                    .rounds
                    .iter()
                    .all(|r| r.horizon == w.horizon.static_h)
            );
            assert!(pair[1].rounds.iter().all(|r| r.horizon >= w.horizon.h_min));
            // Every action is executed exactly once.
            for t in pair {
                let executed: u32 = t.rounds.iter().map(|r| r.executed).sum();
                assert_eq!(executed, t.total_actions, "task {} {}", t.task, t.setting);
            }
            static_rounds += pair[0].rounds.len();
            dynamic_rounds += pair[1].rounds.len();
        }
        assert!(
            (dynamic_rounds as f64) < 0.8 * static_rounds as f64,
            "dynamic {dynamic_rounds} vs static {static_rounds}"
        );
    }

    #[test]
    fn dynamic_horizons_follow_the_ratio_cdf() {
        let mut w = tiny();
        w.tasks.pool = 200;
        let set = generate(&w, 3).unwrap();
        let ratios: Vec<f64> = set
            .variant(DYNAMIC)
            .flat_map(|t| t.rounds.iter())
            .map(|r| f64::from(r.horizon) / f64::from(w.horizon.static_h))
            .collect();
        let at_least_2x = ratios.iter().filter(|&&r| r >= 2.0 - 1e-9).count() as f64;
        let share = at_least_2x / ratios.len() as f64;
        // tiny(): P(ratio >= 2) = 0.5 per round (the clamp to chunk_len and rounding blur it).
        assert!(
            (0.4..0.6).contains(&share),
            "share of rounds >= 2x: {share}"
        );
    }
}
