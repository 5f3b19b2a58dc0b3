//! Engine profiles: latency as a function of batch size, measured offline.
//!
//! `kairos profile` writes one; the scheduler's batching and edge/cloud placement read it
//! (paper §3.2: "batching up to the saturation point of the latency–batch-size profile").

use std::time::Duration;

/// One measured point of a profile.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProfilePoint {
    /// Requests per forward pass.
    pub batch: u32,
    /// Median latency of one whole generation (all steps) at this batch size, in milliseconds.
    pub latency_ms: f64,
}

/// Latency versus batch size for one engine instance on one device.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EngineProfile {
    /// Model name, as in `ModelSpec::name`.
    pub model: String,
    /// Device description, e.g. `cpu (2 threads, AMD EPYC)` or `cuda:0 (H100)`.
    pub device: String,
    /// Measured points, sorted by batch size, batch 1 first.
    pub points: Vec<ProfilePoint>,
    /// Largest batch worth forming: beyond it throughput stops improving.
    pub max_batch: u32,
}

impl EngineProfile {
    /// Latency of one batch of `batch` requests, interpolated linearly between measured points
    /// and extrapolated from the last two beyond the largest. Batches of 0 cost nothing.
    pub fn latency(&self, batch: u32) -> Duration {
        if batch == 0 || self.points.is_empty() {
            return Duration::ZERO;
        }
        let ms = match self.points.iter().position(|p| p.batch >= batch) {
            Some(0) => {
                self.points[0].latency_ms * f64::from(batch)
                    / f64::from(self.points[0].batch.max(1))
            }
            Some(i) => lerp(self.points[i - 1], self.points[i], batch),
            None if self.points.len() == 1 => {
                self.points[0].latency_ms * f64::from(batch)
                    / f64::from(self.points[0].batch.max(1))
            }
            None => {
                let n = self.points.len();
                lerp(self.points[n - 2], self.points[n - 1], batch)
            }
        };
        // Profiles come from files and from remote workers: a huge or non-finite latency must
        // not panic here (`from_secs_f64` would), it saturates.
        Duration::try_from_secs_f64(ms.max(0.0) / 1e3).unwrap_or(Duration::MAX)
    }
}

/// Default relative throughput gain below which a larger batch is "not worth forming".
pub const DEFAULT_MIN_GAIN: f64 = 0.05;

/// The saturation batch size of measured `points` (sorted by batch): the smallest measured batch
/// `b` such that no larger measured batch has a throughput (requests per second, `batch /
/// latency`) more than `min_gain` above `b`'s. Beyond it, batching more only adds latency.
/// 1 for an empty profile.
pub fn saturation_batch(points: &[ProfilePoint], min_gain: f64) -> u32 {
    let throughput = |p: &ProfilePoint| f64::from(p.batch) / p.latency_ms.max(f64::MIN_POSITIVE);
    for (i, p) in points.iter().enumerate() {
        let best_later = points[i + 1..].iter().map(throughput).fold(0.0, f64::max);
        if best_later <= throughput(p) * (1.0 + min_gain) {
            return p.batch;
        }
    }
    points.last().map_or(1, |p| p.batch)
}

fn lerp(a: ProfilePoint, b: ProfilePoint, batch: u32) -> f64 {
    let span = f64::from(b.batch) - f64::from(a.batch);
    if span <= 0.0 {
        return b.latency_ms;
    }
    let f = (f64::from(batch) - f64::from(a.batch)) / span;
    a.latency_ms + f * (b.latency_ms - a.latency_ms)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn profile() -> EngineProfile {
        EngineProfile {
            model: "m".into(),
            device: "cpu".into(),
            points: vec![
                ProfilePoint {
                    batch: 1,
                    latency_ms: 100.0,
                },
                ProfilePoint {
                    batch: 4,
                    latency_ms: 160.0,
                },
                ProfilePoint {
                    batch: 8,
                    latency_ms: 300.0,
                },
            ],
            max_batch: 4,
        }
    }

    fn points(latencies: &[(u32, f64)]) -> Vec<ProfilePoint> {
        latencies
            .iter()
            .map(|&(batch, latency_ms)| ProfilePoint { batch, latency_ms })
            .collect()
    }

    #[test]
    fn saturation_is_where_throughput_stops_improving() {
        // Throughput 10, 25, 40, 41, 40 req/s: saturated at 8.
        let p = points(&[(1, 100.0), (4, 160.0), (8, 200.0), (16, 390.0), (32, 800.0)]);
        assert_eq!(saturation_batch(&p, 0.05), 8);
        // A stricter rule keeps the 2.5% gain of 16.
        assert_eq!(saturation_batch(&p, 0.01), 16);
        // Linear latency (no batching gain) saturates at once.
        assert_eq!(
            saturation_batch(&points(&[(1, 100.0), (2, 200.0), (4, 400.0)]), 0.05),
            1
        );
        // Still improving at the largest measured batch: that batch.
        assert_eq!(
            saturation_batch(&points(&[(1, 100.0), (2, 110.0), (4, 120.0)]), 0.05),
            4
        );
        // A dip then a rise: the later gain counts.
        assert_eq!(
            saturation_batch(&points(&[(1, 100.0), (2, 210.0), (4, 200.0)]), 0.05),
            4
        );
        assert_eq!(saturation_batch(&[], 0.05), 1);
    }

    #[test]
    fn latency_interpolates_and_extrapolates() {
        let p = profile();
        assert_eq!(p.latency(0), Duration::ZERO);
        assert_eq!(p.latency(1), Duration::from_millis(100));
        assert_eq!(p.latency(2), Duration::from_millis(120));
        assert_eq!(p.latency(4), Duration::from_millis(160));
        assert_eq!(p.latency(6), Duration::from_millis(230));
        assert_eq!(p.latency(12), Duration::from_millis(440));
    }

    #[test]
    fn latency_of_absurd_points_saturates_instead_of_panicking() {
        let mut p = profile();
        p.points[0].latency_ms = 1e300;
        assert_eq!(p.latency(1), Duration::MAX);
        p.points[0].latency_ms = f64::INFINITY;
        assert_eq!(p.latency(1), Duration::MAX);
        p.points[0].latency_ms = f64::NAN;
        assert_eq!(p.latency(1), Duration::ZERO);
    }
}
