//! What the horizon signals actually correlate with (issue #14 §2): for every action of every
//! chunk a closed-loop run generates, the signals a horizon policy can read at serving time
//! beside how wrong the action turns out to be.
//!
//! The run is static `H` (the bench's episodes, the same noise seeds). At each request the
//! chunk is also rolled out open loop to its end on a copy of the episode — the copy carries the
//! episode's random generator, so it meets the same actuation noise and pushes the robot would
//! meet executing that far — and action `n`'s **error** is its distance to the nearer of the
//! scripted expert's two modes ([`env::expert_action`], either bend side) at the state the
//! rollout reached when `n` would run. That uses the simulator's ground truth: it is an
//! analysis, never an input of a policy.
//!
//! Signals per action `n` (sample 0):
//! - `ratio@k`: the §3.1 statistic reading denoising step `k`, `‖U[k][n]‖ / mean_{j<k} ‖U[j][n]‖`
//!   (`k = K − 1` is the paper's final-step rule);
//! - `final update`: `‖U[K−1][n]‖`;
//! - `jump`: `‖A[n] − A[n−1]‖`, the signal of the `steady` policy (0 for `n = 0`);
//! - `position`: `n`; `noise`: `‖ε_n‖`, the sampler's initial noise of the action.

use std::fmt::Write as _;

use kairos_engine::ActionChunk;

use super::env::{ACTION_DIM, Env, EnvConfig, expert_action};
use super::model::FlowPolicy;
use super::{BenchError, noise_seed};
use kairos_core::horizon::threshold::l2;
use kairos_core::stats::spearman;

/// The signals and the error of one action of one chunk.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionRecord {
    /// `ratio@k` for `k = 1..K` (index `k − 1`).
    pub ratios: Vec<f64>,
    /// `‖U[K−1][n]‖`.
    pub final_update: f64,
    /// `‖A[n] − A[n−1]‖` (0 for the first action).
    pub jump: f64,
    /// The action's index in its chunk.
    pub position: usize,
    /// `‖ε_n‖`.
    pub noise: f64,
    /// Distance to the nearer expert mode at the state the open-loop rollout reached.
    pub error: f64,
    /// Whether the object was held when the chunk was generated (the carry phase).
    pub held: bool,
}

fn distance(a: &[f32], b: &[f32]) -> f64 {
    let mut acc = 0.0f64;
    for (&x, &y) in a.iter().zip(b) {
        let d = f64::from(x) - f64::from(y);
        acc += d * d;
    }
    acc.sqrt()
}

/// The records of one chunk generated in `env` (sample 0), rolled out open loop on a copy
/// (`foresight`: with the episode's own future noise and pushes; otherwise with none).
fn chunk_records(chunk: &ActionChunk, env: &Env, foresight: bool) -> Vec<ActionRecord> {
    let (k, n_len, d) = (chunk.steps, chunk.chunk_len, chunk.action_dim);
    let update = |step: usize, n: usize| {
        let start = (step * n_len + n) * d;
        l2(&chunk.updates[start..start + d])
    };
    let action = |n: usize| &chunk.actions[n * d..(n + 1) * d];
    let mut rollout = if foresight {
        env.clone()
    } else {
        env.without_randomness()
    };
    let held = env.observe()[8] > 0.5;
    let mut out = Vec::with_capacity(n_len);
    for n in 0..n_len {
        if rollout.done() {
            break;
        }
        let obs = rollout.observe();
        let cfg = rollout.config().clone();
        let error = [1.0f32, -1.0]
            .iter()
            .map(|&side| distance(action(n), &expert_action(&obs, &cfg, side)))
            .fold(f64::INFINITY, f64::min);
        let mut ratios = Vec::with_capacity(k.saturating_sub(1));
        let mut sum = 0.0f64;
        for step in 0..k {
            let norm = update(step, n);
            if step > 0 {
                ratios.push(norm / (sum / step as f64));
            }
            sum += norm;
        }
        out.push(ActionRecord {
            ratios,
            final_update: update(k - 1, n),
            jump: if n == 0 {
                0.0
            } else {
                distance(action(n - 1), action(n))
            },
            position: n,
            noise: l2(&chunk.noise[n * d..(n + 1) * d]),
            error,
            held,
        });
        rollout.step(action(n));
    }
    out
}

/// Runs `episodes` episodes from `seed` at static horizon `h` and records every action of
/// every chunk (see the module doc).
pub fn collect(
    model: &FlowPolicy,
    env_cfg: &EnvConfig,
    seed: u64,
    episodes: usize,
    h: usize,
) -> Result<Vec<ActionRecord>, BenchError> {
    let mut records = Vec::new();
    for e in 0..episodes as u64 {
        let mut env = Env::new(env_cfg.clone(), seed + e);
        let mut call = 0u32;
        while !env.done() {
            let chunk = model.sample(&env.observe(), 1, noise_seed(seed + e, call))?;
            call += 1;
            records.extend(chunk_records(&chunk, &env, true));
            for a in chunk
                .sample_actions(0)
                .chunks_exact(ACTION_DIM)
                .take(h.max(1))
            {
                if env.done() {
                    break;
                }
                env.step(a);
            }
        }
    }
    Ok(records)
}

/// The markdown table: Spearman's ρ of every signal with the action's error, its position
/// and its noise, and the mean error by position.
pub fn correlation_table(records: &[ActionRecord]) -> String {
    let column = |f: &dyn Fn(&ActionRecord) -> f64| records.iter().map(f).collect::<Vec<f64>>();
    let error = column(&|r| r.error);
    let position = column(&|r| r.position as f64);
    let noise = column(&|r| r.noise);
    let steps = records.first().map_or(0, |r| r.ratios.len());
    let mut rows: Vec<(String, Vec<f64>)> = (0..steps)
        .map(|i| {
            let name = if i + 1 == steps {
                format!("ratio@{} (final step, §3.1)", i + 1)
            } else {
                format!("ratio@{}", i + 1)
            };
            (
                name,
                column(&|r| r.ratios.get(i).copied().unwrap_or(f64::NAN)),
            )
        })
        .collect();
    rows.push(("final update ‖U[K−1]‖".into(), column(&|r| r.final_update)));
    rows.push(("jump ‖A[n]−A[n−1]‖ (steady)".into(), column(&|r| r.jump)));
    rows.push(("position n".into(), position.clone()));
    let mut s = format!(
        "{} actions. Spearman's ρ of each signal with:\n\n| signal | error | position n | noise ‖ε_n‖ |\n|---|---|---|---|\n",
        records.len()
    );
    for (name, values) in &rows {
        let _ = writeln!(
            s,
            "| {name} | {:+.3} | {:+.3} | {:+.3} |",
            spearman(values, &error),
            spearman(values, &position),
            spearman(values, &noise)
        );
    }
    let max_pos = records.iter().map(|r| r.position).max().unwrap_or(0);
    s.push_str("\nMean error by position in the chunk (what a static horizon pays per extra action):\n\n| n |");
    for n in 0..=max_pos {
        let _ = write!(s, " {n} |");
    }
    s.push_str("\n|---|");
    for _ in 0..=max_pos {
        s.push_str("---|");
    }
    // Phase filter: every action, or only those generated while the object was (not) held.
    let phases = [("all", None), ("reach", Some(false)), ("carry", Some(true))];
    for (label, held) in phases {
        let _ = write!(s, "\n| error, {label} |");
        for n in 0..=max_pos {
            let at: Vec<f64> = records
                .iter()
                .filter(|r| r.position == n && held.is_none_or(|h| r.held == h))
                .map(|r| r.error)
                .collect();
            let _ = write!(
                s,
                " {:.3} |",
                at.iter().sum::<f64>() / at.len().max(1) as f64
            );
        }
    }
    s.push('\n');
    s
}

/// The ground-truth oracle, an upper bound for horizon policies: at each request it rolls the
/// chunk out on a copy of the episode and executes up to the first action whose error exceeds
/// `max_error` (at least one). With `foresight` the copy carries the episode's random
/// generator, so the rollout is exactly what executing the chunk will do, future pushes and
/// noise included; without, the copy has no future randomness
/// ([`Env::without_randomness`]): the oracle then knows the true state and which of the
/// chunk's actions are wrong, but not the future — the most a perfect reader of this model's
/// chunks could know. No serving-time policy sees either.
pub fn oracle_episode(
    model: &FlowPolicy,
    env_cfg: &EnvConfig,
    seed: u64,
    max_error: f64,
    foresight: bool,
) -> Result<super::Episode, BenchError> {
    let mut env = Env::new(env_cfg.clone(), seed);
    let mut out = super::Episode::default();
    while !env.done() {
        let chunk = model.sample(&env.observe(), 1, noise_seed(seed, out.calls))?;
        out.calls += 1;
        let records = chunk_records(&chunk, &env, foresight);
        let h = records
            .iter()
            .position(|r| r.error.is_nan() || r.error > max_error)
            .unwrap_or(records.len())
            .max(1);
        out.horizon_sum += h as u64;
        for a in chunk.sample_actions(0).chunks_exact(ACTION_DIM).take(h) {
            if env.done() {
                break;
            }
            env.step(a);
        }
    }
    out.success = env.success();
    out.steps = env.steps();
    Ok(out)
}

/// [`oracle_episode`] over `episodes` episodes from `seed` on `threads` threads, summarised as
/// the point `oracle` (with foresight) or `oracle-nominal` (without).
pub fn oracle_point(
    model: &FlowPolicy,
    env_cfg: &EnvConfig,
    (seed, episodes, threads): (u64, usize, usize),
    max_error: f64,
    foresight: bool,
) -> Result<super::PointResult, BenchError> {
    let threads = threads.clamp(1, episodes.max(1));
    let chunks: Vec<Result<Vec<super::Episode>, BenchError>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|t| {
                scope.spawn(move || {
                    (t..episodes)
                        .step_by(threads)
                        .map(|e| {
                            oracle_episode(model, env_cfg, seed + e as u64, max_error, foresight)
                        })
                        .collect::<Result<Vec<_>, _>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(BenchError::Setup("an oracle thread panicked".into())))
            })
            .collect()
    });
    let mut all = Vec::with_capacity(episodes);
    for c in chunks {
        all.extend(c?);
    }
    let family = if foresight {
        "oracle"
    } else {
        "oracle-nominal"
    };
    Ok(super::summarize(
        &super::PolicyPoint::new(family, &[("max_error", max_error)]),
        &all,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chunk of the expert's own actions along the nominal (randomness-free) future of `env`.
    fn expert_chunk(env: &Env, n: usize) -> ActionChunk {
        let mut nominal = env.without_randomness();
        let mut actions = Vec::with_capacity(n * ACTION_DIM);
        for _ in 0..n {
            let a = expert_action(&nominal.observe(), nominal.config(), 1.0);
            actions.extend_from_slice(&a);
            nominal.step(&a);
        }
        ActionChunk {
            samples: 1,
            steps: 2,
            chunk_len: n,
            action_dim: ACTION_DIM,
            updates: vec![1.0; 2 * n * ACTION_DIM],
            noise: vec![0.5; n * ACTION_DIM],
            actions,
        }
    }

    #[test]
    fn the_experts_own_chunk_has_no_error_without_foresight_and_some_with_it() {
        let env = Env::new(EnvConfig::default(), 4);
        let chunk = expert_chunk(&env, 12);
        let nominal = chunk_records(&chunk, &env, false);
        assert_eq!(nominal.len(), 12);
        assert!(nominal.iter().all(|r| r.error == 0.0), "{nominal:?}");
        assert!(
            nominal
                .iter()
                .all(|r| r.ratios == [1.0] && r.final_update > 0.0)
        );
        assert_eq!(nominal[0].jump, 0.0);
        let jump3 = distance(&chunk.actions[6..9], &chunk.actions[9..12]);
        assert_eq!(nominal[3].jump, jump3);
        // The real future has actuation noise, so the plan drifts off what the expert would do.
        let real = chunk_records(&chunk, &env, true);
        assert_eq!(real[0].error, 0.0, "the first action sees the present");
        assert!(real.iter().any(|r| r.error > 0.0));
        let table = correlation_table(&real);
        let row = table
            .lines()
            .find(|l| l.starts_with("| position n |"))
            .unwrap_or_default();
        assert!(
            row.contains("| +1.000 |"),
            "ρ(position, position) = 1: {table}"
        );
    }
}
