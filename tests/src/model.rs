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
//! emulate a model whose forward pass is slow (e.g. to keep a round in flight while a test drops
//! the connection); tests that use it say so.

use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineError, ModelSpec};
use rand::{Rng, SeedableRng};

/// The test flow model.
#[derive(Clone, Debug)]
pub struct TestFlow {
    spec: ModelSpec,
    latency: std::time::Duration,
}

impl TestFlow {
    /// `N=16` actions of `D=4`, `K=4` steps, a 6-value state, up to 2 images.
    pub fn new() -> TestFlow {
        TestFlow {
            spec: ModelSpec {
                name: "test-flow".into(),
                chunk_len: 16,
                action_dim: 4,
                state_dim: 6,
                steps: 4,
                max_images: 2,
            },
            latency: std::time::Duration::ZERO,
        }
    }

    /// The same model, with every batch taking at least `latency` (emulated forward-pass time).
    pub fn with_latency(latency: std::time::Duration) -> TestFlow {
        TestFlow {
            latency,
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
            state: vec![0.5, 0.2, 0.0, 0.0, 0.0, 0.0],
            images: Vec::new(),
            instruction: String::new(),
            samples: 2,
            seed: 9,
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
