//! Prometheus metrics and readiness: what `/metrics` and `/ready` serve ([`http`]).
//!
//! One [`Metrics`] per process (the scheduler's `kairos serve`, or a `kairos worker`), cheap to
//! clone (an `Arc`), owning the [`prometheus_client`] registry. Each fact has one owner, and
//! nothing here keeps a second copy of a count:
//! - the driver core counts rounds, batches, latencies, deadline misses, re-dispatches and
//!   engine busy time, and reports them as data; the driver's shell publishes each report to
//!   [`DriverExport`] and every scrape encodes the latest ([`driver`]); the action manager's
//!   fallbacks are read from it the same way;
//! - the plugin host counts its fallbacks in the [`Counter`] handed to it
//!   ([`Metrics::fallback_counter`]);
//! - the scheduler's worker registration counts the workers it removes
//!   (`kairos_worker_removed_total{reason}`), and the driver's shell says whether the driver
//!   thread runs (`kairos_driver_alive`);
//! - a `kairos worker` process ([`Metrics::for_worker`]) counts its own facts in typed families:
//!   its connection state, batches answered, heartbeats sent, compute time per batch, its
//!   engine's busy time and batch sizes, fed by `crate::worker`.
//!
//! No label names a robot or a task: a fleet of thousands must not become thousands of series.
//! Label values are engine instances, worker ids, tiers, re-dispatch reasons and policy names,
//! all bounded by the deployment's configuration.

use crate::plugin::PluginKind;

pub mod driver;
pub mod fleet;
pub mod http;
mod listener;
mod operations;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::{Registry, Unit};

use kairos_core::sync::lock;

pub use self::driver::DriverExport;
pub use self::operations::{DoorConnections, PluginHealth, RefusalCount};

/// `Content-Type` of [`Metrics::encode`]'s output (OpenMetrics text, which Prometheus scrapes).
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Shortest interval over which [`Metrics::encode`] recomputes `kairos_engine_busy_ratio`;
/// scrapes closer together than this see the previous value rather than a noisy ratio over a
/// few milliseconds.
pub const BUSY_RATIO_MIN_WINDOW: Duration = Duration::from_secs(1);

/// A worker process's connection to its scheduler, as `kairos_worker_connection{state}` shows
/// it (1 for the current state, 0 for the others).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum WorkerConnection {
    /// Dialling the scheduler or waiting for `Registered`.
    Connecting,
    /// In the scheduler's pool, taking batches.
    Registered,
    /// Sent `Drain`: finishing the batches it holds.
    Draining,
    /// Not connected (lost, drained, or refused).
    Disconnected,
}

impl WorkerConnection {
    /// Every state, in the order exported.
    pub const ALL: [WorkerConnection; 4] = [
        WorkerConnection::Connecting,
        WorkerConnection::Registered,
        WorkerConnection::Draining,
        WorkerConnection::Disconnected,
    ];

    /// The label value.
    pub fn as_str(self) -> &'static str {
        match self {
            WorkerConnection::Connecting => "connecting",
            WorkerConnection::Registered => "registered",
            WorkerConnection::Draining => "draining",
            WorkerConnection::Disconnected => "disconnected",
        }
    }
}

/// Why the scheduler removed a worker (or refused its registration), as
/// `kairos_worker_removed_total{reason}` labels it. A worker that drains is not removed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum WorkerRemoval {
    /// Its `Register` broke the protocol's rules (an unusable profile, oversized strings).
    InvalidRegistration,
    /// It answered a batch with something unusable (wrong count or shapes, non-finite values,
    /// oversized error text).
    InvalidAnswer,
    /// A batch's deadline passed without an answer.
    Deadline,
    /// A batch's stream was reset or finished without an answer.
    StreamFailed,
    /// No heartbeat for about three periods.
    Silent,
    /// A message its registration stream may not carry.
    ProtocolError,
    /// Its connection was lost.
    ConnectionLost,
}

impl WorkerRemoval {
    /// Every reason, in the order exported.
    pub const ALL: [WorkerRemoval; 7] = [
        WorkerRemoval::InvalidRegistration,
        WorkerRemoval::InvalidAnswer,
        WorkerRemoval::Deadline,
        WorkerRemoval::StreamFailed,
        WorkerRemoval::Silent,
        WorkerRemoval::ProtocolError,
        WorkerRemoval::ConnectionLost,
    ];

    /// The label value.
    pub fn as_str(self) -> &'static str {
        match self {
            WorkerRemoval::InvalidRegistration => "invalid_registration",
            WorkerRemoval::InvalidAnswer => "invalid_answer",
            WorkerRemoval::Deadline => "deadline",
            WorkerRemoval::StreamFailed => "stream_failed",
            WorkerRemoval::Silent => "silent",
            WorkerRemoval::ProtocolError => "protocol_error",
            WorkerRemoval::ConnectionLost => "connection_lost",
        }
    }
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct EngineLabel {
    engine: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StateLabel {
    state: &'static str,
}

type FloatGauge = Gauge<f64, AtomicU64>;
type FloatCounter = Counter<f64, AtomicU64>;

/// The busy seconds an engine had at the last recomputation of its busy ratio.
#[derive(Clone, Copy, Debug)]
struct BusyMark {
    at: Instant,
    busy_secs: f64,
}

struct EngineBusy {
    busy: FloatCounter,
    ratio: FloatGauge,
    mark: Option<BusyMark>,
}

struct Inner {
    registry: Registry,
    /// Connections, refusals, removed workers, plugins ([`operations`]).
    operations: operations::Operations,
    /// When the registry was built: the process's start, near enough.
    started: Instant,
    /// The scheduler's: the driver core's latest report, encoded at every scrape. `None` in a
    /// worker.
    driver: Option<DriverExport>,
    /// The worker process's own families ([`Metrics::for_worker`]); `None` in a scheduler.
    worker: Option<WorkerFamilies>,
}

/// What only a `kairos worker` process exports.
struct WorkerFamilies {
    batch_size: Histogram,
    engine_busy: Family<EngineLabel, FloatCounter>,
    engine_busy_ratio: Family<EngineLabel, FloatGauge>,
    /// Per engine: its busy counter and ratio gauge, and where the ratio's window started.
    engines: Mutex<BTreeMap<String, EngineBusy>>,
    connection: Family<StateLabel, Gauge>,
    batches: Counter,
    failed_batches: Counter,
    heartbeats: Counter,
    compute: Histogram,
}

/// The process's metrics: a Prometheus registry and typed handles to every family in it.
#[derive(Clone)]
pub struct Metrics(Arc<Inner>);

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Metrics").finish_non_exhaustive()
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

impl Metrics {
    /// A registry with every Kairos family, all at zero.
    pub fn new() -> Metrics {
        Metrics::build(false)
    }

    /// A `kairos worker` process's registry: every family of [`Metrics::new`] plus the
    /// worker's own (`kairos_worker_connection{state}`, `kairos_worker_batches_total`,
    /// `kairos_worker_failed_batches_total`, `kairos_worker_heartbeats_total`,
    /// `kairos_worker_compute_seconds`), starting `connecting`.
    pub fn for_worker() -> Metrics {
        let metrics = Metrics::build(true);
        metrics.set_worker_connection(WorkerConnection::Connecting);
        metrics
    }

    fn build(worker: bool) -> Metrics {
        let mut registry = Registry::default();
        let operations = operations::Operations::register(&mut registry, !worker);
        if !worker {
            // Every removal reason is a series from the start, so that `increase()` sees the first.
            for reason in WorkerRemoval::ALL {
                operations.removed_counter(reason.as_str());
            }
        }
        let driver = (!worker).then(|| {
            let export = DriverExport::default();
            registry.register_collector(Box::new(driver::DriverCollector(export.clone())));
            export
        });
        let worker = worker.then(|| {
            // 1 .. 512 requests per batch.
            let batch_size = Histogram::new(exponential_buckets(1.0, 2.0, 10));
            registry.register(
                "kairos_batch_size",
                "Requests per batch given to an engine instance",
                batch_size.clone(),
            );
            let engine_busy = Family::<EngineLabel, FloatCounter>::default();
            registry.register_with_unit(
                "kairos_engine_busy",
                "Time an engine instance spent running forward passes; \
                 rate() of it is the busy fraction",
                Unit::Seconds,
                engine_busy.clone(),
            );
            let engine_busy_ratio = Family::<EngineLabel, FloatGauge>::default();
            registry.register(
                "kairos_engine_busy_ratio",
                "Fraction of the time since the previous scrape (at least 1 s) an engine instance \
                 spent running forward passes",
                engine_busy_ratio.clone(),
            );
            let connection = Family::<StateLabel, Gauge>::default();
            registry.register(
                "kairos_worker_connection",
                "This worker's connection to its scheduler: 1 for the current state",
                connection.clone(),
            );
            let batches = Counter::default();
            registry.register(
                "kairos_worker_batches",
                "Batches this worker ran and answered",
                batches.clone(),
            );
            let failed_batches = Counter::default();
            registry.register(
                "kairos_worker_failed_batches",
                "Batches this worker received but could not answer (engine failure, stream lost)",
                failed_batches.clone(),
            );
            let heartbeats = Counter::default();
            registry.register(
                "kairos_worker_heartbeats",
                "Heartbeats this worker sent to its scheduler",
                heartbeats.clone(),
            );
            // 0.5 ms .. ~8 s: one forward pass of a batch.
            let compute = Histogram::new(exponential_buckets(0.0005, 2.0, 15));
            registry.register_with_unit(
                "kairos_worker_compute",
                "Compute time of one batch on this worker (what it reports as compute_us)",
                Unit::Seconds,
                compute.clone(),
            );
            WorkerFamilies {
                batch_size,
                engine_busy,
                engine_busy_ratio,
                engines: Mutex::new(BTreeMap::new()),
                connection,
                batches,
                failed_batches,
                heartbeats,
                compute,
            }
        });
        Metrics(Arc::new(Inner {
            registry,
            operations,
            started: Instant::now(),
            driver,
            worker,
        }))
    }

    /// Where the driver's shell publishes the core's reports (`None` in a worker process).
    pub fn driver(&self) -> Option<&DriverExport> {
        self.0.driver.as_ref()
    }

    /// `kairos_worker_removed_total{reason}`: the scheduler removed a worker (or refused its
    /// registration) for `reason`.
    pub fn record_worker_removed(&self, reason: WorkerRemoval) {
        self.0.operations.removed_counter(reason.as_str()).inc();
    }

    /// Workers removed for `reason` so far (`kairos_worker_removed_total`).
    pub fn workers_removed_for(&self, reason: WorkerRemoval) -> u64 {
        self.0.operations.removed_counter(reason.as_str()).get()
    }

    /// `kairos_worker_connection{state}`: the worker is now in `state`. No-op in a scheduler.
    pub fn set_worker_connection(&self, state: WorkerConnection) {
        if let Some(w) = &self.0.worker {
            for s in WorkerConnection::ALL {
                w.connection
                    .get_or_create(&StateLabel { state: s.as_str() })
                    .set(i64::from(s == state));
            }
        }
    }

    /// A worker answered a batch of `requests` requests that computed for `compute`:
    /// `kairos_worker_batches_total`, `kairos_worker_compute_seconds` and `kairos_batch_size`
    /// (the engine's busy time is [`Metrics::record_engine_busy`], counted even when the answer
    /// cannot be sent).
    pub fn record_worker_batch(&self, requests: usize, compute: Duration) {
        if let Some(w) = &self.0.worker {
            w.batches.inc();
            w.compute.observe(compute.as_secs_f64());
            w.batch_size.observe(requests as f64);
        }
    }

    /// `kairos_worker_failed_batches_total`: a batch the worker could not answer.
    pub fn record_worker_failed_batch(&self) {
        if let Some(w) = &self.0.worker {
            w.failed_batches.inc();
        }
    }

    /// `kairos_worker_heartbeats_total`: one heartbeat sent.
    pub fn record_worker_heartbeat(&self) {
        if let Some(w) = &self.0.worker {
            w.heartbeats.inc();
        }
    }

    /// Batches this worker answered (`kairos_worker_batches_total`; 0 in a scheduler).
    pub fn worker_batches(&self) -> u64 {
        self.0.worker.as_ref().map_or(0, |w| w.batches.get())
    }

    /// The counter of fallbacks of `policy` (`kairos_plugin_fallbacks_total{kind,policy}`),
    /// for its owner to count in. Handles to the same labels share one value.
    pub fn fallback_counter(&self, kind: PluginKind, policy: &str) -> Counter {
        self.0.operations.plugin(kind, policy).fallbacks
    }

    /// The gauge of `policy`'s quarantine (`kairos_plugin_quarantined{kind,policy}`, 1 while
    /// quarantined), for its owner to set.
    pub fn quarantine_gauge(&self, kind: PluginKind, policy: &str) -> Gauge {
        self.0.operations.plugin(kind, policy).quarantined
    }

    /// The counter of refusals at `door` for `reason` (`kairos_refusals_total{door,reason}`),
    /// for the guard that refuses to count in; the series exists at zero from this call on.
    /// Both labels are chosen by the code, so the label set stays bounded.
    pub fn refusal_counter(&self, door: &'static str, reason: &'static str) -> Counter {
        self.0.operations.refusal_counter(door, reason)
    }

    /// Exports `door`'s places for authenticated robot connections (a semaphore of `capacity`
    /// permits, one held per connection) as `kairos_robot_connections{door}`, for as long as
    /// the semaphore exists.
    pub fn watch_connection_places(
        &self,
        door: &'static str,
        places: &Arc<tokio::sync::Semaphore>,
        capacity: usize,
    ) {
        self.0.operations.watch_places(door, places, capacity);
    }

    /// Every refusal counted so far, by door and reason.
    pub fn refusals(&self) -> Vec<RefusalCount> {
        self.0.operations.refusals()
    }

    /// Remote workers removed so far, by reason.
    pub fn workers_removed(&self) -> BTreeMap<&'static str, u64> {
        self.0.operations.removed()
    }

    /// Every policy plugin's fallbacks and quarantine state.
    pub fn plugins(&self) -> Vec<PluginHealth> {
        self.0.operations.plugins()
    }

    /// Authenticated robot connections per door.
    pub fn robot_connections(&self) -> Vec<DoorConnections> {
        self.0.operations.connections()
    }

    /// Time since the registry was built (the process's uptime, near enough).
    pub fn uptime(&self) -> Duration {
        self.0.started.elapsed()
    }

    /// Makes `engine` appear in `kairos_engine_busy_*` at zero before its first batch (a worker
    /// process's; in a scheduler the driver's report carries its engines).
    pub fn add_engine(&self, engine: &str) {
        self.with_engine(engine, |_| ());
    }

    /// `kairos_engine_busy_seconds_total{engine}`: the worker's `engine` ran a forward pass for
    /// `busy`. No-op in a scheduler, whose driver core counts its engines' busy time.
    pub fn record_engine_busy(&self, engine: &str, busy: Duration) {
        self.with_engine(engine, |e| {
            e.busy.inc_by(busy.as_secs_f64());
        });
    }

    fn with_engine(&self, engine: &str, f: impl FnOnce(&EngineBusy)) {
        let Some(w) = &self.0.worker else {
            return;
        };
        let mut engines = lock(&w.engines);
        if let Some(e) = engines.get(engine) {
            return f(e);
        }
        let label = EngineLabel {
            engine: engine.to_string(),
        };
        let e = EngineBusy {
            busy: w.engine_busy.get_or_create(&label).clone(),
            ratio: w.engine_busy_ratio.get_or_create(&label).clone(),
            mark: None,
        };
        f(&e);
        engines.insert(engine.to_string(), e);
    }

    /// The registry in the OpenMetrics text format ([`CONTENT_TYPE`]), after recomputing the
    /// busy ratios.
    pub fn encode(&self) -> String {
        self.encode_at(Instant::now())
    }

    pub(crate) fn encode_at(&self, now: Instant) -> String {
        self.refresh_busy_ratios(now);
        let mut out = String::new();
        if let Err(error) = prometheus_client::encoding::text::encode(&mut out, &self.0.registry) {
            // Writing into a String cannot fail; a label encoder that does is a bug here.
            tracing::error!(%error, "cannot encode the metrics");
        }
        out
    }

    /// `kairos_engine_busy_ratio`: busy seconds gained over the time since the previous
    /// recomputation (at least [`BUSY_RATIO_MIN_WINDOW`] ago), per engine.
    fn refresh_busy_ratios(&self, now: Instant) {
        let Some(w) = &self.0.worker else {
            return;
        };
        for e in lock(&w.engines).values_mut() {
            let busy_secs = e.busy.get();
            let Some(mark) = e.mark else {
                e.mark = Some(BusyMark { at: now, busy_secs });
                continue;
            };
            let window = now.saturating_duration_since(mark.at);
            if window < BUSY_RATIO_MIN_WINDOW {
                continue;
            }
            let ratio = ((busy_secs - mark.busy_secs) / window.as_secs_f64()).clamp(0.0, 1.0);
            e.ratio.set(ratio);
            e.mark = Some(BusyMark { at: now, busy_secs });
        }
    }
}

/// Whether the process can serve: `/ready` answers 200 while it is set, 503 otherwise. Cheap to
/// clone; every clone sees the same flag.
#[derive(Clone, Debug, Default)]
pub struct Readiness(Arc<AtomicBool>);

impl Readiness {
    /// A flag, not ready yet.
    pub fn new() -> Readiness {
        Readiness::default()
    }

    /// Marks the process ready (engines present, endpoint listening) or not (starting,
    /// draining, no engine left).
    pub fn set(&self, ready: bool) {
        self.0.store(ready, Ordering::Release);
    }

    /// Whether it is ready now.
    pub fn is_ready(&self) -> bool {
        self.0.load(Ordering::Acquire)
    }
}

#[cfg(test)]
mod tests {
    use kairos_core::action::ActionManager;
    use kairos_core::driver::{
        DriverReport, DriverStats, EngineReport, EngineState, Histogram as CoreHistogram,
    };
    use kairos_core::error::LossReason;
    use kairos_core::scheduler::Tier;

    use super::*;

    /// The sample line of `name` (with its labels) in `text`, parsed.
    fn sample(text: &str, series: &str) -> Option<f64> {
        text.lines()
            .find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
    }

    fn engine(name: &str, tier: Tier, state: EngineState, busy_ms: u64) -> EngineReport {
        EngineReport {
            name: name.into(),
            tier,
            state,
            busy: false,
            busy_time: Duration::from_millis(busy_ms),
            rtt: None,
        }
    }

    /// A report as the driver core would publish it.
    fn report() -> DriverReport {
        let mut stats = DriverStats {
            round_latency: CoreHistogram::round_latency(),
            batch_size: CoreHistogram::batch_size(),
            deadline_misses: 1,
            ..DriverStats::default()
        };
        stats.round_latency.observe(0.003);
        stats.batch_size.observe(4.0);
        stats.delay_predicted = CoreHistogram::delay_steps();
        stats.delay_predicted.observe(3.0);
        stats.delay_error = CoreHistogram::delay_error();
        stats.delay_error.observe(1.0);
        stats.delay_error.observe(0.0);
        stats.delay_error_signed = -1;
        stats
            .chunking
            .count(kairos_sdk::protocol::ChunkingStrategy::Rtc);
        stats.chunking.fallbacks = 2;
        for _ in 0..3 {
            stats.redispatched.count(LossReason::ConnectionLost);
        }
        let mut gpu = engine("gpu-0", Tier::Cloud, EngineState::Draining, 0);
        gpu.rtt = Some(Duration::from_millis(20));
        DriverReport {
            stats,
            queue_depth: 7,
            running: 0,
            open_tasks: 3,
            engines: vec![
                engine("edge-0", Tier::Edge, EngineState::Ready, 250),
                engine("edge-1", Tier::Edge, EngineState::Ready, 0),
                gpu,
            ],
        }
    }

    #[test]
    fn every_family_is_exported_and_typed() {
        let metrics = Metrics::new();
        let export = metrics.driver().expect("a scheduler's registry");
        export.publish(report());
        metrics.fallback_counter(PluginKind::Priority, "plas").inc();
        let text = metrics.encode();
        for (series, value) in [
            ("kairos_queue_depth", 7.0),
            (r#"kairos_workers{tier="edge",state="ready"}"#, 2.0),
            (r#"kairos_workers{tier="cloud",state="draining"}"#, 1.0),
            (r#"kairos_workers{tier="cloud",state="ready"}"#, 0.0),
            ("kairos_round_latency_seconds_count", 1.0),
            ("kairos_round_latency_seconds_sum", 0.003),
            (r#"kairos_round_latency_seconds_bucket{le="0.004"}"#, 1.0),
            (r#"kairos_round_latency_seconds_bucket{le="0.002"}"#, 0.0),
            ("kairos_batch_size_count", 1.0),
            (r#"kairos_batch_size_bucket{le="4.0"}"#, 1.0),
            (r#"kairos_batch_size_bucket{le="2.0"}"#, 0.0),
            (r#"kairos_batch_size_bucket{le="+Inf"}"#, 1.0),
            ("kairos_deadline_misses_total", 1.0),
            (r#"kairos_redispatch_total{reason="connection_lost"}"#, 3.0),
            (r#"kairos_redispatch_total{reason="deadline"}"#, 0.0),
            (r#"kairos_worker_rtt_seconds{worker="gpu-0"}"#, 0.02),
            (
                r#"kairos_plugin_fallbacks_total{kind="priority",policy="plas"}"#,
                1.0,
            ),
            (r#"kairos_engine_busy_seconds_total{engine="edge-0"}"#, 0.25),
            (r#"kairos_engine_busy_ratio{engine="edge-0"}"#, 0.0),
            ("kairos_delay_predicted_steps_count", 1.0),
            (r#"kairos_delay_predicted_steps_bucket{le="3.0"}"#, 1.0),
            ("kairos_delay_prediction_error_steps_count", 2.0),
            (
                r#"kairos_delay_prediction_error_steps_bucket{le="0.0"}"#,
                1.0,
            ),
            ("kairos_delay_prediction_bias_steps", -0.5),
            (r#"kairos_chunking_rounds_total{strategy="rtc"}"#, 1.0),
            (r#"kairos_chunking_rounds_total{strategy="skip"}"#, 0.0),
            ("kairos_chunking_fallbacks_total", 2.0),
        ] {
            assert_eq!(sample(&text, series), Some(value), "{series} in\n{text}");
        }
        assert!(text.contains("# TYPE kairos_round_latency_seconds histogram"));
        assert!(text.contains("# TYPE kairos_deadline_misses counter"));
        assert!(text.ends_with("# EOF\n"), "OpenMetrics ends with EOF");
        assert!(
            !text.contains(r#"kairos_worker_rtt_seconds{worker="edge-0"}"#),
            "a local engine has no round trip"
        );

        // A departed worker's series go away with it from the report.
        let mut next = report();
        next.engines.pop();
        export.publish(next);
        assert!(!metrics.encode().contains("gpu-0"));
    }

    #[test]
    fn the_action_managers_fallbacks_are_exported_by_policy() {
        use kairos_core::registry::native_horizon_policies;
        let metrics = Metrics::new();
        let natives = native_horizon_policies();
        let actions = Arc::new(
            ActionManager::new(natives.clone(), &natives, "threshold", BTreeMap::new()).unwrap(),
        );
        metrics.driver().unwrap().attach_actions(actions.clone());
        let text = metrics.encode();
        for policy in natives.names() {
            let series = format!("kairos_horizon_fallbacks_total{{policy=\"{policy}\"}} 0");
            assert!(text.contains(&series), "{series} from the start: {text}");
        }
        assert_eq!(actions.fallback_count(), 0);
    }

    #[test]
    fn worker_families_exist_only_in_a_worker_registry() {
        let scheduler = Metrics::new();
        scheduler.record_worker_heartbeat();
        scheduler.set_worker_connection(WorkerConnection::Registered);
        let text = scheduler.encode();
        for family in [
            "kairos_worker_connection",
            "kairos_worker_batches",
            "kairos_worker_heartbeats",
            "kairos_worker_compute",
        ] {
            assert!(!text.contains(family), "{family} in a scheduler's registry");
        }

        let worker = Metrics::for_worker();
        let connected = |text: &str, state: &str| {
            sample(
                text,
                &format!("kairos_worker_connection{{state=\"{state}\"}}"),
            )
        };
        let text = worker.encode();
        assert_eq!(connected(&text, "connecting"), Some(1.0));
        assert_eq!(connected(&text, "registered"), Some(0.0));
        worker.set_worker_connection(WorkerConnection::Registered);
        worker.record_worker_heartbeat();
        worker.record_worker_heartbeat();
        worker.record_worker_batch(3, Duration::from_millis(40));
        worker.record_engine_busy("engine-0", Duration::from_millis(40));
        worker.record_worker_failed_batch();
        let text = worker.encode();
        assert_eq!(connected(&text, "connecting"), Some(0.0));
        assert_eq!(connected(&text, "registered"), Some(1.0));
        for (series, value) in [
            ("kairos_worker_heartbeats_total", 2.0),
            ("kairos_worker_batches_total", 1.0),
            ("kairos_worker_failed_batches_total", 1.0),
            ("kairos_worker_compute_seconds_count", 1.0),
            ("kairos_worker_compute_seconds_sum", 0.04),
            ("kairos_batch_size_sum", 3.0),
            (
                r#"kairos_engine_busy_seconds_total{engine="engine-0"}"#,
                0.04,
            ),
        ] {
            assert_eq!(sample(&text, series), Some(value), "{series} in\n{text}");
        }
        assert_eq!(worker.worker_batches(), 1);
    }

    #[test]
    fn fallback_counters_of_the_same_labels_share_one_value() {
        let metrics = Metrics::new();
        let a = metrics.fallback_counter(PluginKind::Horizon, "wasm-threshold");
        let b = metrics.fallback_counter(PluginKind::Horizon, "wasm-threshold");
        a.inc();
        b.inc_by(2);
        assert_eq!(a.get(), 3);
        let other = metrics.fallback_counter(PluginKind::Priority, "wasm-threshold");
        assert_eq!(other.get(), 0, "kind is part of the series");
    }

    #[test]
    fn busy_ratio_is_busy_time_over_the_window_since_the_last_scrape() {
        let export = DriverExport::default();
        let publish = |busy_ms: u64| {
            export.publish(DriverReport {
                engines: vec![engine("edge-0", Tier::Edge, EngineState::Ready, busy_ms)],
                ..DriverReport::default()
            })
        };
        publish(0);
        let t0 = Instant::now();
        let ratio = |now: Instant| export.encode_at(now).busy_ratios.get("edge-0").copied();
        // The first scrape starts the window.
        assert_eq!(ratio(t0), Some(0.0));
        publish(500);
        // Too soon: the previous value stands and the window keeps its start.
        assert_eq!(ratio(t0 + Duration::from_millis(100)), Some(0.0));
        assert_eq!(ratio(t0 + Duration::from_secs(2)), Some(0.25));
        // An idle window decays to zero.
        assert_eq!(ratio(t0 + Duration::from_secs(4)), Some(0.0));
        // An engine that left is forgotten.
        export.publish(DriverReport::default());
        assert_eq!(ratio(t0 + Duration::from_secs(6)), None);
    }

    #[test]
    fn a_workers_busy_ratio_follows_its_engine() {
        let metrics = Metrics::for_worker();
        metrics.add_engine("edge-0");
        let t0 = Instant::now();
        let ratio = |text: &str| sample(text, r#"kairos_engine_busy_ratio{engine="edge-0"}"#);
        assert_eq!(ratio(&metrics.encode_at(t0)), Some(0.0));
        metrics.record_engine_busy("edge-0", Duration::from_millis(500));
        assert_eq!(
            ratio(&metrics.encode_at(t0 + Duration::from_secs(2))),
            Some(0.25)
        );
    }

    #[test]
    fn readiness_is_shared_by_clones() {
        let ready = Readiness::new();
        let probe = ready.clone();
        assert!(!probe.is_ready());
        ready.set(true);
        assert!(probe.is_ready());
    }
}
