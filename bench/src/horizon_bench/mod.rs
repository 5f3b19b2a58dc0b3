//! `kairos bench horizon`: horizon policies judged in closed loop, by task success.
//!
//! A latency replay cannot say what a longer execution horizon costs in accuracy. This bench
//! runs a small seeded control task ([`env`]: reach → grasp → carry with pushes, a moving goal
//! and actuation noise) with a flow-matching policy trained on a scripted expert ([`model`]),
//! and for each horizon policy measures the success rate (with a 95% Wilson interval), the mean
//! executed horizon, inference calls per episode and episode length, over the same episode
//! seeds for every policy.
//!
//! Each episode runs the robot side's real chunk executor (`kairos_sdk::robot::ChunkExecutor`,
//! with its alignment and discard rules; synchronous inference: the next request goes out when
//! the chunk runs out, `trigger = 1`) and the server's real horizon code: the
//! [`ActionManager`] with the server's horizon registry (natives plus any plugin loaded by the
//! server's plugin factory), which validates every answer and falls back as it does in `serve`.
//! Inference is in-process and takes no virtual time; control runs at
//! [`env::EnvConfig::control_hz`].

pub mod env;
pub mod live;
pub mod model;
pub mod served;
pub mod signals;

use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use kairos_sdk::robot::ChunkExecutor;

use env::{ACTION_DIM, Env, EnvConfig};
use kairos_core::action::{ActionManager, NoHorizon, PolicyLookupError, RoundContext};
use kairos_core::horizon::PolicyParams;
use kairos_core::registry::{HorizonRegistry, native_horizon_policies};
use model::{FlowPolicy, ModelError};

/// Why the bench could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The model failed.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// A policy name or its parameters were refused.
    #[error(transparent)]
    Lookup(#[from] PolicyLookupError),
    /// Neither the policy nor the native fallback chose a horizon.
    #[error(transparent)]
    NoHorizon(#[from] NoHorizon),
    /// The action manager could not be set up.
    #[error("{0}")]
    Setup(String),
    /// The executor had no action to run (a bug: every reply carries at least one).
    #[error("episode {0}: no action to execute")]
    NoAction(u64),
    /// `--live`: the loopback server, the connection or a round failed.
    #[error("live: {0}")]
    Live(String),
}

/// One horizon policy under test: a name in the horizon registry and its parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct PolicyPoint {
    /// The family shown in `pareto.csv`'s `policy` column (`static`, `threshold`, `spread`, a
    /// plugin's name).
    pub family: String,
    /// The registry name it is built from.
    pub name: String,
    /// Its parameters.
    pub params: PolicyParams,
    /// Samples drawn per request (the spread policy needs several, drawn in one batch).
    pub samples: usize,
}

impl PolicyPoint {
    /// `name` with `params`, one sample per request, shown as `name`.
    pub fn new(name: &str, params: &[(&str, f64)]) -> PolicyPoint {
        PolicyPoint {
            family: name.to_string(),
            name: name.to_string(),
            params: params.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            samples: 1,
        }
    }

    /// Parses `name` or `name:k=v,k=v` (a native or loaded policy and its parameters). The
    /// key `samples` is not a policy parameter: it sets the samples drawn per request (default 1).
    pub fn parse(spec: &str) -> Result<PolicyPoint, String> {
        let (name, rest) = spec.split_once(':').unwrap_or((spec, ""));
        let name = name.trim();
        if name.is_empty() {
            return Err(format!("`{spec}`: empty policy name"));
        }
        let mut point = PolicyPoint::new(name, &[]);
        for pair in rest.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (k, v) = pair
                .split_once('=')
                .ok_or_else(|| format!("`{pair}` is not key=value"))?;
            let v: f64 = v
                .trim()
                .parse()
                .map_err(|_| format!("{k}: `{v}` is not a number"))?;
            if k.trim() == "samples" {
                if !(v >= 1.0 && v.fract() == 0.0 && v <= 1024.0) {
                    return Err(format!("samples: {v} is not a whole number in 1..=1024"));
                }
                point.samples = v as usize;
            } else {
                point.params.insert(k.trim().to_string(), v);
            }
        }
        Ok(point)
    }

    /// The parameters as `k=v;k=v` (a CSV cell without commas).
    pub fn params_text(&self) -> String {
        self.params
            .iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect::<Vec<_>>()
            .join(";")
    }
}

/// Static horizons of the full grid.
pub const STATIC_GRID: [f64; 7] = [1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 16.0];
/// Thresholds `t` of the §3.1 rule in the full grid.
pub const THRESHOLD_GRID: [f64; 5] = [0.05, 0.2, 0.4, 1.0, 3.0];
/// Spread thresholds (4 samples, action units: commands are in [−1, 1]) in the full grid.
pub const SPREAD_GRID: [f64; 4] = [0.1, 0.2, 0.3, 0.5];
/// Which denoising step the §3.1 rule reads (0-based; the default reads the last, 9 of 10), at
/// thresholds `t` 0.05 and 0.4, in the full grid.
pub const THRESHOLD_STEP_GRID: [f64; 3] = [1.0, 3.0, 6.0];
/// Spread thresholds with 8 samples and at least 2 actions in the full grid (the best
/// serving-time trade-off on held-out seeds).
pub const SPREAD8_GRID: [f64; 3] = [0.2, 0.25, 0.3];
/// `steady` settings `(delta, margin, h_max)` in the full grid (0: no cap).
pub const STEADY_GRID: [(f64, f64, f64); 4] = [
    (0.3, 0.0, 4.0),
    (0.5, 1.0, 4.0),
    (0.5, 2.0, 6.0),
    (0.5, 1.0, 0.0),
];

/// `contact` settings `(slow, margin, h_min)` in the contact task's full grid (0: no floor
/// above the robot's 1). Chosen on held-out seeds (10001..10150, 20001..20150, 30001..30200).
pub const CONTACT_GRID: [(f64, f64, f64); 4] = [
    (0.7, 1.0, 0.0),
    (0.9, 1.0, 0.0),
    (0.5, 1.0, 0.0),
    (0.7, 1.0, 2.0),
];

/// `contact` settings `(slow, margin)` that execute through a release 8 samples agree on
/// (`release` [`CONTACT_RELEASE`], `quorum` [`CONTACT_QUORUM`]), in the contact task's full grid.
/// Chosen on held-out seeds (10001..10200, 20001..20200, 30001..30200).
pub const CONTACT_RELEASE_GRID: [(f64, f64); 2] = [(0.8, 0.0), (0.7, 1.0)];
/// Actions executed through a planned release in [`CONTACT_RELEASE_GRID`].
pub const CONTACT_RELEASE: f64 = 4.0;
/// Samples drawn per request in [`CONTACT_RELEASE_GRID`], and how many must plan the release.
pub const CONTACT_SAMPLES: (usize, f64) = (8, 6.0);

/// The contact-aware policy's points, run on the contact task beside [`builtin_points`]
/// (`quick`: the first setting of each grid).
pub fn contact_points(quick: bool) -> Vec<PolicyPoint> {
    let take = |len: usize| if quick { 1 } else { len };
    let mut points: Vec<PolicyPoint> = CONTACT_GRID[..take(CONTACT_GRID.len())]
        .iter()
        .map(|&(slow, margin, floor)| {
            let mut p = PolicyPoint::new("contact", &[("slow", slow), ("margin", margin)]);
            if floor > 0.0 {
                p.params.insert("h_min".into(), floor);
            }
            p
        })
        .collect();
    let (samples, quorum) = CONTACT_SAMPLES;
    points.extend(
        CONTACT_RELEASE_GRID[..take(CONTACT_RELEASE_GRID.len())]
            .iter()
            .map(|&(slow, margin)| PolicyPoint {
                family: format!("contact S={samples}"),
                samples,
                ..PolicyPoint::new(
                    "contact",
                    &[
                        ("slow", slow),
                        ("margin", margin),
                        ("release", CONTACT_RELEASE),
                        ("quorum", quorum),
                    ],
                )
            }),
    );
    points
}

/// The built-in policies of a run: static H over a grid, the §3.1 threshold rule at several
/// thresholds, and the multi-sample spread rule (`quick`: a few of each).
pub fn builtin_points(quick: bool) -> Vec<PolicyPoint> {
    let pick = |grid: &[f64], quick_idx: &[usize]| -> Vec<f64> {
        if quick {
            quick_idx.iter().map(|&i| grid[i]).collect()
        } else {
            grid.to_vec()
        }
    };
    let mut points: Vec<PolicyPoint> = pick(&STATIC_GRID, &[0, 3, 6])
        .into_iter()
        .map(|h| PolicyPoint::new("static", &[("h", h)]))
        .collect();
    points.extend(
        pick(&THRESHOLD_GRID, &[2, 4])
            .into_iter()
            .map(|t| PolicyPoint::new("threshold", &[("t", t)])),
    );
    points.extend(pick(&SPREAD_GRID, &[2]).into_iter().map(|th| PolicyPoint {
        samples: 4,
        ..PolicyPoint::new("spread", &[("threshold", th)])
    }));
    let steady = |&(delta, margin, cap): &(f64, f64, f64)| {
        let mut p = PolicyPoint::new("steady", &[("delta", delta), ("margin", margin)]);
        if cap > 0.0 {
            p.params.insert("h_max".into(), cap);
        }
        p
    };
    if quick {
        points.push(steady(&STEADY_GRID[1]));
        return points;
    }
    for step in THRESHOLD_STEP_GRID {
        points.extend([0.05, 0.4].map(|t| PolicyPoint {
            family: format!("threshold step={step}"),
            ..PolicyPoint::new("threshold", &[("t", t), ("step", step)])
        }));
    }
    points.extend(SPREAD8_GRID.iter().map(|&th| PolicyPoint {
        family: "spread S=8".into(),
        samples: 8,
        ..PolicyPoint::new("spread", &[("threshold", th), ("h_min", 2.0)])
    }));
    points.extend(STEADY_GRID.iter().map(steady));
    points
}

/// One episode's outcome.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Episode {
    /// Whether the object reached the goal in time.
    pub success: bool,
    /// Control steps taken.
    pub steps: u32,
    /// Inference calls (chunks requested).
    pub calls: u32,
    /// Sum of the horizons chosen.
    pub horizon_sum: u64,
}

/// Noise seed of request `call` of episode `episode`.
pub(crate) fn noise_seed(episode: u64, call: u32) -> u64 {
    episode
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(u64::from(call))
}

/// Horizons remembered per episode for `HorizonInput::recent_horizons`: as many as the server
/// keeps per task, so a policy that reads them decides alike in-process and `--live`.
const RECENT: usize = kairos_core::lifecycle::RECENT_HORIZONS;

/// The horizon policy that answers when the one under test fails (and the default when a
/// request names none): the native §3.1 rule with its default parameters, in-process and on the
/// `--live` server alike.
pub const FALLBACK_POLICY: &str = "threshold";

/// Runs episode `seed` with `policy` choosing horizons through `manager`.
pub fn run_episode(
    model: &FlowPolicy,
    manager: &ActionManager,
    point: &PolicyPoint,
    env_cfg: &EnvConfig,
    seed: u64,
) -> Result<Episode, BenchError> {
    let mut round = manager.build(Some(point.name.as_str()), Some(&point.params))?;
    let mut env = Env::new(env_cfg.clone(), seed);
    let hz = env_cfg.control_hz;
    let period_us = (1e6 / f64::from(hz)).round() as u64;
    let mut exec = ChunkExecutor::new(hz, 1.0);
    let mut out = Episode::default();
    let mut recent: Vec<u32> = Vec::with_capacity(RECENT);
    let mut now_us = 0u64;
    while !env.done() {
        if exec.wants_request() {
            let id = u64::from(out.calls);
            exec.request_sent(id, now_us);
            let chunk = model.sample(&env.observe(), point.samples, noise_seed(seed, out.calls))?;
            let choice = manager.choose(
                &mut round,
                &chunk,
                RoundContext {
                    control_hz: hz,
                    round_index: id,
                    recent_horizons: &recent,
                    load: None,
                },
            )?;
            let h = choice.horizon;
            let actions: Vec<Vec<f32>> = chunk
                .sample_actions(0)
                .chunks_exact(ACTION_DIM)
                .take(h)
                .map(<[f32]>::to_vec)
                .collect();
            exec.reply_arrived(id, actions);
            out.calls += 1;
            out.horizon_sum += h as u64;
            if recent.len() == RECENT {
                recent.remove(0);
            }
            recent.push(u32::try_from(h).unwrap_or(u32::MAX));
        }
        let step = exec.next_action(now_us).ok_or(BenchError::NoAction(seed))?;
        env.step(step.action);
        now_us += period_us;
    }
    out.success = env.success();
    out.steps = env.steps();
    Ok(out)
}

/// One policy's results.
#[derive(Clone, Debug, PartialEq)]
pub struct PointResult {
    /// The policy.
    pub point: PolicyPoint,
    /// Episodes run.
    pub episodes: usize,
    /// Episodes that succeeded.
    pub successes: usize,
    /// Actions executed per chunk: steps / calls over all episodes.
    pub mean_horizon: f64,
    /// Mean horizon the policy chose (the last chunk of an episode may be cut short).
    pub mean_chosen: f64,
    /// Inference calls per episode.
    pub calls_per_episode: f64,
    /// Control steps per episode.
    pub mean_steps: f64,
    /// Every episode's outcome, in the order summarised (for the bench's policies: episode
    /// seed order).
    pub outcomes: Vec<Episode>,
}

impl PointResult {
    /// Successes / episodes.
    pub fn success_rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }

    /// 95% Wilson score interval of the success rate.
    pub fn ci(&self) -> (f64, f64) {
        wilson(self.successes, self.episodes, 1.96)
    }
}

/// The Wilson score interval of `k` successes in `n` trials at normal quantile `z`.
pub fn wilson(k: usize, n: usize, z: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let (k, n) = (k as f64, n as f64);
    let p = k / n;
    let z2 = z * z;
    let centre = (p + z2 / (2.0 * n)) / (1.0 + z2 / n);
    let half = z * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt() / (1.0 + z2 / n);
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchPlan {
    /// The policies.
    pub points: Vec<PolicyPoint>,
    /// Episodes per policy; episode `i` has seed `seed + i` for every policy.
    pub episodes: usize,
    /// First episode seed.
    pub seed: u64,
    /// The task.
    pub env: EnvConfig,
    /// Worker threads.
    pub threads: usize,
}

/// An action manager over the natives and `extra` (plugins), falling back to the native
/// `threshold` rule as `serve` does by default.
pub fn action_manager(extra: HorizonRegistry) -> Result<ActionManager, BenchError> {
    ActionManager::new(
        extra,
        &native_horizon_policies(),
        FALLBACK_POLICY,
        PolicyParams::new(),
    )
    .map_err(|e| BenchError::Setup(e.to_string()))
}

/// The jobs of `plan`, `(policy index, episode index)`, in plan order: every policy's episodes
/// in seed order.
pub(crate) fn plan_jobs(plan: &BenchPlan) -> Vec<(usize, u64)> {
    (0..plan.points.len())
        .flat_map(|p| (0..plan.episodes as u64).map(move |e| (p, e)))
        .collect()
}

/// Summarises the outcomes of [`plan_jobs`]' jobs (one slot each, in the same order) per policy.
pub(crate) fn gather(
    plan: &BenchPlan,
    slots: Vec<Option<Result<Episode, BenchError>>>,
) -> Result<Vec<PointResult>, BenchError> {
    let mut out = Vec::with_capacity(plan.points.len());
    let mut slots = slots.into_iter();
    for point in &plan.points {
        let mut episodes = Vec::with_capacity(plan.episodes);
        for slot in slots.by_ref().take(plan.episodes) {
            match slot {
                Some(Ok(e)) => episodes.push(e),
                Some(Err(e)) => return Err(e),
                None => return Err(BenchError::Setup("an episode did not run".into())),
            }
        }
        if episodes.len() != plan.episodes {
            return Err(BenchError::Setup("an episode did not run".into()));
        }
        out.push(summarize(point, &episodes));
    }
    Ok(out)
}

/// Runs every policy of `plan` on the same episodes, `on_episode` after each. Results come in
/// plan order, the same whatever the thread count.
pub fn run_bench(
    model: &FlowPolicy,
    manager: &ActionManager,
    plan: &BenchPlan,
    on_episode: &(dyn Fn() + Sync),
) -> Result<Vec<PointResult>, BenchError> {
    let jobs = plan_jobs(plan);
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Result<Episode, BenchError>>>> =
        Mutex::new((0..jobs.len()).map(|_| None).collect());
    std::thread::scope(|scope| {
        for _ in 0..plan.threads.max(1) {
            scope.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(p, e)) = jobs.get(i) else { break };
                    let r = run_episode(model, manager, &plan.points[p], &plan.env, plan.seed + e);
                    if let Ok(mut slots) = results.lock() {
                        slots[i] = Some(r);
                    }
                    on_episode();
                }
            });
        }
    });
    gather(
        plan,
        results
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner()),
    )
}

pub(crate) fn summarize(point: &PolicyPoint, episodes: &[Episode]) -> PointResult {
    let n = episodes.len().max(1) as f64;
    let calls: u64 = episodes.iter().map(|e| u64::from(e.calls)).sum();
    let steps: u64 = episodes.iter().map(|e| u64::from(e.steps)).sum();
    let chosen: u64 = episodes.iter().map(|e| e.horizon_sum).sum();
    PointResult {
        point: point.clone(),
        episodes: episodes.len(),
        successes: episodes.iter().filter(|e| e.success).count(),
        mean_horizon: steps as f64 / calls.max(1) as f64,
        mean_chosen: chosen as f64 / calls.max(1) as f64,
        calls_per_episode: calls as f64 / n,
        mean_steps: steps as f64 / n,
        outcomes: episodes.to_vec(),
    }
}

/// `episodes.csv`: one row per episode of `results` (the bench's policies, whose outcomes are
/// in seed order from `first_seed`), to compare runs episode for episode (`--live` against
/// in-process).
pub fn episodes_csv(results: &[PointResult], first_seed: u64) -> String {
    let mut s = String::from("policy,params,seed,success,steps,calls,horizon_sum\n");
    for r in results {
        for (i, e) in r.outcomes.iter().enumerate() {
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{}",
                r.point.family,
                r.point.params_text(),
                first_seed + i as u64,
                u8::from(e.success),
                e.steps,
                e.calls,
                e.horizon_sum
            );
        }
    }
    s
}

/// `pareto.csv`: one row per policy.
pub fn pareto_csv(results: &[PointResult]) -> String {
    let mut s = String::from(
        "policy,params,mean_horizon,success_rate,ci_low,ci_high,episodes,successes,mean_chosen_horizon,calls_per_episode,mean_episode_steps\n",
    );
    for r in results {
        let (lo, hi) = r.ci();
        let _ = writeln!(
            s,
            "{},{},{:.3},{:.4},{:.4},{:.4},{},{},{:.3},{:.2},{:.2}",
            r.point.family,
            r.point.params_text(),
            r.mean_horizon,
            r.success_rate(),
            lo,
            hi,
            r.episodes,
            r.successes,
            r.mean_chosen,
            r.calls_per_episode,
            r.mean_steps
        );
    }
    s
}

/// The markdown table of `summary.md`.
pub fn markdown_table(results: &[PointResult]) -> String {
    let mut s = String::from(
        "| policy | params | success | 95% CI | mean executed H | calls / episode | steps / episode |\n|---|---|---|---|---|---|---|\n",
    );
    for r in results {
        let (lo, hi) = r.ci();
        let _ = writeln!(
            s,
            "| {} | {} | {:.1}% | {:.1}–{:.1}% | {:.2} | {:.1} | {:.1} |",
            r.point.family,
            r.point.params_text(),
            100.0 * r.success_rate(),
            100.0 * lo,
            100.0 * hi,
            r.mean_horizon,
            r.calls_per_episode,
            r.mean_steps
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_matches_the_textbook_values() {
        // 81/263 at 95%: (0.2553, 0.3662) (Wilson 1927 as tabulated by Newcombe 1998, case 3... )
        let (lo, hi) = wilson(81, 263, 1.96);
        assert!(
            (lo - 0.2553).abs() < 5e-4 && (hi - 0.3662).abs() < 5e-4,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(0, 10, 1.96);
        assert_eq!(lo, 0.0);
        assert!((hi - 0.2775).abs() < 5e-4, "{hi}");
        assert_eq!(wilson(0, 0, 1.96), (0.0, 1.0));
    }

    #[test]
    fn policy_specs_parse_with_their_sample_count() {
        let p = PolicyPoint::parse("steady:delta=0.5,margin=1").unwrap();
        assert_eq!((p.name.as_str(), p.samples), ("steady", 1));
        assert_eq!(p.params_text(), "delta=0.5;margin=1");
        let p = PolicyPoint::parse("spread:threshold=0.25,samples=8").unwrap();
        assert_eq!((p.samples, p.params_text().as_str()), (8, "threshold=0.25"));
        assert!(PolicyPoint::parse("static").unwrap().params.is_empty());
        assert!(PolicyPoint::parse("spread:samples=0").is_err());
        assert!(PolicyPoint::parse("static:h").is_err());
        assert!(PolicyPoint::parse(":h=1").is_err());
    }

    #[test]
    fn contact_episodes_with_the_committed_model_are_a_function_of_their_seed() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../workloads/horizon-contact/model");
        let (model, saved) = FlowPolicy::load(&dir).unwrap();
        assert_eq!(saved.train.env.task_name(), "contact");
        let manager = action_manager(HorizonRegistry::new()).unwrap();
        let point = &contact_points(true)[0];
        let run = |seed| run_episode(&model, &manager, point, &saved.train.env, seed).unwrap();
        let (a, b) = (run(7), run(7));
        assert_eq!(a, b);
        // Other seeds, other episodes (the chunk-by-chunk horizons differ somewhere).
        assert!((8..12).any(|s| run(s) != a));
        assert!(a.calls >= 1 && a.steps >= a.calls);
    }

    #[test]
    fn the_quick_plan_has_every_family() {
        let points = builtin_points(true);
        for family in ["static", "threshold", "spread", "steady"] {
            assert!(points.iter().any(|p| p.family == family), "{family}");
        }
        assert!(builtin_points(false).len() > points.len());
    }
}
