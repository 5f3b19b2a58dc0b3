//! [`RobotRunner`]: a task run in real time on the tokio clock, a [`ChunkExecutor`] between a
//! [`Robot`] and a [`RoundTransport`], with asynchronous inference (the next round is generated
//! while the current chunk executes).

use std::future::Future;
use std::time::Duration;

use tokio::sync::{mpsc, oneshot};
use tokio::time::Instant;

use super::{Alignment, ChunkExecutor, Robot, RobotError, RoundTransport};
use crate::client::{ClientError, Clock, ObservationSource, RoundReply, RoundRequest};
use crate::protocol::{
    ChunkingSelection, FetchObservation, HorizonSelection, LastExecInfo, Observation,
    RemainingHint, TaskEnded, TaskOutcome, Timing,
};

/// The time between two actions at `control_hz` (at least 1 mHz; never a panic, whatever the
/// rate).
pub fn control_period(control_hz: f32) -> Duration {
    Duration::try_from_secs_f64(1.0 / f64::from(control_hz.max(1e-3))).unwrap_or(Duration::MAX)
}

/// How a [`RobotRunner`] runs a task.
#[derive(Clone, Debug, PartialEq)]
pub struct RunnerConfig {
    /// Actions per second.
    pub control_hz: f32,
    /// Executed fraction of a chunk at which the next request goes out, in [0, 1].
    pub trigger: f32,
    /// Rounds (replies) the task takes.
    pub rounds: u64,
    /// Horizon policy sent with every round; `None` = the server's default.
    pub horizon: Option<HorizonSelection>,
    /// Answer the server's re-fetches with a new observation (otherwise the submitted one is
    /// sent again).
    pub refetch: bool,
    /// Retryable round failures in a row (e.g. `overloaded`) before the task is abandoned.
    pub max_consecutive_failures: u32,
    /// Wait before re-requesting after a retryable failure, unless the server says otherwise.
    pub retry_delay: Duration,
    /// Chunking strategy sent with every round; `None` = the server's default.
    pub chunking: Option<ChunkingSelection>,
    /// Where an arriving chunk starts executing.
    pub alignment: Alignment,
}

impl Default for RunnerConfig {
    fn default() -> RunnerConfig {
        RunnerConfig {
            control_hz: 30.0,
            trigger: 0.5,
            rounds: 10,
            horizon: None,
            refetch: true,
            max_consecutive_failures: 5,
            retry_delay: Duration::from_millis(100),
            chunking: None,
            alignment: Alignment::default(),
        }
    }
}

/// What happened during a task, in order, for traces and progress displays. Times are on the
/// client clock, µs.
#[derive(Clone, Debug, PartialEq)]
pub enum RunnerEvent {
    /// A round was requested.
    RequestSent {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// The Last Exec Info sent.
        last_exec: Option<LastExecInfo>,
    },
    /// The server asked for a fresher observation and got one. The round's chunk is aligned to
    /// this capture from now on (see the module docs).
    ObservationRefetched {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// Actions the task had executed when the fresh observation was captured: the action
        /// index the chunk's action 0 now corresponds to.
        actions_executed: u64,
    },
    /// A round's chunk arrived and was aligned.
    ReplyReceived {
        /// Task id.
        task: u64,
        /// The round's record so far (`executed` is 0 until the chunk ends).
        record: RoundRecord,
    },
    /// A round failed.
    RoundFailed {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// When.
        at_us: u64,
        /// What went wrong.
        error: String,
        /// Whether the runner will request again.
        retrying: bool,
    },
    /// A chunk stopped executing: it ran out or a newer chunk replaced it.
    ChunkEnded {
        /// Task id.
        task: u64,
        /// Round id.
        round: u64,
        /// Actions executed.
        executed: u32,
        /// Actions dropped unexecuted (replaced by a newer chunk).
        dropped: u32,
    },
    /// The robot had nothing to execute from `from_us` to `to_us`.
    Idle {
        /// Task id.
        task: u64,
        /// Start of the gap.
        from_us: u64,
        /// End of the gap.
        to_us: u64,
    },
    /// The task is over.
    TaskFinished(TaskSummary),
}

/// One round as the robot saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct RoundRecord {
    /// Round id.
    pub round: u64,
    /// When the round was first sent.
    pub sent_at_us: u64,
    /// When its reply arrived.
    pub received_at_us: u64,
    /// Sends (more than 1 after a lost connection).
    pub attempts: u32,
    /// Fresh observations sent for it.
    pub refetches: u32,
    /// `H`.
    pub horizon: u32,
    /// `N`.
    pub chunk_len: u32,
    /// Actions discarded on arrival (their time had passed).
    pub discarded: u32,
    /// Actions executed.
    pub executed: u32,
    /// The horizon policy that answered.
    pub policy: String,
    /// The server's timing.
    pub timing: Timing,
}

impl RoundRecord {
    /// Round latency as the robot saw it, µs.
    pub fn latency_us(&self) -> u64 {
        self.received_at_us.saturating_sub(self.sent_at_us)
    }
}

/// A finished task.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskSummary {
    /// Task id.
    pub task: u64,
    /// Its rounds, in order.
    pub rounds: Vec<RoundRecord>,
    /// When the first request was sent.
    pub started_at_us: u64,
    /// When the last action was executed.
    pub finished_at_us: u64,
    /// Actions executed.
    pub actions_executed: u64,
    /// Total time the robot had nothing to execute, µs (the wait before the first chunk
    /// included).
    pub idle_us: u64,
    /// Rounds that failed (and were retried).
    pub failed_rounds: u32,
    /// The server's record, if `EndTask` succeeded.
    pub server_record: Option<TaskEnded>,
    /// Why `EndTask` failed, if it did (then `server_record` is `None`): the task may still be
    /// open on the server until its idle timeout, e.g. after a server restart forgot it
    /// (`unknown_task`) or the connection was lost. Reports count these.
    pub end_error: Option<String>,
}

impl TaskSummary {
    /// Task latency: first request to last action, µs.
    pub fn latency_us(&self) -> u64 {
        self.finished_at_us.saturating_sub(self.started_at_us)
    }
}

/// Why a task could not be run.
#[derive(Debug, thiserror::Error)]
pub enum RunnerError {
    /// The robot's shim failed.
    #[error(transparent)]
    Robot(#[from] RobotError),
    /// A round failed for good.
    #[error("round {round} failed: {source}")]
    Round {
        /// The round.
        round: u64,
        /// Why.
        source: ClientError,
    },
    /// The server's reply is not an `[H, D]` chunk of f32.
    #[error("bad chunk in round {round}: {reason}")]
    BadChunk {
        /// The round.
        round: u64,
        /// What is wrong.
        reason: String,
    },
    /// The round task panicked or was cancelled.
    #[error("round task failed: {0}")]
    Join(#[from] tokio::task::JoinError),
}

/// Answers the server's re-fetches by asking the runner loop, which owns the robot.
struct RunnerSource {
    requests: mpsc::Sender<oneshot::Sender<Observation>>,
}

impl ObservationSource for RunnerSource {
    fn fresh_observation(
        &mut self,
        _fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send {
        let requests = self.requests.clone();
        async move {
            let (reply, answer) = oneshot::channel();
            requests.send(reply).await.ok()?;
            answer.await.ok()
        }
    }
}

type InFlight<T> = tokio::task::JoinHandle<(T, u64, Result<RoundReply, ClientError>)>;

/// Runs one task on one robot: the control loop, asynchronous inference, alignment.
#[derive(Clone, Debug)]
pub struct RobotRunner {
    config: RunnerConfig,
}

impl RobotRunner {
    /// A runner with `config`.
    pub fn new(config: RunnerConfig) -> RobotRunner {
        RobotRunner { config }
    }

    /// Runs the task to its end (`config.rounds` replies executed, or `robot.task_done()`), then
    /// sends `EndTask`. `on_event` sees every [`RunnerEvent`].
    pub async fn run<R: Robot, T: RoundTransport, E: FnMut(&RunnerEvent) + Send>(
        &self,
        robot: &mut R,
        transport: T,
        on_event: E,
    ) -> Result<TaskSummary, RunnerError> {
        let (fetch_tx, mut fetch_rx) = mpsc::channel(1);
        let mut run = Run {
            config: &self.config,
            task: transport.task_id(),
            clock: transport.clock(),
            period: control_period(self.config.control_hz),
            executor: ChunkExecutor::new(self.config.control_hz, self.config.trigger)
                .with_alignment(self.config.alignment),
            robot,
            transport: Some(transport),
            in_flight: None,
            fetch_tx,
            on_event,
            next_tick: None,
            idle_since: None,
            retry_at: None,
            records: Vec::new(),
            replies: 0,
            failures_in_row: 0,
            failed_rounds: 0,
            idle_us: 0,
            started_at_us: None,
            last_action_at_us: None,
        };
        loop {
            let now = Instant::now();
            let task_done = run.robot.task_done();
            if task_done {
                // The robot reached its goal: the rest of the chunk is not executed (executing
                // it would lengthen the task by up to a whole horizon). A round still in flight
                // is awaited so that it is answered exactly once, but nothing more runs.
                run.next_tick = None;
                run.idle_since = None;
                if let Some((round, executed, dropped)) = run.executor.drop_rest() {
                    run.chunk_ended(round, executed, dropped);
                }
            }
            let stop_requesting = run.replies >= run.config.rounds || task_done;
            if !stop_requesting
                && run.retry_at.is_none_or(|at| now >= at)
                && run.executor.wants_request()
            {
                run.send_request(now).await?;
            }
            if stop_requesting && run.in_flight.is_none() && run.executor.remaining() == 0 {
                break;
            }
            tokio::select! {
                Some(answer) = fetch_rx.recv() => run.refetch(answer).await?,
                joined = async {
                    match run.in_flight.as_mut() {
                        Some(handle) => handle.await,
                        None => std::future::pending().await,
                    }
                } => {
                    run.in_flight = None;
                    let (transport, round, result) = joined?;
                    run.transport = Some(transport);
                    run.round_done(round, result).await?;
                }
                () = sleep_until_some(run.next_tick) => run.tick().await?,
                () = sleep_until_some(run.retry_at) => {}
            }
        }
        run.finish().await
    }
}

/// The state of one [`RobotRunner::run`].
struct Run<'a, R, T, E> {
    config: &'a RunnerConfig,
    task: u64,
    clock: Clock,
    period: Duration,
    executor: ChunkExecutor,
    robot: &'a mut R,
    /// The transport, while no round is in flight (the round's task holds it meanwhile).
    transport: Option<T>,
    in_flight: Option<InFlight<T>>,
    fetch_tx: mpsc::Sender<oneshot::Sender<Observation>>,
    on_event: E,
    /// When the next action is due; `None` while the robot idles.
    next_tick: Option<Instant>,
    /// Since when the robot has had nothing to execute.
    idle_since: Option<Instant>,
    retry_at: Option<Instant>,
    records: Vec<RoundRecord>,
    replies: u64,
    failures_in_row: u32,
    failed_rounds: u32,
    idle_us: u64,
    started_at_us: Option<u64>,
    last_action_at_us: Option<u64>,
}

impl<R: Robot, T: RoundTransport, E: FnMut(&RunnerEvent) + Send> Run<'_, R, T, E> {
    /// Captures an observation and starts the next round in its own tokio task.
    async fn send_request(&mut self, now: Instant) -> Result<(), RunnerError> {
        let Some(mut transport) = self.transport.take() else {
            return Ok(());
        };
        self.retry_at = None;
        let now_us = self.clock.to_us(now);
        let observation = self.robot.get_obs(now_us).await?;
        let round = transport.next_round();
        let last_exec = self.executor.request_sent(round, now_us);
        self.started_at_us.get_or_insert(now_us);
        if self.started_at_us == Some(now_us) && self.executor.remaining() == 0 {
            // Nothing to execute until the first chunk arrives.
            self.idle_since = Some(now);
        }
        (self.on_event)(&RunnerEvent::RequestSent {
            task: self.task,
            round,
            at_us: now_us,
            last_exec,
        });
        let request = RoundRequest {
            observation,
            last_exec,
            horizon: self.config.horizon.clone(),
            remaining: Some(RemainingHint {
                rounds: u32::try_from(self.config.rounds.saturating_sub(self.replies)).ok(),
                seconds: None,
            }),
            control_hz: Some(self.config.control_hz),
            seed: None,
            chunking: self.config.chunking.clone(),
        };
        let refetch = self.config.refetch;
        let requests = self.fetch_tx.clone();
        self.in_flight = Some(tokio::spawn(async move {
            let result = if refetch {
                transport
                    .submit(request, &mut RunnerSource { requests })
                    .await
            } else {
                transport
                    .submit(request, &mut crate::client::NoRefetch)
                    .await
            };
            (transport, round, result)
        }));
        Ok(())
    }

    /// The server re-fetches the in-flight round's observation.
    async fn refetch(&mut self, answer: oneshot::Sender<Observation>) -> Result<(), RunnerError> {
        let now_us = self.clock.now_us();
        let observation = self.robot.get_obs(now_us).await?;
        self.executor.observation_refreshed();
        if let Some(round) = self.executor.in_flight_round() {
            (self.on_event)(&RunnerEvent::ObservationRefetched {
                task: self.task,
                round,
                at_us: now_us,
                actions_executed: self.executor.executed_total(),
            });
        }
        // The round may have ended meanwhile; then nobody needs the observation.
        let _ = answer.send(observation);
        Ok(())
    }

    /// The in-flight round finished.
    async fn round_done(
        &mut self,
        round: u64,
        result: Result<RoundReply, ClientError>,
    ) -> Result<(), RunnerError> {
        match result {
            Ok(reply) => {
                self.failures_in_row = 0;
                self.replies += 1;
                let actions =
                    chunk_rows(&reply).map_err(|reason| RunnerError::BadChunk { round, reason })?;
                let applied = self
                    .executor
                    .reply_arrived_from(round, actions, reply.reply.start);
                if let Some((old, executed, dropped)) = applied.replaced {
                    self.chunk_ended(old, executed, dropped);
                }
                let record = RoundRecord {
                    round,
                    sent_at_us: reply.sent_at_us,
                    received_at_us: reply.received_at_us,
                    attempts: reply.attempts,
                    refetches: reply.refetches,
                    horizon: reply.reply.horizon,
                    chunk_len: reply.reply.chunk_len,
                    discarded: applied.discarded,
                    executed: 0,
                    policy: reply.reply.policy,
                    timing: reply.reply.timing,
                };
                (self.on_event)(&RunnerEvent::ReplyReceived {
                    task: self.task,
                    record: record.clone(),
                });
                self.records.push(record);
                if applied.executable == 0 {
                    self.chunk_ended(round, 0, 0);
                } else if self.next_tick.is_none() {
                    // Idle robot: the chunk's first action runs now.
                    self.next_tick = Some(Instant::now());
                }
                Ok(())
            }
            Err(error) => {
                self.executor.request_failed();
                self.failed_rounds += 1;
                self.failures_in_row += 1;
                let retrying = error.is_retryable()
                    && self.failures_in_row <= self.config.max_consecutive_failures;
                (self.on_event)(&RunnerEvent::RoundFailed {
                    task: self.task,
                    round,
                    at_us: self.clock.now_us(),
                    error: error.to_string(),
                    retrying,
                });
                if !retrying {
                    if let Some(transport) = self.transport.take() {
                        let last_exec = self.executor.last_exec(self.clock.now_us());
                        // The task failed either way; the round's error is the one to report.
                        let _ = transport.end(TaskOutcome::Failed, last_exec).await;
                    }
                    return Err(RunnerError::Round {
                        round,
                        source: error,
                    });
                }
                let delay = match &error {
                    ClientError::Server(reply) => {
                        reply.retry_after_ms.map_or(self.config.retry_delay, |ms| {
                            Duration::from_millis(u64::from(ms))
                        })
                    }
                    _ => self.config.retry_delay,
                };
                self.retry_at = Some(Instant::now() + delay);
                Ok(())
            }
        }
    }

    /// An action is due.
    async fn tick(&mut self) -> Result<(), RunnerError> {
        let tick = self.next_tick.unwrap_or_else(Instant::now);
        let tick_us = self.clock.to_us(tick);
        let Some(step) = self.executor.next_action(tick_us) else {
            // An action was due and there is none: the robot idles from here.
            self.idle_since = Some(tick);
            self.next_tick = None;
            return Ok(());
        };
        let (round, last) = (step.round, step.last_of_chunk);
        self.robot.send_act(step.action).await?;
        if let Some(since) = self.idle_since.take() {
            let from_us = self.clock.to_us(since);
            self.idle_us += tick_us.saturating_sub(from_us);
            (self.on_event)(&RunnerEvent::Idle {
                task: self.task,
                from_us,
                to_us: tick_us,
            });
        }
        self.last_action_at_us = Some(tick_us);
        if last {
            let executed = self.executor.current_chunk().map_or(0, |(_, n)| n);
            self.chunk_ended(round, executed, 0);
        }
        self.next_tick = Some(tick + self.period);
        Ok(())
    }

    fn chunk_ended(&mut self, round: u64, executed: u32, dropped: u32) {
        if let Some(record) = self.records.iter_mut().rev().find(|r| r.round == round) {
            record.executed = executed;
        }
        (self.on_event)(&RunnerEvent::ChunkEnded {
            task: self.task,
            round,
            executed,
            dropped,
        });
    }

    /// Sends `EndTask` and builds the summary.
    async fn finish(mut self) -> Result<TaskSummary, RunnerError> {
        let now_us = self.clock.now_us();
        let finished_at_us = self.last_action_at_us.unwrap_or(now_us);
        let last_exec = self.executor.last_exec(now_us);
        let (server_record, end_error) = match self.transport.take() {
            Some(transport) => match transport.end(TaskOutcome::Done, last_exec).await {
                Ok(record) => (Some(record), None),
                Err(error) => {
                    tracing::warn!(task = self.task, %error, "EndTask failed");
                    (None, Some(error.to_string()))
                }
            },
            None => (None, None),
        };
        let summary = TaskSummary {
            task: self.task,
            rounds: self.records,
            started_at_us: self.started_at_us.unwrap_or(finished_at_us),
            finished_at_us,
            actions_executed: self.executor.executed_total(),
            idle_us: self.idle_us,
            failed_rounds: self.failed_rounds,
            server_record,
            end_error,
        };
        (self.on_event)(&RunnerEvent::TaskFinished(summary.clone()));
        Ok(summary)
    }
}

async fn sleep_until_some(deadline: Option<Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// The reply's actions as rows of `D` values.
fn chunk_rows(reply: &RoundReply) -> Result<Vec<Vec<f32>>, String> {
    let actions = &reply.reply.actions;
    let values = actions.to_f32().map_err(|error| error.to_string())?;
    let [rows, dim] = actions.shape[..] else {
        return Err(format!("shape {:?} is not [H, D]", actions.shape));
    };
    if dim == 0 {
        return Ok(vec![Vec::new(); rows as usize]);
    }
    Ok(values.chunks(dim as usize).map(<[f32]>::to_vec).collect())
}
