//! Measuring an engine profile at start, when the configuration names no profile file.
//!
//! The scheduler needs latency by batch size (paper §3.2: batches grow up to the saturation
//! point of the latency–batch-size profile). A profile measured offline (`kairos profile`) is
//! more careful; this one is measured in a few seconds when the server starts so that a server
//! with no configuration still batches sensibly.

use std::time::Instant;

use kairos_engine::{ActionModel, ActionRequest, EngineError, EngineProfile, ProfilePoint};

/// Throughput must grow by at least this factor from one measured batch size to the next for
/// the larger one to count as worth forming.
pub const SATURATION_GAIN: f64 = 1.10;

/// Batch sizes to measure: powers of two up to `max_batch`, and `max_batch` itself.
pub fn batch_sizes(max_batch: u32) -> Vec<u32> {
    let mut sizes = Vec::new();
    let mut b = 1u32;
    while b < max_batch {
        sizes.push(b);
        b = b.saturating_mul(2);
    }
    sizes.push(max_batch.max(1));
    sizes
}

/// The largest measured batch size that still raised throughput (requests per second) by
/// [`SATURATION_GAIN`] over the previous measured size.
pub fn saturation_batch(points: &[ProfilePoint]) -> u32 {
    let throughput = |p: &ProfilePoint| {
        if p.latency_ms > 0.0 {
            f64::from(p.batch) / p.latency_ms
        } else {
            f64::INFINITY
        }
    };
    let Some(first) = points.first() else {
        return 1;
    };
    let mut best = first;
    for p in &points[1..] {
        if throughput(p) < SATURATION_GAIN * throughput(best) {
            break;
        }
        best = p;
    }
    best.batch.max(1)
}

/// Measures `model` at each of [`batch_sizes`]`(max_batch)`: one warm-up pass, then the median
/// of `reps` passes, each on synthetic requests (a zero state, no images, one sample). Blocking;
/// call it off the async runtime.
pub fn measure(
    model: &dyn ActionModel,
    device: &str,
    max_batch: u32,
    reps: usize,
) -> Result<EngineProfile, EngineError> {
    let spec = model.spec();
    let mut points = Vec::new();
    for batch in batch_sizes(max_batch) {
        let requests: Vec<ActionRequest> = (0..batch)
            .map(|i| ActionRequest {
                state: vec![0.0; spec.state_dim],
                images: Vec::new(),
                instruction: String::new(),
                samples: 1,
                seed: u64::from(i),
            })
            .collect();
        model.generate(&requests)?;
        let mut times: Vec<f64> = (0..reps.max(1))
            .map(|_| {
                let start = Instant::now();
                model
                    .generate(&requests)
                    .map(|_| start.elapsed().as_secs_f64() * 1e3)
            })
            .collect::<Result<_, _>>()?;
        times.sort_by(f64::total_cmp);
        points.push(ProfilePoint {
            batch,
            latency_ms: times[times.len() / 2],
        });
    }
    let max_batch = saturation_batch(&points);
    Ok(EngineProfile {
        model: spec.name.clone(),
        device: device.to_string(),
        points,
        max_batch,
    })
}

#[cfg(test)]
mod tests {
    use super::super::test_model::LinearFlow;
    use super::*;

    fn point(batch: u32, latency_ms: f64) -> ProfilePoint {
        ProfilePoint { batch, latency_ms }
    }

    #[test]
    fn batch_sizes_are_powers_of_two_capped_by_the_maximum() {
        assert_eq!(batch_sizes(1), vec![1]);
        assert_eq!(batch_sizes(8), vec![1, 2, 4, 8]);
        assert_eq!(batch_sizes(12), vec![1, 2, 4, 8, 12]);
    }

    #[test]
    fn saturation_is_where_throughput_stops_growing() {
        // Throughput 1, 1.9, 3.3, 3.4 per ms: 8 adds only 3%.
        let points = [
            point(1, 1.0),
            point(2, 1.05),
            point(4, 1.2),
            point(8, 2.35),
        ];
        assert_eq!(saturation_batch(&points), 4);
        // Linear latency: batching never pays.
        assert_eq!(saturation_batch(&[point(1, 1.0), point(2, 2.0)]), 1);
        assert_eq!(saturation_batch(&[]), 1);
    }

    #[test]
    fn measure_reports_every_batch_size_in_order() {
        let model = LinearFlow::new();
        let profile = measure(&model, "cpu", 4, 2).unwrap();
        let batches: Vec<u32> = profile.points.iter().map(|p| p.batch).collect();
        assert_eq!(batches, vec![1, 2, 4]);
        assert!(profile.points.iter().all(|p| p.latency_ms >= 0.0));
        assert!((1..=4).contains(&profile.max_batch));
        assert_eq!(profile.model, "linear-flow");
    }
}
