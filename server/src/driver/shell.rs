//! The driver's shell: the core on a thread of its own, and the waiting it leaves to tokio.
//!
//! The thread reads commands, stamps each with the clock, hands it to the [`DriverCore`] and
//! carries out the effects: oneshot answers and re-fetch asks (non-blocking sends), and tasks
//! spawned on the runtime that wait (a re-fetch deadline, an engine's answer, the next timer).
//! A batch's horizon policies, which may block, run on tokio's blocking pool.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use kairos_sdk::protocol::{ErrorReply, TaskEnded};
use tokio::runtime::Handle;
use tokio::sync::{mpsc, oneshot, watch};

use super::{DriverConfig, DriverStats, RefetchAsk, RoundAnswer, TaskSnapshot, WaiterId};
use crate::pool::BatchLabel;
use crate::pool::{EngineInstance, EnginePool, PoolBuildError, PoolError};
use kairos_core::action::ActionManager;
use kairos_core::driver::{BatchJob, ChunkingModel, DriverCore, Effect};
use kairos_core::error::LossReason;
use kairos_core::scheduler::{
    BatchId, EngineId, EngineSpec, RequestId, RobotId, Scheduler, ServerLoad, TaskId, Tier,
};
use kairos_core::time::Timestamp;

use crate::clock::Clock;
use crate::metrics::DriverExport;
use crate::validation::RequestError;
use kairos_core::round::{ValidEndTask, ValidObservation, ValidSubmit};

/// Messages to the driver thread.
#[derive(Debug)]
enum Command {
    Submit {
        submit: Box<ValidSubmit>,
        received: Timestamp,
        waiter: WaiterId,
        link: mpsc::Sender<RefetchAsk>,
        answer: oneshot::Sender<RoundAnswer>,
    },
    Detach {
        task: TaskId,
        round: u64,
        waiter: WaiterId,
    },
    EndTask {
        robot: RobotId,
        end: ValidEndTask,
        answer: oneshot::Sender<Result<TaskEnded, ErrorReply>>,
    },
    Snapshot {
        task: TaskId,
        answer: oneshot::Sender<Option<TaskSnapshot>>,
    },
    Stats {
        answer: oneshot::Sender<DriverStats>,
    },
    Refetched {
        batch: BatchId,
        request: RequestId,
        observation: Option<ValidObservation>,
    },
    GenerationEnded {
        batch: BatchId,
        engine: EngineId,
        inference: Duration,
        /// Gets the server's load right after the generation ended, for the batch's horizon
        /// policies.
        load: oneshot::Sender<ServerLoad>,
    },
    BatchLost {
        batch: BatchId,
        reason: LossReason,
        inputs: Vec<kairos_engine::ActionRequest>,
        rounds: Vec<kairos_core::action::HorizonJob>,
    },
    AddEngine {
        instance: NewInstance,
        answer: oneshot::Sender<Result<EngineId, PoolBuildError>>,
    },
    RemoveEngine {
        engine: EngineId,
    },
    Engines {
        answer: oneshot::Sender<Vec<EngineView>>,
    },
    BatchDone {
        batch: BatchId,
        results: Vec<(RequestId, RoundAnswer)>,
    },
    Timeout,
    Shutdown,
}

/// A cloneable handle to the driver.
#[derive(Clone, Debug)]
pub struct DriverHandle {
    commands: mpsc::Sender<Command>,
    waiters: Arc<AtomicU64>,
    clock: Clock,
    /// How the driver thread ended, once it has.
    end: watch::Receiver<Option<DriverEnd>>,
}

/// How the driver thread ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DriverEnd {
    /// It drained after a shutdown (or once every handle was dropped) and returned its totals.
    Stopped,
    /// It died: a panic (the message), or it could not start. No round can be served any more.
    Failed(String),
}

/// The driver has stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the driver has stopped")]
pub struct DriverGone;

/// An instance on its way to the pool (a command must be `Debug`).
struct NewInstance(Arc<dyn EngineInstance>);

impl std::fmt::Debug for NewInstance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.0.name())
    }
}

/// One engine instance as the scheduler plans with it now (for `/metrics`, logs and tests).
#[derive(Clone, Debug, PartialEq)]
pub struct EngineView {
    /// Its id (never reused).
    pub id: EngineId,
    /// Its name.
    pub name: String,
    /// Edge or cloud.
    pub tier: Tier,
    /// The round trip placement uses (a worker's measured one).
    pub rtt: Duration,
    /// Still in the pool (false: drained or lost).
    pub live: bool,
    /// Running a batch.
    pub busy: bool,
}

/// A round accepted by the driver: await its answer, and detach if the stream goes away first.
#[derive(Debug)]
pub struct PendingRound {
    /// The task.
    pub task: TaskId,
    /// The round.
    pub round: u64,
    /// This stream's waiter id.
    pub waiter: WaiterId,
    /// The answer.
    pub answer: oneshot::Receiver<RoundAnswer>,
}

impl DriverHandle {
    /// The server clock the driver runs on.
    pub fn clock(&self) -> Clock {
        self.clock
    }

    /// Hands a validated round to the driver. `received` is when its `Submit` frame was read, on
    /// [`DriverHandle::clock`] (replies' timing counts from there); `link` receives re-fetch
    /// asks for it.
    pub async fn submit(
        &self,
        submit: ValidSubmit,
        received: Timestamp,
        link: mpsc::Sender<RefetchAsk>,
    ) -> Result<PendingRound, DriverGone> {
        let (answer_tx, answer) = oneshot::channel();
        let waiter = WaiterId(self.waiters.fetch_add(1, Ordering::Relaxed));
        let (task, round) = (submit.round.task, submit.round.round);
        self.commands
            .send(Command::Submit {
                submit: Box::new(submit),
                received,
                waiter,
                link,
                answer: answer_tx,
            })
            .await
            .map_err(|_| DriverGone)?;
        Ok(PendingRound {
            task,
            round,
            waiter,
            answer,
        })
    }

    /// The stream waiting for `pending` is gone. If no other stream waits for the round and it is
    /// still queued, it is withdrawn (the robot may send it again).
    pub async fn detach(&self, pending: &PendingRound) {
        let _ = self
            .commands
            .send(Command::Detach {
                task: pending.task,
                round: pending.round,
                waiter: pending.waiter,
            })
            .await;
    }

    /// Ends a task on behalf of `robot`.
    pub async fn end_task(
        &self,
        robot: RobotId,
        end: ValidEndTask,
    ) -> Result<Result<TaskEnded, ErrorReply>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::EndTask { robot, end, answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// The task's record: open tasks, or recently ended ones.
    pub async fn snapshot(&self, task: TaskId) -> Result<Option<TaskSnapshot>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::Snapshot { task, answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// Adds an engine instance (a remote worker that registered) to the pool and the
    /// scheduler, if it serves the site's shapes.
    pub async fn add_engine(
        &self,
        instance: Arc<dyn EngineInstance>,
    ) -> Result<Result<EngineId, PoolBuildError>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::AddEngine {
                instance: NewInstance(instance),
                answer,
            })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// The instance leaves the pool: no new batch goes to it (the one it runs finishes or is
    /// lost).
    pub async fn remove_engine(&self, engine: EngineId) {
        let _ = self.commands.send(Command::RemoveEngine { engine }).await;
    }

    /// Resolves once the driver has stopped: after a shutdown, when every round it accepted
    /// was answered (or at once if it died).
    pub async fn stopped(&self) {
        self.commands.closed().await;
    }

    /// Resolves once the driver thread has ended, with how.
    pub async fn ended(&self) -> DriverEnd {
        let mut end = self.end.clone();
        match end.wait_for(Option::is_some).await {
            Ok(end) => end.clone().unwrap_or(DriverEnd::Stopped),
            // The thread is gone without saying how.
            Err(_) => DriverEnd::Failed("the driver thread ended without a word".into()),
        }
    }

    /// Why the driver thread died, if it has.
    pub fn failure(&self) -> Option<String> {
        match &*self.end.borrow() {
            Some(DriverEnd::Failed(reason)) => Some(reason.clone()),
            _ => None,
        }
    }

    /// Every engine instance the scheduler knows, live or not.
    pub async fn engines(&self) -> Result<Vec<EngineView>, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::Engines { answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }

    /// The driver's running totals.
    pub async fn stats(&self) -> Result<DriverStats, DriverGone> {
        let (answer, rx) = oneshot::channel();
        self.commands
            .send(Command::Stats { answer })
            .await
            .map_err(|_| DriverGone)?;
        rx.await.map_err(|_| DriverGone)
    }
}

/// One stream waiting for a round: where its answer and its re-fetch asks go.
struct Waiter {
    answer: oneshot::Sender<RoundAnswer>,
    link: mpsc::Sender<RefetchAsk>,
}

struct Shell {
    core: DriverCore,
    commands: mpsc::Receiver<Command>,
    /// For the tasks the shell spawns to report back; weak so that the driver stops once every
    /// handle is gone.
    reports: mpsc::WeakSender<Command>,
    waiters: HashMap<WaiterId, Waiter>,
    pool: EnginePool,
    actions: Arc<ActionManager>,
    clock: Clock,
    runtime: Handle,
    refetch_timeout: Duration,
    timer: watch::Sender<Option<Timestamp>>,
    shutdown: watch::Receiver<bool>,
    /// Where the core's report goes after every event (`/metrics`).
    export: Option<DriverExport>,
    /// `kairos_driver_alive` is 1 while the thread holds this (dropped however it ends).
    _running: Option<crate::metrics::driver::DriverRunning>,
}

/// Starts the driver: its core on a thread of its own, its waiting on the current tokio runtime.
/// It runs until `shutdown` turns true (or its sender is dropped, or every handle is dropped)
/// and every accepted round has been answered; the returned task then yields the totals.
pub fn spawn(
    scheduler: Scheduler,
    pool: EnginePool,
    actions: Arc<ActionManager>,
    config: DriverConfig,
    shutdown: watch::Receiver<bool>,
) -> (DriverHandle, tokio::task::JoinHandle<DriverStats>) {
    let runtime = Handle::current();
    let clock = Clock::start();
    let (commands_tx, commands) = mpsc::channel(config.queue.max(1));
    let (timer, deadlines) = watch::channel(None);
    runtime.spawn(run_timer(deadlines, clock, commands_tx.downgrade()));
    runtime.spawn(watch_shutdown(shutdown.clone(), commands_tx.downgrade()));
    let mut core = DriverCore::new(scheduler, config.ended_snapshots);
    core.set_redispatch_rule(config.redispatch);
    core.set_chunking_model(ChunkingModel {
        action_dim: pool.spec().action_dim,
        action_space: pool.chunking().action_space,
    });
    let export = config.metrics.driver().cloned();
    if let Some(export) = &export {
        export.attach_actions(actions.clone());
        export.publish(core.report());
    }
    let shell = Shell {
        core,
        _running: export.as_ref().map(DriverExport::running),
        export,
        commands,
        reports: commands_tx.downgrade(),
        waiters: HashMap::new(),
        pool,
        actions,
        clock,
        runtime: runtime.clone(),
        refetch_timeout: config.refetch_timeout,
        timer,
        shutdown,
    };
    let (done, stats) = oneshot::channel();
    let (ended, end) = watch::channel(None);
    let thread = std::thread::Builder::new()
        .name("kairos-driver".into())
        .spawn(move || {
            // A panic anywhere in the core or a policy it calls ends the thread; it is caught
            // here only to say so (the server then turns unready and stops), never to go on:
            // the core's state may be half-updated. The command channel closed as the shell
            // unwound, so every waiting round already got `DriverGone`.
            let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| shell.run()));
            match run {
                Ok(stats) => {
                    let _ = ended.send(Some(DriverEnd::Stopped));
                    let _ = done.send(stats);
                }
                Err(panic) => {
                    let reason = format!("the driver thread panicked: {}", panic_message(&*panic));
                    tracing::error!(%reason, "the driver died: no round can be served");
                    let _ = ended.send(Some(DriverEnd::Failed(reason)));
                }
            }
        });
    let end = match thread {
        Ok(_) => end,
        Err(error) => {
            // The command channel's receiver died with the failed spawn: every call answers
            // `DriverGone`.
            tracing::error!(%error, "cannot start the driver thread");
            watch::channel(Some(DriverEnd::Failed(format!(
                "cannot start the driver thread: {error}"
            ))))
            .1
        }
    };
    let join = runtime.spawn(async move {
        stats.await.unwrap_or_else(|_| {
            tracing::error!("the driver thread ended without its totals");
            DriverStats::default()
        })
    });
    let handle = DriverHandle {
        commands: commands_tx,
        waiters: Arc::new(AtomicU64::new(0)),
        clock,
        end,
    };
    (handle, join)
}

/// The text of a panic's payload (a `&str` or `String`, as `panic!` makes them).
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

impl Shell {
    fn run(mut self) -> DriverStats {
        // Inside the runtime's context: tokio's clock (virtual in paused tests) and spawns. The
        // thread is not a runtime worker, so it may block on the channel.
        let runtime = self.runtime.clone();
        let _context = runtime.enter();
        while !self.core.is_done() {
            let Some(command) = self.commands.blocking_recv() else {
                break;
            };
            self.handle(command);
        }
        // Commands already queued get their answer (a submit: `shutting_down`).
        self.core.shut_down();
        self.commands.close();
        while let Ok(command) = self.commands.try_recv() {
            self.handle(command);
        }
        self.core.stats()
    }

    fn handle(&mut self, command: Command) {
        // Read synchronously, so a shutdown signalled before a command was handled is seen first
        // and a round sent after it is refused.
        if *self.shutdown.borrow() {
            self.core.shut_down();
        }
        let now = self.clock.now();
        match command {
            Command::Submit {
                submit,
                received,
                waiter,
                link,
                answer,
            } => {
                self.waiters.insert(waiter, Waiter { answer, link });
                self.core.submit(now, *submit, received, waiter);
            }
            Command::Detach {
                task,
                round,
                waiter,
            } => {
                self.waiters.remove(&waiter);
                self.core.detach(now, task, round, waiter);
            }
            Command::EndTask { robot, end, answer } => {
                let _ = answer.send(self.core.end_task(now, robot, end));
            }
            Command::Snapshot { task, answer } => {
                let _ = answer.send(self.core.snapshot(task));
            }
            Command::Stats { answer } => {
                let _ = answer.send(self.core.stats());
            }
            Command::Refetched {
                batch,
                request,
                observation,
            } => self.core.refetched(now, batch, request, observation),
            Command::GenerationEnded {
                batch,
                engine,
                inference,
                load,
            } => {
                if let Some(instance) = self.pool.get(engine)
                    && instance.can_lose_batches()
                {
                    self.core
                        .engine_link(engine, instance.rtt(), instance.tier());
                }
                let _ = load.send(self.core.generation_ended(now, batch, inference));
            }
            Command::BatchLost {
                batch,
                reason,
                inputs,
                rounds,
            } => self.core.batch_lost(now, batch, reason, inputs, rounds),
            Command::AddEngine {
                instance: NewInstance(instance),
                answer,
            } => {
                let spec = EngineSpec {
                    name: instance.name().to_string(),
                    tier: instance.tier(),
                    profile: instance.profile().clone(),
                    rtt: instance.rtt(),
                };
                let added = self.pool.add(instance).inspect(|&id| {
                    let scheduled = self.core.add_engine(now, spec);
                    debug_assert_eq!(id, scheduled, "pool and scheduler ids move together");
                });
                let _ = answer.send(added);
            }
            Command::RemoveEngine { engine } => {
                self.pool.remove(engine);
                self.core.remove_engine(now, engine);
            }
            Command::Engines { answer } => {
                let views = self
                    .core
                    .scheduler()
                    .engines()
                    .map(|e| EngineView {
                        id: e.id,
                        name: e.spec.name.clone(),
                        tier: e.spec.tier,
                        rtt: e.spec.rtt,
                        live: e.live,
                        busy: e.batch.is_some(),
                    })
                    .collect();
                let _ = answer.send(views);
            }
            Command::BatchDone { batch, results } => self.core.batch_done(now, batch, results),
            Command::Timeout => self.core.timeout(now),
            Command::Shutdown => self.core.shut_down(),
        }
        self.carry_out(now);
        if let Some(export) = &self.export {
            export.publish(self.core.report());
        }
    }

    fn carry_out(&mut self, now: Timestamp) {
        while let Some(effect) = self.core.poll_effect() {
            match effect {
                Effect::Answer { waiters, answer } => {
                    for waiter in waiters {
                        if let Some(waiter) = self.waiters.remove(&waiter) {
                            let _ = waiter.answer.send(answer.clone());
                        }
                    }
                }
                Effect::Refetch {
                    batch,
                    request,
                    waiter,
                    age,
                } => self.refetch(now, batch, request, waiter, age),
                Effect::RunBatch(job) => self.run_batch(now, job),
                Effect::SetTimer(deadline) => {
                    let _ = self.timer.send(deadline);
                }
            }
        }
    }

    /// Asks the round's stream for a fresh observation and waits for it (on the runtime) up to
    /// the re-fetch deadline. With no stream to ask, the core hears `None` at once.
    fn refetch(
        &mut self,
        now: Timestamp,
        batch: BatchId,
        request: RequestId,
        waiter: WaiterId,
        age: Duration,
    ) {
        let (reply, fresh) = oneshot::channel();
        let asked = self
            .waiters
            .get(&waiter)
            .is_some_and(|w| w.link.try_send(RefetchAsk { age, reply }).is_ok());
        let reports = self.reports.upgrade();
        let (true, Some(reports)) = (asked, reports) else {
            self.core.refetched(now, batch, request, None);
            return;
        };
        let timeout = self.refetch_timeout;
        self.runtime.spawn(async move {
            let observation = tokio::time::timeout(timeout, fresh)
                .await
                .ok()
                .and_then(Result::ok);
            let _ = reports
                .send(Command::Refetched {
                    batch,
                    request,
                    observation,
                })
                .await;
        });
    }

    /// Runs the batch on its engine instance (an OS thread or a remote link: the task only
    /// waits), reports the end of generation, then chooses the horizons on the blocking pool.
    fn run_batch(&mut self, now: Timestamp, job: BatchJob) {
        let BatchJob {
            batch,
            engine,
            attempt,
            inputs,
            rounds,
        } = job;
        let requests: Vec<RequestId> = rounds.iter().map(|r| r.request).collect();
        let fail_all = move |error: RequestError| {
            let reply = ErrorReply::from(&error);
            requests
                .into_iter()
                .map(|r| (r, Err(reply.clone())))
                .collect::<Vec<_>>()
        };
        let engine_id = engine;
        let Some(engine) = self.pool.get(engine_id).cloned() else {
            // The instance left (a worker drained or was lost) between placement and the end
            // of the batch's re-fetches: the batch runs elsewhere.
            self.core
                .batch_lost(now, batch, LossReason::Gone, inputs, rounds);
            return;
        };
        let Some(reports) = self.reports.upgrade() else {
            let results = fail_all(RequestError::internal("no engine instance for the batch"));
            self.core.generation_ended(now, batch, Duration::ZERO);
            self.core.batch_done(now, batch, results);
            return;
        };
        let (actions, clock) = (self.actions.clone(), self.clock);
        // A batch that can be lost with its instance may have to run again: keep its inputs.
        let kept = engine.can_lose_batches().then(|| inputs.clone());
        let label = BatchLabel { batch, attempt };
        self.runtime.spawn(async move {
            let started = clock.now();
            let outcome = engine.run_labeled(label, inputs).await;
            if let (Err(PoolError::Lost { reason, .. }), Some(inputs)) = (&outcome, kept) {
                if let Err(PoolError::Lost { engine, detail, .. }) = &outcome {
                    tracing::warn!(%engine, %reason, %detail, ?batch, "batch lost with its engine");
                }
                let _ = reports
                    .send(Command::BatchLost {
                        batch,
                        reason: *reason,
                        inputs,
                        rounds,
                    })
                    .await;
                return;
            }
            let inference = clock.now().saturating_since(started);
            let (load_tx, load_rx) = oneshot::channel();
            let _ = reports
                .send(Command::GenerationEnded {
                    batch,
                    engine: engine_id,
                    inference,
                    load: load_tx,
                })
                .await;
            // `None` only if the driver is shutting down.
            let load = load_rx.await.ok();
            let results = match outcome {
                Ok(chunks) => {
                    // A request the engine failed alone gets its own wire error; the batch's
                    // others go on.
                    let chunks = chunks
                        .into_iter()
                        .map(|c| c.map_err(|e| ErrorReply::from(&RequestError::Engine(e))))
                        .collect();
                    let chosen = tokio::task::spawn_blocking(move || {
                        actions.answer_batch(rounds, chunks, load)
                    })
                    .await;
                    match chosen {
                        Ok(results) => results,
                        Err(error) => {
                            tracing::error!(%error, "horizon policies panicked");
                            fail_all(RequestError::internal(format!(
                                "horizon policies panicked: {error}"
                            )))
                        }
                    }
                }
                Err(error) => {
                    tracing::error!(%error, "batch failed");
                    fail_all(RequestError::Engine(error))
                }
            };
            let _ = reports.send(Command::BatchDone { batch, results }).await;
        });
    }
}

/// Wakes the core at the deadline it last asked for.
async fn run_timer(
    mut deadlines: watch::Receiver<Option<Timestamp>>,
    clock: Clock,
    reports: mpsc::WeakSender<Command>,
) {
    loop {
        let deadline = (*deadlines.borrow_and_update()).and_then(|t| clock.instant(t));
        let sleep = async {
            match deadline {
                Some(deadline) => tokio::time::sleep_until(deadline).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            changed = deadlines.changed() => {
                if changed.is_err() {
                    return;
                }
            }
            () = sleep => {
                let Some(reports) = reports.upgrade() else {
                    return;
                };
                if reports.send(Command::Timeout).await.is_err() {
                    return;
                }
                // The core asks for its next timer after handling this one.
                if deadlines.changed().await.is_err() {
                    return;
                }
            }
        }
    }
}

/// Tells the driver thread when the shutdown signal is set (or its sender is gone), so that it
/// wakes up to drain even when no command comes.
async fn watch_shutdown(mut shutdown: watch::Receiver<bool>, reports: mpsc::WeakSender<Command>) {
    let _ = shutdown.wait_for(|stop| *stop).await;
    if let Some(reports) = reports.upgrade() {
        let _ = reports.send(Command::Shutdown).await;
    }
}
