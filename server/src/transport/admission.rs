//! Rate limit on failed `Hello` tokens, per source address (sans-IO: time is an argument).
//!
//! Each source has a token bucket of `burst` failures that refills at `per_minute` failures per
//! minute. A source whose bucket is empty is refused before its token is looked at, so a
//! guesser gets a handful of tries and then `per_minute` tries a minute, whatever it sends.
//! IPv6 sources are keyed by their /64 prefix, since one host usually owns a whole /64.
//!
//! The table is bounded: at `max_sources` entries, inserting a new source first drops every
//! source whose bucket has refilled (those are the same as absent), then, if it is still full,
//! the source closest to full (the one forgetting costs least).

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

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
}
