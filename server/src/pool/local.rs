//! An `ActionModel` on its own OS thread.

use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineProfile, ModelSpec};
use tokio::sync::oneshot;

use super::{EngineInstance, PoolError, check_output};
use crate::scheduler::Tier;

type Answer = Result<Vec<ActionChunk>, PoolError>;

struct Job {
    batch: Vec<ActionRequest>,
    reply: oneshot::Sender<Answer>,
}

/// A model running on a dedicated thread. Batches queue in a channel; the scheduler sends one at
/// a time per instance, so the queue is normally empty. Several instances may share one model
/// (`Arc`): weights are immutable after loading.
///
/// Dropping the last handle closes the channel; the thread finishes the batch in hand and exits.
pub struct LocalEngine {
    name: String,
    spec: ModelSpec,
    profile: EngineProfile,
    jobs: mpsc::Sender<Job>,
}

impl LocalEngine {
    /// Starts the worker thread for `model`.
    pub fn start(
        name: impl Into<String>,
        model: Arc<dyn ActionModel>,
        profile: EngineProfile,
    ) -> LocalEngine {
        let name = name.into();
        let spec = model.spec().clone();
        let (jobs, queue) = mpsc::channel::<Job>();
        let thread_name = format!("engine-{name}");
        let worker_name = name.clone();
        let worker_spec = spec.clone();
        let spawned = std::thread::Builder::new()
            .name(thread_name)
            .spawn(move || worker(&worker_name, &worker_spec, model.as_ref(), queue));
        if let Err(error) = spawned {
            // The channel's receiver died with the failed spawn, so every `run` answers `Stopped`.
            tracing::error!(engine = %name, %error, "cannot start engine thread");
        }
        LocalEngine {
            name,
            spec,
            profile,
            jobs,
        }
    }
}

fn worker(name: &str, spec: &ModelSpec, model: &dyn ActionModel, queue: mpsc::Receiver<Job>) {
    while let Ok(job) = queue.recv() {
        if job.reply.is_closed() {
            continue;
        }
        let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| model.generate(&job.batch)));
        let answer = match outcome {
            Ok(Ok(chunks)) => check_output(name, spec, &job.batch, &chunks).map(|()| chunks),
            Ok(Err(source)) => Err(PoolError::Engine {
                engine: name.to_string(),
                source,
            }),
            Err(payload) => {
                let message = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "non-string panic payload".into());
                tracing::error!(engine = %name, %message, "model panicked");
                Err(PoolError::Panicked {
                    engine: name.to_string(),
                    message,
                })
            }
        };
        // The caller may have gone away (shutdown); nothing to do then.
        let _ = job.reply.send(answer);
    }
}

impl EngineInstance for LocalEngine {
    fn name(&self) -> &str {
        &self.name
    }

    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn profile(&self) -> &EngineProfile {
        &self.profile
    }

    fn tier(&self) -> Tier {
        Tier::Edge
    }

    fn rtt(&self) -> Duration {
        Duration::ZERO
    }

    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Answer> {
        let (reply, answer) = oneshot::channel();
        let stopped = || PoolError::Stopped {
            engine: self.name.clone(),
        };
        if self.jobs.send(Job { batch, reply }).is_err() {
            let error = stopped();
            return async move { Err(error) }.boxed();
        }
        let error = stopped();
        async move { answer.await.unwrap_or(Err(error)) }.boxed()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::Ordering;

    use super::super::test_model::{LinearFlow, request};
    use super::*;

    fn profile() -> EngineProfile {
        EngineProfile {
            model: "linear-flow".into(),
            device: "cpu".into(),
            points: Vec::new(),
            max_batch: 8,
        }
    }

    #[tokio::test]
    async fn runs_batches_on_its_own_thread_and_survives_a_panic() {
        let mut model = LinearFlow::new();
        model.panic_on_state = Some(-1.0);
        let model = Arc::new(model);
        let engine = LocalEngine::start("e0", model.clone(), profile());

        let chunks = engine
            .run(vec![request(1.0, 7), request(2.0, 8)])
            .await
            .unwrap();
        assert_eq!(chunks.len(), 2);
        // Two Euler steps of dt=1/2 towards the target halve the distance twice.
        let expected = 2.0 + (8.0 - 2.0) * 0.25;
        assert!((chunks[1].actions[0] - expected).abs() < 1e-5);

        let err = engine.run(vec![request(-1.0, 1)]).await.unwrap_err();
        assert!(matches!(err, PoolError::Panicked { .. }), "{err}");
        let err = engine
            .run(vec![kairos_engine::ActionRequest {
                state: vec![1.0],
                ..request(0.0, 0)
            }])
            .await
            .unwrap_err();
        assert!(matches!(err, PoolError::Engine { .. }), "{err}");

        let again = engine.run(vec![request(3.0, 1)]).await.unwrap();
        assert_eq!(again.len(), 1, "the thread keeps serving after a panic");
        assert_eq!(model.calls.load(Ordering::SeqCst), 4);
    }

    #[tokio::test]
    async fn forward_passes_do_not_run_on_the_calling_thread() {
        struct ThreadProbe(ModelSpec);
        impl ActionModel for ThreadProbe {
            fn spec(&self) -> &ModelSpec {
                &self.0
            }
            fn generate(
                &self,
                _batch: &[ActionRequest],
            ) -> Result<Vec<ActionChunk>, kairos_engine::EngineError> {
                let name = std::thread::current().name().map(str::to_string);
                Err(kairos_engine::EngineError::InvalidInput(
                    name.unwrap_or_default(),
                ))
            }
        }
        let engine = LocalEngine::start(
            "probe",
            Arc::new(ThreadProbe(LinearFlow::new().spec)),
            profile(),
        );
        match engine.run(vec![request(0.0, 0)]).await {
            Err(PoolError::Engine { source, .. }) => {
                assert_eq!(source.to_string(), "invalid input: engine-probe")
            }
            other => panic!("unexpected {other:?}"),
        }
    }
}
