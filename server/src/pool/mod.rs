//! The engine pool: every engine instance the scheduler can place batches on.
//!
//! An [`EngineInstance`] runs one batch at a time and answers asynchronously; the pool never
//! runs a forward pass on a tokio reactor thread. Two kinds plug in behind the trait:
//! - [`LocalEngine`]: an `ActionModel` on its own OS thread, fed by a channel with oneshot replies;
//! - [`EmulatedLinkEngine`]: any instance behind an emulated network link (a fixed round trip
//!   added to every batch), so a cloud tier can be exercised on one machine. It is labelled as
//!   emulated wherever it shows up; it is not a remote engine.
//! - `crate::worker::RemoteEngine`: a `kairos worker` on another machine, reached over QUIC
//!   (`kairos-worker/1`); it joins and leaves while the server runs.
//!
//! The scheduler plans with [`EnginePool::specs`], built from each instance's profile, tier and
//! round trip. Membership is dynamic: [`EnginePool::add`] and [`EnginePool::remove`] are called by
//! the driver's shell (the one owner of the live pool) when a worker registers or goes away;
//! ids are never reused.

mod build;
mod link;
mod local;
pub mod replay;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use futures::future::BoxFuture;
use kairos_engine::{
    ActionChunk, ActionRequest, ActionSpace, EngineError, EngineProfile, GuidanceSupport,
    ModelChunking, ModelSpec,
};

pub use build::{BuildEvent, ModelSchemes, PoolConfigError, ResolveModel, build_pool};
pub use link::EmulatedLinkEngine;
pub use local::LocalEngine;

pub use kairos_core::error::LossReason;
use kairos_core::scheduler::{EngineId, EngineSpec, Tier};

/// Why a batch produced no chunks.
#[derive(Debug, thiserror::Error)]
pub enum PoolError {
    /// The model refused the batch or failed inside.
    #[error("engine {engine}: {source}")]
    Engine {
        /// The instance.
        engine: String,
        /// The model's error.
        source: EngineError,
    },
    /// The model panicked; the instance survives and takes the next batch.
    #[error("engine {engine} panicked: {message}")]
    Panicked {
        /// The instance.
        engine: String,
        /// The panic payload, if it was a string.
        message: String,
    },
    /// The model returned chunks that do not match the batch or its own spec.
    #[error("engine {engine} returned a malformed result: {reason}")]
    BadOutput {
        /// The instance.
        engine: String,
        /// What is wrong.
        reason: String,
    },
    /// The instance's worker is gone (its thread exited).
    #[error("engine {engine} is not running")]
    Stopped {
        /// The instance.
        engine: String,
    },
    /// A remote worker's engine failed this request (its error, as the worker reported it).
    #[error("engine {engine}: {message}")]
    Remote {
        /// The instance.
        engine: String,
        /// The worker's error.
        message: String,
    },
    /// A remote instance was lost before it answered (connection lost, stream reset, deadline
    /// passed): the batch produced nothing and may run again elsewhere.
    #[error("engine {engine} was lost ({reason}): {detail}")]
    Lost {
        /// The instance.
        engine: String,
        /// Which way it was lost.
        reason: LossReason,
        /// What the transport said.
        detail: String,
    },
}

/// One result per request of a batch, in order: its chunk, or why that request got none.
pub type BatchChunks = Vec<Result<ActionChunk, PoolError>>;

/// One engine instance: runs a batch of requests and returns one result per request, in order.
pub trait EngineInstance: Send + Sync {
    /// A name for logs and metrics, unique in the pool.
    fn name(&self) -> &str;
    /// What the model consumes and produces.
    fn spec(&self) -> &ModelSpec;
    /// What the chunking strategies may do with the instance's model. A remote worker does not
    /// say, so it gets the default: no guidance, no action space.
    fn chunking(&self) -> ModelChunking {
        ModelChunking::default()
    }
    /// Latency by batch size; `max_batch` caps the batches the scheduler forms for it.
    fn profile(&self) -> &EngineProfile;
    /// Edge or cloud.
    fn tier(&self) -> Tier;
    /// Network round trip between the server and the instance, zero when local.
    fn rtt(&self) -> Duration;
    /// Runs one batch. A request the model cannot serve fails alone: its entry is an error and
    /// the others carry the chunks a clean batch would have given them. The whole answer is an
    /// error only when the instance could run nothing (it stopped). The future does no heavy
    /// work on the caller's thread.
    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Result<BatchChunks, PoolError>>;
    /// Runs one batch, told its scheduler id and attempt (a remote instance puts them on the
    /// wire to match the answer; others ignore them).
    fn run_labeled(
        &self,
        label: BatchLabel,
        batch: Vec<ActionRequest>,
    ) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        let _ = label;
        self.run(batch)
    }
    /// Whether a batch can be lost with the instance ([`PoolError::Lost`]), so the caller keeps
    /// what it needs to run the batch again elsewhere. Local instances never lose one.
    fn can_lose_batches(&self) -> bool {
        false
    }
}

/// Which batch an instance runs: the scheduler's id and how many times its rounds ran before.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BatchLabel {
    /// The scheduler's batch id (never reused).
    pub batch: kairos_core::scheduler::BatchId,
    /// Earlier dispatches of its rounds (0: none ran in a lost batch).
    pub attempt: u32,
}

/// All engine instances, by [`EngineId`]. Ids are handed out in order and never reused (the
/// scheduler's are the same: both count every instance added); an instance that left is
/// dropped, so workers that register again and again leave nothing behind.
#[derive(Clone)]
pub struct EnginePool {
    spec: ModelSpec,
    instances: BTreeMap<EngineId, Arc<dyn EngineInstance>>,
    /// The id the next instance added gets.
    next: usize,
}

impl std::fmt::Debug for EnginePool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.iter().map(|i| i.name()))
            .finish()
    }
}

/// The pool cannot be formed.
#[derive(Debug, thiserror::Error)]
pub enum PoolBuildError {
    /// No instance at all.
    #[error("the engine pool is empty")]
    Empty,
    /// Instances disagree on the model's shapes: a request validated for one must fit all.
    #[error("engine {engine} serves {found:?}, but {first} serves {expected:?}")]
    SpecMismatch {
        /// The first instance.
        first: String,
        /// The disagreeing one.
        engine: String,
        /// The first instance's spec.
        expected: Box<ModelSpec>,
        /// The other's.
        found: Box<ModelSpec>,
    },
}

impl EnginePool {
    /// A pool of instances that all serve the same model shapes (at least one: the first
    /// gives the site's spec).
    pub fn new(instances: Vec<Arc<dyn EngineInstance>>) -> Result<EnginePool, PoolBuildError> {
        let first = instances.first().ok_or(PoolBuildError::Empty)?;
        EnginePool::with_spec(first.spec().clone(), instances)
    }

    /// A pool serving `spec`, possibly empty at first (a scheduler served only by remote
    /// workers, `--local-engines 0`): every instance must have `spec`'s shapes.
    pub fn with_spec(
        spec: ModelSpec,
        instances: Vec<Arc<dyn EngineInstance>>,
    ) -> Result<EnginePool, PoolBuildError> {
        let mut pool = EnginePool {
            spec,
            instances: BTreeMap::new(),
            next: 0,
        };
        for instance in instances {
            pool.add(instance)?;
        }
        Ok(pool)
    }

    /// Adds an instance under the next [`EngineId`] if it serves the pool's shapes (the same
    /// check for local engines at start and for workers that register).
    pub fn add(&mut self, instance: Arc<dyn EngineInstance>) -> Result<EngineId, PoolBuildError> {
        if !same_shapes(instance.spec(), &self.spec) {
            return Err(PoolBuildError::SpecMismatch {
                first: self.spec.name.clone(),
                engine: instance.name().to_string(),
                expected: Box::new(self.spec.clone()),
                found: Box::new(instance.spec().clone()),
            });
        }
        let id = EngineId(self.next);
        self.next = self.next.saturating_add(1);
        self.instances.insert(id, instance);
        Ok(id)
    }

    /// The instance leaves the pool; its id is never given again. Returns it, if it was there.
    pub fn remove(&mut self, id: EngineId) -> Option<Arc<dyn EngineInstance>> {
        self.instances.remove(&id)
    }

    /// The model shapes every instance shares.
    pub fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    /// Number of instances in the pool now.
    pub fn len(&self) -> usize {
        self.instances.len()
    }

    /// Whether no instance is in the pool now.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The instance `id`, if it is in the pool.
    pub fn get(&self, id: EngineId) -> Option<&Arc<dyn EngineInstance>> {
        self.instances.get(&id)
    }

    /// Every instance in the pool, in [`EngineId`] order.
    pub fn iter(&self) -> impl Iterator<Item = &Arc<dyn EngineInstance>> {
        self.instances.values()
    }

    /// What the chunking strategies may do with every instance of the pool now: the guidance
    /// all of them apply, and their action space if they agree on it.
    pub fn chunking(&self) -> ModelChunking {
        let mut instances = self.iter().map(|i| i.chunking());
        let Some(first) = instances.next() else {
            return ModelChunking::default();
        };
        instances.fold(first, |all, one| ModelChunking {
            guidance: GuidanceSupport {
                prefix: all.guidance.prefix && one.guidance.prefix,
                vjp: all.guidance.vjp && one.guidance.vjp,
            },
            action_space: if all.action_space == one.action_space {
                all.action_space
            } else {
                ActionSpace::Unspecified
            },
        })
    }

    /// What the scheduler plans with, in [`EngineId`] order (call it before any instance
    /// left, as `Scheduler::new` indexes engines by position).
    pub fn specs(&self) -> Vec<EngineSpec> {
        self.iter()
            .map(|i| EngineSpec {
                name: i.name().to_string(),
                tier: i.tier(),
                profile: i.profile().clone(),
                rtt: i.rtt(),
            })
            .collect()
    }
}

/// Instances may differ in name (a checkpoint vs the same weights elsewhere) but not in shapes.
pub fn same_shapes(a: &ModelSpec, b: &ModelSpec) -> bool {
    a.chunk_len == b.chunk_len
        && a.action_dim == b.action_dim
        && a.state_dim == b.state_dim
        && a.steps == b.steps
        && a.max_images == b.max_images
        && a.cameras == b.cameras
}

/// Checks a model's answer against the batch it was given, so a buggy model cannot make the
/// action manager index out of bounds.
pub(crate) fn check_output(
    engine: &str,
    spec: &ModelSpec,
    batch: &[ActionRequest],
    chunks: &[ActionChunk],
) -> Result<(), PoolError> {
    let bad = |reason: String| PoolError::BadOutput {
        engine: engine.to_string(),
        reason,
    };
    if chunks.len() != batch.len() {
        return Err(bad(format!(
            "{} chunks for {} requests",
            chunks.len(),
            batch.len()
        )));
    }
    for (i, (chunk, request)) in chunks.iter().zip(batch).enumerate() {
        let per_sample = chunk.chunk_len * chunk.action_dim;
        let consistent = chunk.samples == request.samples.max(1)
            && chunk.chunk_len == spec.chunk_len
            && chunk.action_dim == spec.action_dim
            && chunk.steps == spec.steps
            && chunk.actions.len() == chunk.samples * per_sample
            && chunk.updates.len() == chunk.samples * chunk.steps * per_sample;
        if !consistent {
            return Err(bad(format!(
                "chunk {i} is {}x{}x{}x{} with {} actions / {} updates, expected {} samples of \
                 {}x{}x{}",
                chunk.samples,
                chunk.steps,
                chunk.chunk_len,
                chunk.action_dim,
                chunk.actions.len(),
                chunk.updates.len(),
                request.samples.max(1),
                spec.steps,
                spec.chunk_len,
                spec.action_dim
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod test_model {
    //! A small deterministic `ActionModel` for the pool's own tests: a real computation (Euler
    //! steps of a fixed linear velocity field), so outputs can be checked exactly.

    use std::sync::atomic::{AtomicUsize, Ordering};

    use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineError, ModelSpec};

    /// Moves every action towards the state's first element; `panic_on_state` triggers a panic.
    pub struct LinearFlow {
        pub spec: ModelSpec,
        pub calls: AtomicUsize,
        pub panic_on_state: Option<f32>,
    }

    impl LinearFlow {
        pub fn new() -> Self {
            LinearFlow {
                spec: ModelSpec {
                    cameras: Vec::new(),
                    camera_aliases: Default::default(),
                    name: "linear-flow".into(),
                    chunk_len: 4,
                    action_dim: 2,
                    state_dim: 3,
                    steps: 2,
                    max_images: 1,
                },
                calls: AtomicUsize::new(0),
                panic_on_state: None,
            }
        }
    }

    impl ActionModel for LinearFlow {
        fn spec(&self) -> &ModelSpec {
            &self.spec
        }

        fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
            self.calls.fetch_add(1, Ordering::SeqCst);
            let s = &self.spec;
            batch
                .iter()
                .map(|r| {
                    if r.state.len() != s.state_dim {
                        return Err(EngineError::InvalidInput("state length".into()));
                    }
                    if Some(r.state[0]) == self.panic_on_state {
                        panic!("model bug triggered on purpose");
                    }
                    let n = r.samples.max(1) * s.chunk_len * s.action_dim;
                    let noise: Vec<f32> = (0..n).map(|i| (r.seed as f32) + i as f32).collect();
                    let mut x = noise.clone();
                    let mut updates = Vec::new();
                    let mut per_step = vec![Vec::new(); s.steps];
                    for step in per_step.iter_mut() {
                        let dt = 1.0 / s.steps as f32;
                        let u: Vec<f32> = x.iter().map(|v| dt * (r.state[0] - v)).collect();
                        for (v, d) in x.iter_mut().zip(&u) {
                            *v += d;
                        }
                        *step = u;
                    }
                    let per_sample = s.chunk_len * s.action_dim;
                    for sample in 0..r.samples.max(1) {
                        for step in &per_step {
                            updates.extend_from_slice(
                                &step[sample * per_sample..(sample + 1) * per_sample],
                            );
                        }
                    }
                    Ok(ActionChunk {
                        samples: r.samples.max(1),
                        steps: s.steps,
                        chunk_len: s.chunk_len,
                        action_dim: s.action_dim,
                        actions: x,
                        updates,
                        noise,
                    })
                })
                .collect()
        }
    }

    pub fn request(first: f32, seed: u64) -> ActionRequest {
        ActionRequest {
            cameras: Vec::new(),
            state: vec![first, 0.0, 0.0],
            images: Vec::new(),
            instruction: String::new(),
            samples: 1,
            seed,
            guidance: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::test_model::{LinearFlow, request};
    use super::*;

    fn flat_profile() -> EngineProfile {
        EngineProfile {
            model: "linear-flow".into(),
            device: "cpu".into(),
            points: vec![kairos_engine::ProfilePoint {
                batch: 1,
                latency_ms: 1.0,
            }],
            max_batch: 4,
        }
    }

    #[tokio::test]
    async fn pool_specs_follow_instances_and_reject_mismatched_shapes() {
        let local: Arc<dyn EngineInstance> = Arc::new(LocalEngine::start(
            "edge-0",
            Arc::new(LinearFlow::new()),
            flat_profile(),
        ));
        let cloud: Arc<dyn EngineInstance> = Arc::new(EmulatedLinkEngine::new(
            Arc::new(LocalEngine::start(
                "cloud-0",
                Arc::new(LinearFlow::new()),
                flat_profile(),
            )),
            Duration::from_millis(3),
        ));
        let pool = EnginePool::new(vec![local, cloud]).unwrap();
        let specs = pool.specs();
        assert_eq!(specs.len(), 2);
        assert_eq!(specs[0].tier, Tier::Edge);
        assert_eq!(specs[0].rtt, Duration::ZERO);
        assert_eq!(specs[1].tier, Tier::Cloud);
        assert_eq!(specs[1].rtt, Duration::from_millis(3));
        assert!(specs[1].name.contains("emulated"));
        assert_eq!(specs[0].profile.max_batch, 4);

        let mut other = LinearFlow::new();
        other.spec.chunk_len = 9;
        let odd: Arc<dyn EngineInstance> =
            Arc::new(LocalEngine::start("odd", Arc::new(other), flat_profile()));
        let first = pool.get(EngineId(0)).unwrap().clone();
        // Ids move on with each instance added and are never given again; a removed instance
        // leaves nothing behind.
        let mut growing = pool.clone();
        for round in 0..1_000 {
            let id = growing.add(first.clone()).unwrap();
            assert_eq!(id, EngineId(2 + round));
            assert!(growing.remove(id).is_some());
            assert!(growing.get(id).is_none(), "a removed id is refused");
            assert!(growing.remove(id).is_none());
        }
        assert_eq!(growing.len(), 2);
        assert_eq!(growing.instances.len(), 2);
        assert!(matches!(
            EnginePool::new(vec![first, odd]),
            Err(PoolBuildError::SpecMismatch { .. })
        ));
        assert!(matches!(
            EnginePool::new(Vec::new()),
            Err(PoolBuildError::Empty)
        ));
    }

    #[test]
    fn check_output_catches_wrong_counts_and_shapes() {
        let model = LinearFlow::new();
        let batch = vec![request(1.0, 1), request(2.0, 2)];
        let mut chunks = kairos_engine::ActionModel::generate(&model, &batch).unwrap();
        assert!(check_output("e", &model.spec, &batch, &chunks).is_ok());
        chunks[1].updates.pop();
        assert!(check_output("e", &model.spec, &batch, &chunks).is_err());
        chunks.pop();
        assert!(check_output("e", &model.spec, &batch, &chunks).is_err());
    }
}
