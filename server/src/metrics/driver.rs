//! The scheduler's facts, exported from the driver core's report.
//!
//! The driver core counts what happens to rounds, batches and engines itself and reports it as
//! data ([`DriverReport`]); the driver's shell publishes the latest report here after every
//! event, and each scrape encodes it. Nothing here counts: the report is the one copy of each
//! fact. The action manager's fallbacks are read from the manager the same way.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use kairos_core::action::ActionManager;
use kairos_core::driver::{DriverReport, EngineState, Histogram};
use kairos_core::error::LossReason;
use kairos_core::scheduler::Tier;
use kairos_core::sync::lock;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::registry::Unit;

use super::BUSY_RATIO_MIN_WINDOW;

/// What the collector reads at each scrape.
#[derive(Debug, Default)]
struct Published {
    report: DriverReport,
    actions: Option<Arc<ActionManager>>,
    /// Per engine, its busy seconds at the last recomputation of its busy ratio, and the ratio.
    busy: BTreeMap<String, BusyMark>,
    /// Whether the driver's thread holds a [`DriverRunning`] now.
    alive: bool,
}

/// Held by the driver's thread for as long as it runs: `kairos_driver_alive` is 1 from
/// [`DriverExport::running`] until this is dropped, which happens however the thread ends (its
/// loop returned, or a panic unwound it).
#[derive(Debug)]
#[must_use = "the driver counts as alive only while this is held"]
pub struct DriverRunning(DriverExport);

impl Drop for DriverRunning {
    fn drop(&mut self) {
        self.0.lock().alive = false;
    }
}

#[derive(Clone, Copy, Debug)]
struct BusyMark {
    at: Instant,
    busy_secs: f64,
    ratio: f64,
}

/// The latest driver report and the action manager, shared by the shell (which publishes) and
/// the registry (which encodes). Cheap to clone.
#[derive(Clone, Debug, Default)]
pub struct DriverExport(Arc<Mutex<Published>>);

impl DriverExport {
    /// Replaces the report the next scrape encodes.
    pub fn publish(&self, report: DriverReport) {
        self.lock().report = report;
    }

    /// The report last published.
    pub fn report(&self) -> DriverReport {
        self.lock().report.clone()
    }

    /// Marks the driver alive until the returned guard is dropped.
    pub fn running(&self) -> DriverRunning {
        self.lock().alive = true;
        DriverRunning(self.clone())
    }

    /// Whether the driver's thread runs now (`kairos_driver_alive`).
    pub fn is_alive(&self) -> bool {
        self.lock().alive
    }

    /// Rounds whose horizon policy fell back, by policy (`kairos_horizon_fallbacks_total`).
    pub fn horizon_fallbacks(&self) -> BTreeMap<String, u64> {
        self.lock()
            .actions
            .as_ref()
            .map(|a| a.fallbacks_by_policy())
            .unwrap_or_default()
    }

    /// Exports `actions`' fallbacks (`kairos_horizon_fallbacks_total{policy}`).
    pub fn attach_actions(&self, actions: Arc<ActionManager>) {
        self.lock().actions = Some(actions);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Published> {
        lock(&self.0)
    }

    /// Recomputes each engine's busy ratio over the time since its previous recomputation (at
    /// least [`BUSY_RATIO_MIN_WINDOW`]), and forgets engines that left.
    fn refresh_busy_ratios(&self, now: Instant) {
        let mut published = self.lock();
        let Published { report, busy, .. } = &mut *published;
        busy.retain(|name, _| report.engines.iter().any(|e| &e.name == name));
        for engine in &report.engines {
            let busy_secs = engine.busy_time.as_secs_f64();
            let mark = busy.entry(engine.name.clone()).or_insert(BusyMark {
                at: now,
                busy_secs,
                ratio: 0.0,
            });
            let window = now.saturating_duration_since(mark.at);
            if window < BUSY_RATIO_MIN_WINDOW {
                continue;
            }
            let ratio = ((busy_secs - mark.busy_secs) / window.as_secs_f64()).clamp(0.0, 1.0);
            *mark = BusyMark {
                at: now,
                busy_secs,
                ratio,
            };
        }
    }

    pub(super) fn encode_at(&self, now: Instant) -> Snapshot {
        self.refresh_busy_ratios(now);
        let published = self.lock();
        Snapshot {
            alive: published.alive,
            report: published.report.clone(),
            fallbacks: published
                .actions
                .as_ref()
                .map(|a| a.fallbacks_by_policy())
                .unwrap_or_default(),
            busy_ratios: published
                .busy
                .iter()
                .map(|(name, mark)| (name.clone(), mark.ratio))
                .collect(),
        }
    }
}

/// What one scrape encodes, read under the lock once.
#[derive(Debug, Default)]
pub(super) struct Snapshot {
    pub(super) alive: bool,
    pub(super) report: DriverReport,
    pub(super) fallbacks: BTreeMap<String, u64>,
    pub(super) busy_ratios: BTreeMap<String, f64>,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WorkerLabels {
    tier: &'static str,
    state: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ReasonLabel {
    reason: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StrategyLabel {
    strategy: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WorkerLabel {
    worker: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct EngineLabel {
    engine: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct PolicyLabel {
    policy: String,
}

/// The label of a tier.
pub fn tier_label(tier: Tier) -> &'static str {
    match tier {
        Tier::Edge => "edge",
        Tier::Cloud => "cloud",
    }
}

fn saturating_i64(n: usize) -> i64 {
    i64::try_from(n).unwrap_or(i64::MAX)
}

/// The registry's view of a [`DriverExport`]: encodes a [`Snapshot`] at every scrape.
#[derive(Debug)]
pub(super) struct DriverCollector(pub(super) DriverExport);

impl Collector for DriverCollector {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let snapshot = self.0.encode_at(Instant::now());
        let report = &snapshot.report;
        let stats = &report.stats;

        ConstGauge::new(i64::from(snapshot.alive)).encode(encoder.encode_descriptor(
            "kairos_driver_alive",
            "1 while the scheduler's driver thread runs; 0 once it has ended, for any reason",
            None,
            MetricType::Gauge,
        )?)?;

        ConstGauge::new(saturating_i64(report.running)).encode(encoder.encode_descriptor(
            "kairos_rounds_running",
            "Rounds in batches that have not finished",
            None,
            MetricType::Gauge,
        )?)?;

        ConstGauge::new(saturating_i64(report.open_tasks)).encode(encoder.encode_descriptor(
            "kairos_open_tasks",
            "Tasks open now (started by a robot, not yet ended or expired)",
            None,
            MetricType::Gauge,
        )?)?;

        let gauge = ConstGauge::new(saturating_i64(report.queue_depth));
        gauge.encode(encoder.encode_descriptor(
            "kairos_queue_depth",
            "Rounds waiting for dispatch (accepted by the scheduler, not yet in a batch)",
            None,
            MetricType::Gauge,
        )?)?;

        let mut workers = encoder.encode_descriptor(
            "kairos_workers",
            "Engine instances (local engines and remote workers) by tier and state",
            None,
            MetricType::Gauge,
        )?;
        for tier in [Tier::Edge, Tier::Cloud] {
            for state in [EngineState::Ready, EngineState::Draining] {
                let count = report
                    .engines
                    .iter()
                    .filter(|e| e.tier == tier && e.state == state)
                    .count();
                let labels = WorkerLabels {
                    tier: tier_label(tier),
                    state: state.as_str(),
                };
                ConstGauge::new(saturating_i64(count)).encode(workers.encode_family(&labels)?)?;
            }
        }

        encode_histogram(
            &mut encoder,
            "kairos_round_latency",
            "Server-side latency of answered rounds, from the Submit read to the reply",
            Some(&Unit::Seconds),
            &stats.round_latency,
        )?;
        encode_histogram(
            &mut encoder,
            "kairos_batch_size",
            "Requests per batch given to an engine instance",
            None,
            &stats.batch_size,
        )?;

        encode_histogram(
            &mut encoder,
            "kairos_round_horizon",
            "Actions each answered round asked its robot to execute (the horizon H)",
            None,
            &stats.horizon,
        )?;
        encode_histogram(
            &mut encoder,
            "kairos_delay_predicted_steps",
            "The d predicted for answered rounds: control steps from the observation's capture \
             to the reply's arrival",
            None,
            &stats.delay_predicted,
        )?;
        encode_histogram(
            &mut encoder,
            "kairos_delay_prediction_error_steps",
            "|predicted - actual| d of rounds whose robot reported the actual d (its next Last \
             Exec Info), control steps",
            None,
            &stats.delay_error,
        )?;
        ConstGauge::new(
            stats.delay_error_signed as f64 / stats.delay_error.count().max(1) as f64,
        )
        .encode(encoder.encode_descriptor(
            "kairos_delay_prediction_bias_steps",
            "Mean of predicted - actual d over the rounds of kairos_delay_prediction_error_steps \
             (positive: the server predicts late arrivals)",
            None,
            MetricType::Gauge,
        )?)?;
        let mut chunking = encoder.encode_descriptor(
            "kairos_chunking_rounds",
            "Answered rounds by the chunking strategy applied",
            None,
            MetricType::Counter,
        )?;
        for (strategy, rounds) in stats.chunking.iter() {
            let labels = StrategyLabel {
                strategy: strategy.as_str(),
            };
            ConstCounter::new(rounds).encode(chunking.encode_family(&labels)?)?;
        }
        ConstCounter::new(stats.chunking.fallbacks).encode(encoder.encode_descriptor(
            "kairos_chunking_fallbacks",
            "Rounds whose chunking strategy could not apply (the robot executes a chunk the \
             server does not know, or arrival_state without a forecast) and fell back to skip",
            None,
            MetricType::Counter,
        )?)?;

        ConstCounter::new(stats.deadline_misses).encode(encoder.encode_descriptor(
            "kairos_deadline_misses",
            "Rounds answered after their robot ran out of actions (E.end of its previous round), \
             plus rounds refused because they could no longer be served in time",
            None,
            MetricType::Counter,
        )?)?;

        let mut redispatch = encoder.encode_descriptor(
            "kairos_redispatch",
            "Rounds put back at the front of the queue after their worker failed, by reason",
            None,
            MetricType::Counter,
        )?;
        for reason in LossReason::ALL {
            let labels = ReasonLabel {
                reason: reason.as_str(),
            };
            ConstCounter::new(stats.redispatched.get(reason))
                .encode(redispatch.encode_family(&labels)?)?;
        }

        // A labelled family is written with its first series, as prometheus-client does for
        // its own families: no remote worker, no `kairos_worker_rtt_seconds`.
        let remote: Vec<_> = report
            .engines
            .iter()
            .filter_map(|e| Some((&e.name, e.rtt?)))
            .collect();
        if !remote.is_empty() {
            let mut rtt = encoder.encode_descriptor(
                "kairos_worker_rtt",
                "Moving average of a remote worker's round trip (batch time less its compute time)",
                Some(&Unit::Seconds),
                MetricType::Gauge,
            )?;
            for (name, value) in remote {
                let labels = WorkerLabel {
                    worker: name.clone(),
                };
                ConstGauge::new(value.as_secs_f64()).encode(rtt.encode_family(&labels)?)?;
            }
        }

        let mut busy = encoder.encode_descriptor(
            "kairos_engine_busy",
            "Time an engine instance spent running forward passes; rate() of it is the busy \
             fraction",
            Some(&Unit::Seconds),
            MetricType::Counter,
        )?;
        for engine in &report.engines {
            let labels = EngineLabel {
                engine: engine.name.clone(),
            };
            ConstCounter::new(engine.busy_time.as_secs_f64())
                .encode(busy.encode_family(&labels)?)?;
        }

        let mut ratio = encoder.encode_descriptor(
            "kairos_engine_busy_ratio",
            "Fraction of the time since the previous scrape (at least 1 s) an engine instance \
             spent running forward passes",
            None,
            MetricType::Gauge,
        )?;
        for engine in &report.engines {
            let labels = EngineLabel {
                engine: engine.name.clone(),
            };
            let value = snapshot
                .busy_ratios
                .get(&engine.name)
                .copied()
                .unwrap_or(0.0);
            ConstGauge::new(value).encode(ratio.encode_family(&labels)?)?;
        }

        if !snapshot.fallbacks.is_empty() {
            let mut fallbacks = encoder.encode_descriptor(
                "kairos_horizon_fallbacks",
                "Rounds whose horizon policy failed or answered out of range, answered by the \
                 server's native fallback instead, by the policy that failed",
                None,
                MetricType::Counter,
            )?;
            for (policy, count) in &snapshot.fallbacks {
                let labels = PolicyLabel {
                    policy: policy.clone(),
                };
                ConstCounter::new(*count).encode(fallbacks.encode_family(&labels)?)?;
            }
        }
        Ok(())
    }
}

fn encode_histogram(
    encoder: &mut DescriptorEncoder,
    name: &str,
    help: &str,
    unit: Option<&Unit>,
    histogram: &Histogram,
) -> Result<(), std::fmt::Error> {
    let mut metric = encoder.encode_descriptor(name, help, unit, MetricType::Histogram)?;
    metric.encode_histogram::<prometheus_client::encoding::NoLabelSet>(
        histogram.sum(),
        histogram.count(),
        &histogram.buckets(),
        None,
    )
}
