//! The admission guards every door of the server shares (the QUIC endpoint for robots and
//! workers, the openpi websocket endpoint), counted before a client has authenticated:
//! - [`Handshakes`]: a door's budget of connections between their first packet and an accepted
//!   token, with a cap per source address, so that one source cannot take the whole budget;
//! - [`WrongTokens`]: the rate limit on wrong tokens per source address, one for the whole
//!   server, so a guesser gets no more tries by switching doors.
//!
//! Their rules are sans-IO ([`FailedAuthLimiter`], [`SourceCounts`]: time is an argument, no
//! locks); the shared handles wrap them.
//!
//! **Failed tokens.** Each source has a token bucket of `burst` failures that refills at
//! `per_minute` failures per minute. A source whose bucket is empty is refused before its token
//! is looked at, so a guesser gets a handful of tries and then `per_minute` tries a minute,
//! whatever it sends. IPv6 sources are keyed by their /64 prefix, since one host usually owns a
//! whole /64. The table is bounded: at `max_sources` entries, inserting a new source first drops
//! every source whose bucket has refilled (those are the same as absent), then, if it is still
//! full, the source closest to full (the one forgetting costs least).

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::config::ConnectionsConfig;
use kairos_core::sync::lock;

/// The key a source address is counted under: the IPv4 address, or the IPv6 /64 prefix.
/// IPv4-mapped IPv6 addresses count as their IPv4 address.
pub fn source_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(v4) => IpAddr::V4(v4),
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let prefix = u128::from(v6) & !((1u128 << 64) - 1);
                IpAddr::V6(prefix.into())
            }
        },
    }
}

#[derive(Clone, Copy, Debug)]
struct Bucket {
    /// Failures still allowed at `at`.
    tokens: f64,
    at: Instant,
}

/// Failed-token limiter: see the module docs.
#[derive(Debug)]
pub struct FailedAuthLimiter {
    burst: f64,
    per_second: f64,
    max_sources: usize,
    sources: HashMap<IpAddr, Bucket>,
}

impl FailedAuthLimiter {
    /// `burst` failures at once, refilling at `per_minute` a minute, at most `max_sources`
    /// sources remembered (at least 1).
    pub fn new(burst: u32, per_minute: u32, max_sources: usize) -> FailedAuthLimiter {
        FailedAuthLimiter {
            burst: f64::from(burst),
            per_second: f64::from(per_minute) / 60.0,
            max_sources: max_sources.max(1),
            sources: HashMap::new(),
        }
    }

    fn tokens_at(&self, bucket: &Bucket, now: Instant) -> f64 {
        let elapsed = now.saturating_duration_since(bucket.at).as_secs_f64();
        (bucket.tokens + elapsed * self.per_second).min(self.burst)
    }

    /// Whether `ip` may try a token now: false once its failures have emptied its bucket.
    pub fn allows(&self, ip: IpAddr, now: Instant) -> bool {
        match self.sources.get(&source_key(ip)) {
            Some(bucket) => self.tokens_at(bucket, now) >= 1.0,
            None => self.burst >= 1.0,
        }
    }

    /// Counts a failed token from `ip`.
    pub fn record_failure(&mut self, ip: IpAddr, now: Instant) {
        let key = source_key(ip);
        let tokens = match self.sources.get(&key) {
            Some(bucket) => self.tokens_at(bucket, now),
            None => {
                self.make_room(now);
                self.burst
            }
        };
        self.sources.insert(
            key,
            Bucket {
                tokens: (tokens - 1.0).max(0.0),
                at: now,
            },
        );
    }

    /// Sources remembered.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Whether no source is remembered.
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    /// How long until `ip` may try again (zero if it may now).
    pub fn retry_after(&self, ip: IpAddr, now: Instant) -> Duration {
        let Some(bucket) = self.sources.get(&source_key(ip)) else {
            return Duration::ZERO;
        };
        let missing = 1.0 - self.tokens_at(bucket, now);
        if missing <= 0.0 {
            Duration::ZERO
        } else if self.per_second > 0.0 {
            Duration::try_from_secs_f64(missing / self.per_second).unwrap_or(Duration::MAX)
        } else {
            Duration::MAX
        }
    }

    /// Frees one slot if the table is full (see the module docs).
    fn make_room(&mut self, now: Instant) {
        if self.sources.len() < self.max_sources {
            return;
        }
        let burst = self.burst;
        let per_second = self.per_second;
        let refilled = |bucket: &Bucket| {
            let elapsed = now.saturating_duration_since(bucket.at).as_secs_f64();
            bucket.tokens + elapsed * per_second >= burst
        };
        self.sources.retain(|_, bucket| !refilled(bucket));
        if self.sources.len() < self.max_sources {
            return;
        }
        let fullest = self
            .sources
            .iter()
            .map(|(key, bucket)| (*key, self.tokens_at(bucket, now)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(key, _)| key);
        if let Some(key) = fullest {
            self.sources.remove(&key);
        }
    }
}

/// The limiters' clock: tokio's, so tests with a paused clock control it.
pub(crate) fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

/// The failed-token limiter of the whole server ([`FailedAuthLimiter`] on tokio's clock), shared
/// by every door: a source's wrong tokens count the same whichever door they came through.
#[derive(Debug)]
pub struct WrongTokens(Mutex<FailedAuthLimiter>);

impl WrongTokens {
    /// The limiter `[connections]` configures.
    pub fn new(config: &ConnectionsConfig) -> WrongTokens {
        WrongTokens(Mutex::new(FailedAuthLimiter::new(
            config.failed_token_burst,
            config.failed_tokens_per_minute,
            config.failed_token_sources,
        )))
    }

    /// Whether `ip` may try a token now.
    pub fn allows(&self, ip: IpAddr) -> bool {
        lock(&self.0).allows(ip, now())
    }

    /// Counts a wrong token from `ip`.
    pub fn failed(&self, ip: IpAddr) {
        lock(&self.0).record_failure(ip, now());
    }

    /// How long until `ip` may try again (zero if it may now).
    pub fn retry_after(&self, ip: IpAddr) -> Duration {
        lock(&self.0).retry_after(ip, now())
    }
}

/// Handshakes in progress per source (keyed as [`source_key`]), each source capped at
/// `per_source`. Sans-IO; [`Handshakes`] holds one behind a lock. The table has an entry only
/// for a source with a handshake in progress, so it is bounded by the door's budget.
#[derive(Debug)]
pub struct SourceCounts {
    per_source: usize,
    counts: HashMap<IpAddr, usize>,
}

impl SourceCounts {
    /// Counts with a cap of `per_source` (at least 1) handshakes per source.
    pub fn new(per_source: usize) -> SourceCounts {
        SourceCounts {
            per_source: per_source.max(1),
            counts: HashMap::new(),
        }
    }

    /// Counts one more handshake from `ip`, unless it has `per_source` in progress already.
    pub fn try_add(&mut self, ip: IpAddr) -> bool {
        let count = self.counts.entry(source_key(ip)).or_insert(0);
        if *count >= self.per_source {
            return false;
        }
        *count += 1;
        true
    }

    /// One handshake from `ip` ended.
    pub fn remove(&mut self, ip: IpAddr) {
        let key = source_key(ip);
        if let Some(count) = self.counts.get_mut(&key) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                self.counts.remove(&key);
            }
        }
    }

    /// Handshakes in progress from `ip`.
    pub fn count(&self, ip: IpAddr) -> usize {
        self.counts.get(&source_key(ip)).copied().unwrap_or(0)
    }

    /// Sources with a handshake in progress.
    pub fn len(&self) -> usize {
        self.counts.len()
    }

    /// Whether no handshake is in progress.
    pub fn is_empty(&self) -> bool {
        self.counts.is_empty()
    }
}

/// Why a door gave a connection attempt no handshake place.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HandshakeRefusal {
    /// All of the door's places are taken.
    Full,
    /// The attempt's source has its cap of handshakes in progress.
    SourceBusy,
}

/// One door's budget of handshakes in progress (`[connections] max_unauthenticated`), with a cap
/// per source (`max_unauthenticated_per_source`). A place is held from a connection's first
/// packet until its token is accepted or refused, so clients that never authenticate cannot take
/// robots' places, and one source cannot take all of them. The per-source cap is counted only
/// for validated sources: a TCP connection (its handshake proved the address), a QUIC attempt
/// that answered a Retry; an unvalidated QUIC source may be spoofed, and counting it would let a
/// spoofer use up a real robot's share.
#[derive(Clone, Debug)]
pub struct Handshakes {
    places: Arc<Semaphore>,
    max: usize,
    sources: Arc<Mutex<SourceCounts>>,
}

impl Handshakes {
    /// `max` places in all (at least 1), at most `per_source` per validated source.
    pub fn new(max: usize, per_source: usize) -> Handshakes {
        let max = max.max(1);
        Handshakes {
            places: Arc::new(Semaphore::new(max)),
            max,
            sources: Arc::new(Mutex::new(SourceCounts::new(per_source))),
        }
    }

    /// The budget `[connections]` configures for one door.
    pub fn for_door(config: &ConnectionsConfig) -> Handshakes {
        Handshakes::new(
            config.max_unauthenticated,
            config.max_unauthenticated_per_source,
        )
    }

    /// Places in all.
    pub fn max(&self) -> usize {
        self.max
    }

    /// Places taken now.
    pub fn in_progress(&self) -> usize {
        self.max - self.places.available_permits().min(self.max)
    }

    /// A place for an attempt from `validated` (its source address, if validated; `None`
    /// counts against the door's budget only).
    pub fn try_take(&self, validated: Option<IpAddr>) -> Result<HandshakePlace, HandshakeRefusal> {
        let mut sources = lock(&self.sources);
        if let Some(ip) = validated
            && sources.count(ip) >= sources.per_source
        {
            return Err(HandshakeRefusal::SourceBusy);
        }
        let permit = self
            .places
            .clone()
            .try_acquire_owned()
            .map_err(|_| HandshakeRefusal::Full)?;
        let source = validated.map(|ip| {
            sources.try_add(ip);
            SourceSlot {
                sources: self.sources.clone(),
                ip,
            }
        });
        Ok(HandshakePlace {
            _source: source,
            permit,
        })
    }
}

/// A handshake place: given back when dropped.
#[derive(Debug)]
pub struct HandshakePlace {
    permit: OwnedSemaphorePermit,
    _source: Option<SourceSlot>,
}

impl HandshakePlace {
    /// Gives the source's share back and keeps only the door's place (a worker registering
    /// after its QUIC handshake holds the door's place until it has registered).
    pub fn into_door_place(self) -> OwnedSemaphorePermit {
        self.permit
    }
}

/// A source's count of one handshake, taken off when dropped.
#[derive(Debug)]
struct SourceSlot {
    sources: Arc<Mutex<SourceCounts>>,
    ip: IpAddr,
}

impl Drop for SourceSlot {
    fn drop(&mut self) {
        lock(&self.sources).remove(self.ip);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ip(last: u8) -> IpAddr {
        IpAddr::from([10, 0, 0, last])
    }

    #[test]
    fn a_source_is_refused_after_burst_failures_and_refills_at_the_rate() {
        let t0 = Instant::now();
        let mut limiter = FailedAuthLimiter::new(3, 6, 100);
        for _ in 0..3 {
            assert!(limiter.allows(ip(1), t0));
            limiter.record_failure(ip(1), t0);
        }
        assert!(!limiter.allows(ip(1), t0));
        // Another source is unaffected.
        assert!(limiter.allows(ip(2), t0));
        // 6 a minute: one more try after 10 s, not before.
        assert_eq!(limiter.retry_after(ip(1), t0), Duration::from_secs(10));
        assert!(!limiter.allows(ip(1), t0 + Duration::from_millis(9_900)));
        assert!(limiter.allows(ip(1), t0 + Duration::from_secs(10)));
        limiter.record_failure(ip(1), t0 + Duration::from_secs(10));
        assert!(!limiter.allows(ip(1), t0 + Duration::from_secs(10)));
    }

    #[test]
    fn ipv6_sources_count_by_their_64_prefix() {
        let t0 = Instant::now();
        let mut limiter = FailedAuthLimiter::new(1, 0, 100);
        let a: IpAddr = "2001:db8:1:2::1".parse().unwrap();
        let b: IpAddr = "2001:db8:1:2:ffff::9".parse().unwrap();
        let other: IpAddr = "2001:db8:1:3::1".parse().unwrap();
        limiter.record_failure(a, t0);
        assert!(!limiter.allows(b, t0));
        assert!(limiter.allows(other, t0));
        let mapped: IpAddr = "::ffff:10.0.0.1".parse().unwrap();
        limiter.record_failure(mapped, t0);
        assert!(!limiter.allows(ip(1), t0));
        assert_eq!(limiter.retry_after(ip(1), t0), Duration::MAX);
    }

    #[test]
    fn a_full_table_forgets_refilled_sources_first() {
        let t0 = Instant::now();
        let mut limiter = FailedAuthLimiter::new(2, 60, 2);
        limiter.record_failure(ip(1), t0);
        limiter.record_failure(ip(2), t0 + Duration::from_secs(5));
        limiter.record_failure(ip(2), t0 + Duration::from_secs(5));
        // At t0 + 2 s ip(1) has refilled (1 + 2 s × 1/s ≥ 2) and is dropped for ip(3).
        limiter.record_failure(ip(3), t0 + Duration::from_secs(6));
        assert_eq!(limiter.len(), 2);
        assert!(!limiter.allows(ip(2), t0 + Duration::from_secs(5)));
    }

    proptest! {
        /// Whatever the sequence of failures, the table never exceeds its cap, and a source
        /// that failed `burst` times within no time at all is refused.
        #[test]
        fn the_table_is_bounded_and_bursts_are_refused(
            cap in 1usize..16,
            burst in 1u32..5,
            events in proptest::collection::vec((0u8..40, 0u64..5_000), 0..300),
        ) {
            let t0 = Instant::now();
            let mut limiter = FailedAuthLimiter::new(burst, 12, cap);
            let mut now = t0;
            for (source, step_ms) in events {
                now += Duration::from_millis(step_ms);
                limiter.record_failure(ip(source), now);
                prop_assert!(limiter.len() <= cap);
            }
            for _ in 0..burst {
                limiter.record_failure(ip(200), now);
            }
            prop_assert!(!limiter.allows(ip(200), now));
            prop_assert!(limiter.len() <= cap);
        }
    }

    #[test]
    fn a_source_gets_its_share_of_handshakes_and_others_the_rest() {
        let budget = Handshakes::new(4, 2);
        let a = || Some(ip(1));
        let first = budget.try_take(a()).unwrap();
        let _second = budget.try_take(a()).unwrap();
        assert_eq!(
            budget.try_take(a()).unwrap_err(),
            HandshakeRefusal::SourceBusy
        );
        // Another source, and an unvalidated attempt (counted only in the door's budget).
        let _other = budget.try_take(Some(ip(2))).unwrap();
        let _unvalidated = budget.try_take(None).unwrap();
        assert_eq!(budget.in_progress(), 4);
        assert_eq!(
            budget.try_take(Some(ip(3))).unwrap_err(),
            HandshakeRefusal::Full
        );
        // A place given back frees both the door's place and the source's share.
        drop(first);
        assert_eq!(budget.in_progress(), 3);
        let again = budget.try_take(a()).unwrap();
        // A worker keeps the door's place but gives its source's share back.
        let door_only = again.into_door_place();
        assert_eq!(budget.in_progress(), 4);
        drop(door_only);
        assert!(budget.try_take(a()).is_ok());
    }

    proptest! {
        /// Whatever the order of takes and drops, no source holds more than its share, the
        /// door never more than its budget, and everything is given back at the end.
        #[test]
        fn handshake_places_are_bounded_and_given_back(
            max in 1usize..12,
            per_source in 1usize..5,
            events in proptest::collection::vec((0u8..6, proptest::bool::ANY), 0..200),
        ) {
            let budget = Handshakes::new(max, per_source);
            let mut held: Vec<(u8, HandshakePlace)> = Vec::new();
            for (source, take) in events {
                if take {
                    let validated = (source != 0).then(|| ip(source));
                    if let Ok(place) = budget.try_take(validated) {
                        held.push((source, place));
                    }
                } else if !held.is_empty() {
                    held.remove(usize::from(source) % held.len());
                }
                prop_assert!(budget.in_progress() <= max);
                prop_assert_eq!(budget.in_progress(), held.len());
                for s in 1..6u8 {
                    let from_s = held.iter().filter(|(h, _)| *h == s).count();
                    prop_assert!(from_s <= per_source);
                    prop_assert_eq!(lock(&budget.sources).count(ip(s)), from_s);
                }
            }
            held.clear();
            prop_assert_eq!(budget.in_progress(), 0);
            prop_assert!(lock(&budget.sources).is_empty());
        }
    }
}
