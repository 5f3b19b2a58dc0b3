//! The paper's experiments (§5) as simulation jobs, and their tables.
//!
//! [`plan`] turns workloads into a list of independent [`Job`]s (online rate sweep, offline
//! fleet sweep, hybrid edge+cloud, bucket-count and intra-bucket ablations, and the scale
//! experiment of [`super::scale`]); [`run_jobs`] runs
//! them on a few threads (each job is a deterministic function of its configuration, so the
//! thread count never changes a number); [`Report`] renders the paper-style tables and CSV.

use std::fmt::Write as _;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use kairos_sdk::trace::{HorizonSetting, TraceSet};

use super::scale::{self, ScalePlan, ScaleStats};
use super::stats::{Summary, reduction, summarize};
use super::{Load, SimConfig, SimError, SimNetwork, simulate, simulate_timed};
use crate::workload::Workload;
use crate::workload::generate::{DYNAMIC, STATIC};
use kairos_core::registry::Policies;
use kairos_core::scheduler::{EngineSpec, PolicySpec, SchedulerConfig, Tier, refetch_by_default};

/// One experiment of §5.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Experiment {
    /// Poisson arrivals at increasing rates, one edge GPU (Fig. "aggregate_rate", Table
    /// "benchmarks-latency-reduction").
    Online,
    /// A fleet of n robots working through a fixed task list (Fig. "aggregate_scale").
    Fleet,
    /// Edge-only vs cloud-only vs hybrid (Fig. "aggregated_offload").
    Hybrid,
    /// Wait-ratio bucket count B (Fig. "microbenchmark-bin-size").
    Buckets,
    /// Intra-bucket order (Fig. "microbenchmark-intra-bin").
    Intra,
    /// Each online system at the peak rate with its re-fetch setting and with it flipped: the
    /// "re-fetch for all" (and "re-fetch for none") ablation.
    Refetch,
    /// Thousands of robots on many engine instances: what one scheduler's decisions cost, and
    /// the throughput, as the fleet grows ([`super::scale`]; not in the paper).
    Scale,
    /// Kairos at every online rate with the load-aware horizon (`load-aware`, issue #14 §3)
    /// against the threshold rule, the static horizon and the full chunk: latency against mean
    /// horizon and actions run past the threshold's cut. Not part of [`Experiment::ALL`] (the
    /// paper's set); asked for by name.
    LoadHorizon,
}

impl Experiment {
    /// Every experiment, in report order.
    pub const ALL: [Experiment; 7] = [
        Experiment::Online,
        Experiment::Fleet,
        Experiment::Hybrid,
        Experiment::Buckets,
        Experiment::Intra,
        Experiment::Refetch,
        Experiment::Scale,
    ];

    /// Its name on the command line and in CSV.
    pub fn name(self) -> &'static str {
        match self {
            Experiment::Online => "online",
            Experiment::Fleet => "fleet",
            Experiment::Hybrid => "hybrid",
            Experiment::Buckets => "buckets",
            Experiment::Intra => "intra",
            Experiment::Refetch => "refetch",
            Experiment::Scale => "scale",
            Experiment::LoadHorizon => "load-horizon",
        }
    }

    /// Parses a name (the paper's experiments and [`Experiment::LoadHorizon`]).
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL
            .into_iter()
            .chain([Experiment::LoadHorizon])
            .find(|e| e.name() == s)
    }
}

/// Where the engines are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// One edge GPU.
    Edge,
    /// One cloud GPU behind the WAN.
    Cloud,
    /// One of each; Algorithm 1 phase 3 decides.
    Hybrid,
    /// This many edge instances (workers) of the edge profile: the scale experiment.
    Workers(usize),
}

/// A scheduler + horizon combination being compared.
#[derive(Clone, Debug, PartialEq)]
pub struct Variant {
    /// Stable key for CSV and code (`fifo`, `kairos-static`, ...).
    pub key: String,
    /// Label in tables and plots.
    pub label: String,
    /// The priority policy.
    pub policy: PolicySpec,
    /// The trace setting replayed (`static`, `dynamic`, or a horizon plugin's).
    pub setting: String,
    /// Whether robots send the remaining-work hint.
    pub hints: bool,
    /// Whether the scheduler re-fetches stale observations (`SchedulerConfig::refetch`).
    pub refetch: bool,
    /// Engines.
    pub placement: Placement,
    /// Asked for by the user (`--policy`, a plugin): drawn in the online plots beside the
    /// paper's systems.
    pub user: bool,
    /// Replay the chunks with this horizon policy instead of the recording's
    /// ([`SimConfig::replay_horizon`]).
    pub replay_horizon: Option<HorizonSetting>,
}

impl Variant {
    /// `policy` on one edge engine replaying `setting`, without hints, with the policy's own
    /// re-fetch setting ([`refetch_by_default`]).
    pub fn new(key: &str, label: &str, policy: PolicySpec, setting: &str) -> Self {
        Variant {
            key: key.to_string(),
            label: label.to_string(),
            refetch: refetch_by_default(&policy.name),
            policy,
            setting: setting.to_string(),
            hints: false,
            placement: Placement::Edge,
            user: false,
            replay_horizon: None,
        }
    }

    /// The same system with its re-fetch setting flipped, for the re-fetch ablation: key and
    /// label say which way.
    pub fn refetch_flipped(&self) -> Variant {
        let (key, label) = if self.refetch {
            (
                format!("{}-norefetch", self.key),
                format!("{} w/o re-fetch", self.label),
            )
        } else {
            (
                format!("{}-refetch", self.key),
                format!("{} + re-fetch", self.label),
            )
        };
        Variant {
            key,
            label,
            refetch: !self.refetch,
            ..self.clone()
        }
    }
}

fn variant(key: &str, label: &str, policy: &str, setting: &str) -> Variant {
    Variant::new(
        key,
        label,
        policy.parse().unwrap_or_else(|_| PolicySpec::named(policy)),
        setting,
    )
}

/// Name of the better priority policy in the registry.
pub const BETTER: &str = "srw";

/// The variants of the online experiment: the paper's three systems and two ablations, plus the
/// better policy without and with the client's remaining-work hint. Each with its system's own
/// re-fetch setting: Algorithm 1 (Kairos, with either horizon) and SRW re-fetch stale observations,
/// FIFO and Autellix (with either horizon) do not.
pub fn online_variants() -> Vec<Variant> {
    let mut with_hint = variant("srw-hint", "SRW + hint (ours)", BETTER, DYNAMIC);
    with_hint.hints = true;
    vec![
        variant("fifo", "FIFO", "fifo", STATIC),
        variant("autellix", "Autellix", "plas", STATIC),
        variant("kairos", "Kairos", "kairos", DYNAMIC),
        variant("kairos-static", "Kairos w/o dyn. horizon", "kairos", STATIC),
        variant("fifo-dynamic", "FIFO + dyn. horizon", "fifo", DYNAMIC),
        variant(
            "autellix-dynamic",
            "Autellix + dyn. horizon",
            "plas",
            DYNAMIC,
        ),
        variant("srw", "SRW (ours)", BETTER, DYNAMIC),
        with_hint,
    ]
}

fn fleet_variants() -> Vec<Variant> {
    online_variants()
        .into_iter()
        .filter(|v| ["fifo", "autellix", "kairos", "srw"].contains(&v.key.as_str()))
        .collect()
}

/// The re-fetch ablation: every online system with its own re-fetch setting and flipped.
fn refetch_variants() -> Vec<Variant> {
    online_variants()
        .into_iter()
        .flat_map(|v| {
            let flipped = v.refetch_flipped();
            [v, flipped]
        })
        .collect()
}

fn hybrid_variants() -> Vec<Variant> {
    [
        ("edge", "Kairos (edge-only)", Placement::Edge),
        ("cloud", "Kairos (cloud-only)", Placement::Cloud),
        ("hybrid", "Kairos (hybrid)", Placement::Hybrid),
    ]
    .into_iter()
    .map(|(key, label, placement)| {
        let mut v = variant(key, label, "kairos", DYNAMIC);
        v.placement = placement;
        v
    })
    .collect()
}

/// Bucket counts of the ablation; `None` is ∞.
pub const BUCKETS: [Option<u32>; 5] = [Some(2), Some(5), Some(10), Some(20), None];

fn bucket_variants() -> Vec<Variant> {
    BUCKETS
        .iter()
        .map(|b| {
            let text = b.map_or("inf".to_string(), |b| b.to_string());
            let label = b.map_or("B=∞".to_string(), |b| format!("B={b}"));
            variant(
                &format!("buckets-{text}"),
                &label,
                &format!("kairos:buckets={text}"),
                DYNAMIC,
            )
        })
        .collect()
}

/// The system of the scale experiment: Algorithm 1 with the dynamic horizon (re-fetch on).
fn scale_variant() -> Variant {
    variant("kairos", "Kairos", "kairos", DYNAMIC)
}

fn intra_variants() -> Vec<Variant> {
    vec![
        variant("intra-fifo", "FIFO in bucket", "kairos:intra=fifo", DYNAMIC),
        variant(
            "intra-longest",
            "Longest exec. first",
            "kairos:intra=longest-exec",
            DYNAMIC,
        ),
    ]
}

/// The gains of the load-aware horizon in [`Experiment::LoadHorizon`].
pub const LOAD_AWARE_GAINS: [f64; 2] = [1.0, 2.0];

/// The systems of [`Experiment::LoadHorizon`]: Algorithm 1's scheduler with the static horizon
/// (its own traces), the threshold rule (the dynamic traces, as recorded), the load-aware rule
/// at each of [`LOAD_AWARE_GAINS`] and the whole chunk (`static` with `h` above any chunk,
/// clamped to `N`), all three replaying the dynamic traces' rounds.
pub fn load_horizon_variants() -> Vec<Variant> {
    let replayed = |key: &str, label: &str, policy: &str, params: &[(&str, f64)]| {
        let mut v = variant(key, label, "kairos", DYNAMIC);
        v.replay_horizon = Some(HorizonSetting {
            policy: policy.to_string(),
            params: params.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        });
        v
    };
    let mut out = vec![
        variant("kairos-static", "static H", "kairos", STATIC),
        variant("kairos", "threshold (recorded)", "kairos", DYNAMIC),
    ];
    for gain in LOAD_AWARE_GAINS {
        out.push(replayed(
            &format!("load-aware-{gain}"),
            &format!("load-aware, gain {gain}"),
            "load-aware",
            &[("gain", gain)],
        ));
    }
    out.push(replayed(
        "full-chunk",
        "whole chunk",
        "static",
        &[("h", 1e9)],
    ));
    out
}

/// One simulation to run.
#[derive(Clone, Debug)]
pub struct Job {
    /// Index of its workload.
    pub workload: usize,
    /// The experiment.
    pub experiment: Experiment,
    /// The x value: arrival rate (tasks/s) or fleet size.
    pub x: f64,
    /// What is compared.
    pub variant: Variant,
    /// The run.
    pub config: SimConfig,
}

/// What to plan.
#[derive(Clone, Debug)]
pub struct Plan {
    /// Experiments to include.
    pub experiments: Vec<Experiment>,
    /// Seed of every run (arrivals and task picks; the trace set has its own).
    pub seed: u64,
    /// Extra variants for the online experiment (e.g. a policy under test).
    pub extra: Vec<Variant>,
    /// Scale every run's task count by this (1 = the workload's counts).
    pub task_scale: f64,
    /// Policies beyond the natives that variants may name (users' plugins,
    /// [`plugin_policies`]).
    pub policies: Policies,
    /// Fleet sizes and workers of the scale experiment.
    pub scale: ScalePlan,
}

fn engine(w: &Workload, tier: Tier) -> EngineSpec {
    match tier {
        Tier::Edge => EngineSpec {
            name: "edge".into(),
            tier,
            profile: w.edge_profile(),
            rtt: Duration::ZERO,
        },
        Tier::Cloud => EngineSpec {
            name: "cloud".into(),
            tier,
            profile: w.cloud_profile(),
            rtt: w.wan_rtt(),
        },
    }
}

/// The simulation configuration of `variant` on workload `w` under `load`.
pub fn config(w: &Workload, variant: &Variant, load: Load, seed: u64) -> SimConfig {
    let engines = match variant.placement {
        Placement::Edge => vec![engine(w, Tier::Edge)],
        Placement::Cloud => vec![engine(w, Tier::Cloud)],
        Placement::Hybrid => vec![engine(w, Tier::Edge), engine(w, Tier::Cloud)],
        Placement::Workers(n) => (0..n.max(1))
            .map(|i| EngineSpec {
                name: format!("worker-{i}"),
                ..engine(w, Tier::Edge)
            })
            .collect(),
    };
    SimConfig {
        engines,
        scheduler: SchedulerConfig {
            refetch: variant.refetch,
            ..SchedulerConfig::default()
        },
        policy: variant.policy.clone(),
        setting: variant.setting.clone(),
        network: SimNetwork {
            robot_rtt: w.robot_rtt(),
            robot_uplink_mbps: w.network.robot_uplink_mbps,
            wan_mbps: w.network.wan_mbps,
        },
        hints: variant.hints,
        load,
        seed,
        record: false,
        policies: Policies::default(),
        replay_horizon: variant.replay_horizon.clone(),
    }
}

fn scaled(n: usize, scale: f64) -> usize {
    ((n as f64 * scale).round() as usize).max(1)
}

/// Every job of `plan` over `workloads`, in a fixed order.
pub fn plan(workloads: &[Workload], plan: &Plan) -> Vec<Job> {
    let mut jobs = Vec::new();
    for (wi, w) in workloads.iter().enumerate() {
        let x = &w.experiments;
        let tasks = scaled(x.tasks_per_run, plan.task_scale);
        let peak = x.rates.last().copied().unwrap_or(1.0);
        let mut push = |experiment, xval: f64, v: &Variant, load| {
            jobs.push(Job {
                workload: wi,
                experiment,
                x: xval,
                variant: v.clone(),
                config: SimConfig {
                    policies: plan.policies.clone(),
                    ..config(w, v, load, plan.seed)
                },
            });
        };
        for &e in &plan.experiments {
            match e {
                Experiment::Online => {
                    let mut variants = online_variants();
                    variants.extend(plan.extra.iter().cloned());
                    for &rate in &x.rates {
                        for v in &variants {
                            push(e, rate, v, Load::Poisson { rate, tasks });
                        }
                    }
                }
                Experiment::Fleet => {
                    let fleet_tasks = scaled(x.fleet_tasks, plan.task_scale);
                    for &robots in &x.fleet_sizes {
                        for v in &fleet_variants() {
                            push(
                                e,
                                robots as f64,
                                v,
                                Load::Fleet {
                                    robots,
                                    tasks: fleet_tasks,
                                },
                            );
                        }
                    }
                }
                Experiment::Hybrid => {
                    for &rate in &x.hybrid_rates {
                        for v in &hybrid_variants() {
                            push(e, rate, v, Load::Poisson { rate, tasks });
                        }
                    }
                }
                Experiment::Buckets => {
                    for v in &bucket_variants() {
                        push(e, peak, v, Load::Poisson { rate: peak, tasks });
                    }
                }
                Experiment::Intra => {
                    for v in &intra_variants() {
                        push(e, peak, v, Load::Poisson { rate: peak, tasks });
                    }
                }
                Experiment::Refetch => {
                    for v in &refetch_variants() {
                        push(e, peak, v, Load::Poisson { rate: peak, tasks });
                    }
                }
                Experiment::Scale => {
                    // Not scaled by `task_scale`: the fleet size is the experiment's x.
                    for &robots in &plan.scale.robots {
                        let mut v = scale_variant();
                        v.placement = Placement::Workers(plan.scale.workers(robots));
                        push(
                            e,
                            robots as f64,
                            &v,
                            Load::Fleet {
                                robots,
                                tasks: robots,
                            },
                        );
                    }
                }
                Experiment::LoadHorizon => {
                    for &rate in &x.rates {
                        for v in &load_horizon_variants() {
                            push(e, rate, v, Load::Poisson { rate, tasks });
                        }
                    }
                }
            }
        }
    }
    jobs
}

/// The outcome of one job.
#[derive(Clone, Debug, PartialEq)]
pub struct JobResult {
    /// End-to-end latency summary, seconds.
    pub summary: Summary,
    /// Every task's latency, seconds, in completion order.
    pub latencies: Vec<f64>,
    /// Requests per task, mean.
    pub rounds_per_task: f64,
    /// Mean batch size.
    pub mean_batch: f64,
    /// Share of requests re-fetched.
    pub refetch_share: f64,
    /// Share of requests served in the cloud.
    pub cloud_share: f64,
    /// Mean queueing delay per request, seconds.
    pub mean_queue_s: f64,
    /// Events the simulation processed.
    pub events: u64,
    /// The scale experiment's measurements (its jobs only).
    pub scale: Option<ScaleStats>,
    /// Mean horizon over answered requests (`None` where the run does not report it: a live
    /// replay).
    pub mean_horizon: Option<f64>,
    /// Actions per task run past their chunk's recorded horizon ([`SimResult::beyond_cut_actions`];
    /// `None` as `mean_horizon`).
    pub beyond_cut_per_task: Option<f64>,
}

/// Runs one job against its workload's trace set. A scale job is timed
/// ([`super::simulate_timed`]).
pub fn run_job(job: &Job, traces: &TraceSet) -> Result<JobResult, SimError> {
    let (r, scale) = if job.experiment == Experiment::Scale {
        let (r, timing) = simulate_timed(traces, &job.config)?;
        let robots = match job.config.load {
            Load::Fleet { robots, .. } => robots,
            _ => r.tasks.len(),
        };
        let stats = ScaleStats::new(robots, job.config.engines.len(), &r, &timing);
        (r, Some(stats))
    } else {
        (simulate(traces, &job.config)?, None)
    };
    let latencies = r.latencies();
    let requests = r.requests.max(1) as f64;
    Ok(JobResult {
        summary: summarize(&latencies),
        rounds_per_task: r.requests as f64 / r.tasks.len().max(1) as f64,
        mean_batch: r.mean_batch(),
        refetch_share: r.refetches as f64 / requests,
        cloud_share: r.cloud_requests as f64 / requests,
        mean_queue_s: r.queue_s / requests,
        events: r.events,
        mean_horizon: Some(r.mean_horizon()),
        beyond_cut_per_task: Some(r.beyond_cut_actions as f64 / r.tasks.len().max(1) as f64),
        latencies,
        scale,
    })
}

/// Runs `jobs` on `threads` threads (at least 1), calling `on_done` after each. Results come
/// back in job order whatever the interleaving.
pub fn run_jobs(
    jobs: &[Job],
    traces: &[TraceSet],
    threads: usize,
    on_done: &(dyn Fn(&Job) + Sync),
) -> Vec<Result<JobResult, SimError>> {
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Result<JobResult, SimError>>>> =
        Mutex::new((0..jobs.len()).map(|_| None).collect());
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(job) = jobs.get(i) else {
                        break;
                    };
                    let result = match traces.get(job.workload) {
                        Some(t) => run_job(job, t),
                        None => Err(SimError::Config(format!(
                            "no trace set for workload {}",
                            job.workload
                        ))),
                    };
                    if let Ok(mut slots) = results.lock() {
                        slots[i] = Some(result);
                    }
                    on_done(job);
                }
            });
        }
    });
    results
        .into_inner()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
        .into_iter()
        .map(|r| r.unwrap_or_else(|| Err(SimError::Config("job did not run".into()))))
        .collect()
}

/// The arrival rate at which `variant`'s average end-to-end latency on `w` reaches `factor` times
/// its unloaded value, by bisection over `[lo, hi]` tasks/s (`iterations` halvings). Used to place
/// each shipped workload's peak rate by one rule (docs/EVALUATION.md, "Rates").
pub fn calibrate_rate(
    w: &Workload,
    traces: &TraceSet,
    variant: &Variant,
    factor: f64,
    (lo, hi): (f64, f64),
    iterations: u32,
    seed: u64,
) -> Result<f64, SimError> {
    let tasks = w.experiments.tasks_per_run;
    let mean_at = |rate: f64| -> Result<f64, SimError> {
        let r = simulate(
            traces,
            &config(w, variant, Load::Poisson { rate, tasks }, seed),
        )?;
        Ok(summarize(&r.latencies()).mean)
    };
    let unloaded = mean_at(lo)?;
    let target = unloaded * factor;
    let (mut a, mut b) = (lo, hi);
    for _ in 0..iterations {
        let mid = 0.5 * (a + b);
        if mean_at(mid)? < target {
            a = mid;
        } else {
            b = mid;
        }
    }
    Ok(0.5 * (a + b))
}

/// The paper's published reductions at peak (Table "benchmarks-latency-reduction"), for the
/// side-by-side: `[P25, avg, P95]` in percent, for Kairos, Kairos w/o dynamic horizon, and the
/// baseline scheduler with the dynamic horizon ("Kairos w/o scheduler").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PaperRow {
    /// Workload title as in the paper.
    pub title: &'static str,
    /// vs FIFO.
    pub vs_fifo: [[f64; 3]; 3],
    /// vs Autellix.
    pub vs_autellix: [[f64; 3]; 3],
}

/// The six rows of the paper's table that have a shipped workload.
pub const PAPER: [PaperRow; 6] = [
    PaperRow {
        title: "LIBERO/SmolVLA",
        vs_fifo: [[39.5, 31.8, 34.6], [21.1, 10.9, 9.9], [3.9, 16.8, 29.0]],
        vs_autellix: [[41.9, 33.1, 36.1], [24.2, 12.5, 11.9], [8.0, 15.1, 25.5]],
    },
    PaperRow {
        title: "LIBERO/Pi0.5",
        vs_fifo: [[76.4, 65.6, 51.9], [57.0, 33.0, 5.7], [58.0, 54.9, 49.6]],
        vs_autellix: [[77.4, 66.5, 52.0], [59.0, 34.6, 5.9], [55.8, 53.9, 49.8]],
    },
    PaperRow {
        title: "MetaWorld/SmolVLA",
        vs_fifo: [[86.9, 60.5, 43.0], [59.0, 34.1, 4.3], [49.9, 43.7, 39.3]],
        vs_autellix: [[88.4, 63.6, 48.2], [63.5, 39.3, 13.2], [44.5, 41.3, 36.0]],
    },
    PaperRow {
        title: "Isaac/GR00T N1.5",
        vs_fifo: [[59.2, 41.6, 29.0], [41.7, 24.5, 7.6], [24.0, 25.4, 23.4]],
        vs_autellix: [[61.6, 43.3, 29.2], [45.2, 26.7, 7.9], [27.5, 24.2, 22.9]],
    },
    PaperRow {
        title: "Bimanual/Pi0.5",
        vs_fifo: [[53.3, 39.9, 22.2], [47.9, 28.1, 4.1], [24.9, 24.3, 18.9]],
        vs_autellix: [[55.9, 42.3, 24.6], [50.8, 31.0, 7.0], [23.9, 23.1, 19.8]],
    },
    PaperRow {
        title: "RoboTwin/Fast-WAM",
        vs_fifo: [[57.9, 33.0, 25.7], [29.0, 8.1, 8.0], [46.5, 32.5, 21.7]],
        vs_autellix: [[62.4, 36.6, 25.2], [36.6, 12.9, 7.3], [44.2, 34.2, 22.5]],
    },
];

/// Jobs with their results, ready to render.
pub struct Report<'a> {
    /// The workloads, indexed by `Job::workload`.
    pub workloads: &'a [Workload],
    /// The jobs.
    pub jobs: &'a [Job],
    /// Their results, same order.
    pub results: &'a [JobResult],
}

fn pct(v: f64) -> String {
    format!("{v:.1}%")
}

impl Report<'_> {
    /// The result of `key` in `experiment` of workload `w` at `x`.
    pub fn find(&self, w: usize, experiment: Experiment, x: f64, key: &str) -> Option<&JobResult> {
        self.jobs
            .iter()
            .zip(self.results)
            .find(|(j, _)| {
                j.workload == w && j.experiment == experiment && j.x == x && j.variant.key == key
            })
            .map(|(_, r)| r)
    }

    /// Variants of `experiment` that ran for workload `w`, in first-seen order.
    pub fn variants(&self, w: usize, experiment: Experiment) -> Vec<&Variant> {
        let mut out: Vec<&Variant> = Vec::new();
        for j in self.jobs {
            if j.workload == w
                && j.experiment == experiment
                && !out.iter().any(|v| v.key == j.variant.key)
            {
                out.push(&j.variant);
            }
        }
        out
    }

    /// The x values of `experiment` for workload `w`, increasing.
    pub fn xs(&self, w: usize, experiment: Experiment) -> Vec<f64> {
        let mut xs: Vec<f64> = self
            .jobs
            .iter()
            .filter(|j| j.workload == w && j.experiment == experiment)
            .map(|j| j.x)
            .collect();
        xs.sort_by(f64::total_cmp);
        xs.dedup();
        xs
    }

    fn peak(&self, w: usize) -> Option<f64> {
        self.xs(w, Experiment::Online).last().copied()
    }

    /// The paper's Table "benchmarks-latency-reduction" from our runs, at each workload's peak
    /// rate: P25 / avg / P95 reductions of Kairos, Kairos w/o dynamic horizon and "Kairos w/o
    /// scheduler" (the baseline with the dynamic horizon), against `baseline` (`fifo` or
    /// `autellix`), with the paper's numbers beside ours.
    pub fn reduction_table(&self, baseline: &str) -> String {
        let mut s = String::new();
        let paper_side = |row: &PaperRow| {
            if baseline == "fifo" {
                row.vs_fifo
            } else {
                row.vs_autellix
            }
        };
        let _ = writeln!(
            s,
            "| Workload | Kairos P25 | Avg | P95 | w/o dyn. horizon P25 | Avg | P95 | w/o scheduler P25 | Avg | P95 |"
        );
        let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
        for (wi, w) in self.workloads.iter().enumerate() {
            let Some(peak) = self.peak(wi) else { continue };
            let get = |k: &str| self.find(wi, Experiment::Online, peak, k);
            let dynamic_base = format!("{baseline}-dynamic");
            let cells = [
                (get(baseline), get("kairos")),
                (get(baseline), get("kairos-static")),
                (get(baseline), get(&dynamic_base)),
            ];
            let mut line = format!("| {} (ours) ", w.title);
            for (base, ours) in cells {
                match (base, ours) {
                    (Some(b), Some(o)) => {
                        for (bv, ov) in [
                            (b.summary.p25, o.summary.p25),
                            (b.summary.mean, o.summary.mean),
                            (b.summary.p95, o.summary.p95),
                        ] {
                            let _ = write!(line, "| {} ", pct(reduction(bv, ov)));
                        }
                    }
                    _ => line.push_str("| – | – | – "),
                }
            }
            let _ = writeln!(s, "{line}|");
            if let Some(row) = PAPER.iter().find(|r| r.title == w.title) {
                let mut line = format!("| {} (paper) ", w.title);
                for cell in paper_side(row) {
                    for v in cell {
                        let _ = write!(line, "| {} ", pct(v));
                    }
                }
                let _ = writeln!(s, "{line}|");
            }
        }
        s
    }

    /// Absolute P25 / avg / P95 latencies (seconds) of every online variant at each workload's
    /// peak, with the reduction of the average against Kairos.
    pub fn peak_table(&self) -> String {
        let mut s = String::new();
        for (wi, w) in self.workloads.iter().enumerate() {
            let Some(peak) = self.peak(wi) else { continue };
            let _ = writeln!(s, "\n**{}** at {peak} tasks/s\n", w.title);
            let _ = writeln!(
                s,
                "| System | P25 (s) | Avg (s) | P95 (s) | Avg vs Kairos | P95 vs Kairos | rounds/task | batch | re-fetched |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
            let kairos = self.find(wi, Experiment::Online, peak, "kairos");
            for v in self.variants(wi, Experiment::Online) {
                let Some(r) = self.find(wi, Experiment::Online, peak, &v.key) else {
                    continue;
                };
                let (vs_avg, vs_p95) = match kairos {
                    Some(k) => (
                        pct(reduction(k.summary.mean, r.summary.mean)),
                        pct(reduction(k.summary.p95, r.summary.p95)),
                    ),
                    None => ("–".into(), "–".into()),
                };
                let _ = writeln!(
                    s,
                    "| {} | {:.2} | {:.2} | {:.2} | {} | {} | {:.1} | {:.2} | {:.0}% |",
                    v.label,
                    r.summary.p25,
                    r.summary.mean,
                    r.summary.p95,
                    vs_avg,
                    vs_p95,
                    r.rounds_per_task,
                    r.mean_batch,
                    r.refetch_share * 100.0
                );
            }
        }
        s
    }

    /// The re-fetch ablation at each workload's peak: every online system with its own re-fetch
    /// setting and with it flipped, average (P95) latency, rounds per task and share of requests
    /// re-fetched. Replayed work is fixed, so the rounds must not move.
    pub fn refetch_table(&self) -> String {
        let mut s = String::new();
        for (wi, w) in self.workloads.iter().enumerate() {
            let Some(&x) = self.xs(wi, Experiment::Refetch).last() else {
                continue;
            };
            let _ = writeln!(s, "\n**{}** at {x} tasks/s\n", w.title);
            let _ = writeln!(
                s,
                "| System | own re-fetch | avg (P95) s | rounds/task | re-fetched | flipped: avg (P95) s | rounds/task | re-fetched | avg change |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
            for own in online_variants() {
                let flipped = own.refetch_flipped();
                let (Some(a), Some(b)) = (
                    self.find(wi, Experiment::Refetch, x, &own.key),
                    self.find(wi, Experiment::Refetch, x, &flipped.key),
                ) else {
                    continue;
                };
                let _ = writeln!(
                    s,
                    "| {} | {} | {:.2} ({:.2}) | {:.1} | {:.0}% | {:.2} ({:.2}) | {:.1} | {:.0}% | {} |",
                    own.label,
                    if own.refetch { "on" } else { "off" },
                    a.summary.mean,
                    a.summary.p95,
                    a.rounds_per_task,
                    a.refetch_share * 100.0,
                    b.summary.mean,
                    b.summary.p95,
                    b.rounds_per_task,
                    b.refetch_share * 100.0,
                    pct(-reduction(a.summary.mean, b.summary.mean)),
                );
            }
        }
        s
    }

    /// Average latency per x for `experiment` (one row per x, one column per variant), with
    /// Kairos's reduction against the first two variants where present.
    pub fn sweep_table(&self, experiment: Experiment, x_name: &str) -> String {
        let mut s = String::new();
        for (wi, w) in self.workloads.iter().enumerate() {
            let variants = self.variants(wi, experiment);
            if variants.is_empty() {
                continue;
            }
            let _ = writeln!(s, "\n**{}**\n", w.title);
            let mut header = format!("| {x_name} ");
            for v in &variants {
                let _ = write!(header, "| {} avg (P95) ", v.label);
            }
            let _ = writeln!(s, "{header}|");
            let _ = writeln!(s, "|---{}|", "|---".repeat(variants.len()));
            for x in self.xs(wi, experiment) {
                let mut line = format!("| {x} ");
                for v in &variants {
                    match self.find(wi, experiment, x, &v.key) {
                        Some(r) => {
                            let _ = write!(line, "| {:.2} ({:.2}) ", r.summary.mean, r.summary.p95);
                        }
                        None => line.push_str("| – "),
                    }
                }
                let _ = writeln!(s, "{line}|");
            }
        }
        s
    }

    /// The scale experiment, one table per workload (empty without scale runs).
    pub fn scale_table(&self) -> String {
        let mut s = String::new();
        for (wi, w) in self.workloads.iter().enumerate() {
            let runs = self.scale_runs(wi);
            if runs.is_empty() {
                continue;
            }
            let _ = writeln!(s, "\n**{}**\n", w.title);
            s.push_str(&scale::table(&runs));
        }
        s
    }

    /// The scale runs of workload `w`, smallest fleet first.
    pub fn scale_runs(&self, w: usize) -> Vec<&ScaleStats> {
        let mut runs: Vec<&ScaleStats> = self
            .jobs
            .iter()
            .zip(self.results)
            .filter(|(j, _)| j.workload == w && j.experiment == Experiment::Scale)
            .filter_map(|(_, r)| r.scale.as_ref())
            .collect();
        runs.sort_by_key(|r| r.robots);
        runs
    }

    /// The scale runs as CSV (header only without any).
    pub fn scale_csv(&self) -> String {
        let mut s = format!("{}\n", scale::CSV_HEADER);
        for (wi, w) in self.workloads.iter().enumerate() {
            for r in self.scale_runs(wi) {
                let _ = writeln!(s, "{}", scale::csv_row(&w.name, r));
            }
        }
        s
    }

    /// [`Experiment::LoadHorizon`]: per workload and arrival rate, each horizon's average (P95)
    /// latency, mean horizon and actions per task run past the threshold rule's cut.
    pub fn load_horizon_table(&self) -> String {
        let e = Experiment::LoadHorizon;
        let mut s = String::new();
        for (wi, w) in self.workloads.iter().enumerate() {
            let variants = self.variants(wi, e);
            if variants.is_empty() {
                continue;
            }
            let _ = writeln!(s, "\n**{}**\n", w.title);
            let mut header = "| tasks/s ".to_string();
            for v in &variants {
                let _ = write!(header, "| {} avg (P95) s · H · past cut ", v.label);
            }
            let _ = writeln!(s, "{header}|");
            let _ = writeln!(s, "|---{}|", "|---".repeat(variants.len()));
            for x in self.xs(wi, e) {
                let mut line = format!("| {x} ");
                for v in &variants {
                    match self.find(wi, e, x, &v.key) {
                        Some(r) => {
                            let _ = write!(
                                line,
                                "| {:.2} ({:.2}) · {:.1} · {:.1} ",
                                r.summary.mean,
                                r.summary.p95,
                                r.mean_horizon.unwrap_or(f64::NAN),
                                r.beyond_cut_per_task.unwrap_or(f64::NAN)
                            );
                        }
                        None => line.push_str("| – "),
                    }
                }
                let _ = writeln!(s, "{line}|");
            }
        }
        s
    }

    /// Every job as one CSV row.
    pub fn csv(&self) -> String {
        let mut s = String::from(
            "workload,experiment,x,variant,policy,setting,hints,refetch,tasks,p25_s,mean_s,p50_s,p95_s,p99_s,max_s,rounds_per_task,mean_batch,refetch_share,cloud_share,mean_queue_s,events\n",
        );
        for (j, r) in self.jobs.iter().zip(self.results) {
            let w = &self.workloads[j.workload];
            let m = &r.summary;
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.2},{:.3},{:.4},{:.4},{:.4},{}",
                w.name,
                j.experiment.name(),
                j.x,
                j.variant.key,
                j.variant.policy,
                j.variant.setting,
                j.variant.hints,
                j.variant.refetch,
                m.n,
                m.p25,
                m.mean,
                m.p50,
                m.p95,
                m.p99,
                m.max,
                r.rounds_per_task,
                r.mean_batch,
                r.refetch_share,
                r.cloud_share,
                r.mean_queue_s,
                r.events
            );
        }
        s
    }
}
