//! What the serving paths count beside the driver: robot connections per door, refusals by door
//! and reason, workers removed from the pool by reason, and each policy plugin's fallbacks and
//! quarantine.
//!
//! Each fact is counted once, in the handle its owner holds; this module keeps a second handle
//! to the same value (a Prometheus handle is an `Arc`) so that the fleet page
//! ([`super::fleet`]) can list the series without a second count. Every label value is a
//! `&'static str` chosen by the code, or a plugin name from the configuration: the label sets are
//! bounded by the program and the deployment, never by what a client sends.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError, Weak};

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeLabelSet, EncodeMetric};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::{ConstGauge, Gauge};
use prometheus_client::registry::Registry;
use tokio::sync::Semaphore;

use super::PolicyKind;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct DoorReason {
    door: &'static str,
    reason: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ReasonLabel {
    reason: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct DoorLabel {
    door: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub(super) struct PluginLabels {
    pub(super) kind: &'static str,
    pub(super) policy: String,
}

/// A door's places for authenticated robot connections: taken places are connected robots.
#[derive(Debug)]
struct Places {
    door: &'static str,
    places: Weak<Semaphore>,
    capacity: usize,
}

/// One plugin's exported handles.
#[derive(Clone, Debug)]
pub(super) struct PluginHandles {
    pub(super) fallbacks: Counter,
    pub(super) quarantined: Gauge,
}

/// Counts of one door and reason, for the fleet page.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RefusalCount {
    /// The door: `quic`, `openpi`, `workers`, `metrics`.
    pub door: &'static str,
    /// Why, `snake_case`.
    pub reason: &'static str,
    /// Refusals since the process started.
    pub total: u64,
}

/// Connected robots at one door, for the fleet page.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct DoorConnections {
    /// The door: `quic` or `openpi`.
    pub door: &'static str,
    /// Authenticated robot connections open now.
    pub connected: u64,
    /// The door's `max_connections`.
    pub capacity: u64,
}

/// One policy plugin's health, for the fleet page.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PluginHealth {
    /// `horizon` or `priority`.
    pub kind: &'static str,
    /// The name it is registered under.
    pub policy: String,
    /// Decisions answered by its fallback policy.
    pub fallbacks: u64,
    /// Whether it is quarantined now.
    pub quarantined: bool,
}

#[derive(Debug, Default)]
struct Known {
    refusals: BTreeMap<(&'static str, &'static str), Counter>,
    removed: BTreeMap<&'static str, Counter>,
    plugins: BTreeMap<(&'static str, String), PluginHandles>,
    places: Vec<Places>,
}

/// The families of this module and the handles the fleet page lists. Cheap to clone.
#[derive(Clone, Debug)]
pub(super) struct Operations {
    refusals: Family<DoorReason, Counter>,
    removed: Family<ReasonLabel, Counter>,
    plugin_fallbacks: Family<PluginLabels, Counter>,
    quarantined: Family<PluginLabels, Gauge>,
    known: Arc<Mutex<Known>>,
}

impl Operations {
    /// Registers the families in `registry`. `scheduler`: the families only a scheduler has
    /// (refusals at its doors, removed workers, connected robots).
    pub(super) fn register(registry: &mut Registry, scheduler: bool) -> Operations {
        let ops = Operations {
            refusals: Family::default(),
            removed: Family::default(),
            plugin_fallbacks: Family::default(),
            quarantined: Family::default(),
            known: Arc::default(),
        };
        registry.register(
            "kairos_plugin_fallbacks",
            "Decisions a policy plugin answered through its fallback policy because it failed",
            ops.plugin_fallbacks.clone(),
        );
        registry.register(
            "kairos_plugin_quarantined",
            "1 while a policy plugin is quarantined (its fallback answers every decision)",
            ops.quarantined.clone(),
        );
        registry.register(
            "kairos_refusals",
            "Connections and requests a guard refused, by door and reason",
            ops.refusals.clone(),
        );
        if scheduler {
            registry.register(
                "kairos_worker_removed",
                "Remote workers taken out of the pool, by reason",
                ops.removed.clone(),
            );
            registry.register_collector(Box::new(ConnectionsCollector(ops.known.clone())));
        }
        ops
    }

    fn known(&self) -> std::sync::MutexGuard<'_, Known> {
        self.known.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The counter of refusals at `door` for `reason`; it exists (at zero) from this call on.
    pub(super) fn refusal_counter(&self, door: &'static str, reason: &'static str) -> Counter {
        let counter = self
            .refusals
            .get_or_create(&DoorReason { door, reason })
            .clone();
        self.known()
            .refusals
            .entry((door, reason))
            .or_insert_with(|| counter.clone());
        counter
    }

    /// The counter of workers removed for `reason`.
    pub(super) fn removed_counter(&self, reason: &'static str) -> Counter {
        let counter = self.removed.get_or_create(&ReasonLabel { reason }).clone();
        self.known()
            .removed
            .entry(reason)
            .or_insert_with(|| counter.clone());
        counter
    }

    /// The handles of the plugin `policy` of `kind`.
    pub(super) fn plugin(&self, kind: PolicyKind, policy: &str) -> PluginHandles {
        let labels = PluginLabels {
            kind: kind.as_str(),
            policy: policy.to_string(),
        };
        let handles = PluginHandles {
            fallbacks: self.plugin_fallbacks.get_or_create(&labels).clone(),
            quarantined: self.quarantined.get_or_create(&labels).clone(),
        };
        self.known()
            .plugins
            .entry((labels.kind, labels.policy))
            .or_insert_with(|| handles.clone());
        handles
    }

    /// Exports `places` (a door's semaphore of `capacity` authenticated places) as
    /// `kairos_robot_connections{door}`: its taken places, for as long as it exists.
    pub(super) fn watch_places(
        &self,
        door: &'static str,
        places: &Arc<Semaphore>,
        capacity: usize,
    ) {
        let mut known = self.known();
        known.places.retain(|p| p.door != door);
        known.places.push(Places {
            door,
            places: Arc::downgrade(places),
            capacity,
        });
    }

    /// Every refusal counter so far.
    pub(super) fn refusals(&self) -> Vec<RefusalCount> {
        self.known()
            .refusals
            .iter()
            .map(|(&(door, reason), counter)| RefusalCount {
                door,
                reason,
                total: counter.get(),
            })
            .collect()
    }

    /// Workers removed, by reason.
    pub(super) fn removed(&self) -> BTreeMap<&'static str, u64> {
        self.known()
            .removed
            .iter()
            .map(|(&reason, counter)| (reason, counter.get()))
            .collect()
    }

    /// Every plugin's fallbacks and quarantine state.
    pub(super) fn plugins(&self) -> Vec<PluginHealth> {
        self.known()
            .plugins
            .iter()
            .map(|((kind, policy), handles)| PluginHealth {
                kind,
                policy: policy.clone(),
                fallbacks: handles.fallbacks.get(),
                quarantined: handles.quarantined.get() > 0,
            })
            .collect()
    }

    /// Connected robots per watched door.
    pub(super) fn connections(&self) -> Vec<DoorConnections> {
        connections(&self.known())
    }
}

fn connections(known: &Known) -> Vec<DoorConnections> {
    known
        .places
        .iter()
        .filter_map(|p| {
            let places = p.places.upgrade()?;
            let taken = p.capacity.saturating_sub(places.available_permits());
            Some(DoorConnections {
                door: p.door,
                connected: u64::try_from(taken).unwrap_or(u64::MAX),
                capacity: u64::try_from(p.capacity).unwrap_or(u64::MAX),
            })
        })
        .collect()
}

/// `kairos_robot_connections{door}`, read from the doors' semaphores at each scrape.
#[derive(Debug)]
struct ConnectionsCollector(Arc<Mutex<Known>>);

impl Collector for ConnectionsCollector {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let doors = connections(&self.0.lock().unwrap_or_else(PoisonError::into_inner));
        if doors.is_empty() {
            return Ok(());
        }
        let mut family = encoder.encode_descriptor(
            "kairos_robot_connections",
            "Authenticated robot connections open now, by door",
            None,
            MetricType::Gauge,
        )?;
        for door in doors {
            let value = i64::try_from(door.connected).unwrap_or(i64::MAX);
            ConstGauge::new(value).encode(family.encode_family(&DoorLabel { door: door.door })?)?;
        }
        Ok(())
    }
}
