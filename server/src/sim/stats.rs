//! Summary statistics of end-to-end latencies.

/// P25 / mean / P50 / P95 / P99 / max of a sample.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Summary {
    /// Sample size.
    pub n: usize,
    /// Arithmetic mean.
    pub mean: f64,
    /// 25th percentile.
    pub p25: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest value.
    pub max: f64,
}

/// The `q`-quantile (0..=1) of an ascending sample, interpolating linearly between order
/// statistics (NumPy's default, so the numbers can be checked with `numpy.percentile`).
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    match sorted.len() {
        0 => f64::NAN,
        1 => sorted[0],
        n => {
            let pos = q.clamp(0.0, 1.0) * (n - 1) as f64;
            let lo = pos.floor() as usize;
            let hi = (lo + 1).min(n - 1);
            sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
        }
    }
}

/// Summarises a sample (NaN fields for an empty one).
pub fn summarize(values: &[f64]) -> Summary {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let mean = if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    };
    Summary {
        n: v.len(),
        mean,
        p25: quantile(&v, 0.25),
        p50: quantile(&v, 0.50),
        p95: quantile(&v, 0.95),
        p99: quantile(&v, 0.99),
        max: v.last().copied().unwrap_or(f64::NAN),
    }
}

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
    fn quantiles_match_numpy_linear_interpolation() {
        // numpy.percentile([1, 2, 3, 4, 10], [25, 50, 95]) == [2.0, 3.0, 8.8]
        let s = summarize(&[10.0, 3.0, 1.0, 4.0, 2.0]);
        assert_eq!(s.p25, 2.0);
        assert_eq!(s.p50, 3.0);
        assert!((s.p95 - 8.8).abs() < 1e-12);
        assert_eq!(s.mean, 4.0);
        assert_eq!(s.max, 10.0);
        assert!(summarize(&[]).mean.is_nan());
    }

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
