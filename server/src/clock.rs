//! The server's clock: tokio's, so that a test runtime started paused
//! (`#[tokio::test(start_paused = true)]`) runs the live server's logic in virtual time. The pure
//! logic only ever sees the [`Timestamp`]s it produces.

use std::time::Duration;

use kairos_core::time::{Timestamp, duration_micros};

/// The server clock: [`Timestamp`]s are microseconds since the clock's epoch, read from tokio's
/// clock. Read it on a runtime thread, or on a thread that entered the runtime
/// (`Handle::enter`): elsewhere tokio falls back to the system's monotonic clock, which a paused
/// test runtime does not control.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Clock {
    epoch: tokio::time::Instant,
}

impl Clock {
    /// A clock whose epoch is now.
    pub fn start() -> Clock {
        Clock {
            epoch: tokio::time::Instant::now(),
        }
    }

    /// Now on the server clock.
    pub fn now(&self) -> Timestamp {
        self.at(tokio::time::Instant::now())
    }

    /// `instant` on the server clock (the epoch for instants before it).
    pub fn at(&self, instant: tokio::time::Instant) -> Timestamp {
        Timestamp::from_micros(duration_micros(
            instant.saturating_duration_since(self.epoch),
        ))
    }

    /// The instant of a server timestamp, or `None` for [`Timestamp::MAX`] and anything else
    /// beyond what the platform's instants can represent (a deadline that never comes).
    pub fn instant(&self, t: Timestamp) -> Option<tokio::time::Instant> {
        if t == Timestamp::MAX {
            return None;
        }
        self.epoch.checked_add(Duration::from_micros(t.as_micros()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn the_clock_follows_tokio_time() {
        let clock = Clock::start();
        assert_eq!(clock.now(), Timestamp::ZERO);
        tokio::time::advance(Duration::from_millis(1500)).await;
        assert_eq!(clock.now().as_micros(), 1_500_000);
        let later = Timestamp::from_micros(2_000_000);
        assert_eq!(clock.at(clock.instant(later).unwrap()), later);
        assert_eq!(clock.instant(Timestamp::ZERO + Duration::MAX), None);
    }
}
