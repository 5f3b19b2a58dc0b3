//! `kairos bench chunking`: what a robot should do with a chunk that arrives `D` control steps
//! after its observation was captured, judged in closed loop by task success.
//!
//! For each task (the horizon bench's tasks: `uniform`, whose expert is bimodal; `contact`;
//! `reactive`, whose goal moves fast), each delay `D` ∈ {0, 1, 2, 3, 4, 8} and each re-planning
//! period (every `max(2, D)` steps, and every `max(N/4, D)`: one request in flight at a time),
//! every execution ([`episode::Execution`]: synchronous, and asynchronous with each server
//! chunking strategy) runs the same episode seeds ([`episode::run_episode`]). A cell reports the
//! success rate with its 95% Wilson interval, the mean jump of the velocity command at chunk
//! switches against within a chunk, and the sampling time per chunk. [`cost`] measures each
//! strategy's sampling time against plain sampling on one thread. `--live`
//! ([`live`]) runs a subset over loopback QUIC against a loaded server that predicts `d` itself.

pub mod episode;
pub mod live;
pub mod report;

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use kairos_core::chunking::ChunkingDefaults;
use kairos_engine::{Guidance, GuidanceMode};

use crate::horizon_bench::env::{ACTION_DIM, Env, EnvConfig};
use crate::horizon_bench::model::{FlowPolicy, ModelError};
use crate::horizon_bench::wilson;
use episode::{EpisodeSpec, Execution, Outcome, run_episode};

/// The delays of the full run, control steps.
pub const DELAYS: [u32; 6] = [0, 1, 2, 3, 4, 8];

/// One cell of the grid: a task, a delay, a re-planning period and an execution.
#[derive(Clone, Debug, PartialEq)]
pub struct Cell {
    /// The task's name.
    pub task: String,
    /// Steps from capture to arrival.
    pub delay: u32,
    /// Steps between requests.
    pub period: u32,
    /// Synchronous or a strategy.
    pub execution: Execution,
}

/// The re-planning periods of delay `delay` for chunks of `chunk_len`: `max(2, D)` and
/// `max(N/4, D)`, once each.
pub fn periods(delay: u32, chunk_len: usize) -> Vec<u32> {
    let quarter = u32::try_from(chunk_len / 4).unwrap_or(u32::MAX).max(1);
    let mut out = vec![delay.max(2), delay.max(quarter)];
    out.dedup();
    out
}

/// The grid of one task: every delay, period and execution.
pub fn cells(task: &str, delays: &[u32], chunk_len: usize, executions: &[Execution]) -> Vec<Cell> {
    let mut out = Vec::new();
    for &delay in delays {
        for period in periods(delay, chunk_len) {
            for &execution in executions {
                out.push(Cell {
                    task: task.to_string(),
                    delay,
                    period,
                    execution,
                });
            }
        }
    }
    out
}

/// One cell's results over its episodes.
#[derive(Clone, Debug, PartialEq)]
pub struct CellResult {
    /// The cell.
    pub cell: Cell,
    /// Episodes run.
    pub episodes: usize,
    /// Episodes that succeeded.
    pub successes: usize,
    /// Mean jump of the velocity command at chunk switches.
    pub switch_jump: f64,
    /// Mean jump between consecutive actions of one chunk.
    pub within_jump: f64,
    /// Chunks per episode.
    pub calls_per_episode: f64,
    /// Mean wall time of one chunk's sampling, µs.
    pub sampling_us: f64,
    /// Episodes in which a chunk's sampling diverged ([`Outcome::diverged`]).
    pub diverged: usize,
    /// Every episode's outcome, in seed order.
    pub outcomes: Vec<Outcome>,
}

impl CellResult {
    /// Successes / episodes.
    pub fn success_rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }

    /// 95% Wilson score interval of the success rate.
    pub fn ci(&self) -> (f64, f64) {
        wilson(self.successes, self.episodes, 1.96)
    }
}

/// Summarises one cell's outcomes.
pub fn summarize(cell: &Cell, outcomes: Vec<Outcome>) -> CellResult {
    let sum = |f: &dyn Fn(&Outcome) -> f64| outcomes.iter().map(f).sum::<f64>();
    let switches = sum(&|o| f64::from(o.switches));
    let within = sum(&|o| f64::from(o.within));
    let calls = sum(&|o| f64::from(o.calls));
    CellResult {
        cell: cell.clone(),
        episodes: outcomes.len(),
        successes: outcomes.iter().filter(|o| o.success).count(),
        switch_jump: sum(&|o| o.switch_jump) / switches.max(1.0),
        within_jump: sum(&|o| o.within_jump) / within.max(1.0),
        calls_per_episode: calls / outcomes.len().max(1) as f64,
        sampling_us: sum(&|o| o.sampling.as_secs_f64() * 1e6) / calls.max(1.0),
        diverged: outcomes.iter().filter(|o| o.diverged).count(),
        outcomes,
    }
}

/// What to run on one task.
#[derive(Clone, Debug)]
pub struct TaskPlan<'a> {
    /// The task.
    pub env: EnvConfig,
    /// Its policy.
    pub model: &'a FlowPolicy,
    /// The cells.
    pub cells: Vec<Cell>,
}

/// What to run.
#[derive(Clone, Debug)]
pub struct BenchPlan<'a> {
    /// The tasks.
    pub tasks: Vec<TaskPlan<'a>>,
    /// Episodes per cell; episode `i` has seed `seed + i` in every cell.
    pub episodes: usize,
    /// First episode seed.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
    /// The server's real-time chunking settings.
    pub defaults: ChunkingDefaults,
}

/// Runs every cell of `plan` on the same seeds, `on_episode` after each. Results come in plan
/// order (tasks, then cells), the same whatever the thread count.
pub fn run_bench(
    plan: &BenchPlan<'_>,
    on_episode: &(dyn Fn() + Sync),
) -> Result<Vec<CellResult>, ModelError> {
    let jobs: Vec<(usize, usize, u64)> = plan
        .tasks
        .iter()
        .enumerate()
        .flat_map(|(t, task)| {
            (0..task.cells.len())
                .flat_map(move |c| (0..plan.episodes as u64).map(move |e| (t, c, e)))
        })
        .collect();
    let next = AtomicUsize::new(0);
    let slots: Mutex<Vec<Option<Result<Outcome, ModelError>>>> =
        Mutex::new((0..jobs.len()).map(|_| None).collect());
    std::thread::scope(|scope| {
        for _ in 0..plan.threads.max(1) {
            scope.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(t, c, e)) = jobs.get(i) else { break };
                    let task = &plan.tasks[t];
                    let cell = &task.cells[c];
                    let spec = EpisodeSpec {
                        env: &task.env,
                        delay: cell.delay,
                        period: cell.period,
                        execution: cell.execution,
                        defaults: &plan.defaults,
                    };
                    let outcome = run_episode(task.model, &spec, plan.seed + e);
                    if let Ok(mut slots) = slots.lock() {
                        slots[i] = Some(outcome);
                    }
                    on_episode();
                }
            });
        }
    });
    let mut slots = slots
        .into_inner()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
        .into_iter();
    let mut results = Vec::new();
    for task in &plan.tasks {
        for cell in &task.cells {
            let mut outcomes = Vec::with_capacity(plan.episodes);
            for slot in slots.by_ref().take(plan.episodes) {
                match slot {
                    Some(Ok(o)) => outcomes.push(o),
                    Some(Err(e)) => return Err(e),
                    None => {
                        return Err(ModelError::Sampler(
                            kairos_engine::EngineError::InvalidInput(
                                "an episode did not run".into(),
                            ),
                        ));
                    }
                }
            }
            results.push(summarize(cell, outcomes));
        }
    }
    Ok(results)
}

/// One strategy's sampling cost against plain sampling.
#[derive(Clone, Debug, PartialEq)]
pub struct Cost {
    /// `plain` (no guidance) or the guidance mode's name.
    pub name: &'static str,
    /// Median time of one chunk, µs.
    pub median_us: f64,
    /// `median_us` over plain sampling's.
    pub relative: f64,
}

/// Sampling time of one chunk with each guidance mode against plain sampling, on the calling
/// thread: `rounds` alternating passes over the modes (so load on the machine hits them alike),
/// the median of each. `skip`, `from_start`, `arrival_state` and `ensemble` sample plainly (the
/// server's work around them is a copy of a few actions).
pub fn cost(model: &FlowPolicy, env: &EnvConfig, rounds: usize) -> Result<Vec<Cost>, ModelError> {
    let obs = Env::new(env.clone(), 1).observe();
    let n = model.config().chunk_len;
    let prefix: Vec<f32> =
        model.sample(&obs, 1, 7)?.sample_actions(0)[..n / 2 * ACTION_DIM].to_vec();
    let guidance = |mode| Guidance {
        mode,
        prefix: prefix.clone(),
        delay: 2,
        execution_horizon: n,
        schedule: kairos_engine::PrefixSchedule::Linear,
        max_guidance_weight: 10.0,
    };
    let modes: [(&'static str, Option<Guidance>); 4] = [
        ("plain", None),
        ("rtc", Some(guidance(GuidanceMode::Rtc))),
        ("rtc_vjp", Some(guidance(GuidanceMode::RtcVjp))),
        ("inpaint", Some(guidance(GuidanceMode::Inpaint))),
    ];
    let mut times: Vec<Vec<Duration>> = vec![Vec::with_capacity(rounds); modes.len()];
    for r in 0..rounds.max(1) {
        for (i, (_, g)) in modes.iter().enumerate() {
            let started = Instant::now();
            model.sample_guided(&obs, 1, r as u64, g.as_ref())?;
            times[i].push(started.elapsed());
        }
    }
    let median = |t: &mut Vec<Duration>| {
        t.sort();
        t[t.len() / 2].as_secs_f64() * 1e6
    };
    let medians: Vec<f64> = times.iter_mut().map(median).collect();
    Ok(modes
        .iter()
        .zip(&medians)
        .map(|((name, _), &m)| Cost {
            name,
            median_us: m,
            relative: m / medians[0],
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::horizon_bench::model::ModelConfig;
    use kairos_sdk::protocol::ChunkingStrategy;

    #[test]
    fn the_grid_has_both_periods_until_they_meet() {
        assert_eq!(periods(0, 16), [2, 4]);
        assert_eq!(periods(3, 16), [3, 4]);
        assert_eq!(periods(4, 16), [4]);
        assert_eq!(periods(8, 16), [8]);
        let grid = cells("uniform", &DELAYS, 16, &Execution::all());
        // D = 0..3: two periods each, D = 4 and 8: one; 10 executions each.
        assert_eq!(grid.len(), (4 * 2 + 2) * 10);
    }

    fn tiny() -> FlowPolicy {
        FlowPolicy::new(ModelConfig {
            hidden: 16,
            steps: 3,
            ..ModelConfig::default()
        })
        .unwrap()
    }

    #[test]
    fn an_episode_is_a_function_of_its_seed_and_strategies_share_the_first_chunk() {
        let model = tiny();
        let env = EnvConfig::default();
        let defaults = ChunkingDefaults::default();
        let spec = |execution, delay| EpisodeSpec {
            env: &env,
            delay,
            period: delay.max(2),
            execution,
            defaults: &defaults,
        };
        for execution in Execution::all() {
            let a = run_episode(&model, &spec(execution, 2), 5).unwrap();
            let b = run_episode(&model, &spec(execution, 2), 5).unwrap();
            assert_eq!(
                a,
                Outcome {
                    sampling: a.sampling,
                    ..b
                },
                "{}",
                execution.name()
            );
            assert!(a.calls >= 2 && a.steps >= 1, "{}: {a:?}", execution.name());
        }
        // With no delay nothing is committed when a chunk arrives: every asynchronous strategy
        // but ensemble (which blends the overlap even then) plans and executes the same.
        let skip = run_episode(
            &model,
            &spec(Execution::Async(ChunkingStrategy::Skip), 0),
            5,
        )
        .unwrap();
        for strategy in [
            ChunkingStrategy::FromStart,
            ChunkingStrategy::ArrivalState,
            ChunkingStrategy::Inpaint,
        ] {
            let other = run_episode(&model, &spec(Execution::Async(strategy), 0), 5).unwrap();
            assert_eq!(
                (other.success, other.steps, other.switch_jump),
                (skip.success, skip.steps, skip.switch_jump),
                "{strategy}"
            );
        }
    }

    #[test]
    fn cost_names_every_guidance_mode_against_plain() {
        let costs = cost(&tiny(), &EnvConfig::default(), 3).unwrap();
        let names: Vec<&str> = costs.iter().map(|c| c.name).collect();
        assert_eq!(names, ["plain", "rtc", "rtc_vjp", "inpaint"]);
        assert_eq!(costs[0].relative, 1.0);
        assert!(costs.iter().all(|c| c.median_us > 0.0));
    }
}
