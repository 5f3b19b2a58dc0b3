//! The conformance suite `kairos plugin check` runs: random valid inputs plus edge cases,
//! every answer validated, every call timed.
//!
//! Horizon cases: random chunks (S, K, N, D drawn from realistic ranges, update norms that
//! shrink over the steps with random late spikes), and the edge cases every policy meets in
//! production — all actions unconverged, all converged, `N = 1`, `K = 1`, a huge `K`,
//! several samples, `h_min = h_max`, non-finite updates. An answer outside `[h_min, h_max]`,
//! a trap, a timeout, an exceeded limit or a refusal other than `unsupported` fails the case.
//!
//! Priority cases: pending lists of 0, 1, 2, 10, 100, 1 000 and 10 000 requests with random
//! lifecycle summaries (some fields absent), all-equal summaries (ties), and extreme values.
//! Anything but a permutation of the indices fails the case.

use std::time::Duration;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::health::FailureKind;
use super::runtime::LoadError;
use super::{PluginKind, PluginOptions, PluginSource, WasmHorizonPolicy, WasmPriorityPolicy};
use kairos_core::horizon::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use kairos_core::scheduler::{
    FinishedTask, PendingView, PolicyError, PriorityPolicy, RemainingWork, RequestId, ServerLoad,
    TaskId,
};
use kairos_core::time::Timestamp;

/// What to run.
#[derive(Clone, Debug)]
pub struct CheckConfig {
    /// Parameters passed to the plugin on every call.
    pub params: PolicyParams,
    /// Random cases on top of the edge cases.
    pub random_cases: usize,
    /// Seed of the random cases (the report prints it, so a failure can be replayed).
    pub seed: u64,
}

impl Default for CheckConfig {
    fn default() -> Self {
        CheckConfig {
            params: PolicyParams::new(),
            random_cases: 200,
            seed: 0x6b61_6972_6f73,
        }
    }
}

/// One failed case.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct CaseFailure {
    /// Which case (`random #17`, `all unconverged`, ...).
    pub case: String,
    /// Why it failed.
    pub reason: String,
}

/// Call-time statistics of one group of cases.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Timing {
    /// The group (`random`, `N=50 K=10 D=7`, `1000 pending`, ...).
    pub group: String,
    /// Calls measured.
    pub calls: usize,
    /// Median.
    pub p50: Duration,
    /// 99th percentile.
    pub p99: Duration,
    /// Slowest.
    pub max: Duration,
}

/// The outcome of a check.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CheckReport {
    /// The plugin's name.
    pub plugin: String,
    /// Its world.
    pub kind: PluginKind,
    /// The `kairos:policy` version it targets.
    pub version: String,
    /// Whether it imports WASI.
    pub imports_wasi: bool,
    /// Component size in bytes.
    pub size: usize,
    /// Compile (or cache load) time.
    pub load_time: Duration,
    /// Cases run.
    pub cases: usize,
    /// Cases that failed.
    pub failures: Vec<CaseFailure>,
    /// Cases where the plugin declined with `unsupported` (allowed, reported).
    pub unsupported: Vec<CaseFailure>,
    /// Call times by group.
    pub timings: Vec<Timing>,
    /// Largest linear memory of any instance, in bytes.
    pub peak_memory: usize,
    /// The seed of the random cases.
    pub seed: u64,
}

impl CheckReport {
    /// Whether every case passed.
    pub fn passed(&self) -> bool {
        self.failures.is_empty()
    }
}

/// A parameter a plugin refused before any case ran.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ParamRefusal {
    /// The parameter.
    pub name: String,
    /// The plugin's reason.
    pub reason: String,
    /// The value given, or `None` when it was not given (the plugin requires it).
    pub given: Option<f64>,
}

/// Why a check could not run its cases.
#[derive(Debug, thiserror::Error)]
pub enum CheckError {
    /// The plugin could not be loaded.
    #[error(transparent)]
    Load(#[from] LoadError),
    /// The plugin refused the parameters on a trial call, so every case would fail alike.
    #[error("{}", describe_refusals(plugin, refused))]
    Params {
        /// The plugin.
        plugin: String,
        /// What it refused, missing parameters first in the order it named them.
        refused: Vec<ParamRefusal>,
    },
}

fn describe_refusals(plugin: &str, refused: &[ParamRefusal]) -> String {
    let missing: Vec<String> = refused
        .iter()
        .filter(|r| r.given.is_none())
        .map(|r| format!("`{}` ({})", r.name, r.reason))
        .collect();
    let invalid: Vec<String> = refused
        .iter()
        .filter_map(|r| {
            r.given
                .map(|value| format!("`{}={value}` ({})", r.name, r.reason))
        })
        .collect();
    let mut parts = Vec::new();
    if !missing.is_empty() {
        parts.push(format!(
            "plugin `{plugin}` requires {}: {}; pass {} with --param NAME=VALUE",
            if missing.len() == 1 {
                "a parameter"
            } else {
                "parameters"
            },
            missing.join(", "),
            if missing.len() == 1 { "it" } else { "them" },
        ));
    }
    if !invalid.is_empty() {
        parts.push(format!("plugin `{plugin}` refuses {}", invalid.join(", ")));
    }
    format!("{}; no cases were run", parts.join("; "))
}

/// Loads `source` (of `kind`, or whichever world it implements) and runs the suite.
/// `progress(done, total)` is called after every case.
///
/// A horizon plugin is first asked once, on a SmolVLA-sized chunk, with `config.params`; if it
/// refuses a parameter (`invalid-param`), the check stops with [`CheckError::Params`] naming
/// every parameter it requires and was not given, instead of failing every case with the same
/// refusal. (A priority plugin's parameters are checked by its load, which makes a trial call.)
pub fn check(
    source: &PluginSource,
    kind: Option<PluginKind>,
    options: PluginOptions,
    config: &CheckConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CheckReport, CheckError> {
    let kind = match kind {
        Some(kind) => kind,
        None => detect_kind(source)?,
    };
    let options = PluginOptions {
        // A check measures the plugin, not the reload machinery, and never quarantines.
        reload_poll: None,
        quarantine_after: u32::MAX,
        ..options
    };
    match kind {
        PluginKind::Horizon => check_horizon(source, options, config, progress),
        PluginKind::Priority => Ok(check_priority(source, options, config, progress)?),
    }
}

/// Most parameters a trial finds missing before it gives up.
const MAX_MISSING_PARAMS: usize = 16;

/// Asks `policy` once on `case` with `given`, and again after each refusal of a parameter that
/// was not given (with that parameter set to 1, a valid count or size for most policies), to
/// collect every parameter it requires. Stops at the first answer, at a refusal of a given
/// parameter (recorded) or of one it set itself (its placeholder was not acceptable: the
/// parameter is already recorded as missing), or at anything else.
fn refused_params(
    policy: &mut WasmHorizonPolicy,
    case: &HorizonCase,
    given: &PolicyParams,
) -> Vec<ParamRefusal> {
    let mut params = given.clone();
    let mut refused: Vec<ParamRefusal> = Vec::new();
    while refused.len() < MAX_MISSING_PARAMS {
        let Ok((Err(HorizonError::InvalidParam { name, reason }), _)) =
            policy.call_plugin(&case.input(&params))
        else {
            break;
        };
        if let Some(&value) = given.get(&name) {
            refused.push(ParamRefusal {
                name,
                reason,
                given: Some(value),
            });
            break;
        }
        if params.contains_key(&name) {
            break;
        }
        params.insert(name.clone(), 1.0);
        refused.push(ParamRefusal {
            name,
            reason,
            given: None,
        });
    }
    refused
}

fn detect_kind(source: &PluginSource) -> Result<PluginKind, LoadError> {
    let name = source.name();
    let wasm = match source {
        PluginSource::File(path) => std::fs::read(path).map_err(|e| LoadError::Read {
            path: path.clone(),
            source: e,
        })?,
        PluginSource::Bytes { wasm, .. } => wasm.clone(),
    };
    let info = super::inspect::inspect(&wasm).map_err(|source| LoadError::Inspect {
        name: name.clone(),
        source,
    })?;
    info.exports
        .first()
        .map(|(kind, _)| *kind)
        .ok_or_else(|| LoadError::Inspect {
            name,
            source: super::inspect::InspectError::NoPolicyExport {
                found: "nothing".into(),
            },
        })
}

/// A policy that never answers: a check reports plugin failures instead of hiding them.
struct NoFallback;

impl HorizonPolicy for NoFallback {
    fn name(&self) -> &str {
        "none"
    }
    fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        Err(HorizonError::Failed("no fallback during a check".into()))
    }
}

impl PriorityPolicy for NoFallback {
    fn name(&self) -> &str {
        "none"
    }
    fn order(
        &mut self,
        _: Timestamp,
        _: &[PendingView],
        _: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        Err(PolicyError::Failed("no fallback during a check".into()))
    }
}

/// A horizon test input with owned buffers.
#[derive(Clone, Debug)]
pub struct HorizonCase {
    /// Case name.
    pub name: String,
    /// Timing group.
    pub group: String,
    /// `S`, `K`, `N`, `D`.
    pub dims: (usize, usize, usize, usize),
    /// `[S][K][N][D]`.
    pub updates: Vec<f32>,
    /// `[S][N][D]`.
    pub actions: Vec<f32>,
    /// `h_min`, `h_max`.
    pub bounds: (usize, usize),
    /// Control frequency.
    pub control_hz: f32,
    /// Round index.
    pub round_index: u64,
    /// Recent horizons.
    pub recent: Vec<u32>,
    /// The server's load (`None` in a third of the random cases: no server).
    pub load: Option<ServerLoad>,
}

impl HorizonCase {
    /// Borrows it as the input a policy sees.
    pub fn input<'a>(&'a self, params: &'a PolicyParams) -> HorizonInput<'a> {
        let (samples, steps, chunk_len, action_dim) = self.dims;
        HorizonInput {
            chunk: ChunkView {
                samples,
                steps,
                chunk_len,
                action_dim,
                updates: &self.updates,
                actions: &self.actions,
            },
            h_min: self.bounds.0,
            h_max: self.bounds.1,
            control_hz: self.control_hz,
            round_index: self.round_index,
            recent_horizons: &self.recent,
            params,
            load: self.load,
        }
    }
}

/// How the per-step update norms of a generated case behave.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum UpdateShape {
    /// Shrinking over the steps, with a random late spike on some actions.
    Realistic,
    /// Every action's final update far above its earlier mean.
    AllUnconverged,
    /// Every action's final update far below its earlier mean.
    AllConverged,
}

/// A random chunk of the given dimensions.
pub fn horizon_case(
    rng: &mut StdRng,
    name: impl Into<String>,
    group: impl Into<String>,
    (s, k, n, d): (usize, usize, usize, usize),
    shape: UpdateShape,
) -> HorizonCase {
    let mut updates = Vec::with_capacity(s * k * n * d);
    // Per action: the step at which it "spikes" (for realistic shapes), or never.
    let spikes: Vec<Option<usize>> = (0..s * n)
        .map(|_| rng.random_bool(0.2).then(|| rng.random_range(0..k)))
        .collect();
    for sample in 0..s {
        for step in 0..k {
            let decay = 1.0 / (1.0 + step as f32);
            for action in 0..n {
                let scale = match shape {
                    UpdateShape::AllUnconverged if step + 1 == k => 50.0,
                    UpdateShape::AllConverged if step + 1 == k => 1e-3,
                    UpdateShape::Realistic if spikes[sample * n + action] == Some(step) => {
                        rng.random_range(1.0..4.0)
                    }
                    _ => decay,
                };
                for _ in 0..d {
                    updates.push(scale * rng.random_range(-1.0f32..1.0));
                }
            }
        }
    }
    let actions = (0..s * n * d)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    let h_min = rng.random_range(1..=n);
    let h_max = rng.random_range(h_min..=n);
    HorizonCase {
        name: name.into(),
        group: group.into(),
        dims: (s, k, n, d),
        updates,
        actions,
        bounds: (h_min, h_max),
        control_hz: [10.0, 30.0, 50.0][rng.random_range(0..3)],
        round_index: rng.random_range(0..10_000),
        recent: (0..rng.random_range(0..8))
            .map(|_| rng.random_range(1..=n as u32))
            .collect(),
        load: random_load(rng),
    }
}

/// A random server load, or (one time in three) none: idle servers, deep queues and backlogs
/// from microseconds to seconds.
pub fn random_load(rng: &mut StdRng) -> Option<ServerLoad> {
    if rng.random_range(0..3) == 0 {
        return None;
    }
    let queued = [0, rng.random_range(1..64), rng.random_range(64..4096)][rng.random_range(0..3)];
    Some(ServerLoad {
        queued,
        running: rng.random_range(0..128),
        open_tasks: queued + rng.random_range(0..256),
        backlog: if queued == 0 && rng.random_bool(0.5) {
            Duration::ZERO
        } else {
            Duration::from_nanos(rng.random_range(1..5_000_000_000))
        },
    })
}

/// The horizon suite: edge cases first, then `random` random cases.
pub fn horizon_cases(seed: u64, random: usize) -> Vec<HorizonCase> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut cases = vec![
        horizon_case(
            &mut rng,
            "SmolVLA-sized chunk (S=1 K=10 N=50 D=7)",
            "N=50 K=10 D=7",
            (1, 10, 50, 7),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "all actions unconverged",
            "edge",
            (1, 10, 50, 7),
            UpdateShape::AllUnconverged,
        ),
        horizon_case(
            &mut rng,
            "all actions converged",
            "edge",
            (1, 10, 50, 7),
            UpdateShape::AllConverged,
        ),
        horizon_case(
            &mut rng,
            "N=1",
            "edge",
            (1, 10, 1, 7),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "K=1 (no earlier steps)",
            "edge",
            (1, 1, 50, 7),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "D=1",
            "edge",
            (1, 10, 50, 1),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "4 samples",
            "edge",
            (4, 10, 50, 7),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "huge K (K=1000 N=50 D=7)",
            "huge K",
            (1, 1000, 50, 7),
            UpdateShape::Realistic,
        ),
        horizon_case(
            &mut rng,
            "pi0-sized chunk (K=10 N=50 D=32)",
            "edge",
            (1, 10, 50, 32),
            UpdateShape::Realistic,
        ),
    ];
    let mut pinned = horizon_case(
        &mut rng,
        "h_min = h_max",
        "edge",
        (1, 10, 50, 7),
        UpdateShape::Realistic,
    );
    pinned.bounds = (7, 7);
    cases.push(pinned);
    let mut full = horizon_case(
        &mut rng,
        "h_min = 1, h_max = N",
        "edge",
        (1, 10, 50, 7),
        UpdateShape::AllConverged,
    );
    full.bounds = (1, 50);
    cases.push(full);
    let mut nan = horizon_case(
        &mut rng,
        "non-finite updates",
        "edge",
        (1, 10, 50, 7),
        UpdateShape::Realistic,
    );
    nan.updates[3] = f32::NAN;
    nan.updates[40] = f32::INFINITY;
    cases.push(nan);
    for i in 0..random {
        let dims = (
            if rng.random_bool(0.1) {
                rng.random_range(2..=4)
            } else {
                1
            },
            rng.random_range(1..=16),
            rng.random_range(1..=64),
            rng.random_range(1..=14),
        );
        cases.push(horizon_case(
            &mut rng,
            format!("random #{i}"),
            "random",
            dims,
            UpdateShape::Realistic,
        ));
    }
    cases
}

fn check_horizon(
    source: &PluginSource,
    options: PluginOptions,
    config: &CheckConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CheckReport, CheckError> {
    let mut policy = WasmHorizonPolicy::load(source, options, Box::new(NoFallback))?;
    let cases = horizon_cases(config.seed, config.random_cases);
    if let Some(first) = cases.first() {
        let refused = refused_params(&mut policy, first, &config.params);
        if !refused.is_empty() {
            return Err(CheckError::Params {
                plugin: policy.meta().name,
                refused,
            });
        }
    }
    let mut failures = Vec::new();
    let mut unsupported = Vec::new();
    let mut times: Vec<(String, Duration)> = Vec::new();
    for (done, case) in cases.iter().enumerate() {
        let input = case.input(&config.params);
        match policy.call_plugin(&input) {
            Ok((Ok(_), cost)) => times.push((case.group.clone(), cost.elapsed)),
            Ok((Err(HorizonError::Unsupported(reason)), _)) => unsupported.push(CaseFailure {
                case: case.name.clone(),
                reason,
            }),
            Ok((Err(refusal), _)) => failures.push(CaseFailure {
                case: case.name.clone(),
                reason: format!("refused: {refusal}"),
            }),
            Err(failure) => failures.push(CaseFailure {
                case: case.name.clone(),
                reason: failure.to_string(),
            }),
        }
        progress(done + 1, cases.len());
    }
    let meta = policy.meta().clone();
    Ok(CheckReport {
        plugin: meta.name,
        kind: PluginKind::Horizon,
        version: meta.version.to_string(),
        imports_wasi: meta.info.imports_wasi,
        size: meta.size,
        load_time: meta.load_time,
        cases: cases.len(),
        failures,
        unsupported,
        timings: summarize(times),
        peak_memory: policy.peak_memory(),
        seed: config.seed,
    })
}

/// A random pending request at or before `now`.
pub fn random_pending(rng: &mut StdRng, i: usize, now: Timestamp) -> PendingView {
    let now_us = now.as_micros();
    let task_started = rng.random_range(0..=now_us);
    let arrived = rng.random_range(task_started..=now_us);
    let life = now_us - task_started;
    let micros = |rng: &mut StdRng, max: u64| Duration::from_micros(rng.random_range(0..=max));
    let maybe = |rng: &mut StdRng, max: u64| {
        rng.random_bool(0.8)
            .then(|| Duration::from_micros(rng.random_range(0..=max)))
    };
    PendingView {
        request: RequestId(1_000_000 + i as u64),
        task: TaskId(rng.random_range(0..1_000_000)),
        round_index: rng.random_range(0..500),
        arrived_at: Timestamp::from_micros(arrived),
        task_started_at: Timestamp::from_micros(task_started),
        skipped: if rng.random_bool(0.7) {
            0
        } else {
            rng.random_range(1..40)
        },
        wait: micros(rng, life),
        attained_service: micros(rng, life),
        queued: micros(rng, life),
        last_exec: maybe(rng, 3_000_000),
        exec_ends_at: rng
            .random_bool(0.8)
            .then(|| Timestamp::from_micros(rng.random_range(arrived..=now_us + 3_000_000))),
        last_gen: maybe(rng, 1_000_000),
        rounds_completed: rng.random_range(0..500),
        remaining: rng.random_bool(0.3).then(|| RemainingWork {
            rounds: rng.random_bool(0.7).then(|| rng.random_range(0..200)),
            seconds: rng
                .random_bool(0.7)
                .then(|| rng.random_range(0.0f32..600.0)),
        }),
    }
}

/// A random pending list of `len` requests, decided at `now`.
pub fn pending_case(rng: &mut StdRng, len: usize) -> (Timestamp, Vec<PendingView>) {
    let now = Timestamp::from_micros(rng.random_range(1_000_000..10_000_000_000));
    (now, (0..len).map(|i| random_pending(rng, i, now)).collect())
}

fn check_priority(
    source: &PluginSource,
    options: PluginOptions,
    config: &CheckConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<CheckReport, LoadError> {
    let mut policy =
        WasmPriorityPolicy::load(source, &config.params, options, Box::new(NoFallback))?;
    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut cases: Vec<(String, String, Timestamp, Vec<PendingView>)> = Vec::new();
    for len in [0usize, 1, 2, 10, 100, 1_000, 10_000] {
        let (now, pending) = pending_case(&mut rng, len);
        cases.push((
            format!("{len} pending"),
            format!("{len} pending"),
            now,
            pending,
        ));
    }
    let (now, mut ties) = pending_case(&mut rng, 100);
    let first = ties[0];
    for (i, p) in ties.iter_mut().enumerate() {
        *p = PendingView {
            request: RequestId(i as u64),
            ..first
        };
    }
    cases.push((
        "100 identical summaries (ties)".into(),
        "edge".into(),
        now,
        ties,
    ));
    let (_, mut extreme) = pending_case(&mut rng, 50);
    let now = Timestamp::from_micros(u64::MAX / 2);
    for p in &mut extreme {
        p.task_started_at = Timestamp::ZERO;
        p.arrived_at = Timestamp::ZERO;
        p.wait = Duration::from_secs(u64::MAX / 4_000_000_000_000);
        p.queued = p.wait;
        p.attained_service = Duration::ZERO;
        p.skipped = u32::MAX;
        p.last_exec = None;
        p.last_gen = None;
    }
    cases.push(("extreme values".into(), "edge".into(), now, extreme));
    let (now, mut fresh) = pending_case(&mut rng, 20);
    for p in &mut fresh {
        p.task_started_at = now;
        p.arrived_at = now;
        p.wait = Duration::ZERO;
        p.queued = Duration::ZERO;
        p.rounds_completed = 0;
        p.round_index = 0;
    }
    cases.push((
        "20 tasks that started now".into(),
        "edge".into(),
        now,
        fresh,
    ));
    for i in 0..config.random_cases {
        let len = rng.random_range(0..200);
        let (now, pending) = pending_case(&mut rng, len);
        cases.push((
            format!("random #{i}"),
            "random (0-200 pending)".into(),
            now,
            pending,
        ));
    }
    let mut failures = Vec::new();
    let mut times = Vec::new();
    let mut order = Vec::new();
    let total = cases.len() + 1;
    for (done, (name, group, now, pending)) in cases.iter().enumerate() {
        match policy.call_plugin(*now, pending, &mut order) {
            Ok(cost) => times.push((group.clone(), cost.elapsed)),
            Err(failure) => failures.push(CaseFailure {
                case: name.clone(),
                reason: if failure.kind == FailureKind::InvalidAnswer {
                    format!("{failure} (an order must list every index exactly once)")
                } else {
                    failure.to_string()
                },
            }),
        }
        progress(done + 1, total);
    }
    if let Err(failure) = policy.call_task_finished(&FinishedTask {
        task: TaskId(7),
        rounds: 12,
        latency: Duration::from_secs(40),
        attained_service: Duration::from_secs(3),
        wait: Duration::from_secs(5),
    }) {
        failures.push(CaseFailure {
            case: "task-finished".into(),
            reason: failure.to_string(),
        });
    }
    progress(total, total);
    let meta = policy.meta().clone();
    Ok(CheckReport {
        plugin: meta.name,
        kind: PluginKind::Priority,
        version: meta.version.to_string(),
        imports_wasi: meta.info.imports_wasi,
        size: meta.size,
        load_time: meta.load_time,
        cases: total,
        failures,
        unsupported: Vec::new(),
        timings: summarize(times),
        peak_memory: policy.peak_memory(),
        seed: config.seed,
    })
}

fn summarize(times: Vec<(String, Duration)>) -> Vec<Timing> {
    let mut groups: Vec<(String, Vec<Duration>)> = Vec::new();
    for (group, t) in times {
        match groups.iter_mut().find(|(g, _)| *g == group) {
            Some((_, ts)) => ts.push(t),
            None => groups.push((group, vec![t])),
        }
    }
    groups
        .into_iter()
        .map(|(group, mut ts)| {
            ts.sort_unstable();
            let secs: Vec<f64> = ts.iter().map(Duration::as_secs_f64).collect();
            // Quantiles of durations are durations: the conversion back cannot fail.
            let at = |q: f64| {
                Duration::try_from_secs_f64(kairos_core::stats::quantile(&secs, q))
                    .unwrap_or(Duration::MAX)
            };
            Timing {
                group,
                calls: ts.len(),
                p50: at(0.5),
                p99: at(0.99),
                max: ts[ts.len() - 1],
            }
        })
        .collect()
}
