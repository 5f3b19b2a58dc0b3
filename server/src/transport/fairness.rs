//! Fairness between tenants: what one robot (one token) may take of the server, whatever its
//! robots do, so that it cannot lock the others out.
//!
//! - **Connection places.** A robot holds at most `max_connections_per_robot` authenticated
//!   connections at once ([`RobotPlaces`]); `max_connections` stays the last line for all of
//!   them together. Unset, the cap is an equal share of `max_connections` per configured robot,
//!   so every robot can always get its share; a fleet that shares one token (the generated
//!   `default` robot) has every place.
//! - **Round rates.** Rounds are token buckets ([`TokenBucket`]): one per connection (one robot
//!   process) and one per robot over all its connections, QUIC and openpi alike
//!   ([`RobotRounds`], checked in `ServerContext::admit`). A round over either is refused at
//!   once, before validation, with a retryable `overloaded` and the wait until the bucket
//!   allows one more.
//!
//! The buckets are sans-IO (time is an argument); the table of robots is bounded by the robots
//! the configuration allows.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use kairos_core::scheduler::RobotId;

use crate::config::ConnectionsConfig;

/// A token bucket: `burst` tokens at most, refilled at `rate` tokens per second. Sans-IO.
#[derive(Clone, Copy, Debug)]
pub struct TokenBucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    at: Option<Instant>,
}

impl TokenBucket {
    /// A full bucket of `burst` tokens (at least 1) refilled at `rate_per_s` (a positive
    /// finite number; anything else refills nothing).
    pub fn new(rate_per_s: f64, burst: u32) -> TokenBucket {
        let burst = f64::from(burst.max(1));
        TokenBucket {
            rate: if rate_per_s.is_finite() && rate_per_s > 0.0 {
                rate_per_s
            } else {
                0.0
            },
            burst,
            tokens: burst,
            at: None,
        }
    }

    fn refill(&mut self, now: Instant) {
        if let Some(at) = self.at {
            let elapsed = now.saturating_duration_since(at).as_secs_f64();
            self.tokens = (self.tokens + elapsed * self.rate).min(self.burst);
        }
        self.at = Some(now);
    }

    /// Takes one token at `now`; if there is none, how long until there is one.
    pub fn try_take(&mut self, now: Instant) -> Result<(), Duration> {
        self.refill(now);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            return Ok(());
        }
        if self.rate <= 0.0 {
            return Err(Duration::MAX);
        }
        let wait = (1.0 - self.tokens) / self.rate;
        Err(Duration::try_from_secs_f64(wait).unwrap_or(Duration::MAX))
    }

    /// Returns a token taken for something that was refused elsewhere.
    pub fn give_back(&mut self) {
        self.tokens = (self.tokens + 1.0).min(self.burst);
    }
}

/// Places for authenticated connections, counted per robot (see the module docs).
#[derive(Debug)]
pub struct RobotPlaces {
    cap: usize,
    held: Mutex<HashMap<RobotId, usize>>,
}

/// One connection's place among its robot's; given back when dropped.
#[derive(Debug)]
pub struct RobotPlace {
    places: Arc<RobotPlaces>,
    robot: RobotId,
}

impl RobotPlaces {
    /// `cap` places per robot (at least 1).
    pub fn new(cap: usize) -> Arc<RobotPlaces> {
        Arc::new(RobotPlaces {
            cap: cap.max(1),
            held: Mutex::new(HashMap::new()),
        })
    }

    /// The cap `config` gives for `robots` configured robots: `max_connections_per_robot`, or
    /// else an equal share of `max_connections` (at least 1).
    pub fn cap_for(config: &ConnectionsConfig, robots: usize) -> usize {
        config
            .max_connections_per_robot
            .unwrap_or(config.max_connections / robots.max(1))
            .max(1)
    }

    /// Places per robot.
    pub fn cap(&self) -> usize {
        self.cap
    }

    fn held(&self) -> std::sync::MutexGuard<'_, HashMap<RobotId, usize>> {
        // Counters only: a panic while holding the lock leaves them usable.
        self.held.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A place for one more connection of `robot`, if it holds fewer than the cap.
    pub fn take(self: &Arc<Self>, robot: RobotId) -> Option<RobotPlace> {
        let mut held = self.held();
        let count = held.entry(robot).or_insert(0);
        if *count >= self.cap {
            return None;
        }
        *count += 1;
        Some(RobotPlace {
            places: self.clone(),
            robot,
        })
    }

    /// Connections `robot` holds now.
    pub fn holding(&self, robot: RobotId) -> usize {
        self.held().get(&robot).copied().unwrap_or(0)
    }
}

impl Drop for RobotPlace {
    fn drop(&mut self) {
        let mut held = self.places.held();
        if let Some(count) = held.get_mut(&self.robot) {
            *count = count.saturating_sub(1);
            if *count == 0 {
                held.remove(&self.robot);
            }
        }
    }
}

/// Each robot's round bucket, over all its connections.
#[derive(Debug)]
pub struct RobotRounds {
    rate: f64,
    burst: u32,
    buckets: Mutex<HashMap<RobotId, TokenBucket>>,
}

impl RobotRounds {
    /// Buckets of `burst` rounds refilled at `rate_per_s`.
    pub fn new(rate_per_s: f64, burst: u32) -> RobotRounds {
        RobotRounds {
            rate: rate_per_s,
            burst,
            buckets: Mutex::new(HashMap::new()),
        }
    }

    /// One round of `robot` at `now`; if its bucket is empty, how long until it is not.
    pub fn try_take(&self, robot: RobotId, now: Instant) -> Result<(), Duration> {
        let mut buckets = self.buckets.lock().unwrap_or_else(PoisonError::into_inner);
        buckets
            .entry(robot)
            .or_insert_with(|| TokenBucket::new(self.rate, self.burst))
            .try_take(now)
    }
}

/// What the connection tasks of every transport share to keep tenants apart.
#[derive(Debug)]
pub struct Fairness {
    /// Connection places per robot.
    pub places: Arc<RobotPlaces>,
    /// Round rates per robot.
    pub rounds: RobotRounds,
    connection_rate: f64,
    connection_burst: u32,
}

impl Fairness {
    /// The limits `config` sets for a server of `robots` configured robots.
    pub fn new(config: &ConnectionsConfig, robots: usize) -> Fairness {
        Fairness {
            places: RobotPlaces::new(RobotPlaces::cap_for(config, robots)),
            rounds: RobotRounds::new(config.rounds_per_s_per_robot, config.round_burst_per_robot),
            connection_rate: config.rounds_per_s_per_connection,
            connection_burst: config.round_burst_per_connection,
        }
    }

    /// A new connection's round bucket.
    pub fn connection_rounds(&self) -> TokenBucket {
        TokenBucket::new(self.connection_rate, self.connection_burst)
    }
}

/// The fairness clock: tokio's, so tests with a paused clock control it.
pub(crate) fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bucket_allows_its_burst_then_its_rate() {
        let t0 = Instant::now();
        let mut bucket = TokenBucket::new(2.0, 3);
        for _ in 0..3 {
            assert_eq!(bucket.try_take(t0), Ok(()));
        }
        assert_eq!(bucket.try_take(t0), Err(Duration::from_millis(500)));
        // Half a second later one token is back, and only one.
        let t1 = t0 + Duration::from_millis(500);
        assert_eq!(bucket.try_take(t1), Ok(()));
        assert!(bucket.try_take(t1).is_err());
        // A token given back is there at once; the bucket never holds more than its burst.
        bucket.give_back();
        assert_eq!(bucket.try_take(t1), Ok(()));
        let later = t1 + Duration::from_secs(3600);
        for _ in 0..3 {
            assert_eq!(bucket.try_take(later), Ok(()));
        }
        assert!(bucket.try_take(later).is_err());
        // Time that runs backwards refills nothing.
        assert!(bucket.try_take(t0).is_err());
        // No rate: the burst, then never again.
        let mut once = TokenBucket::new(0.0, 1);
        assert_eq!(once.try_take(t0), Ok(()));
        assert_eq!(once.try_take(later), Err(Duration::MAX));
    }

    #[test]
    fn places_are_capped_per_robot_and_given_back_on_drop() {
        let places = RobotPlaces::new(2);
        let (a, b) = (RobotId(0), RobotId(1));
        let first = places.take(a).unwrap();
        let second = places.take(a).unwrap();
        assert!(places.take(a).is_none(), "a third place for `a`");
        let other = places.take(b).unwrap();
        assert_eq!((places.holding(a), places.holding(b)), (2, 1));
        drop(first);
        assert_eq!(places.holding(a), 1);
        let again = places.take(a).unwrap();
        drop((second, again, other));
        assert_eq!((places.holding(a), places.holding(b)), (0, 0));
    }

    #[test]
    fn the_default_cap_is_an_equal_share_of_max_connections() {
        let config = ConnectionsConfig {
            max_connections: 50,
            ..ConnectionsConfig::default()
        };
        assert_eq!(RobotPlaces::cap_for(&config, 1), 50, "one fleet token");
        assert_eq!(RobotPlaces::cap_for(&config, 2), 25);
        assert_eq!(RobotPlaces::cap_for(&config, 3), 16);
        assert_eq!(RobotPlaces::cap_for(&config, 1000), 1);
        assert_eq!(RobotPlaces::cap_for(&config, 0), 50);
        let set = ConnectionsConfig {
            max_connections_per_robot: Some(4),
            ..config
        };
        assert_eq!(RobotPlaces::cap_for(&set, 1), 4);
    }

    #[test]
    fn each_robot_has_its_own_round_bucket() {
        let t0 = Instant::now();
        let rounds = RobotRounds::new(0.5, 2);
        let (a, b) = (RobotId(0), RobotId(1));
        assert!(rounds.try_take(a, t0).is_ok());
        assert!(rounds.try_take(a, t0).is_ok());
        let wait = rounds.try_take(a, t0).unwrap_err();
        assert_eq!(wait, Duration::from_secs(2));
        assert!(rounds.try_take(b, t0).is_ok());
    }
}
