//! [`Readmission`]: how long a worker removed for unusable answers waits before it may register
//! again.
//!
//! A worker that answers a batch unusably (NaN or inf actions, the wrong number of results, an
//! oversized error text) is removed and the batch's rounds go back to the queue. Without a
//! delay, a buggy worker registers again within milliseconds as a new, idle, fast-looking
//! engine and attracts the very rounds it spoiled: each of them is charged an attempt per
//! spoiled dispatch, and once a round has used `[workers] max_attempts` its robot gets an
//! error although a healthy worker was registered the whole time.
//!
//! So after a removal for an unusable answer, the same worker (its registered `worker_id` and
//! the IP address it came from) is refused at registration for `[workers]
//! readmit_after_invalid_ms`, with a retryable `Refused` that says for how long, counted in
//! `kairos_refusals_total{door="workers",reason="readmit_delay"}` and logged at warn level
//! like the door's other refusals. With the delay at least `redispatch_within_ms` (the
//! defaults: 30 s and 10 s), a round spoiled by a worker is past its re-dispatch window before
//! that worker can take it again: each worker spoils each round at most once, and the retries
//! of a spoiled batch go to the other engines.
//!
//! The alternative, not charging an attempt for a failure that was the worker's fault and
//! steering the retry to another engine, was not taken: an engine that registers again is a
//! new engine to the scheduler (ids are never reused), so "another engine" cannot be told from
//! "the same worker again" in the scheduler's pure core, and with uncharged attempts a worker
//! that keeps spoiling would keep its rounds busy until their window ends; the attempt limit
//! stays the bound on wasted work.
//!
//! What the delay does not stop: a holder of the worker token who changes its `worker_id` on
//! every registration. The worker token is an operator's credential; the delay contains a
//! buggy or broken worker, and a token that misbehaves on purpose is revoked by rotating it.
//! The table is bounded ([`MAX_BARRED`] entries) so that such a worker cannot grow it either.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::Duration;

use kairos_core::sync::lock;
use tokio::time::Instant;

/// Most workers barred at once; beyond it the one whose delay ends first is forgotten.
pub const MAX_BARRED: usize = 1024;

/// Workers barred from registering, by `worker_id` and source IP, until their delay ends.
#[derive(Debug)]
pub struct Readmission {
    delay: Duration,
    barred: Mutex<HashMap<(String, IpAddr), Instant>>,
}

impl Readmission {
    /// Bars a worker removed for unusable answers for `delay` (zero: never barred).
    pub fn new(delay: Duration) -> Readmission {
        Readmission {
            delay,
            barred: Mutex::new(HashMap::new()),
        }
    }

    /// The worker `worker_id` from `ip` was removed for an unusable answer at `now`: it may not
    /// register again before `now + delay`.
    pub fn bar(&self, worker_id: &str, ip: IpAddr, now: Instant) {
        if self.delay.is_zero() {
            return;
        }
        let until = now.checked_add(self.delay).unwrap_or(now);
        let mut barred = lock(&self.barred);
        let key = (worker_id.to_string(), ip);
        if barred.len() >= MAX_BARRED && !barred.contains_key(&key) {
            barred.retain(|_, until| *until > now);
            if barred.len() >= MAX_BARRED
                && let Some(first) = barred
                    .iter()
                    .min_by_key(|(_, until)| **until)
                    .map(|(key, _)| key.clone())
            {
                barred.remove(&first);
            }
        }
        barred.insert(key, until);
    }

    /// Whether the worker `worker_id` from `ip` may register at `now`; if not, how long it must
    /// still wait. A delay that has ended is forgotten here.
    pub fn check(&self, worker_id: &str, ip: IpAddr, now: Instant) -> Result<(), Duration> {
        let mut barred = lock(&self.barred);
        let key = (worker_id.to_string(), ip);
        match barred.get(&key) {
            Some(&until) if until > now => Err(until - now),
            Some(_) => {
                barred.remove(&key);
                Ok(())
            }
            None => Ok(()),
        }
    }

    /// Workers barred now or whose delay ended but who have not come back yet.
    pub fn len(&self) -> usize {
        lock(&self.barred).len()
    }

    /// Whether no worker is barred.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOCAL: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);
    const OTHER: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 2));

    #[test]
    fn a_barred_worker_waits_out_its_delay_and_no_one_else_does() {
        let readmission = Readmission::new(Duration::from_secs(30));
        let t0 = Instant::now();
        assert_eq!(readmission.check("w", LOCAL, t0), Ok(()));
        readmission.bar("w", LOCAL, t0);
        assert_eq!(
            readmission.check("w", LOCAL, t0 + Duration::from_secs(1)),
            Err(Duration::from_secs(29))
        );
        // Another name from the same address, and the same name from another address, are
        // other workers.
        assert_eq!(readmission.check("healthy", LOCAL, t0), Ok(()));
        assert_eq!(readmission.check("w", OTHER, t0), Ok(()));
        assert_eq!(
            readmission.check("w", LOCAL, t0 + Duration::from_secs(30)),
            Ok(())
        );
        assert!(readmission.is_empty(), "an ended delay is forgotten");
    }

    #[test]
    fn a_zero_delay_bars_no_one() {
        let readmission = Readmission::new(Duration::ZERO);
        let t0 = Instant::now();
        readmission.bar("w", LOCAL, t0);
        assert_eq!(readmission.check("w", LOCAL, t0), Ok(()));
        assert!(readmission.is_empty());
    }

    #[test]
    fn the_table_stays_bounded_and_forgets_the_delay_that_ends_first() {
        let readmission = Readmission::new(Duration::from_secs(30));
        let t0 = Instant::now();
        for i in 0..MAX_BARRED as u64 * 3 {
            readmission.bar(&format!("w{i}"), LOCAL, t0 + Duration::from_millis(i));
            assert!(readmission.len() <= MAX_BARRED);
        }
        let last = MAX_BARRED as u64 * 3 - 1;
        let at = t0 + Duration::from_millis(last);
        assert!(readmission.check(&format!("w{last}"), LOCAL, at).is_err());
        assert_eq!(
            readmission.check("w0", LOCAL, at),
            Ok(()),
            "the oldest went"
        );
    }
}
