//! Every time a guard turns a client away: counted by door and reason
//! (`kairos_refusals_total{door, reason}`), logged at warn level at most once per door and
//! reason per [`LOG_INTERVAL`] (the line says how many went unlogged, [`LogThrottle`]), and
//! summed in the shutdown report ([`RefusalCounts`]). One counter per fact: the transport and
//! the openpi endpoint count here and nowhere else, in the server's one `kairos_refusals_total`
//! family ([`Metrics::refusal_counter`], where the metrics listener counts its own refusals).
//!
//! Both labels come from closed enums, so these doors add a fixed, small set of series (every
//! door's reasons exist at zero from the server's start, so a dashboard sees them before the
//! first refusal).

use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use prometheus_client::metrics::counter::Counter;

use super::admission::now;
use super::log_throttle::LogThrottle;
use crate::metrics::Metrics;

/// Shortest interval between two log lines of the same door and reason.
pub const LOG_INTERVAL: Duration = Duration::from_secs(10);

/// Where a client came in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Door {
    /// The QUIC endpoint: robots, and workers until their handshake is done.
    Quic,
    /// The openpi websocket endpoint.
    Openpi,
    /// Remote workers' registrations, once their QUIC handshake (counted at `Quic`) is done.
    Workers,
}

impl Door {
    /// Every door, in the order reported.
    pub const ALL: [Door; 3] = [Door::Quic, Door::Openpi, Door::Workers];

    /// The `door` label value.
    pub fn as_str(self) -> &'static str {
        match self {
            Door::Quic => "quic",
            Door::Openpi => "openpi",
            Door::Workers => "workers",
        }
    }

    /// The reasons this door refuses for.
    pub fn reasons(self) -> &'static [Reason] {
        use Reason::*;
        match self {
            Door::Quic => &[
                HandshakeBudget,
                SourceHandshakes,
                WrongTokenLimit,
                Unauthorized,
                HandshakeTimeout,
                HelloTimeout,
                BadHello,
                AtCapacity,
                RobotAtCapacity,
                RoundRate,
                TooSlow,
                TooLarge,
            ],
            Door::Openpi => &[
                HandshakeBudget,
                SourceHandshakes,
                WrongTokenLimit,
                Unauthorized,
                HandshakeTimeout,
                BadUpgrade,
                AtCapacity,
                RobotAtCapacity,
                RoundRate,
                TooSlow,
                TooLarge,
            ],
            // What a worker breaks after its token is accepted removes it instead
            // (`kairos_worker_removed_total{reason}`).
            Door::Workers => &[WrongTokenLimit, Unauthorized, RegisterTimeout, ReadmitDelay],
        }
    }
}

/// Why a client was turned away.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Reason {
    /// Every one of the door's `max_unauthenticated` handshake places was taken.
    HandshakeBudget,
    /// The source had `max_unauthenticated_per_source` handshakes in progress.
    SourceHandshakes,
    /// The source had used up its wrong tokens (`failed_token_burst`, `failed_tokens_per_minute`):
    /// refused before its token was looked at.
    WrongTokenLimit,
    /// A wrong or missing token.
    Unauthorized,
    /// The QUIC handshake, or the openpi websocket upgrade, was not done within
    /// `hello_timeout_ms`.
    HandshakeTimeout,
    /// No accepted `Hello` within `hello_timeout_ms` of the first packet (QUIC).
    HelloTimeout,
    /// The first message was not an acceptable `Hello` (malformed, another kind, an unsupported
    /// version) (QUIC).
    BadHello,
    /// The request was not a websocket upgrade (openpi).
    BadUpgrade,
    /// No `Register` within `hello_timeout_ms` of the first packet (workers).
    RegisterTimeout,
    /// A worker removed for an unusable answer registered again before
    /// `readmit_after_invalid_ms` passed (workers).
    ReadmitDelay,
    /// The door's `max_connections` authenticated places were taken.
    AtCapacity,
    /// The robot held `max_connections_per_robot` connections (on every door together).
    RobotAtCapacity,
    /// A round over its connection's or its robot's round rate (`rounds_per_s_per_connection`,
    /// `rounds_per_s_per_robot`), refused `overloaded` before validation.
    RoundRate,
    /// An upload fell behind `min_upload_bytes_per_s` after `upload_grace_ms`.
    TooSlow,
    /// A frame or message over `limits.max_frame`.
    TooLarge,
}

impl Reason {
    /// The `reason` label value.
    pub fn as_str(self) -> &'static str {
        match self {
            Reason::HandshakeBudget => "handshake_budget",
            Reason::SourceHandshakes => "source_handshakes",
            Reason::WrongTokenLimit => "wrong_token_limit",
            Reason::Unauthorized => "unauthorized",
            Reason::HandshakeTimeout => "handshake_timeout",
            Reason::HelloTimeout => "hello_timeout",
            Reason::BadHello => "bad_hello",
            Reason::BadUpgrade => "bad_upgrade",
            Reason::RegisterTimeout => "register_timeout",
            Reason::ReadmitDelay => "readmit_delay",
            Reason::AtCapacity => "at_capacity",
            Reason::RobotAtCapacity => "robot_at_capacity",
            Reason::RoundRate => "round_rate",
            Reason::TooSlow => "too_slow",
            Reason::TooLarge => "too_large",
        }
    }
}

struct Inner {
    /// Where the counters live; a pair outside its door's list is counted there too.
    metrics: Metrics,
    /// Every door's reasons, each with its counter; a position here is its log throttle key.
    counters: Vec<(Door, Reason, Counter)>,
    log: LogThrottle,
    logged: AtomicU64,
}

/// The refusal counters and their log (see the module docs). Cheap to clone; every clone counts
/// into the same series.
#[derive(Clone)]
pub struct Refusals(Arc<Inner>);

impl fmt::Debug for Refusals {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_tuple("Refusals").field(&self.counts()).finish()
    }
}

impl Refusals {
    /// Every door's reasons, at zero, counted in `metrics`' `kairos_refusals_total`.
    pub fn new(metrics: &Metrics) -> Refusals {
        let counters: Vec<(Door, Reason, Counter)> = Door::ALL
            .iter()
            .flat_map(|&door| door.reasons().iter().map(move |&reason| (door, reason)))
            .map(|(door, reason)| {
                let counter = metrics.refusal_counter(door.as_str(), reason.as_str());
                (door, reason, counter)
            })
            .collect();
        let log = LogThrottle::new(counters.len(), LOG_INTERVAL);
        Refusals(Arc::new(Inner {
            metrics: metrics.clone(),
            counters,
            log,
            logged: AtomicU64::new(0),
        }))
    }

    fn position(&self, door: Door, reason: Reason) -> Option<usize> {
        self.0
            .counters
            .iter()
            .position(|&(d, r, _)| d == door && r == reason)
    }

    /// Counts a refusal of `remote` at `door` for `reason`, and logs it at warn level with
    /// `detail` unless a line for the same door and reason was written within [`LOG_INTERVAL`].
    pub fn refuse(
        &self,
        door: Door,
        reason: Reason,
        remote: std::net::SocketAddr,
        detail: &dyn fmt::Display,
    ) {
        let key = match self.position(door, reason) {
            Some(key) => {
                self.0.counters[key].2.inc();
                key
            }
            // A pair outside the door's list: still counted (its own series), logged every time.
            None => {
                self.0
                    .metrics
                    .refusal_counter(door.as_str(), reason.as_str())
                    .inc();
                usize::MAX
            }
        };
        let unlogged = if key == usize::MAX {
            Some(0)
        } else {
            self.0.log.admit(key, now())
        };
        if let Some(unlogged) = unlogged {
            self.0.logged.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(
                door = door.as_str(),
                reason = reason.as_str(),
                %remote,
                unlogged,
                "connection refused: {detail}"
            );
        }
    }

    /// Refusals of `door` for `reason` so far.
    pub fn count(&self, door: Door, reason: Reason) -> u64 {
        match self.position(door, reason) {
            Some(key) => self.0.counters[key].2.get(),
            None => self
                .0
                .metrics
                .refusal_counter(door.as_str(), reason.as_str())
                .get(),
        }
    }

    /// Every refusal so far, for the shutdown report.
    pub fn counts(&self) -> RefusalCounts {
        RefusalCounts {
            by_reason: self
                .0
                .counters
                .iter()
                .map(|(door, reason, counter)| (*door, *reason, counter.get()))
                .filter(|&(_, _, count)| count > 0)
                .collect(),
            logged: self.0.logged.load(Ordering::Relaxed),
        }
    }
}

/// The refusals a server made, as its shutdown report shows them.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RefusalCounts {
    /// Each door and reason that refused at least once, with its count, in the order of
    /// [`Door::ALL`] and [`Door::reasons`].
    pub by_reason: Vec<(Door, Reason, u64)>,
    /// Log lines written for them (the rest went unlogged, [`LOG_INTERVAL`]).
    pub logged: u64,
}

impl RefusalCounts {
    /// All refusals.
    pub fn total(&self) -> u64 {
        self.by_reason.iter().map(|&(_, _, count)| count).sum()
    }

    /// Refusals of `door` for `reason`.
    pub fn get(&self, door: Door, reason: Reason) -> u64 {
        self.by_reason
            .iter()
            .find(|&&(d, r, _)| d == door && r == reason)
            .map_or(0, |&(_, _, count)| count)
    }
}

/// `none`, or per door its counts: `quic: 3 unauthorized, 1 too_slow; openpi: 2 at_capacity`.
impl fmt::Display for RefusalCounts {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.by_reason.is_empty() {
            return f.write_str("none");
        }
        let mut first_door = true;
        for door in Door::ALL {
            let counts: Vec<String> = self
                .by_reason
                .iter()
                .filter(|&&(d, _, _)| d == door)
                .map(|&(_, reason, count)| format!("{count} {}", reason.as_str()))
                .collect();
            if counts.is_empty() {
                continue;
            }
            if !first_door {
                f.write_str("; ")?;
            }
            first_door = false;
            write!(f, "{}: {}", door.as_str(), counts.join(", "))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn remote() -> std::net::SocketAddr {
        "192.0.2.1:4000".parse().unwrap()
    }

    #[test]
    fn refusals_are_counted_by_door_and_reason_and_exported() {
        let metrics = Metrics::new();
        let refusals = Refusals::new(&metrics);
        for _ in 0..3 {
            refusals.refuse(Door::Openpi, Reason::Unauthorized, remote(), &"unknown key");
        }
        refusals.refuse(Door::Quic, Reason::TooSlow, remote(), &"upload too slow");
        assert_eq!(refusals.count(Door::Openpi, Reason::Unauthorized), 3);
        assert_eq!(refusals.count(Door::Quic, Reason::Unauthorized), 0);

        let text = metrics.encode();
        assert!(
            text.contains(r#"kairos_refusals_total{door="openpi",reason="unauthorized"} 3"#),
            "{text}"
        );
        assert!(text.contains(r#"kairos_refusals_total{door="quic",reason="too_slow"} 1"#));
        // Every door's reasons exist from the start, and no others of these doors.
        let series = text
            .lines()
            .filter(|l| l.starts_with("kairos_refusals_total{"))
            .filter(|l| {
                Door::ALL
                    .iter()
                    .any(|d| l.contains(&format!("door=\"{}\"", d.as_str())))
            })
            .count();
        let expected: usize = Door::ALL.iter().map(|d| d.reasons().len()).sum();
        assert_eq!(series, expected);
        // The same counts as the metrics' own listing (the fleet page's).
        let listed = metrics
            .refusals()
            .into_iter()
            .find(|r| r.door == "openpi" && r.reason == "unauthorized")
            .map(|r| r.total);
        assert_eq!(listed, Some(3));
        assert!(text.contains(r#"kairos_refusals_total{door="quic",reason="at_capacity"} 0"#));

        let counts = refusals.counts();
        assert_eq!(counts.total(), 4);
        assert_eq!(counts.get(Door::Openpi, Reason::Unauthorized), 3);
        assert_eq!(
            counts.to_string(),
            "quic: 1 too_slow; openpi: 3 unauthorized"
        );
        // The three openpi refusals came within one interval: one line for them.
        assert_eq!(counts.logged, 2);
        assert_eq!(RefusalCounts::default().to_string(), "none");
    }
}
