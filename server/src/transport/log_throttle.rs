//! A log line per kind of event at most once per interval, however often the event happens.
//!
//! A guard that refuses a flood must not turn the flood into log lines: each kind of event (a
//! key) may write one line, then none for `interval`; the next line says how many events went
//! unlogged in between. Time is an argument, so the rule is tested without a clock.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use kairos_core::sync::lock;

#[derive(Clone, Copy, Debug, Default)]
struct Slot {
    /// When the key last wrote a line.
    last: Option<Instant>,
    /// Events of the key since that line.
    unlogged: u64,
}

/// Rate limit of log lines for `keys` kinds of event (see the module docs).
#[derive(Debug)]
pub struct LogThrottle {
    interval: Duration,
    slots: Mutex<Vec<Slot>>,
}

impl LogThrottle {
    /// One line per key per `interval`, for keys `0..keys`.
    pub fn new(keys: usize, interval: Duration) -> LogThrottle {
        LogThrottle {
            interval,
            slots: Mutex::new(vec![Slot::default(); keys]),
        }
    }

    /// An event of `key` at `now`: `Some(unlogged)` if it may write a line (with the number of
    /// events of `key` that wrote none since the previous line), `None` if it must stay silent.
    /// A key out of range is always silent.
    pub fn admit(&self, key: usize, now: Instant) -> Option<u64> {
        // A panic while holding this lock leaves at worst one count stale.
        let mut slots = lock(&self.slots);
        let slot = slots.get_mut(key)?;
        let due = slot
            .last
            .is_none_or(|last| now.saturating_duration_since(last) >= self.interval);
        if due {
            let unlogged = slot.unlogged;
            *slot = Slot {
                last: Some(now),
                unlogged: 0,
            };
            Some(unlogged)
        } else {
            slot.unlogged = slot.unlogged.saturating_add(1);
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_per_key_per_interval_and_the_next_counts_the_silent_ones() {
        let t0 = Instant::now();
        let throttle = LogThrottle::new(2, Duration::from_secs(10));
        assert_eq!(throttle.admit(0, t0), Some(0));
        for ms in [1, 500, 9_999] {
            assert_eq!(throttle.admit(0, t0 + Duration::from_millis(ms)), None);
        }
        // Another key has its own budget.
        assert_eq!(throttle.admit(1, t0 + Duration::from_millis(2)), Some(0));
        assert_eq!(throttle.admit(0, t0 + Duration::from_secs(10)), Some(3));
        assert_eq!(throttle.admit(0, t0 + Duration::from_secs(11)), None);
        assert_eq!(throttle.admit(0, t0 + Duration::from_secs(25)), Some(1));
        assert_eq!(throttle.admit(2, t0), None, "an unknown key writes nothing");
    }

    #[test]
    fn a_flood_writes_one_line_per_interval() {
        let t0 = Instant::now();
        let throttle = LogThrottle::new(1, Duration::from_secs(10));
        // 81,000 events over 25 s (one every ~0.3 ms): lines at 0, 10 and 20 s.
        let lines = (0..81_000u64)
            .filter(|i| {
                let now = t0 + Duration::from_micros(i * 25_000_000 / 81_000);
                throttle.admit(0, now).is_some()
            })
            .count();
        assert_eq!(lines, 3);
    }
}
