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
        Duration::from_secs_f64(ms.max(0.0) / 1e3)
    }
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
}
