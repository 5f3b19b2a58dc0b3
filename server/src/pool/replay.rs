//! The trace-replay engine: the paper's evaluation engine (§5.1), labelled as such everywhere.
//!
//! Live replay (`kairos bench live`, the sim-vs-live test) runs the real server — QUIC, driver,
//! scheduler, action manager — against robots that replay recorded traces. The GPU model those
//! traces were recorded with is not on this machine, so its place is taken by
//! [`TraceReplayModel`]: a batch takes exactly the *profiled* generation time of its size
//! (`EngineProfile::latency`, the same number the simulator charges), and each request gets back
//! the chunk its trace recorded.
//!
//! What a trace records of a chunk is what the horizon policy reads: per action, the ratio of
//! the final diffusion update's norm to the mean of the earlier ones (`RoundTrace::confidence`,
//! docs/TRACES.md). The replaying robot sends that vector as its observation's `state` (see
//! [`replay_state`]); the model answers a one-dimensional, two-step chunk whose step-0 updates
//! have norm 1 and whose final updates have norm `confidence[n]` — the same reconstruction the
//! simulator feeds its horizon policies (`sim::horizon`). The server's action manager then runs
//! the round's real horizon policy on it, so the live `H` is computed, not copied. The actions
//! themselves are zeros: a replayed robot executes time slots, not motions.
//!
//! The replaying robot also attaches one blank camera frame of the trace's observation size, so
//! the observation costs on the wire what the recorded one did.

use std::sync::Arc;
use std::time::{Duration, Instant};

use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineError, EngineProfile, ModelSpec,
};
use kairos_sdk::trace::RoundTrace;

use super::{EngineInstance, LocalEngine};

/// Name of the replay model in `ModelSpec::name` (and so in the server's `Welcome`).
pub const REPLAY_MODEL: &str = "trace-replay";

/// Profiled latency, recorded chunk. See the module docs.
pub struct TraceReplayModel {
    spec: ModelSpec,
    profile: EngineProfile,
}

impl TraceReplayModel {
    /// A replay model for traces whose chunks have `chunk_len` actions, taking `profile`'s
    /// latency per batch.
    pub fn new(chunk_len: usize, profile: EngineProfile) -> Result<Self, EngineError> {
        if chunk_len == 0 || profile.points.is_empty() {
            return Err(EngineError::InvalidInput(
                "a replay model needs a chunk length and a latency profile".into(),
            ));
        }
        Ok(TraceReplayModel {
            spec: ModelSpec {
                cameras: Vec::new(),
                camera_aliases: Default::default(),
                name: REPLAY_MODEL.to_string(),
                chunk_len,
                action_dim: 1,
                state_dim: chunk_len,
                steps: 2,
                max_images: 1,
            },
            profile,
        })
    }

    /// The latency curve it reproduces.
    pub fn profile(&self) -> &EngineProfile {
        &self.profile
    }

    fn chunk(&self, request: &ActionRequest) -> Result<ActionChunk, EngineError> {
        let n = self.spec.chunk_len;
        let confidence = &request.state;
        if confidence.len() != n || confidence.iter().any(|c| !c.is_finite() || *c < 0.0) {
            return Err(EngineError::InvalidInput(format!(
                "a replayed observation's state is the round's {n} recorded confidence ratios \
                 (finite, non-negative); got {} values",
                confidence.len()
            )));
        }
        let samples = request.samples.max(1);
        let mut updates = Vec::with_capacity(samples * 2 * n);
        let mut noise = Vec::with_capacity(samples * n);
        for _ in 0..samples {
            updates.extend(std::iter::repeat_n(1.0f32, n));
            updates.extend_from_slice(confidence);
            // The actions are zeros; `noise + Σ updates = actions` keeps the chunk's invariant.
            noise.extend(confidence.iter().map(|c| -(1.0 + c)));
        }
        Ok(ActionChunk {
            samples,
            steps: 2,
            chunk_len: n,
            action_dim: 1,
            actions: vec![0.0; samples * n],
            updates,
            noise,
        })
    }
}

impl ActionModel for TraceReplayModel {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        let started = Instant::now();
        let chunks = batch
            .iter()
            .map(|r| self.chunk(r))
            .collect::<Result<Vec<_>, _>>()?;
        let size = u32::try_from(batch.len()).unwrap_or(u32::MAX);
        let due = started + self.profile.latency(size);
        // A deadline rather than a fixed sleep, so building the chunks costs no extra time.
        let left = due.saturating_duration_since(Instant::now());
        if left > Duration::ZERO {
            std::thread::sleep(left);
        }
        Ok(chunks)
    }
}

/// An edge engine instance running [`TraceReplayModel`] on its own thread, like any local model.
pub fn replay_engine(
    name: impl Into<String>,
    chunk_len: usize,
    profile: EngineProfile,
) -> Result<Arc<dyn EngineInstance>, EngineError> {
    let model = TraceReplayModel::new(chunk_len, profile.clone())?;
    Ok(Arc::new(LocalEngine::start(name, Arc::new(model), profile)))
}

/// The observation state a replaying robot sends for `round`: its recorded confidence ratios,
/// or all ones (nothing cuts the chunk early) for a round recorded without them, whose horizon
/// the robot then requests as `static` with the recorded `H`.
pub fn replay_state(round: &RoundTrace, chunk_len: usize) -> Vec<f32> {
    match &round.confidence {
        Some(c) if c.len() == chunk_len => c.clone(),
        _ => vec![1.0; chunk_len],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use kairos_engine::ProfilePoint;

    fn profile() -> EngineProfile {
        EngineProfile {
            model: "modelled".into(),
            device: "test".into(),
            points: vec![
                ProfilePoint {
                    batch: 1,
                    latency_ms: 20.0,
                },
                ProfilePoint {
                    batch: 4,
                    latency_ms: 50.0,
                },
            ],
            max_batch: 4,
        }
    }

    fn request(state: Vec<f32>) -> ActionRequest {
        ActionRequest {
            cameras: Vec::new(),
            state,
            images: Vec::new(),
            instruction: String::new(),
            samples: 1,
            seed: 0,
            guidance: None,
        }
    }

    fn round(confidence: Option<Vec<f32>>, horizon: u32) -> RoundTrace {
        RoundTrace {
            issued_at_action: 0,
            aligned_at_action: None,
            horizon,
            executed: horizon,
            gen_latency_us: 0,
            round_trip_us: None,
            obs_bytes: 100,
            confidence,
        }
    }

    #[test]
    fn a_batch_takes_its_profiled_time_and_every_request_its_own_chunk() {
        let model = TraceReplayModel::new(3, profile()).unwrap();
        assert_eq!(model.spec().state_dim, 3);
        let batch = vec![request(vec![1.0, 2.0, 3.0]), request(vec![0.5, 0.5, 0.5])];
        let started = Instant::now();
        let chunks = model.generate(&batch).unwrap();
        let took = started.elapsed();
        assert!(
            took >= model.profile().latency(2),
            "{took:?} < {:?}",
            model.profile().latency(2)
        );
        assert_eq!(chunks.len(), 2);
        assert_eq!(chunks[0].updates, [1.0, 1.0, 1.0, 1.0, 2.0, 3.0]);
        assert_eq!(chunks[1].sample_updates(0)[3..], [0.5, 0.5, 0.5]);
        for c in &chunks {
            // noise + Σ updates = actions (zeros), the chunk invariant.
            for i in 0..3 {
                assert_eq!(c.noise[i] + c.updates[i] + c.updates[3 + i], c.actions[i]);
            }
        }
        let wrong_length = model.generate(&[request(vec![1.0; 4])]);
        assert!(wrong_length.is_err());
        let negative = model.generate(&[request(vec![1.0, -1.0, 1.0])]);
        assert!(negative.is_err());
        assert!(TraceReplayModel::new(0, profile()).is_err());
    }

    #[test]
    fn a_round_without_confidence_is_replayed_with_nothing_cut() {
        assert_eq!(replay_state(&round(None, 7), 4), vec![1.0; 4]);
        let with = round(Some(vec![1.0, 1.2, 3.0, 4.0]), 2);
        assert_eq!(replay_state(&with, 4), vec![1.0, 1.2, 3.0, 4.0]);
    }
}
