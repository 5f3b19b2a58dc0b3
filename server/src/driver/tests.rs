//! The driver as connection tasks see it (handle, thread, tokio tasks), in tokio's virtual time.
//!
//! The engine here runs a real model ([`LinearFlow`]) on tokio's blocking pool after a gate the
//! test opens, so virtual time stands still while it computes and moves only while everything
//! waits on a timer.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{ActionModel, ActionRequest, EngineProfile, ModelSpec};
use kairos_sdk::protocol::{
    EndTask, ErrorCode, ErrorReply, FreshObservation, HorizonSelection, LastExecInfo, Limits,
    Observation, Submit, TaskEnded, TaskOutcome, Tensor,
};
use tokio::sync::{Semaphore, mpsc, watch};

use super::*;
use crate::pool::test_model::LinearFlow;
use crate::pool::{BatchChunks, EngineInstance, EnginePool, PoolError};
use crate::validation::Validator;
use kairos_core::action::ActionManager;
use kairos_core::clock_map::ClockMap;
use kairos_core::horizon::{HorizonError, HorizonInput, HorizonPolicy};
use kairos_core::registry::{HorizonRegistry, native_horizon_policies};
use kairos_core::scheduler::fifo::Fifo;
use kairos_core::scheduler::{RobotId, Scheduler, SchedulerConfig, TaskId, Tier};

/// `LinearFlow` behind a gate: each batch takes one permit, then runs on the blocking pool. It
/// draws its noise from seed 0, so that the first action shows which observation was used:
/// two Euler steps from 0 towards `state[0]` give `0.75 × state[0]`.
struct GatedEngine {
    model: Arc<LinearFlow>,
    profile: EngineProfile,
    gate: Arc<Semaphore>,
}

impl EngineInstance for GatedEngine {
    fn name(&self) -> &str {
        "gated"
    }
    fn spec(&self) -> &ModelSpec {
        &self.model.spec
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
    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        let (model, gate) = (self.model.clone(), self.gate.clone());
        let mut batch = batch;
        for request in &mut batch {
            request.seed = 0;
        }
        let stopped = || PoolError::Stopped {
            engine: "gated".into(),
        };
        async move {
            gate.acquire().await.map_err(|_| stopped())?.forget();
            let generated = tokio::task::spawn_blocking(move || model.generate(&batch)).await;
            match generated {
                Ok(Ok(chunks)) => Ok(chunks.into_iter().map(Ok).collect()),
                Ok(Err(source)) => Err(PoolError::Engine {
                    engine: "gated".into(),
                    source,
                }),
                Err(_) => Err(stopped()),
            }
        }
        .boxed()
    }
}

struct Fixture {
    driver: DriverHandle,
    join: tokio::task::JoinHandle<DriverStats>,
    stop: watch::Sender<bool>,
    gate: Arc<Semaphore>,
    validator: Validator,
    actions: Arc<ActionManager>,
    /// The simulated robot's clock: 1 s ahead of the driver's, so the mapping is exercised.
    client_clock: ClockMap,
}

/// What differs between fixtures.
struct Setup {
    stale_after: Duration,
    task_idle_timeout: Duration,
    /// Horizon policies beside the natives.
    horizon: HorizonRegistry,
}

impl Setup {
    /// Observations older than `stale_after` are re-fetched; tasks never expire.
    fn stale_after(stale_after: Duration) -> Setup {
        Setup {
            stale_after,
            task_idle_timeout: Duration::MAX,
            horizon: HorizonRegistry::new(),
        }
    }
}

fn fixture(stale_after: Duration) -> Fixture {
    fixture_with(Setup::stale_after(stale_after))
}

/// One engine instance (batches of one) with a closed gate, FIFO, default horizon `static` 3.
fn fixture_with(setup: Setup) -> Fixture {
    let gate = Arc::new(Semaphore::new(0));
    let model = Arc::new(LinearFlow::new());
    let spec = model.spec.clone();
    let profile = EngineProfile {
        model: spec.name.clone(),
        device: "cpu".into(),
        points: vec![kairos_engine::ProfilePoint {
            batch: 1,
            latency_ms: 1.0,
        }],
        max_batch: 1,
    };
    let engine: Arc<dyn EngineInstance> = Arc::new(GatedEngine {
        model,
        profile,
        gate: gate.clone(),
    });
    let pool = EnginePool::new(vec![engine]).unwrap();
    let config = SchedulerConfig {
        stale_after: setup.stale_after,
        task_idle_timeout: setup.task_idle_timeout,
        ..SchedulerConfig::default()
    };
    let scheduler = Scheduler::new(config, pool.specs(), Box::new(Fifo::default()));
    let natives = native_horizon_policies();
    let actions = Arc::new(
        ActionManager::new(
            setup.horizon,
            &natives,
            "static",
            [("h".to_string(), 3.0)].into(),
        )
        .unwrap(),
    );
    let (stop, stop_rx) = watch::channel(false);
    let (driver, join) = spawn(
        scheduler,
        pool,
        actions.clone(),
        DriverConfig {
            refetch_timeout: Duration::from_millis(200),
            ..DriverConfig::default()
        },
        stop_rx,
    );
    let client_clock = ClockMap::new(driver.clock().now(), 1_000_000, Duration::ZERO);
    Fixture {
        client_clock,
        driver,
        join,
        stop,
        gate,
        validator: Validator {
            spec,
            limits: Limits::default(),
            chunking: Default::default(),
        },
        actions,
    }
}

fn observation(f: &Fixture, state0: f32) -> Observation {
    Observation {
        captured_at_us: f.client_now(),
        state: Tensor::from_f32(vec![3], &[state0, 0.0, 0.0]).unwrap(),
        images: Vec::new(),
        instruction: String::new(),
    }
}

fn wire_submit(
    f: &Fixture,
    task: u64,
    round: u64,
    state0: f32,
    last_exec: Option<LastExecInfo>,
) -> Submit {
    Submit {
        task,
        round,
        sent_at_us: f.client_now(),
        observation: observation(f, state0),
        last_exec,
        horizon: None,
        remaining: None,
        attempt: 0,
        control_hz: None,
        seed: None,
        chunking: None,
    }
}

/// Observations older than this are re-fetched in the tests that re-fetch.
const STALE_AFTER: Duration = Duration::from_millis(10);

/// `submit` with an observation captured `2 × STALE_AFTER` before it was sent: on the paused
/// clock nothing ages by itself.
fn stale(mut submit: Submit) -> Submit {
    let age = u64::try_from(2 * STALE_AFTER.as_micros()).unwrap();
    submit.observation.captured_at_us = submit.observation.captured_at_us.saturating_sub(age);
    submit
}

impl Fixture {
    fn client_now(&self) -> u64 {
        self.client_clock.to_client(self.driver.clock().now())
    }

    async fn submit(
        &self,
        robot: u32,
        submit: Submit,
    ) -> (PendingRound, mpsc::Receiver<RefetchAsk>) {
        let valid = self
            .validator
            .submit(submit, RobotId(robot), &self.actions, self.client_clock)
            .unwrap();
        let (link, asks) = mpsc::channel(1);
        let received = self.driver.clock().now();
        (
            self.driver.submit(valid, received, link).await.unwrap(),
            asks,
        )
    }

    /// Lets `n` more batches through the engine.
    fn open(&self, n: usize) {
        self.gate.add_permits(n);
    }

    /// Answers a re-fetch ask with a fresh observation whose `state[0]` is `state0`.
    fn answer_refetch(&self, ask: RefetchAsk, state0: f32) {
        let fresh = FreshObservation {
            sent_at_us: self.client_now(),
            observation: observation(self, state0),
        };
        let valid = self.validator.fresh(fresh, self.client_clock).unwrap();
        ask.reply.send(valid).unwrap();
    }

    async fn end(&self, robot: u32, task: u64) -> Result<TaskEnded, ErrorReply> {
        let now = self.client_now();
        let end = EndTask {
            task,
            outcome: TaskOutcome::Done,
            sent_at_us: now,
            last_exec: Some(LastExecInfo {
                exec_started_at_us: now,
                actions_remaining: 0,
                control_hz: 10.0,
                round: None,
                delay: None,
            }),
        };
        let valid = self.validator.end_task(end, self.client_clock).unwrap();
        self.driver.end_task(RobotId(robot), valid).await.unwrap()
    }
}

#[tokio::test(start_paused = true)]
async fn rounds_are_answered_and_a_resent_finished_round_gets_the_cached_reply() {
    let f = fixture(Duration::from_secs(10));
    f.open(1);
    let (round, _asks) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    let reply = round.answer.await.unwrap().unwrap();
    assert_eq!((reply.task, reply.round, reply.horizon), (1, 0, 3));
    assert_eq!(reply.policy, "static");
    assert_eq!(reply.actions.shape, vec![3, 2]);
    assert_eq!(reply.timing.batch_size, 1);
    assert!(reply.timing.total_us >= reply.timing.inference_us);

    let (again, _asks) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    assert_eq!(again.answer.await.unwrap().unwrap(), reply);
    let stats = f.driver.stats().await.unwrap();
    assert_eq!((stats.replies, stats.cached_replies), (1, 1));
    let snapshot = f.driver.snapshot(TaskId(1)).await.unwrap().unwrap();
    assert_eq!(snapshot.generated.get(&0), Some(&1));
    assert_eq!(snapshot.rounds_completed, 1);
}

#[tokio::test(start_paused = true)]
async fn a_round_resent_while_queued_attaches_and_is_generated_once() {
    let f = fixture(Duration::from_secs(10));
    // Task 1 occupies the only engine; task 2's round waits.
    let (busy, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    let (first, _b) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
    let (second, _c) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
    f.open(2);
    busy.answer.await.unwrap().unwrap();
    let a = first.answer.await.unwrap().unwrap();
    let b = second.answer.await.unwrap().unwrap();
    assert_eq!(a, b);
    let stats = f.driver.stats().await.unwrap();
    assert_eq!(stats.attached, 1);
    assert_eq!(stats.replies, 2, "one generation per round");
}

#[tokio::test(start_paused = true)]
async fn detaching_the_last_waiter_withdraws_a_queued_round() {
    let f = fixture(Duration::from_secs(10));
    let (busy, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    let (queued, _b) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
    f.driver.detach(&queued).await;
    assert_eq!(f.driver.stats().await.unwrap().cancelled, 1);
    assert!(
        queued.answer.await.is_err(),
        "a detached stream gets no answer"
    );
    // The robot may send the same round again after a withdrawal.
    let (again, _c) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
    f.open(2);
    busy.answer.await.unwrap().unwrap();
    assert_eq!(again.answer.await.unwrap().unwrap().round, 0);
}

#[tokio::test(start_paused = true)]
async fn another_robot_can_neither_advance_nor_read_a_task() {
    let f = fixture(Duration::from_secs(10));
    f.open(1);
    let (own, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    own.answer.await.unwrap().unwrap();
    // Robot 1 re-sends robot 0's finished round: no cached reply for it.
    let (read, _b) = f.submit(1, wire_submit(&f, 1, 0, 1.0, None)).await;
    assert_eq!(
        read.answer.await.unwrap().unwrap_err().code,
        ErrorCode::UnknownTask
    );
    let (advance, _c) = f.submit(1, wire_submit(&f, 1, 1, 1.0, None)).await;
    assert_eq!(
        advance.answer.await.unwrap().unwrap_err().code,
        ErrorCode::UnknownTask
    );
    assert_eq!(f.end(1, 1).await.unwrap_err().code, ErrorCode::UnknownTask);
    assert_eq!(f.end(0, 1).await.unwrap().rounds, 1);
}

#[tokio::test(start_paused = true)]
async fn task_end_returns_the_history_and_later_rounds_are_refused() {
    let f = fixture(Duration::from_secs(10));
    f.open(2);
    let (r0, _a) = f.submit(0, wire_submit(&f, 7, 0, 1.0, None)).await;
    r0.answer.await.unwrap().unwrap();
    // The robot executes for a while on the paused clock before asking again.
    tokio::time::advance(Duration::from_millis(30)).await;
    let exec_start = f.client_now();
    tokio::time::advance(Duration::from_millis(250)).await;
    let exec = LastExecInfo {
        exec_started_at_us: exec_start,
        actions_remaining: 1,
        control_hz: 10.0,
        round: None,
        delay: None,
    };
    let submit1 = wire_submit(&f, 7, 1, 1.0, Some(exec));
    let sent1 = submit1.sent_at_us;
    let (r1, _b) = f.submit(0, submit1).await;
    r1.answer.await.unwrap().unwrap();
    let ended = f.end(0, 7).await.unwrap();
    assert_eq!(ended.rounds, 2);
    assert_eq!(ended.history.len(), 2);
    assert!(ended.history.iter().all(|r| r.generation.is_some()));
    let first_exec = ended.history[0].execution.unwrap();
    assert_eq!(
        first_exec.start_us, exec_start,
        "E_0 maps back to the robot's clock"
    );
    assert_eq!(
        first_exec.end_us - sent1,
        100_000,
        "E_0 ends one action (100 ms at 10 Hz) after round 1 was sent"
    );
    assert!(
        ended.history[1].execution.is_some(),
        "the end report closes E_1"
    );
    let (late, _c) = f.submit(0, wire_submit(&f, 7, 2, 1.0, None)).await;
    assert_eq!(
        late.answer.await.unwrap().unwrap_err().code,
        ErrorCode::UnknownTask
    );
    let snapshot = f.driver.snapshot(TaskId(7)).await.unwrap().unwrap();
    assert!(snapshot.ended);
    assert_eq!(snapshot.history.len(), 2);
    assert_eq!(f.driver.stats().await.unwrap().tasks_ended, 1);
}

#[tokio::test(start_paused = true)]
async fn ending_a_task_answers_its_queued_round() {
    let f = fixture(Duration::from_secs(10));
    let (busy, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    let (queued, _b) = f.submit(0, wire_submit(&f, 2, 0, 2.0, None)).await;
    f.end(0, 2).await.unwrap();
    assert_eq!(
        queued.answer.await.unwrap().unwrap_err().code,
        ErrorCode::UnknownTask,
        "nothing will run the ended task's round: its stream is told at once"
    );
    f.open(1);
    busy.answer.await.unwrap().unwrap();
}

#[tokio::test(start_paused = true)]
async fn an_idle_task_expires_on_the_virtual_clock_and_keeps_its_snapshot() {
    let f = fixture_with(Setup {
        task_idle_timeout: Duration::from_secs(60),
        ..Setup::stale_after(Duration::from_secs(10))
    });
    f.open(1);
    let (round, _a) = f.submit(0, wire_submit(&f, 4, 0, 1.0, None)).await;
    round.answer.await.unwrap().unwrap();
    let open = f.driver.snapshot(TaskId(4)).await.unwrap().unwrap();
    assert!(!open.ended);
    // Nothing else is scheduled: the paused clock jumps to the expiry deadline.
    tokio::time::sleep(Duration::from_secs(61)).await;
    let stats = f.driver.stats().await.unwrap();
    assert_eq!(stats.tasks_ended, 1);
    let ended = f.driver.snapshot(TaskId(4)).await.unwrap().unwrap();
    assert!(ended.ended);
    assert_eq!(ended.history, open.history);
    let (late, _b) = f.submit(0, wire_submit(&f, 4, 1, 1.0, None)).await;
    assert_eq!(
        late.answer.await.unwrap().unwrap_err().code,
        ErrorCode::UnknownTask
    );
}

#[tokio::test(start_paused = true)]
async fn stale_observations_are_refetched_through_the_round_link() {
    let f = fixture(STALE_AFTER);
    // Past the epoch, so an observation can be older than the server's first instant.
    tokio::time::advance(Duration::from_secs(1)).await;
    f.open(3);
    let (fresh, _asks) = f.submit(0, wire_submit(&f, 3, 0, 1.0, None)).await;
    fresh.answer.await.unwrap().unwrap();
    let (round, mut asks) = f.submit(0, stale(wire_submit(&f, 3, 1, 1.0, None))).await;
    let ask = asks.recv().await.unwrap();
    // The robot takes 5 ms (virtual) to answer.
    tokio::time::advance(Duration::from_millis(5)).await;
    f.answer_refetch(ask, 50.0);
    let reply = round.answer.await.unwrap().unwrap();
    // The fresh observation's state[0] is 50, the queued one's 1.
    assert_eq!(reply.actions.to_f32().unwrap()[0], 37.5);
    assert!(reply.timing.refetch_us >= 5_000);
    assert!(reply.timing.refetch_us < 200_000);

    // A client that never answers: the queued observation is used after the deadline.
    let (round, mut asks) = f.submit(0, stale(wire_submit(&f, 3, 2, 1.0, None))).await;
    let _ignored = asks.recv().await.unwrap();
    let reply = round.answer.await.unwrap().unwrap();
    assert!(reply.timing.refetch_us >= 200_000);
    assert_eq!(
        reply.actions.to_f32().unwrap()[0],
        0.75,
        "the queued observation"
    );
    let stats = f.driver.stats().await.unwrap();
    assert_eq!((stats.refetch_asked, stats.refetch_used), (2, 1));
}

#[tokio::test(start_paused = true)]
async fn shutdown_answers_accepted_rounds_and_refuses_new_ones() {
    let f = fixture(Duration::from_secs(10));
    let (running, _a) = f.submit(0, wire_submit(&f, 1, 0, 1.0, None)).await;
    let (queued, _b) = f.submit(0, wire_submit(&f, 2, 0, 1.0, None)).await;
    // A round trip through the driver: both rounds are accepted before the shutdown.
    assert_eq!(f.driver.stats().await.unwrap().accepted, 2);
    f.stop.send(true).unwrap();
    let (late, _c) = f.submit(0, wire_submit(&f, 3, 0, 1.0, None)).await;
    assert_eq!(
        late.answer.await.unwrap().unwrap_err().code,
        ErrorCode::ShuttingDown
    );
    f.open(2);
    assert!(running.answer.await.unwrap().is_ok());
    assert!(queued.answer.await.unwrap().is_ok());
    let stats = f.join.await.unwrap();
    assert_eq!(stats.replies, 2);
    assert_eq!(stats.overhead.count, 2);
    assert!(stats.overhead.p50_us <= stats.overhead.p99_us);
    assert!(stats.processing.max_us <= stats.overhead.max_us);
}

/// A horizon policy that announces it was entered, then blocks its thread until released.
struct Blocker {
    entered: mpsc::UnboundedSender<()>,
    release: Arc<Mutex<std::sync::mpsc::Receiver<()>>>,
}

impl HorizonPolicy for Blocker {
    fn name(&self) -> &str {
        "blocker"
    }
    fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let _ = self.entered.send(());
        let release = self
            .release
            .lock()
            .map_err(|_| HorizonError::Failed("release lock poisoned".into()))?;
        release
            .recv()
            .map_err(|_| HorizonError::Failed("never released".into()))?;
        Ok(1)
    }
}

/// Issue #11 §2. A horizon policy blocks its round; the runtime has a single thread. While it
/// blocks, another robot's rounds are accepted, its stale observation is re-fetched through its
/// stream and its rounds complete, on the same (single) engine instance. Released, the blocked
/// round completes too. Before the fix the policy ran on the runtime's only thread and the
/// driver stalled: the watchdog below turns that hang into a failure (it never fires when the
/// driver works; nothing here waits on wall-clock time otherwise).
#[test]
fn slow_policy_does_not_stall_the_driver() {
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .start_paused(true)
            .build()
            .unwrap();
        runtime.block_on(slow_policy_scenario());
        let _ = done_tx.send(());
    });
    match done_rx.recv_timeout(Duration::from_secs(120)) {
        Ok(()) => {}
        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
            panic!("the scenario failed (see its panic above)")
        }
        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {
            panic!("the driver stalled while a horizon policy blocked")
        }
    }
}

async fn slow_policy_scenario() {
    let (entered_tx, mut entered) = mpsc::unbounded_channel();
    let (release, release_rx) = std::sync::mpsc::channel::<()>();
    let release_rx = Arc::new(Mutex::new(release_rx));
    let mut horizon = HorizonRegistry::new();
    horizon.register("blocker", move |_| {
        Ok(Box::new(Blocker {
            entered: entered_tx.clone(),
            release: release_rx.clone(),
        }) as Box<dyn HorizonPolicy>)
    });
    let f = fixture_with(Setup {
        horizon,
        ..Setup::stale_after(STALE_AFTER)
    });
    tokio::time::advance(Duration::from_secs(1)).await;
    f.open(16);

    // Robot 0's round picks the blocking policy.
    let mut blocked_submit = wire_submit(&f, 1, 0, 1.0, None);
    blocked_submit.horizon = Some(HorizonSelection {
        policy: "blocker".into(),
        params: Default::default(),
        samples: 1,
    });
    let (blocked, mut blocked_asks) = f.submit(0, stale(blocked_submit)).await;
    f.answer_refetch(blocked_asks.recv().await.unwrap(), 1.0);
    entered.recv().await.unwrap();

    // Robot 1: two rounds with stale observations, each re-fetched through its stream and
    // answered, while robot 0's policy blocks.
    for round in 0..2 {
        let (pending, mut asks) = f
            .submit(1, stale(wire_submit(&f, 2, round, 1.0, None)))
            .await;
        let ask = asks.recv().await.expect("a FetchObservation for robot 1");
        f.answer_refetch(ask, 40.0 + round as f32);
        let reply = pending.answer.await.unwrap().unwrap();
        assert_eq!(
            (reply.task, reply.round, reply.policy.as_str()),
            (2, round, "static")
        );
        let first_action = reply.actions.to_f32().unwrap()[0];
        assert_eq!(
            first_action,
            0.75 * (40.0 + round as f32),
            "the fresh observation"
        );
    }
    let stats = f.driver.stats().await.unwrap();
    assert_eq!((stats.replies, stats.refetch_used), (2, 3));
    let waiting = f.driver.snapshot(TaskId(1)).await.unwrap().unwrap();
    assert_eq!(
        waiting.rounds_completed, 0,
        "robot 0's round is still blocked"
    );

    release.send(()).unwrap();
    let reply = blocked.answer.await.unwrap().unwrap();
    assert_eq!(
        (reply.task, reply.horizon, reply.policy.as_str()),
        (1, 1, "blocker")
    );
    let done = f.driver.snapshot(TaskId(1)).await.unwrap().unwrap();
    assert_eq!(done.rounds_completed, 1);
}
