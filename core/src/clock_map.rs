//! Robot clocks onto the server clock.
//!
//! Client timestamps are microseconds on the robot's own monotonic clock. Each message carries
//! `sent_at_us`; the server maps the robot's clock onto its own with an offset estimated per
//! connection by [`ClockEstimator`]: `offset = min(server_read − sent_at_us) − RTT/2` over the
//! connection's most recent first-attempt messages, where RTT is quinn's smoothed estimate.
//! `server_read − sent_at_us` is the true offset plus that message's one-way delay (network,
//! queueing, server scheduling); the minimum over a window picks the least delayed message, and
//! half the RTT stands in for its network delay. Robots need no clock synchronisation; the
//! mapping error is the least-delayed message's deviation from RTT/2 — tens of microseconds on
//! loopback, of the order of the jitter on Wi-Fi — and does not grow when the server is busy.
//! Re-sent rounds (after a reconnect) keep their first `sent_at_us`, so they never feed the
//! estimate. The window (32 messages) bounds the effect of clock drift between the two machines.

use std::collections::VecDeque;
use std::time::Duration;

use crate::time::{Timestamp, duration_micros};

/// Maps one robot's clock onto the server's, for one request.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ClockMap {
    /// `server_us − client_us`.
    offset_us: i128,
}

impl ClockMap {
    /// The mapping implied by a request sent at `sent_at_us` (client clock) and read at
    /// `server_now`, over a connection whose round trip is `rtt`.
    pub fn new(server_now: Timestamp, sent_at_us: u64, rtt: Duration) -> ClockMap {
        let sent_on_server =
            i128::from(server_now.as_micros()) - i128::from(duration_micros(rtt) / 2);
        ClockMap {
            offset_us: sent_on_server - i128::from(sent_at_us),
        }
    }

    /// A client time on the server clock (clamped to the server's epoch).
    pub fn to_server(&self, client_us: u64) -> Timestamp {
        let server = i128::from(client_us) + self.offset_us;
        Timestamp::from_micros(u64::try_from(server.max(0)).unwrap_or(u64::MAX))
    }

    /// A server time on the client clock (clamped to the client's zero).
    pub fn to_client(&self, t: Timestamp) -> u64 {
        let client = i128::from(t.as_micros()) - self.offset_us;
        u64::try_from(client.max(0)).unwrap_or(u64::MAX)
    }
}

/// Estimates one connection's clock offset from the messages it sends (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct ClockEstimator {
    /// `server_read − sent_at` of the most recent first-attempt messages, µs.
    samples: VecDeque<i128>,
}

impl ClockEstimator {
    /// Messages the estimate is the minimum over.
    pub const WINDOW: usize = 32;

    /// Records a message sent at `sent_at_us` (client clock) and read at `server_now`, and returns
    /// the mapping to use for it. `first_attempt` is false for a re-sent round, whose `sent_at_us`
    /// is its first send's: it is mapped with the current estimate and does not change it (unless
    /// there is none yet).
    pub fn observe(
        &mut self,
        server_now: Timestamp,
        sent_at_us: u64,
        rtt: Duration,
        first_attempt: bool,
    ) -> ClockMap {
        let sample = i128::from(server_now.as_micros()) - i128::from(sent_at_us);
        let half_rtt = i128::from(duration_micros(rtt) / 2);
        if first_attempt || self.samples.is_empty() {
            if self.samples.len() >= Self::WINDOW {
                self.samples.pop_front();
            }
            self.samples.push_back(sample);
        }
        let best = self.samples.iter().copied().min().unwrap_or(sample);
        ClockMap {
            offset_us: best - half_rtt,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clock_map_subtracts_half_the_rtt_and_round_trips() {
        let clock = ClockMap::new(
            Timestamp::from_micros(5_000_000),
            1_000_000,
            Duration::from_micros(200),
        );
        assert_eq!(clock.to_server(1_000_000).as_micros(), 4_999_900);
        assert_eq!(clock.to_server(900_000).as_micros(), 4_899_900);
        assert_eq!(clock.to_client(Timestamp::from_micros(4_899_900)), 900_000);
        // A client clock far ahead of the server's epoch clamps instead of wrapping.
        let ahead = ClockMap::new(Timestamp::from_micros(10), u64::MAX / 2, Duration::ZERO);
        assert_eq!(ahead.to_server(0), Timestamp::ZERO);
    }

    #[test]
    fn clock_estimator_takes_the_least_delayed_message_and_ignores_resends() {
        let mut est = ClockEstimator::default();
        let rtt = Duration::from_micros(100);
        // True offset 1_000_000 µs; one-way delays 500, 80 and 3000 µs.
        let map = est.observe(Timestamp::from_micros(1_010_500), 10_000, rtt, true);
        assert_eq!(map.to_server(10_000).as_micros(), 1_010_450);
        let map = est.observe(Timestamp::from_micros(1_020_080), 20_000, rtt, true);
        assert_eq!(map.to_server(20_000).as_micros(), 1_020_030);
        let map = est.observe(Timestamp::from_micros(1_033_000), 30_000, rtt, true);
        assert_eq!(
            map.to_server(30_000).as_micros(),
            1_030_030,
            "a delayed message does not move the estimate"
        );
        // A round re-sent 2 s later with its first sent_at.
        let map = est.observe(Timestamp::from_micros(3_040_000), 40_000, rtt, false);
        assert_eq!(map.to_server(40_000).as_micros(), 1_040_030);
        for i in 0..ClockEstimator::WINDOW as u64 {
            est.observe(
                Timestamp::from_micros(1_100_000 + i * 10 + 200),
                100_000 + i * 10,
                rtt,
                true,
            );
        }
        let map = est.observe(Timestamp::from_micros(1_200_200), 200_000, rtt, true);
        assert_eq!(
            map.to_server(200_000).as_micros(),
            1_200_150,
            "old samples leave the window"
        );
    }
}
