//! Engine profiles: latency as a function of batch size, measured offline.
//!
//! `kairos profile` writes one; the scheduler's batching and edge/cloud placement read it
//! (paper §3.2: "batching up to the saturation point of the latency–batch-size profile").

use std::time::{Duration, Instant};

use crate::{ActionModel, ActionRequest, EngineError, ImageInput};
pub use kairos_engine_types::profile::{
    DEFAULT_MIN_GAIN, EngineProfile, ProfilePoint, saturation_batch,
};

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
            guidance: None,
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

/// CPU time of the calling thread in ms (0 without a per-thread CPU clock).
pub fn thread_cpu_ms() -> f64 {
    thread_cpu_time().map_or(0.0, |t| t.as_secs_f64() * 1e3)
}

/// CPU time the calling thread has used, if the platform has a per-thread CPU clock (nanosecond
/// resolution on Linux). Unlike wall time it does not grow while the thread waits for a core.
#[cfg(unix)]
pub fn thread_cpu_time() -> Option<Duration> {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, exclusively borrowed `timespec` for the whole call, which only
    // writes into it; CLOCK_THREAD_CPUTIME_ID needs no other argument.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return None;
    }
    Some(Duration::new(
        u64::try_from(ts.tv_sec).ok()?,
        u32::try_from(ts.tv_nsec).ok()?,
    ))
}

/// CPU time the calling thread has used: no per-thread CPU clock here.
#[cfg(not(unix))]
pub fn thread_cpu_time() -> Option<Duration> {
    None
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
