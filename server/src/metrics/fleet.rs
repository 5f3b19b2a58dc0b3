//! The fleet snapshot behind the fleet page: `GET /api/fleet` on the metrics listener.
//!
//! A [`FleetView`] reads only what the process already counts for `/metrics`: the driver core's
//! latest report (queue, tasks, engines, round latency and horizon histograms), the action
//! manager's fallbacks, the plugins' fallbacks and quarantine, the doors' robot connections and
//! refusals, the removed workers. It adds one thing, memory: a sample of the report's
//! histograms and engines' busy time every [`SAMPLE_EVERY`], kept for [`WINDOW`], so that the
//! snapshot can show percentiles over the last minute rather than since the start, as
//! Prometheus's `rate()` would. Nothing in it names a robot or carries a token; engine names
//! are the ones `/metrics` labels.
//!
//! The JSON is documented in `docs/SERVER.md` ("The fleet page"); [`SCHEMA`] changes when a field
//! changes meaning or goes away.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use kairos_core::driver::{DriverReport, Histogram};
use kairos_core::error::LossReason;
use kairos_core::sync::lock;
use serde::Serialize;

use super::driver::tier_label;
use super::{DoorConnections, Metrics, PluginHealth, Readiness, RefusalCount};

/// The snapshot's schema version (`schema` in the JSON).
pub const SCHEMA: u32 = 1;
/// How often the listener records a sample.
pub const SAMPLE_EVERY: Duration = Duration::from_secs(1);
/// The window of the snapshot's percentiles, rates and horizon distribution.
pub const WINDOW: Duration = Duration::from_secs(60);
/// The window of each point of the latency history and of the engines' busy share: short, so
/// that the chart moves.
pub const RECENT: Duration = Duration::from_secs(10);
/// Points in the latency history (one per [`SAMPLE_EVERY`] at most).
const HISTORY_POINTS: usize = 60;

/// The report's cumulative quantities at one instant.
#[derive(Clone, Debug)]
struct Sample {
    at: Instant,
    latency: Histogram,
    horizon: Histogram,
    batch_size: Histogram,
    /// Busy time per engine name, seconds.
    busy: BTreeMap<String, f64>,
}

impl Sample {
    fn of(at: Instant, report: &DriverReport) -> Sample {
        Sample {
            at,
            latency: report.stats.round_latency.clone(),
            horizon: report.stats.horizon.clone(),
            batch_size: report.stats.batch_size.clone(),
            busy: report
                .engines
                .iter()
                .map(|e| (e.name.clone(), e.busy_time.as_secs_f64()))
                .collect(),
        }
    }
}

/// What `/api/fleet` serves, refreshed from the process's metrics at each request.
#[derive(Debug)]
pub struct FleetView {
    metrics: Metrics,
    ready: Readiness,
    /// Oldest first; spans a little more than [`WINDOW`].
    samples: Mutex<VecDeque<Sample>>,
}

/// `GET /api/fleet`: the fleet now and over the last [`WINDOW`].
#[derive(Clone, Debug, Serialize)]
pub struct FleetSnapshot {
    /// [`SCHEMA`].
    pub schema: u32,
    /// The process.
    pub server: ServerFacts,
    /// Robot connections.
    pub robots: RobotFacts,
    /// Tasks open now and ended so far.
    pub tasks: TaskFacts,
    /// The scheduler's queue now.
    pub queue: QueueFacts,
    /// Totals since the start.
    pub rounds: RoundTotals,
    /// Rates, percentiles and distributions over the last [`WINDOW`] (less right after the
    /// start).
    pub window: WindowFacts,
    /// p50 and p99 of the round latency, each over the [`RECENT`] seconds before its point,
    /// oldest first.
    pub latency_history: Vec<LatencyPoint>,
    /// Engine instances: local engines and remote workers.
    pub engines: Vec<EngineFacts>,
    /// Rounds re-dispatched after their worker failed, by reason.
    pub redispatched_total: BTreeMap<&'static str, u64>,
    /// Remote workers taken out of the pool, by reason.
    pub workers_removed_total: BTreeMap<&'static str, u64>,
    /// Guard refusals by door and reason, since the start.
    pub refusals: Vec<RefusalCount>,
    /// Policy plugins: fallbacks and quarantine.
    pub plugins: Vec<PluginHealth>,
    /// Rounds whose horizon policy fell back to the server's native one, by policy (only the
    /// policies that fell back at least once).
    pub horizon_fallbacks: BTreeMap<String, u64>,
}

/// The process.
#[derive(Clone, Debug, Serialize)]
pub struct ServerFacts {
    /// `kairos/<version>`.
    pub version: String,
    /// Seconds since the metrics registry was built.
    pub uptime_seconds: f64,
    /// What `/ready` answers.
    pub ready: bool,
    /// Whether the driver thread runs (`kairos_driver_alive`).
    pub driver_alive: bool,
}

/// Robot connections.
#[derive(Clone, Debug, Serialize)]
pub struct RobotFacts {
    /// Authenticated robot connections open now, all doors.
    pub connected: u64,
    /// Per door.
    pub doors: Vec<DoorConnections>,
}

/// Tasks.
#[derive(Clone, Debug, Serialize)]
pub struct TaskFacts {
    /// Open now.
    pub open: u64,
    /// Ended (explicitly or by expiry) since the start.
    pub ended_total: u64,
}

/// The queue now.
#[derive(Clone, Debug, Serialize)]
pub struct QueueFacts {
    /// Rounds waiting for dispatch.
    pub depth: u64,
    /// Rounds in batches that have not finished.
    pub running: u64,
}

/// Totals since the start.
#[derive(Clone, Debug, Serialize)]
pub struct RoundTotals {
    /// Rounds answered.
    pub answered: u64,
    /// Rounds whose generation failed.
    pub failed: u64,
    /// Rounds the scheduler refused.
    pub refused: u64,
    /// Rounds answered after their robot ran out of actions.
    pub deadline_misses: u64,
    /// Batches run.
    pub batches: u64,
}

/// Over the window.
#[derive(Clone, Debug, Serialize)]
pub struct WindowFacts {
    /// Its length, seconds.
    pub seconds: f64,
    /// Rounds answered in it.
    pub rounds: u64,
    /// `rounds / seconds`.
    pub rounds_per_second: f64,
    /// Round latency percentiles, seconds; `null` without a round in the window.
    pub latency_seconds: Percentiles,
    /// Mean requests per batch; `null` without a batch.
    pub batch_size_mean: Option<f64>,
    /// Executed horizons: rounds per bucket (`le`: the bucket's upper bound in actions; the
    /// last bucket, `null`, holds longer horizons).
    pub horizon: Vec<Bucket>,
}

/// Percentiles estimated from histogram buckets, as Prometheus's `histogram_quantile` does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Percentiles {
    /// Median.
    pub p50: Option<f64>,
    /// 90th percentile.
    pub p90: Option<f64>,
    /// 99th percentile.
    pub p99: Option<f64>,
}

/// One histogram bucket.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Bucket {
    /// Upper bound; `None` for `+Inf`.
    pub le: Option<f64>,
    /// Observations in this bucket alone.
    pub count: u64,
}

/// One point of the latency history.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct LatencyPoint {
    /// When, relative to the snapshot (negative: in the past).
    pub seconds_ago: f64,
    /// Median over the [`RECENT`] seconds before it.
    pub p50: Option<f64>,
    /// 99th percentile over the same.
    pub p99: Option<f64>,
}

/// One engine instance.
#[derive(Clone, Debug, Serialize)]
pub struct EngineFacts {
    /// Its name, as `/metrics` labels it.
    pub name: String,
    /// `edge` or `cloud`.
    pub tier: &'static str,
    /// `ready` or `draining`.
    pub state: &'static str,
    /// Whether it is a remote worker (it has a measured round trip).
    pub remote: bool,
    /// Whether a batch runs on it now.
    pub busy: bool,
    /// Fraction of the last [`RECENT`] seconds it spent running forward passes.
    pub busy_share: f64,
    /// A remote worker's moving-average round trip, milliseconds.
    pub rtt_ms: Option<f64>,
}

impl FleetView {
    /// The view of a scheduler's metrics; `None` for a worker process (no driver to show).
    pub fn new(metrics: Metrics, ready: Readiness) -> Option<FleetView> {
        metrics.driver()?;
        Some(FleetView {
            metrics,
            ready,
            samples: Mutex::new(VecDeque::new()),
        })
    }

    fn report(&self) -> DriverReport {
        self.metrics
            .driver()
            .map(super::DriverExport::report)
            .unwrap_or_default()
    }

    fn samples(&self) -> std::sync::MutexGuard<'_, VecDeque<Sample>> {
        lock(&self.samples)
    }

    /// Records the report's cumulative quantities at `now`, and forgets samples the window no
    /// longer needs (the newest one at least [`WINDOW`] old stays, as the window's start).
    pub fn sample(&self, now: Instant) {
        let sample = Sample::of(now, &self.report());
        let mut samples = self.samples();
        samples.push_back(sample);
        while samples
            .get(1)
            .is_some_and(|next| now.saturating_duration_since(next.at) >= WINDOW)
        {
            samples.pop_front();
        }
    }

    /// The snapshot at `now`.
    pub fn snapshot(&self, now: Instant) -> FleetSnapshot {
        let report = self.report();
        let current = Sample::of(now, &report);
        let samples = self.samples();
        let started = now.checked_sub(self.metrics.uptime()).unwrap_or(now);
        // The window's start: the oldest sample (at most about WINDOW old), or the start with
        // every histogram empty.
        let base = samples.front().cloned().unwrap_or_else(|| Sample {
            at: started,
            ..Sample::of(started, &DriverReport::default())
        });
        let seconds = now.saturating_duration_since(base.at).as_secs_f64();
        let rounds = current.latency.count().saturating_sub(base.latency.count());
        let batches = current
            .batch_size
            .count()
            .saturating_sub(base.batch_size.count());
        let batch_size_mean = (batches > 0)
            .then(|| (current.batch_size.sum() - base.batch_size.sum()) / batches as f64);
        let window = WindowFacts {
            seconds,
            rounds,
            rounds_per_second: if seconds > 0.0 {
                rounds as f64 / seconds
            } else {
                0.0
            },
            latency_seconds: percentiles(&current.latency, &base.latency),
            batch_size_mean,
            horizon: bucket_delta(&current.horizon, &base.horizon),
        };

        // Each history point: the percentiles over RECENT before a sample.
        let recorded: Vec<&Sample> = samples.iter().chain(Some(&current)).collect();
        let mut latency_history = Vec::new();
        for (i, point) in recorded.iter().enumerate() {
            let from = recorded[..i]
                .iter()
                .rev()
                .find(|s| point.at.saturating_duration_since(s.at) >= RECENT)
                .or_else(|| recorded.first())
                .copied();
            let Some(from) = from.filter(|from| from.at < point.at) else {
                continue;
            };
            let p = percentiles(&point.latency, &from.latency);
            latency_history.push(LatencyPoint {
                seconds_ago: -now.saturating_duration_since(point.at).as_secs_f64(),
                p50: p.p50,
                p99: p.p99,
            });
        }
        let skip = latency_history.len().saturating_sub(HISTORY_POINTS);
        latency_history.drain(..skip);

        let engines = report
            .engines
            .iter()
            .map(|e| {
                // Busy share over RECENT: from the newest sample at least that old that knew
                // the engine, else from the oldest that did (it joined less than RECENT ago).
                let knew = |s: &&Sample| s.busy.contains_key(&e.name);
                let from = samples
                    .iter()
                    .rev()
                    .filter(knew)
                    .find(|s| now.saturating_duration_since(s.at) >= RECENT)
                    .or_else(|| samples.iter().find(knew));
                let busy_now = e.busy_time.as_secs_f64();
                let busy_share = from
                    .and_then(|from| {
                        let then = from.busy.get(&e.name)?;
                        let span = now.saturating_duration_since(from.at).as_secs_f64();
                        (span > 0.0).then(|| ((busy_now - then) / span).clamp(0.0, 1.0))
                    })
                    .unwrap_or(0.0);
                EngineFacts {
                    name: e.name.clone(),
                    tier: tier_label(e.tier),
                    state: e.state.as_str(),
                    remote: e.rtt.is_some(),
                    busy: e.busy,
                    busy_share,
                    rtt_ms: e.rtt.map(|rtt| rtt.as_secs_f64() * 1e3),
                }
            })
            .collect();
        drop(samples);

        let doors = self.metrics.robot_connections();
        let stats = &report.stats;
        FleetSnapshot {
            schema: SCHEMA,
            server: ServerFacts {
                version: format!("kairos/{}", env!("CARGO_PKG_VERSION")),
                uptime_seconds: self.metrics.uptime().as_secs_f64(),
                ready: self.ready.is_ready(),
                driver_alive: self
                    .metrics
                    .driver()
                    .is_some_and(super::DriverExport::is_alive),
            },
            robots: RobotFacts {
                connected: doors.iter().map(|d| d.connected).sum(),
                doors,
            },
            tasks: TaskFacts {
                open: u64::try_from(report.open_tasks).unwrap_or(u64::MAX),
                ended_total: stats.tasks_ended,
            },
            queue: QueueFacts {
                depth: u64::try_from(report.queue_depth).unwrap_or(u64::MAX),
                running: u64::try_from(report.running).unwrap_or(u64::MAX),
            },
            rounds: RoundTotals {
                answered: stats.replies,
                failed: stats.failed,
                refused: stats.refused,
                deadline_misses: stats.deadline_misses,
                batches: stats.batches,
            },
            window,
            latency_history,
            engines,
            redispatched_total: LossReason::ALL
                .iter()
                .map(|&r| (r.as_str(), stats.redispatched.get(r)))
                .collect(),
            workers_removed_total: self.metrics.workers_removed(),
            refusals: self.metrics.refusals(),
            plugins: self.metrics.plugins(),
            horizon_fallbacks: self
                .metrics
                .driver()
                .map(super::DriverExport::horizon_fallbacks)
                .unwrap_or_default()
                .into_iter()
                .filter(|&(_, count)| count > 0)
                .collect(),
        }
    }

    /// [`FleetView::snapshot`] as JSON.
    pub fn json(&self, now: Instant) -> String {
        serde_json::to_string(&self.snapshot(now)).unwrap_or_else(|error| {
            // Every field is a number, a string, a bool or a collection of them.
            tracing::error!(%error, "cannot encode the fleet snapshot");
            String::from("{}")
        })
    }
}

/// Observations in each bucket of `now` less `then` (same bounds), `+Inf` last.
fn bucket_delta(now: &Histogram, then: &Histogram) -> Vec<Bucket> {
    let then = then.buckets();
    now.buckets()
        .iter()
        .enumerate()
        .map(|(i, &(bound, count))| Bucket {
            le: bound.is_finite().then_some(bound),
            count: count.saturating_sub(then.get(i).map_or(0, |b| b.1)),
        })
        .collect()
}

/// p50, p90 and p99 of the observations `now` has and `then` had not.
fn percentiles(now: &Histogram, then: &Histogram) -> Percentiles {
    let buckets = bucket_delta(now, then);
    Percentiles {
        p50: quantile(0.5, &buckets),
        p90: quantile(0.9, &buckets),
        p99: quantile(0.99, &buckets),
    }
}

/// The `q` quantile of `buckets` as Prometheus's `histogram_quantile` estimates it: linear
/// within the bucket that holds the rank, from the previous bound (0 for the first); a rank in
/// the `+Inf` bucket answers the largest finite bound. `None` without observations.
pub fn quantile(q: f64, buckets: &[Bucket]) -> Option<f64> {
    let total: u64 = buckets.iter().map(|b| b.count).sum();
    if total == 0 {
        return None;
    }
    let rank = q.clamp(0.0, 1.0) * total as f64;
    let mut below = 0u64;
    let mut lower = 0.0;
    let mut last_finite = 0.0;
    for bucket in buckets {
        let Some(upper) = bucket.le else {
            return Some(last_finite);
        };
        let cumulative = below + bucket.count;
        if bucket.count > 0 && cumulative as f64 >= rank {
            let into = (rank - below as f64) / bucket.count as f64;
            return Some(lower + (upper - lower) * into.clamp(0.0, 1.0));
        }
        below = cumulative;
        lower = upper;
        last_finite = upper;
    }
    Some(last_finite)
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use kairos_core::driver::{DriverStats, EngineReport, EngineState};
    use kairos_core::scheduler::Tier;

    use super::*;

    fn report(latencies: &[f64], horizons: &[f64], busy_ms: u64) -> DriverReport {
        let mut stats = DriverStats {
            round_latency: Histogram::round_latency(),
            batch_size: Histogram::batch_size(),
            horizon: Histogram::horizon(),
            replies: latencies.len() as u64,
            ..DriverStats::default()
        };
        for &l in latencies {
            stats.round_latency.observe(l);
        }
        for &h in horizons {
            stats.horizon.observe(h);
        }
        stats.batch_size.observe(2.0);
        DriverReport {
            stats,
            queue_depth: 5,
            running: 2,
            open_tasks: 4,
            engines: vec![EngineReport {
                name: "worker:w0@127.0.0.1".into(),
                tier: Tier::Cloud,
                state: EngineState::Ready,
                busy: true,
                busy_time: Duration::from_millis(busy_ms),
                rtt: Some(Duration::from_millis(12)),
            }],
        }
    }

    fn buckets(pairs: &[(Option<f64>, u64)]) -> Vec<Bucket> {
        pairs
            .iter()
            .map(|&(le, count)| Bucket { le, count })
            .collect()
    }

    #[test]
    fn quantiles_interpolate_within_the_bucket_like_prometheus() {
        let b = buckets(&[(Some(1.0), 0), (Some(2.0), 4), (Some(4.0), 4), (None, 0)]);
        assert_eq!(quantile(0.5, &b), Some(2.0));
        assert_eq!(quantile(0.25, &b), Some(1.5));
        assert_eq!(quantile(0.75, &b), Some(3.0));
        assert_eq!(quantile(0.5, &buckets(&[(Some(1.0), 0), (None, 0)])), None);
        // A rank beyond the last finite bound answers that bound.
        assert_eq!(
            quantile(0.99, &buckets(&[(Some(1.0), 1), (None, 9)])),
            Some(1.0)
        );
    }

    #[test]
    fn the_window_counts_only_what_happened_in_it() {
        let metrics = Metrics::new();
        let export = metrics.driver().unwrap().clone();
        let view = FleetView::new(metrics.clone(), Readiness::new()).unwrap();
        let t0 = Instant::now();
        // Before the window: ten slow rounds of horizon 16.
        export.publish(report(&[3.0; 10], &[16.0; 10], 0));
        view.sample(t0);
        // In it: four 3 ms rounds of horizon 4, and the worker busy 5 of 10 s.
        export.publish(report(
            &[[3.0; 10].as_slice(), &[0.003; 4]].concat(),
            &[[16.0; 10].as_slice(), &[4.0; 4]].concat(),
            5_000,
        ));
        let snapshot = view.snapshot(t0 + Duration::from_secs(10));
        assert_eq!(snapshot.window.rounds, 4);
        assert_eq!(snapshot.window.seconds, 10.0);
        let p50 = snapshot.window.latency_seconds.p50.unwrap();
        assert!((0.002..=0.004).contains(&p50), "{p50}");
        let horizons: u64 = snapshot.window.horizon.iter().map(|b| b.count).sum();
        assert_eq!(horizons, 4);
        let four = snapshot.window.horizon.iter().find(|b| b.le == Some(4.0));
        assert_eq!(four.map(|b| b.count), Some(4));
        assert_eq!(snapshot.queue.depth, 5);
        assert_eq!(snapshot.tasks.open, 4);
        let engine = &snapshot.engines[0];
        assert!(engine.remote && engine.busy);
        assert_eq!((engine.tier, engine.rtt_ms), ("cloud", Some(12.0)));
        assert_eq!(engine.busy_share, 0.5);
        assert_eq!(snapshot.latency_history.len(), 1);
    }

    #[test]
    fn an_engine_that_joined_recently_has_its_busy_share_since_it_joined() {
        let metrics = Metrics::new();
        let export = metrics.driver().unwrap().clone();
        let view = FleetView::new(metrics, Readiness::new()).unwrap();
        let t0 = Instant::now();
        view.sample(t0);
        let mut joined = report(&[], &[], 0);
        joined.engines[0].busy_time = Duration::ZERO;
        export.publish(joined);
        view.sample(t0 + Duration::from_secs(2));
        export.publish(report(&[], &[], 1_000));
        let snapshot = view.snapshot(t0 + Duration::from_secs(6));
        assert_eq!(
            snapshot.engines[0].busy_share, 0.25,
            "1 s busy in the 4 s since it joined"
        );
    }

    #[test]
    fn samples_older_than_the_window_are_forgotten_but_one_starts_it() {
        let metrics = Metrics::new();
        let view = FleetView::new(metrics, Readiness::new()).unwrap();
        let t0 = Instant::now();
        for s in 0..200 {
            view.sample(t0 + Duration::from_secs(s));
        }
        let samples = view.samples();
        assert_eq!(
            samples.len(),
            61,
            "60 s of samples and the one that starts the window"
        );
        let span = samples.back().unwrap().at - samples.front().unwrap().at;
        assert_eq!(span, WINDOW);
    }

    #[test]
    fn a_worker_process_has_no_fleet_view() {
        assert!(FleetView::new(Metrics::for_worker(), Readiness::new()).is_none());
    }

    #[test]
    fn the_json_carries_no_token_and_documents_its_schema() {
        let metrics = Metrics::new();
        metrics
            .driver()
            .unwrap()
            .publish(report(&[0.01], &[8.0], 0));
        let view = FleetView::new(metrics, Readiness::new()).unwrap();
        let json: serde_json::Value = serde_json::from_str(&view.json(Instant::now())).unwrap();
        assert_eq!(json["schema"], SCHEMA);
        for key in [
            "server", "robots", "tasks", "queue", "rounds", "window", "engines", "refusals",
            "plugins",
        ] {
            assert!(json.get(key).is_some(), "{key} in {json}");
        }
        assert!(!json.to_string().to_lowercase().contains("token"));
    }

    /// The page and its tests read the snapshot's numbers back: each must parse to the double
    /// that was printed. This one is a latency the fleet page once showed, which a parser that
    /// is not exact reads one unit in the last place off.
    #[test]
    fn numbers_in_the_json_read_back_to_the_same_double() {
        let printed = 0.025758241758241762_f64;
        let text = serde_json::to_string(&printed).unwrap();
        assert_eq!(text, "0.025758241758241762");
        let read: f64 = serde_json::from_str(&text).unwrap();
        assert_eq!(read.to_bits(), printed.to_bits());
    }
}
