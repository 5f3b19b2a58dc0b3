//! A small flow model for transport and scheduling tests.
//!
//! It is a real [`ActionModel`]: `K` Euler steps of a fixed velocity field over an `N×D` chunk,
//! recording every step's update, batched, seeded. It has no learned weights, so its forward
//! pass costs microseconds and the tests measure the server, not the model. The field pulls each
//! action towards the state and, on the last step, pushes actions later in the chunk by
//! `(n / N) · state[1]`, so the §3.1 threshold policy cuts the chunk at a position the robot
//! controls through `state[1]` (0 = every action converges, `H = N`).
//!
//! [`TestFlow::with_latency`] makes every batch take a fixed extra time on the engine thread, to
//! emulate a model whose forward pass is slow; tests that use it say so. To act while a chosen
//! round is in flight (e.g. drop its robot's connection), a test uses [`TestFlow::with_gate`]: the
//! engine thread stops at that round and tells the test, which releases it when done, so the
//! test waits for an event instead of guessing how long a round takes on a loaded machine.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, mpsc};

use kairos_core::round::round_seed;
use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineError, ModelSpec};
use rand::{Rng, SeedableRng};

/// Stops the engine thread at chosen rounds until the test releases it; see
/// [`TestFlow::with_gate`]. Each chosen round stops the engine once (a re-sent copy that is
/// generated again would not stop it again).
#[derive(Debug)]
pub struct RoundGate {
    /// Rounds still to stop at, by their seed (the server seeds a round's noise with
    /// [`round_seed`]`(task, round)`: how the engine recognises a round).
    waiting: Mutex<HashMap<u64, (u64, u64)>>,
    entered: tokio::sync::mpsc::UnboundedSender<Vec<(u64, u64)>>,
    release: Mutex<mpsc::Receiver<()>>,
}

/// The test's side of a [`RoundGate`].
#[derive(Debug)]
pub struct GateControl {
    /// The `(task, round)`s of a batch that reached the engine; the engine thread waits.
    pub entered: tokio::sync::mpsc::UnboundedReceiver<Vec<(u64, u64)>>,
    /// Send once per `entered` message to let that batch run.
    pub release: mpsc::Sender<()>,
}

impl RoundGate {
    /// A gate that stops at each of `rounds` (`(task, round)`).
    pub fn new(rounds: impl IntoIterator<Item = (u64, u64)>) -> (Arc<RoundGate>, GateControl) {
        let (entered_tx, entered) = tokio::sync::mpsc::unbounded_channel();
        let (release, release_rx) = mpsc::channel();
        let gate = RoundGate {
            waiting: Mutex::new(
                rounds
                    .into_iter()
                    .map(|(task, round)| (round_seed(task, round), (task, round)))
                    .collect(),
            ),
            entered: entered_tx,
            release: Mutex::new(release_rx),
        };
        (Arc::new(gate), GateControl { entered, release })
    }

    /// Stops (on the engine thread) if `batch` holds rounds the gate waits for.
    fn stop_at(&self, batch: &[ActionRequest]) {
        let hits: Vec<(u64, u64)> = {
            let mut waiting = self.waiting.lock().unwrap_or_else(|e| e.into_inner());
            batch
                .iter()
                .filter_map(|request| waiting.remove(&request.seed))
                .collect()
        };
        if hits.is_empty() || self.entered.send(hits).is_err() {
            return;
        }
        // A test that went away (its receiver dropped) releases the engine too.
        let release = self.release.lock().unwrap_or_else(|e| e.into_inner());
        let _ = release.recv();
    }
}

/// The test flow model.
#[derive(Clone, Debug)]
pub struct TestFlow {
    spec: ModelSpec,
    latency: std::time::Duration,
    gate: Option<Arc<RoundGate>>,
}

impl TestFlow {
    /// `N=16` actions of `D=4`, `K=4` steps, a 6-value state, up to 2 images.
    pub fn new() -> TestFlow {
        TestFlow {
            spec: ModelSpec {
                cameras: Vec::new(),
                camera_aliases: Default::default(),
                name: "test-flow".into(),
                chunk_len: 16,
                action_dim: 4,
                state_dim: 6,
                steps: 4,
                max_images: 2,
            },
            latency: std::time::Duration::ZERO,
            gate: None,
        }
    }

    /// The same model, with every batch taking at least `latency` (emulated forward-pass time).
    pub fn with_latency(latency: std::time::Duration) -> TestFlow {
        TestFlow {
            latency,
            ..TestFlow::new()
        }
    }

    /// The same model, stopping at the rounds `gate` waits for until the test releases them.
    pub fn with_gate(gate: Arc<RoundGate>) -> TestFlow {
        TestFlow {
            gate: Some(gate),
            ..TestFlow::new()
        }
    }
}

impl Default for TestFlow {
    fn default() -> Self {
        Self::new()
    }
}

impl ActionModel for TestFlow {
    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        let s = &self.spec;
        if let Some(gate) = &self.gate {
            gate.stop_at(batch);
        }
        if !self.latency.is_zero() {
            std::thread::sleep(self.latency);
        }
        batch
            .iter()
            .map(|request| {
                if request.state.len() != s.state_dim {
                    return Err(EngineError::InvalidInput(format!(
                        "state has {} values, expected {}",
                        request.state.len(),
                        s.state_dim
                    )));
                }
                let samples = request.samples.max(1);
                let per_sample = s.chunk_len * s.action_dim;
                let mut rng = rand::rngs::StdRng::seed_from_u64(request.seed);
                let noise: Vec<f32> = (0..samples * per_sample)
                    .map(|_| rng.random_range(-1.0f32..1.0))
                    .collect();
                let mut actions = noise.clone();
                let mut updates = vec![0.0f32; samples * s.steps * per_sample];
                let dt = 1.0 / s.steps as f32;
                for sample in 0..samples {
                    for k in 0..s.steps {
                        for n in 0..s.chunk_len {
                            for d in 0..s.action_dim {
                                let i = sample * per_sample + n * s.action_dim + d;
                                let target = request.state[d % s.state_dim];
                                let mut u = dt * (target - actions[i]);
                                if k + 1 == s.steps {
                                    u += (n as f32 / s.chunk_len as f32) * request.state[1];
                                }
                                actions[i] += u;
                                updates[((sample * s.steps + k) * s.chunk_len + n)
                                    * s.action_dim
                                    + d] = u;
                            }
                        }
                    }
                }
                Ok(ActionChunk {
                    samples,
                    steps: s.steps,
                    chunk_len: s.chunk_len,
                    action_dim: s.action_dim,
                    actions,
                    updates,
                    noise,
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn updates_sum_to_the_chunk_and_seeds_reproduce() {
        let model = TestFlow::new();
        let request = ActionRequest {
            cameras: Vec::new(),
            state: vec![0.5, 0.2, 0.0, 0.0, 0.0, 0.0],
            images: Vec::new(),
            instruction: String::new(),
            samples: 2,
            seed: 9,
            guidance: None,
        };
        let chunks = model.generate(&[request.clone(), request]).unwrap();
        assert_eq!(chunks[0], chunks[1]);
        let c = &chunks[0];
        let per_sample = c.chunk_len * c.action_dim;
        for s in 0..c.samples {
            for i in 0..per_sample {
                let sum: f32 = (0..c.steps)
                    .map(|k| c.updates[(s * c.steps + k) * per_sample + i])
                    .sum();
                let x = c.noise[s * per_sample + i] + sum;
                assert!((x - c.actions[s * per_sample + i]).abs() < 1e-5);
            }
        }
    }
}
