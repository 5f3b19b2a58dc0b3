//! An `ActionModel` on its own OS thread.

use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineError, EngineProfile, ImageLimits,
    ModelChunking, ModelSpec, generate_isolated,
};
use tokio::sync::oneshot;

use super::{BatchChunks, EngineInstance, PoolError, check_output};
use kairos_core::scheduler::Tier;

type Answer = Result<BatchChunks, PoolError>;

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
    chunking: ModelChunking,
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
        let chunking = model.chunking();
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
            chunking,
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
        let answer = run_isolated(name, spec, model, &job.batch);
        // The caller may have gone away (shutdown); nothing to do then.
        let _ = job.reply.send(Ok(answer));
    }
}

/// Runs a batch so that one request that fails, by the model's error or its panic, fails alone:
/// requests the spec refuses are left out, and a batch that still fails is rerun one request
/// at a time ([`generate_isolated`]).
fn run_isolated(
    name: &str,
    spec: &ModelSpec,
    model: &dyn ActionModel,
    batch: &[ActionRequest],
) -> BatchChunks {
    let images = ImageLimits::default();
    let guidance = model.chunking().guidance;
    generate_isolated(
        batch,
        |request| {
            spec.check_request(request, &images)
                .map_err(EngineError::from)
                .and_then(|()| match &request.guidance {
                    // A model that cannot apply the guidance must not sample as if there were
                    // none.
                    Some(g) if !guidance.supports(g.mode) => {
                        Err(EngineError::InvalidInput(format!(
                            "model `{}` cannot apply `{}` guidance",
                            spec.name,
                            g.mode.as_str()
                        )))
                    }
                    _ => Ok(()),
                })
                .map_err(|error| PoolError::Engine {
                    engine: name.to_string(),
                    source: error,
                })
        },
        |requests| generate_guarded(name, spec, model, requests),
        |chunks, requests| PoolError::BadOutput {
            engine: name.to_string(),
            reason: format!("{chunks} chunks for {requests} requests"),
        },
    )
}

/// One forward pass with its panic caught and its output checked.
fn generate_guarded(
    name: &str,
    spec: &ModelSpec,
    model: &dyn ActionModel,
    batch: &[ActionRequest],
) -> Result<Vec<ActionChunk>, PoolError> {
    match std::panic::catch_unwind(AssertUnwindSafe(|| model.generate(batch))) {
        Ok(Ok(chunks)) => check_output(name, spec, batch, &chunks).map(|()| chunks),
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
    }
}

impl EngineInstance for LocalEngine {
    fn name(&self) -> &str {
        &self.name
    }

    fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    fn chunking(&self) -> ModelChunking {
        self.chunking.clone()
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

    /// The chunks of a batch that must all succeed.
    async fn chunks(engine: &LocalEngine, batch: Vec<ActionRequest>) -> Vec<ActionChunk> {
        engine
            .run(batch)
            .await
            .unwrap()
            .into_iter()
            .map(Result::unwrap)
            .collect()
    }

    #[tokio::test]
    async fn runs_batches_on_its_own_thread_and_survives_a_panic() {
        let mut model = LinearFlow::new();
        model.panic_on_state = Some(-1.0);
        let model = Arc::new(model);
        let engine = LocalEngine::start("e0", model.clone(), profile());

        let two = chunks(&engine, vec![request(1.0, 7), request(2.0, 8)]).await;
        assert_eq!(two.len(), 2);
        // Two Euler steps of dt=1/2 towards the target halve the distance twice.
        let expected = 2.0 + (8.0 - 2.0) * 0.25;
        assert!((two[1].actions[0] - expected).abs() < 1e-5);

        let mut answer = engine.run(vec![request(-1.0, 1)]).await.unwrap();
        let err = answer.pop().unwrap().unwrap_err();
        assert!(matches!(err, PoolError::Panicked { .. }), "{err}");
        let mut answer = engine
            .run(vec![kairos_engine::ActionRequest {
                cameras: Vec::new(),
                state: vec![1.0],
                ..request(0.0, 0)
            }])
            .await
            .unwrap();
        let err = answer.pop().unwrap().unwrap_err();
        assert!(matches!(err, PoolError::Engine { .. }), "{err}");

        let again = chunks(&engine, vec![request(3.0, 1)]).await;
        assert_eq!(again.len(), 1, "the thread keeps serving after a panic");
        assert_eq!(
            model.calls.load(Ordering::SeqCst),
            3,
            "the request of the wrong length was refused before the model ran"
        );
    }

    #[tokio::test]
    async fn a_failing_request_fails_alone_and_the_others_get_their_clean_batch_chunks() {
        let mut model = LinearFlow::new();
        // A request the spec accepts but the model fails on (here by panicking): only the rerun
        // one request at a time can tell which request it was.
        model.panic_on_state = Some(-1.0);
        let model = Arc::new(model);
        let engine = LocalEngine::start("e0", model.clone(), profile());
        let good = || vec![request(1.0, 7), request(2.0, 8), request(3.0, 9)];
        let clean = chunks(&engine, good()).await;
        assert_eq!(model.calls.load(Ordering::SeqCst), 1);

        let mut batch = good();
        batch.insert(1, request(-1.0, 4));
        let answer = engine.run(batch).await.unwrap();
        assert_eq!(answer.len(), 4);
        assert!(matches!(answer[1], Err(PoolError::Panicked { .. })));
        let rest: Vec<&ActionChunk> = [0, 2, 3]
            .iter()
            .map(|&i| answer[i].as_ref().unwrap())
            .collect();
        assert_eq!(
            rest,
            clean.iter().collect::<Vec<_>>(),
            "bit-identical chunks"
        );
        assert_eq!(
            model.calls.load(Ordering::SeqCst),
            1 + 1 + 4,
            "the failed batch, then each of its requests alone"
        );

        // A request the spec refuses (a NaN state) is left out before the model runs: the rest
        // run as one batch.
        let mut batch = good();
        batch.insert(
            0,
            ActionRequest {
                cameras: Vec::new(),
                state: vec![f32::NAN, 0.0, 0.0],
                ..request(0.0, 5)
            },
        );
        let answer = engine.run(batch).await.unwrap();
        let Err(PoolError::Engine { source, .. }) = &answer[0] else {
            panic!(
                "expected the NaN request to fail alone, got {:?}",
                answer[0]
            );
        };
        assert!(source.to_string().contains("state[0]"), "{source}");
        let rest: Vec<&ActionChunk> = answer[1..].iter().map(|a| a.as_ref().unwrap()).collect();
        assert_eq!(rest, clean.iter().collect::<Vec<_>>());
        assert_eq!(model.calls.load(Ordering::SeqCst), 7, "one batch of three");
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
        match engine.run(vec![request(0.0, 0)]).await.unwrap().pop() {
            Some(Err(PoolError::Engine { source, .. })) => {
                assert_eq!(source.to_string(), "invalid input: engine-probe")
            }
            other => panic!("unexpected {other:?}"),
        }
    }
}
