//! Summary statistics of end-to-end latencies: reductions and empirical CDFs, on top of the
//! percentile of [`kairos_core::stats`].

// The percentile is the project's one definition, in `kairos_core::stats`; it is re-exported here
// because the simulator's reports are built on it.
pub use kairos_core::stats::{Summary, quantile, summarize};

/// How much lower `ours` is than `base`, in percent (negative: higher).
pub fn reduction(base: f64, ours: f64) -> f64 {
    if base == 0.0 {
        0.0
    } else {
        (base - ours) / base * 100.0
    }
}

/// Points of the empirical CDF of a sample, `(value, cumulative fraction)`, at most `max_points`.
pub fn ecdf(values: &[f64], max_points: usize) -> Vec<(f64, f64)> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 || max_points == 0 {
        return Vec::new();
    }
    let step = n.div_ceil(max_points).max(1);
    let mut out: Vec<(f64, f64)> = (0..n)
        .step_by(step)
        .map(|i| (v[i], (i + 1) as f64 / n as f64))
        .collect();
    if out.last().is_some_and(|p| p.1 < 1.0) {
        out.push((v[n - 1], 1.0));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reduction_is_relative_to_the_baseline() {
        assert_eq!(reduction(10.0, 7.0), 30.0);
        assert_eq!(reduction(10.0, 12.0), -20.0);
    }

    #[test]
    fn ecdf_ends_at_one() {
        let c = ecdf(&[3.0, 1.0, 2.0, 5.0, 4.0], 2);
        assert_eq!(c.first(), Some(&(1.0, 0.2)));
        assert_eq!(c.last(), Some(&(5.0, 1.0)));
    }
}
