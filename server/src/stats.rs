//! The one percentile definition of the project, and summaries built on it.
//!
//! Every percentile Kairos reports — the simulator's tables, `kairos demo`, `kairos bench live`,
//! `kairos robot`'s report, the plugin conformance timings, the driver's server-added latency —
//! is [`quantile`]: linear interpolation between order statistics, NumPy's default
//! (`numpy.percentile(values, 100 * q)`, Hyndman–Fan type 7). Interpolation rather than nearest
//! rank because small samples (a demo's two dozen tasks) would otherwise jump between order
//! statistics as `q` moves, and because anyone can check a number with NumPy.

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

/// The `q`-quantile (`q` in 0..=1, clamped) of an ascending sample, interpolating linearly
/// between order statistics: position `q · (n − 1)` in the sorted sample. NaN for an empty one.
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

/// Summarises a sample in any order (NaN fields for an empty one).
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

/// [`summarize`] of integer samples (e.g. µs), `None` for an empty one.
pub fn summarize_u64(values: &[u64]) -> Option<Summary> {
    if values.is_empty() {
        return None;
    }
    let values: Vec<f64> = values.iter().map(|&v| v as f64).collect();
    Some(summarize(&values))
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
        assert_eq!(s.n, 5);
        assert!(summarize(&[]).mean.is_nan());
        // numpy.percentile(range(1, 101), [50, 95, 99]) == [50.5, 95.05, 99.01]: between order
        // statistics, where nearest rank would give 50, 95 and 99.
        let hundred: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(quantile(&hundred, 0.5), 50.5);
        assert!((quantile(&hundred, 0.95) - 95.05).abs() < 1e-9);
        assert!((quantile(&hundred, 0.99) - 99.01).abs() < 1e-9);
    }

    #[test]
    fn quantiles_are_bounded_by_the_sample_and_monotone_in_q() {
        let sorted = [1.0, 5.0, 5.0, 9.0];
        assert_eq!(quantile(&sorted, 0.0), 1.0);
        assert_eq!(quantile(&sorted, 1.0), 9.0);
        assert_eq!(quantile(&sorted, -3.0), 1.0, "q is clamped");
        assert_eq!(quantile(&sorted, 7.0), 9.0, "q is clamped");
        assert_eq!(quantile(&[4.0], 0.99), 4.0);
        assert!(quantile(&[], 0.5).is_nan());
        let qs: Vec<f64> = (0..=100)
            .map(|i| quantile(&sorted, f64::from(i) / 100.0))
            .collect();
        assert!(qs.windows(2).all(|w| w[0] <= w[1]), "{qs:?}");
    }

    #[test]
    fn integer_samples_summarise_like_floats() {
        assert_eq!(summarize_u64(&[]), None);
        let s = summarize_u64(&[40, 10, 20, 30]).unwrap();
        assert_eq!(s, summarize(&[10.0, 20.0, 30.0, 40.0]));
        assert_eq!((s.p50, s.max), (25.0, 40.0));
    }
}
