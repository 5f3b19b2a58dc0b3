//! Engine profiles: latency as a function of batch size, measured offline.
//!
//! `kairos profile` writes one; the scheduler's batching and edge/cloud placement read it
//! (paper §3.2: "batching up to the saturation point of the latency–batch-size profile").

use std::time::{Duration, Instant};

use crate::{ActionModel, ActionRequest, EngineError, ImageInput};

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

/// What [`measure`] reports as it goes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MeasureEvent {
    /// Measurement begins: `runs` timed generations in all (warm-ups excluded).
    Started {
        /// Timed runs to come.
        runs: usize,
    },
    /// One timed generation finished.
    Run {
        /// Its batch size.
        batch: u32,
        /// Its latency.
        latency: Duration,
    },
    /// A batch size is done.
    Point(ProfilePoint),
}

/// How to measure a profile.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasureOptions {
    /// Batch sizes to measure, ascending.
    pub batches: Vec<u32>,
    /// Timed generations per batch size (after one warm-up); the median is kept.
    pub iterations: usize,
    /// Device description stored in the profile.
    pub device: String,
    /// Saturation rule parameter, see [`saturation_batch`].
    pub min_gain: f64,
}

/// Requests that exercise the whole model: full state, every camera (224x224 RGB), a
/// 30-character instruction, one sample each, distinct seeds.
pub fn synthetic_batch(model: &dyn ActionModel, batch: usize) -> Vec<ActionRequest> {
    let spec = model.spec();
    (0..batch)
        .map(|i| ActionRequest {
            cameras: Vec::new(),
            state: (0..spec.state_dim)
                .map(|j| ((i * 31 + j) as f32 * 0.1).sin())
                .collect(),
            images: (0..spec.max_images)
                .map(|c| ImageInput::RawU8 {
                    height: 224,
                    width: 224,
                    channels: 3,
                    data: (0..224 * 224 * 3)
                        .map(|p| ((p * 7 + i * 13 + c * 29) % 251) as u8)
                        .collect(),
                })
                .collect(),
            instruction: "pick up the red cube and place it".into(),
            samples: 1,
            seed: i as u64,
        })
        .collect()
}

/// Measure latency versus batch size of `model` on this machine and find its saturation batch.
///
/// For each batch size: one warm-up generation, then `iterations` timed ones on
/// [`synthetic_batch`] requests; the point is their median. Reads the clock (it is a
/// measurement); `progress` sees every run.
pub fn measure(
    model: &dyn ActionModel,
    options: &MeasureOptions,
    mut progress: impl FnMut(MeasureEvent),
) -> Result<EngineProfile, EngineError> {
    if options.batches.is_empty() || options.iterations == 0 || options.batches.contains(&0) {
        return Err(EngineError::InvalidInput(
            "profile needs batch sizes >= 1 and at least one iteration".into(),
        ));
    }
    let mut batches = options.batches.clone();
    batches.sort_unstable();
    batches.dedup();
    progress(MeasureEvent::Started {
        runs: batches.len() * options.iterations,
    });
    let mut points = Vec::with_capacity(batches.len());
    for &batch in &batches {
        let requests = synthetic_batch(model, batch as usize);
        model.generate(&requests)?;
        let mut runs = Vec::with_capacity(options.iterations);
        for _ in 0..options.iterations {
            let start = Instant::now();
            let chunks = model.generate(&requests)?;
            let latency = start.elapsed();
            if chunks.len() != requests.len() {
                return Err(EngineError::InvalidInput(format!(
                    "model returned {} chunks for {batch}",
                    chunks.len()
                )));
            }
            progress(MeasureEvent::Run { batch, latency });
            runs.push(latency.as_secs_f64() * 1e3);
        }
        runs.sort_by(f64::total_cmp);
        let point = ProfilePoint {
            batch,
            latency_ms: runs[runs.len() / 2],
        };
        progress(MeasureEvent::Point(point));
        points.push(point);
    }
    Ok(EngineProfile {
        model: model.spec().name.clone(),
        device: options.device.clone(),
        max_batch: saturation_batch(&points, options.min_gain),
        points,
    })
}

fn lerp(a: ProfilePoint, b: ProfilePoint, batch: u32) -> f64 {
    let span = f64::from(b.batch) - f64::from(a.batch);
    if span <= 0.0 {
        return b.latency_ms;
    }
    let f = (f64::from(batch) - f64::from(a.batch)) / span;
    a.latency_ms + f * (b.latency_ms - a.latency_ms)
}

/// CPU time of this process (all threads) in ms, from /proc (Linux); 0 elsewhere. On a shared
/// machine wall time includes waiting for a core, CPU time does not.
pub fn process_cpu_ms() -> f64 {
    stat_cpu_ms("/proc/self/stat")
}

/// Peak resident set size of this process in MB (`VmHWM` from /proc, Linux); 0 elsewhere.
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

/// CPU time of the calling thread in ms, from /proc (Linux, 10 ms resolution); 0 elsewhere.
pub fn thread_cpu_ms() -> f64 {
    stat_cpu_ms("/proc/thread-self/stat")
}

/// utime + stime of a /proc `stat` file, in ms.
fn stat_cpu_ms(path: &str) -> f64 {
    let Ok(stat) = std::fs::read_to_string(path) else {
        return 0.0;
    };
    let Some(rest) = stat.rsplit(')').next() else {
        return 0.0;
    };
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // After the command: state is field 3; utime and stime are fields 14 and 15 (1-based).
    let ticks = |i: usize| {
        fields
            .get(i - 3)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (ticks(14) + ticks(15)) * 10.0
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
}
