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

/// Ranks `1..=n` of `values` in their order, ties sharing their average rank (what Spearman's
/// coefficient ranks with). NaN sorts last.
pub fn ranks(values: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut out = vec![0.0; values.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && values[order[j + 1]] == values[order[i]] {
            j += 1;
        }
        let rank = (i + j) as f64 / 2.0 + 1.0;
        for &o in &order[i..=j] {
            out[o] = rank;
        }
        i = j + 1;
    }
    out
}

/// Pearson's correlation of two equally long samples (NaN when either is constant or they
/// hold fewer than two pairs).
pub fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len().min(y.len());
    if n < 2 {
        return f64::NAN;
    }
    let mx = x[..n].iter().sum::<f64>() / n as f64;
    let my = y[..n].iter().sum::<f64>() / n as f64;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x[..n].iter().zip(&y[..n]) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx) * (a - mx);
        syy += (b - my) * (b - my);
    }
    sxy / (sxx * syy).sqrt()
}

/// Spearman's rank correlation: [`pearson`] of the [`ranks`].
pub fn spearman(x: &[f64], y: &[f64]) -> f64 {
    pearson(&ranks(x), &ranks(y))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rank_correlations_match_scipy() {
        // scipy.stats.rankdata([3, 1, 4, 1, 5]) == [3, 1.5, 4, 1.5, 5]
        assert_eq!(ranks(&[3.0, 1.0, 4.0, 1.0, 5.0]), [3.0, 1.5, 4.0, 1.5, 5.0]);
        // scipy.stats.spearmanr([1, 2, 3, 4, 5], [5, 6, 7, 8, 7]).statistic == 0.8207826816681233
        let rho = spearman(&[1.0, 2.0, 3.0, 4.0, 5.0], &[5.0, 6.0, 7.0, 8.0, 7.0]);
        assert!((rho - 0.820_782_681_668_123_3).abs() < 1e-12, "{rho}");
        assert!((pearson(&[1.0, 2.0, 3.0], &[2.0, 4.0, 6.0]) - 1.0).abs() < 1e-12);
        assert!(pearson(&[1.0, 1.0], &[1.0, 2.0]).is_nan());
    }

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
