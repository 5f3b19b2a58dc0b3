//! Workload descriptions: the data files under `workloads/` that shape a simulated fleet.
//!
//! A workload says what the robots are like (control frequency, chunk length, observation size,
//! when they send their next request), how long their tasks are, how the horizon policies behave
//! on them (static `H`, threshold `t`, and the per-round distribution of the dynamic horizon,
//! paper Fig. "horizon_cdf"), which engines serve them (latency-vs-batch profiles for an edge and
//! a cloud device, plus the network between them) and which experiments to run. Every number in
//! the shipped files carries its source or rationale in a comment next to it.
//!
//! [`generate`] turns a workload into a trace set with a seed; the simulator replays trace sets,
//! so any workload file — not only the shipped ones — can be evaluated.

pub mod generate;

use std::path::Path;
use std::time::Duration;

use serde::Deserialize;

pub use generate::{GenerateError, generate};

/// Why a workload file was refused.
#[derive(Debug, thiserror::Error)]
pub enum WorkloadError {
    /// The file could not be read.
    #[error("cannot read {path}")]
    Read {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not valid TOML for a workload.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: String,
        /// The TOML error, with line and column.
        message: String,
    },
    /// A value is out of range or inconsistent with another.
    #[error("workload `{workload}`: `{field}` {reason}")]
    Invalid {
        /// The workload name.
        workload: String,
        /// The offending field, dotted.
        field: String,
        /// What is wrong.
        reason: String,
    },
}

/// A workload file.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Workload {
    /// Short identifier, used in file names and tables (`libero-smolvla`).
    pub name: String,
    /// Human title, as in the paper's tables (`LIBERO/SmolVLA`).
    pub title: String,
    /// The robots.
    pub robot: RobotSpec,
    /// The task population.
    pub tasks: TaskSpec,
    /// The horizon settings compared.
    pub horizon: HorizonSpec,
    /// The engines.
    pub engines: EnginesSpec,
    /// The network.
    pub network: NetworkSpec,
    /// What to run.
    pub experiments: ExperimentSpec,
}

/// The robot side of a workload.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RobotSpec {
    /// Actions executed per second.
    pub control_hz: f32,
    /// Actions per generated chunk `N`.
    pub chunk_len: u32,
    /// The robot sends its next request once it has executed this fraction of the current
    /// chunk's horizon (counted from the chunk's first action), in (0, 1].
    pub trigger_fraction: f64,
    /// Bytes of one observation on the wire.
    pub obs_bytes: u32,
}

/// How long tasks are.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TaskSpec {
    /// Distinct tasks in a generated trace set; runs sample from them.
    pub pool: usize,
    /// Median task length, seconds of execution.
    pub median_s: f64,
    /// Log-normal shape parameter of the task length (σ of its logarithm).
    pub sigma: f64,
    /// Shortest task, seconds.
    pub min_s: f64,
    /// Longest task, seconds.
    pub max_s: f64,
}

/// The two horizon settings of the paper's comparison.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct HorizonSpec {
    /// The static horizon the baselines use (the largest `H` that keeps the best accuracy).
    #[serde(rename = "static")]
    pub static_h: u32,
    /// `H_min` of the threshold policy (§3.1).
    pub h_min: u32,
    /// The threshold `t` Kairos uses.
    pub threshold: f64,
    /// CDF of the per-round ratio between the horizon the threshold policy picks and the
    /// static one, as `[ratio, cumulative probability]` points with increasing ratio and
    /// probability, the last at probability 1.
    pub ratio_cdf: Vec<[f64; 2]>,
    /// Mean duration of a task phase in seconds: rounds inside one phase share a ratio
    /// (execution is continuous, §3.2 Fig. "exec_latency_corr").
    pub phase_mean_s: f64,
}

/// One engine device.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EngineSpecFile {
    /// Device description, e.g. `RTX A6000 (modelled)`.
    pub device: String,
    /// `[batch, latency_ms]` points, batch 1 first, increasing.
    pub points: Vec<[f64; 2]>,
    /// Largest batch formed.
    pub max_batch: u32,
}

/// The engines a workload runs on.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EnginesSpec {
    /// Model name.
    pub model: String,
    /// The edge device (co-located with the robots).
    pub edge: EngineSpecFile,
    /// The cloud device, for hybrid runs.
    pub cloud: EngineSpecFile,
}

/// Links.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NetworkSpec {
    /// Robot ↔ edge server round trip, ms.
    pub robot_rtt_ms: f64,
    /// Robot → edge uplink, Mbit/s.
    pub robot_uplink_mbps: f64,
    /// Edge ↔ cloud round trip, ms.
    pub wan_rtt_ms: f64,
    /// Edge → cloud bandwidth, Mbit/s.
    pub wan_mbps: f64,
}

/// The experiments `kairos bench sim` runs on this workload.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ExperimentSpec {
    /// Poisson task arrival rates, tasks per second, increasing; the last is "peak".
    pub rates: Vec<f64>,
    /// Tasks arriving in one online run.
    pub tasks_per_run: usize,
    /// Fleet sizes of the offline experiment.
    pub fleet_sizes: Vec<usize>,
    /// Tasks in the offline experiment's fixed task list.
    pub fleet_tasks: usize,
    /// Arrival rates of the hybrid edge+cloud experiment.
    pub hybrid_rates: Vec<f64>,
}

impl Workload {
    /// Reads and validates a workload file.
    pub fn load(path: &Path) -> Result<Self, WorkloadError> {
        let text = std::fs::read_to_string(path).map_err(|source| WorkloadError::Read {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and validates workload TOML; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, WorkloadError> {
        let w: Workload = toml::from_str(text).map_err(|e| WorkloadError::Parse {
            path: origin.to_string(),
            message: e.to_string(),
        })?;
        w.validate()?;
        Ok(w)
    }

    fn invalid(&self, field: &str, reason: impl Into<String>) -> WorkloadError {
        WorkloadError::Invalid {
            workload: self.name.clone(),
            field: field.to_string(),
            reason: reason.into(),
        }
    }

    /// Checks every range and cross-field rule.
    pub fn validate(&self) -> Result<(), WorkloadError> {
        if self.name.is_empty()
            || !self
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(self.invalid("name", "must be non-empty [A-Za-z0-9_-]"));
        }
        let r = &self.robot;
        if !(r.control_hz.is_finite() && r.control_hz > 0.0 && r.control_hz <= 1000.0) {
            return Err(self.invalid("robot.control_hz", "must be in (0, 1000]"));
        }
        if r.chunk_len == 0 || r.chunk_len > kairos_sdk::trace::MAX_CHUNK_LEN {
            return Err(self.invalid("robot.chunk_len", "must be in 1..=4096"));
        }
        if !(r.trigger_fraction > 0.0 && r.trigger_fraction <= 1.0) {
            return Err(self.invalid("robot.trigger_fraction", "must be in (0, 1]"));
        }
        let t = &self.tasks;
        if t.pool == 0 {
            return Err(self.invalid("tasks.pool", "must be at least 1"));
        }
        if !(t.min_s > 0.0 && t.min_s <= t.median_s && t.median_s <= t.max_s && t.max_s.is_finite())
        {
            return Err(self.invalid("tasks", "needs 0 < min_s <= median_s <= max_s"));
        }
        if !(t.sigma >= 0.0 && t.sigma.is_finite()) {
            return Err(self.invalid("tasks.sigma", "must be finite and >= 0"));
        }
        let h = &self.horizon;
        if h.static_h == 0 || h.static_h > r.chunk_len {
            return Err(self.invalid("horizon.static", "must be in 1..=robot.chunk_len"));
        }
        if h.h_min == 0 || h.h_min > h.static_h {
            return Err(self.invalid("horizon.h_min", "must be in 1..=horizon.static"));
        }
        if !(h.threshold > 0.0 && h.threshold.is_finite()) {
            return Err(self.invalid("horizon.threshold", "must be positive"));
        }
        if !(h.phase_mean_s > 0.0 && h.phase_mean_s.is_finite()) {
            return Err(self.invalid("horizon.phase_mean_s", "must be positive"));
        }
        validate_cdf(&h.ratio_cdf).map_err(|e| self.invalid("horizon.ratio_cdf", e))?;
        for (field, e) in [
            ("engines.edge", &self.engines.edge),
            ("engines.cloud", &self.engines.cloud),
        ] {
            validate_engine(e).map_err(|reason| self.invalid(field, reason))?;
        }
        let n = &self.network;
        for (field, v) in [
            ("network.robot_rtt_ms", n.robot_rtt_ms),
            ("network.wan_rtt_ms", n.wan_rtt_ms),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(self.invalid(field, "must be finite and >= 0"));
            }
        }
        for (field, v) in [
            ("network.robot_uplink_mbps", n.robot_uplink_mbps),
            ("network.wan_mbps", n.wan_mbps),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(self.invalid(field, "must be positive"));
            }
        }
        let x = &self.experiments;
        for (field, rates) in [
            ("experiments.rates", &x.rates),
            ("experiments.hybrid_rates", &x.hybrid_rates),
        ] {
            if rates.is_empty() {
                return Err(self.invalid(field, "must not be empty"));
            }
            if rates.iter().any(|r| !(r.is_finite() && *r > 0.0))
                || rates.windows(2).any(|w| w[1] <= w[0])
            {
                return Err(self.invalid(field, "must be positive and increasing"));
            }
        }
        if x.tasks_per_run == 0 || x.fleet_tasks == 0 {
            return Err(self.invalid(
                "experiments",
                "tasks_per_run and fleet_tasks must be at least 1",
            ));
        }
        if x.fleet_sizes.is_empty() || x.fleet_sizes.contains(&0) {
            return Err(self.invalid("experiments.fleet_sizes", "must be non-empty, each >= 1"));
        }
        Ok(())
    }

    /// The edge engine's profile as the scheduler plans with it.
    pub fn edge_profile(&self) -> kairos_engine::EngineProfile {
        profile(&self.engines.model, &self.engines.edge)
    }

    /// The cloud engine's profile.
    pub fn cloud_profile(&self) -> kairos_engine::EngineProfile {
        profile(&self.engines.model, &self.engines.cloud)
    }

    /// Robot ↔ edge round trip.
    pub fn robot_rtt(&self) -> Duration {
        millis(self.network.robot_rtt_ms)
    }

    /// Edge ↔ cloud round trip.
    pub fn wan_rtt(&self) -> Duration {
        millis(self.network.wan_rtt_ms)
    }
}

fn profile(model: &str, e: &EngineSpecFile) -> kairos_engine::EngineProfile {
    kairos_engine::EngineProfile {
        model: model.to_string(),
        device: e.device.clone(),
        points: e
            .points
            .iter()
            .map(|&[b, ms]| kairos_engine::ProfilePoint {
                batch: b as u32,
                latency_ms: ms,
            })
            .collect(),
        max_batch: e.max_batch,
    }
}

fn validate_engine(e: &EngineSpecFile) -> Result<(), String> {
    if e.points.is_empty() {
        return Err("needs at least one [batch, latency_ms] point".into());
    }
    if e.points[0][0] != 1.0 {
        return Err("the first point must be batch 1".into());
    }
    for w in e.points.windows(2) {
        if w[1][0] <= w[0][0] {
            return Err("batch sizes must increase".into());
        }
        if w[1][1] < w[0][1] {
            return Err("latency must not fall as the batch grows".into());
        }
    }
    for &[b, ms] in &e.points {
        if b.fract() != 0.0 || !(1.0..=4096.0).contains(&b) {
            return Err(format!("batch {b} is not a whole number in 1..=4096"));
        }
        if !(ms > 0.0 && ms.is_finite()) {
            return Err(format!("latency {ms} ms must be positive"));
        }
    }
    if e.max_batch == 0 {
        return Err("max_batch must be at least 1".into());
    }
    Ok(())
}

fn validate_cdf(points: &[[f64; 2]]) -> Result<(), String> {
    let Some(last) = points.last() else {
        return Err("needs at least one point".into());
    };
    if points
        .iter()
        .any(|[r, p]| !(r.is_finite() && *r > 0.0 && (0.0..=1.0).contains(p)))
    {
        return Err("ratios must be positive, probabilities in [0, 1]".into());
    }
    if points
        .windows(2)
        .any(|w| w[1][0] <= w[0][0] || w[1][1] < w[0][1])
    {
        return Err("ratios must increase and probabilities must not decrease".into());
    }
    if last[1] != 1.0 {
        return Err("the last point must have probability 1".into());
    }
    Ok(())
}

/// Inverse of a piecewise-linear CDF given as `[value, probability]` points: the value at
/// cumulative probability `u` in [0, 1]. Below the first point's probability the first value is
/// returned (an atom there).
pub fn inverse_cdf(points: &[[f64; 2]], u: f64) -> f64 {
    let mut prev: Option<[f64; 2]> = None;
    for &[v, p] in points {
        if u <= p {
            return match prev {
                None => v,
                Some([v0, p0]) if p > p0 => v0 + (v - v0) * (u - p0) / (p - p0),
                Some(_) => v,
            };
        }
        prev = Some([v, p]);
    }
    points.last().map_or(1.0, |p| p[0])
}

#[cfg(test)]
pub(crate) mod tests_support {
    use super::Workload;

    pub(crate) const MINIMAL: &str = r#"
name = "tiny"
title = "Tiny/Test"
[robot]
control_hz = 10
chunk_len = 20
trigger_fraction = 0.5
obs_bytes = 1000
[tasks]
pool = 4
median_s = 3.0
sigma = 0.3
min_s = 1.0
max_s = 8.0
[horizon]
static = 6
h_min = 3
threshold = 0.4
ratio_cdf = [[1.0, 0.2], [2.0, 0.5], [3.0, 1.0]]
phase_mean_s = 1.0
[engines]
model = "toy"
edge = { device = "toy edge", points = [[1, 50.0], [4, 80.0]], max_batch = 4 }
cloud = { device = "toy cloud", points = [[1, 25.0], [4, 40.0]], max_batch = 4 }
[network]
robot_rtt_ms = 2.5
robot_uplink_mbps = 2000
wan_rtt_ms = 100
wan_mbps = 1000
[experiments]
rates = [0.5, 1.0]
tasks_per_run = 20
fleet_sizes = [2, 4]
fleet_tasks = 10
hybrid_rates = [1.0]
"#;

    /// A small valid workload for tests.
    pub(crate) fn tiny() -> Workload {
        Workload::parse(MINIMAL, "inline").expect("MINIMAL is valid")
    }
}

/// A workload's milliseconds as a duration (read values are checked finite and non-negative;
/// anything else saturates or is zero).
fn millis(ms: f64) -> Duration {
    Duration::try_from_secs_f64(ms.max(0.0) / 1e3).unwrap_or(Duration::MAX)
}

#[cfg(test)]
mod tests {
    use super::tests_support::MINIMAL;
    use super::*;

    #[test]
    fn minimal_workload_parses() {
        let w = Workload::parse(MINIMAL, "inline").unwrap();
        assert_eq!(w.horizon.static_h, 6);
        assert_eq!(w.edge_profile().latency(4), Duration::from_millis(80));
        assert_eq!(w.wan_rtt(), Duration::from_millis(100));
    }

    #[test]
    fn validation_names_the_bad_field() {
        let cases = [
            ("static = 6", "static = 60", "horizon.static"),
            ("h_min = 3", "h_min = 7", "horizon.h_min"),
            (
                "[[1.0, 0.2], [2.0, 0.5], [3.0, 1.0]]",
                "[[1.0, 0.2], [2.0, 0.5]]",
                "ratio_cdf",
            ),
            (
                "[[1, 50.0], [4, 80.0]]",
                "[[1, 50.0], [4, 30.0]]",
                "engines.edge",
            ),
            (
                "rates = [0.5, 1.0]",
                "rates = [1.0, 0.5]",
                "experiments.rates",
            ),
            (
                "trigger_fraction = 0.5",
                "trigger_fraction = 0",
                "trigger_fraction",
            ),
            ("min_s = 1.0", "min_s = 4.0", "tasks"),
        ];
        for (from, to, field) in cases {
            let text = MINIMAL.replace(from, to);
            assert_ne!(text, MINIMAL, "case {field} did not apply");
            let err = Workload::parse(&text, "inline").unwrap_err().to_string();
            assert!(err.contains(field), "{field}: {err}");
        }
    }

    #[test]
    fn unknown_fields_and_bad_toml_are_refused_with_a_location() {
        let err = Workload::parse(
            &MINIMAL.replace("pool = 4", "pool = 4\npoool = 5"),
            "w.toml",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("w.toml") && err.contains("poool"), "{err}");
        let err = Workload::parse("name = ", "w.toml").unwrap_err();
        assert!(matches!(err, WorkloadError::Parse { .. }));
    }

    #[test]
    fn inverse_cdf_interpolates_between_points() {
        let cdf = [[1.0, 0.2], [2.0, 0.5], [3.0, 1.0]];
        assert_eq!(inverse_cdf(&cdf, 0.0), 1.0);
        assert_eq!(inverse_cdf(&cdf, 0.2), 1.0);
        assert!((inverse_cdf(&cdf, 0.35) - 1.5).abs() < 1e-12);
        assert!((inverse_cdf(&cdf, 0.75) - 2.5).abs() < 1e-12);
        assert_eq!(inverse_cdf(&cdf, 1.0), 3.0);
    }

    #[test]
    fn shipped_workloads_are_valid() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../workloads");
        let mut n = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                Workload::load(&path).unwrap();
                n += 1;
            }
        }
        assert!(
            n >= 6,
            "expected the six paper workloads in {}",
            dir.display()
        );
    }
}
