//! Whether two schedulers' average task latencies differ by more than noise.
//!
//! Every scheduler runs the same fleet, so task `i` under one scheduler and task `i` under another
//! are the same work: the comparison is paired. Its noise is how far the relative difference of
//! the two means would move had the fleet drawn other tasks of the same kind: the 95% percentile
//! interval of that difference over [`RESAMPLES`] bootstrap resamples, each drawing the tasks
//! with replacement and keeping each task's two latencies together. A difference whose interval
//! contains zero is within noise.
//!
//! Pairing removes the spread of the task lengths (a long task is long under every scheduler),
//! which would otherwise hide any difference a short run can show. What the interval does not
//! cover is a run that is slower as a whole, e.g. a shared machine busier during one run than
//! another; the engine's busy share per run, printed beside it, shows such a run.

use std::collections::BTreeMap;

use kairos_core::stats::quantile;
use rand::{Rng, SeedableRng, rngs::StdRng};

/// Bootstrap resamples per comparison.
pub const RESAMPLES: usize = 2000;
/// The bootstrap's seed: the same runs always read the same.
const SEED: u64 = 0x6b61_6972_6f73;

/// The relative difference of `other`'s mean task latency against `base`'s, with its interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Comparison {
    /// `mean(other) / mean(base) − 1`: negative when `other` is faster.
    pub change: f64,
    /// 2.5th percentile of `change` over the resamples.
    pub low: f64,
    /// 97.5th percentile of `change` over the resamples.
    pub high: f64,
    /// Tasks finished under both.
    pub pairs: usize,
}

impl Comparison {
    /// Whether the interval contains zero: the difference is within noise.
    pub fn within_noise(&self) -> bool {
        self.low <= 0.0 && self.high >= 0.0
    }
}

/// Compares `other`'s latencies with `base`'s, each `(task id, latency)`, over the tasks both
/// finished. `None` when none did or `base`'s latencies sum to zero.
pub fn compare(base: &[(u64, f64)], other: &[(u64, f64)]) -> Option<Comparison> {
    let base: BTreeMap<u64, f64> = base.iter().copied().collect();
    let pairs: Vec<(f64, f64)> = other
        .iter()
        .filter_map(|&(task, b)| base.get(&task).map(|&a| (a, b)))
        .collect();
    let ratio = |sample: &mut dyn Iterator<Item = (f64, f64)>| {
        let (a, b) = sample.fold((0.0, 0.0), |(sa, sb), (a, b)| (sa + a, sb + b));
        (a > 0.0).then(|| b / a - 1.0)
    };
    let change = ratio(&mut pairs.iter().copied())?;
    let mut rng = StdRng::seed_from_u64(SEED);
    let n = pairs.len();
    let mut changes: Vec<f64> = (0..RESAMPLES)
        .filter_map(|_| ratio(&mut (0..n).map(|_| pairs[rng.random_range(0..n)])))
        .collect();
    changes.sort_by(f64::total_cmp);
    Some(Comparison {
        change,
        low: quantile(&changes, 0.025),
        high: quantile(&changes, 0.975),
        pairs: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tasks(latencies: &[f64]) -> Vec<(u64, f64)> {
        latencies
            .iter()
            .enumerate()
            .map(|(i, &l)| (i as u64, l))
            .collect()
    }

    #[test]
    fn a_consistent_gain_is_not_noise() {
        let base: Vec<f64> = (0..30).map(|i| 2.0 + f64::from(i % 7)).collect();
        let faster: Vec<f64> = base
            .iter()
            .enumerate()
            .map(|(i, l)| l * if i % 2 == 0 { 0.6 } else { 0.7 })
            .collect();
        let c = compare(&tasks(&base), &tasks(&faster)).unwrap();
        assert_eq!(c.pairs, 30);
        assert!(c.change < -0.3 && c.change > -0.4, "{c:?}");
        assert!(c.low <= c.change && c.change <= c.high);
        assert!(c.high < 0.0 && !c.within_noise(), "{c:?}");
    }

    #[test]
    fn differences_that_go_both_ways_are_noise() {
        let base: Vec<f64> = (0..30).map(|i| 2.0 + f64::from(i % 7)).collect();
        let mixed: Vec<f64> = base
            .iter()
            .enumerate()
            .map(|(i, l)| l + if i % 2 == 0 { 1.0 } else { -1.05 })
            .collect();
        let c = compare(&tasks(&base), &tasks(&mixed)).unwrap();
        assert!(c.change.abs() < 0.01, "{c:?}");
        assert!(c.within_noise(), "{c:?}");
    }

    #[test]
    fn only_tasks_finished_under_both_are_paired() {
        let base = [(0, 1.0), (1, 2.0), (2, 3.0)];
        let other = [(2, 1.5), (3, 9.0), (0, 0.5)];
        let c = compare(&base, &other).unwrap();
        assert_eq!(c.pairs, 2);
        assert!((c.change - (2.0 / 4.0 - 1.0)).abs() < 1e-12);
        assert_eq!(compare(&base, &[(7, 1.0)]), None);
        assert_eq!(compare(&[(0, 0.0)], &[(0, 1.0)]), None);
    }

    #[test]
    fn the_same_runs_always_read_the_same() {
        let base = tasks(&[1.0, 4.0, 2.0, 8.0, 3.0]);
        let other = tasks(&[1.2, 3.0, 2.5, 6.0, 2.0]);
        assert_eq!(compare(&base, &other), compare(&base, &other));
    }
}
