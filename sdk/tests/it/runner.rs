//! The robot runner's trigger, alignment and idle accounting, in virtual time against a
//! scripted round transport, and once for real against the QUIC responder.

#![allow(clippy::unwrap_used)] // helpers outside #[test] fns

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::support::{Behavior, Responder};
use kairos_sdk::client::{
    Client, ClientConfig, ClientError, Clock, ObservationSource, RoundReply, RoundRequest,
};
use kairos_sdk::protocol::{
    ErrorCode, ErrorReply, FetchObservation, LastExecInfo, Observation, Reply, TaskEnded,
    TaskOutcome, Tensor, Timing,
};
use kairos_sdk::robot::{
    Robot, RobotError, RobotRunner, RoundTransport, RunnerConfig, RunnerError, RunnerEvent,
    SimulatedRobot,
};

/// What the scripted server saw of one request.
#[derive(Clone, Debug, PartialEq)]
struct Seen {
    round: u64,
    sent_at_ms: u64,
    last_exec: Option<LastExecInfo>,
}

/// A round transport in virtual time: each round takes `latency`, returns `horizon` actions
/// whose values are `[round, index]`; it can re-fetch the observation halfway, or fail a round.
struct Scripted {
    clock: Clock,
    next_round: u64,
    latency: Duration,
    horizon: u32,
    refetch_round: Option<u64>,
    fail: HashMap<u64, ErrorCode>,
    seen: Arc<Mutex<Vec<Seen>>>,
    ended: Arc<Mutex<Option<TaskOutcome>>>,
    /// `EndTask` answers this error (a restarted server that forgot the task).
    end_error: Option<ErrorCode>,
}

impl Scripted {
    fn new(latency_ms: u64, horizon: u32) -> Scripted {
        Scripted {
            clock: Clock::start(),
            next_round: 0,
            latency: Duration::from_millis(latency_ms),
            horizon,
            refetch_round: None,
            fail: HashMap::new(),
            seen: Arc::default(),
            ended: Arc::default(),
            end_error: None,
        }
    }
}

impl RoundTransport for Scripted {
    fn task_id(&self) -> u64 {
        1
    }

    fn next_round(&self) -> u64 {
        self.next_round
    }

    fn clock(&self) -> Clock {
        self.clock
    }

    async fn submit<S: ObservationSource>(
        &mut self,
        request: RoundRequest,
        source: &mut S,
    ) -> Result<RoundReply, ClientError> {
        let round = self.next_round;
        self.next_round += 1;
        let sent_at_us = self.clock.now_us();
        self.seen.lock().unwrap().push(Seen {
            round,
            sent_at_ms: sent_at_us / 1000,
            last_exec: request.last_exec,
        });
        let mut refetches = 0;
        let mut captured = request.observation.captured_at_us;
        if self.refetch_round == Some(round) {
            tokio::time::sleep(self.latency / 2).await;
            let fetch = FetchObservation {
                task: 1,
                round,
                age_us: 0,
            };
            let fresh = source.fresh_observation(&fetch).await.unwrap();
            captured = fresh.captured_at_us;
            refetches = 1;
            tokio::time::sleep(self.latency / 2).await;
        } else {
            tokio::time::sleep(self.latency).await;
        }
        if let Some(code) = self.fail.remove(&round) {
            let mut error = ErrorReply::new(code, "scripted failure");
            error.retry_after_ms = Some(50);
            return Err(ClientError::Server(error));
        }
        let values: Vec<f32> = (0..self.horizon)
            .flat_map(|i| [round as f32, i as f32])
            .collect();
        Ok(RoundReply {
            reply: Reply {
                task: 1,
                round,
                horizon: self.horizon,
                chunk_len: self.horizon,
                actions: Tensor::from_f32(vec![self.horizon, 2], &values).unwrap(),
                policy: "static".to_owned(),
                timing: Timing::default(),
                start: None,
                delay: None,
                chunking: None,
            },
            sent_at_us,
            received_at_us: self.clock.now_us(),
            attempts: 1,
            refetches,
            observation_captured_at_us: captured,
        })
    }

    async fn end(
        self,
        outcome: TaskOutcome,
        _last_exec: Option<LastExecInfo>,
    ) -> Result<TaskEnded, ClientError> {
        *self.ended.lock().unwrap() = Some(outcome);
        if let Some(code) = self.end_error {
            return Err(ClientError::Server(ErrorReply::new(
                code,
                "task 1 is not open",
            )));
        }
        Ok(TaskEnded {
            task: 1,
            rounds: self.next_round as u32,
            wait_us: 0,
            attained_service_us: 0,
            history: vec![],
        })
    }
}

/// Records when each action executed and what it was.
struct Recorder {
    clock: Clock,
    inner: SimulatedRobot,
    executed: Vec<(u64, u64, u64)>,
}

impl Recorder {
    fn new(clock: Clock) -> Recorder {
        Recorder {
            clock,
            inner: SimulatedRobot::new(2, 0, 0, 0),
            executed: Vec::new(),
        }
    }

    /// (time ms, round, index) of every executed action.
    fn log(&self) -> &[(u64, u64, u64)] {
        &self.executed
    }
}

impl Robot for Recorder {
    async fn get_obs(&mut self, now_us: u64) -> Result<Observation, RobotError> {
        self.inner.get_obs(now_us).await
    }

    async fn send_act(&mut self, action: &[f32]) -> Result<(), RobotError> {
        self.executed.push((
            self.clock.now_us() / 1000,
            action[0] as u64,
            action[1] as u64,
        ));
        self.inner.send_act(action).await
    }
}

fn runner(trigger: f32, rounds: u64) -> RobotRunner {
    RobotRunner::new(RunnerConfig {
        control_hz: 10.0,
        trigger,
        rounds,
        ..RunnerConfig::default()
    })
}

#[tokio::test(start_paused = true)]
async fn async_inference_triggers_at_half_and_aligns_chunks() {
    let transport = Scripted::new(350, 10);
    let seen = transport.seen.clone();
    let mut robot = Recorder::new(transport.clock);
    let mut events = Vec::new();
    let summary = runner(0.5, 3)
        .run(&mut robot, transport, |event| events.push(event.clone()))
        .await
        .unwrap();

    let info = |started_ms: u64, remaining: u32, round: u64, delay: u32| {
        Some(LastExecInfo {
            exec_started_at_us: started_ms * 1000,
            actions_remaining: remaining,
            control_hz: 10.0,
            round: Some(round),
            delay: Some(delay),
        })
    };
    assert_eq!(
        *seen.lock().unwrap(),
        [
            Seen {
                round: 0,
                sent_at_ms: 0,
                last_exec: None
            },
            // 5 of round 0's 10 actions executed (350..750 ms); the robot was idle while
            // round 0 was generated, so its actual d was 0.
            Seen {
                round: 1,
                sent_at_ms: 750,
                last_exec: info(350, 5, 0, 0)
            },
            // Round 1 started at 1150 with 7 executable; 4 of them done. Its actual d: the 3
            // actions executed while it was generated.
            Seen {
                round: 2,
                sent_at_ms: 1450,
                last_exec: info(1150, 3, 1, 3)
            },
        ]
    );
    // Round 1 arrived at 1100 after 3 actions (850, 950, 1050) used its first 3 slots.
    let expected: Vec<(u64, u64, u64)> = (0..8)
        .map(|i| (0, i))
        .chain((3..10).map(|i| (1, i)))
        .chain((3..10).map(|i| (2, i)))
        .enumerate()
        .map(|(n, (round, index))| (350 + 100 * n as u64, round, index))
        .collect();
    assert_eq!(robot.log(), expected);

    let per_round: Vec<(u64, u32, u32)> = summary
        .rounds
        .iter()
        .map(|r| (r.round, r.discarded, r.executed))
        .collect();
    assert_eq!(per_round, [(0, 0, 8), (1, 3, 7), (2, 3, 7)]);
    assert_eq!(summary.actions_executed, 22);
    assert_eq!(summary.idle_us, 350_000, "idle only before the first chunk");
    assert_eq!(summary.latency_us(), 2_450_000);
    assert_eq!(summary.rounds[1].latency_us(), 350_000);
    assert!(events.contains(&RunnerEvent::ChunkEnded {
        task: 1,
        round: 0,
        executed: 8,
        dropped: 2
    }));
    assert!(matches!(events.last(), Some(RunnerEvent::TaskFinished(_))));
    let mut ended: Vec<u64> = events
        .iter()
        .filter_map(|event| match event {
            RunnerEvent::ChunkEnded { round, .. } => Some(*round),
            _ => None,
        })
        .collect();
    ended.sort_unstable();
    assert_eq!(ended, [0, 1, 2], "each chunk ends exactly once");
}

#[tokio::test(start_paused = true)]
async fn synchronous_inference_idles_through_every_generation() {
    let transport = Scripted::new(250, 4);
    let seen = transport.seen.clone();
    let mut robot = Recorder::new(transport.clock);
    let mut ended = Vec::new();
    let summary = runner(1.0, 3)
        .run(&mut robot, transport, |event| {
            if let RunnerEvent::ChunkEnded {
                round,
                executed,
                dropped,
                ..
            } = event
            {
                ended.push((*round, *executed, *dropped));
            }
        })
        .await
        .unwrap();
    // Chunks that ran out end once, when their last action starts, not again when replaced.
    assert_eq!(ended, [(0, 4, 0), (1, 4, 0), (2, 4, 0)]);
    let sent: Vec<u64> = seen.lock().unwrap().iter().map(|s| s.sent_at_ms).collect();
    // Each round: 250 ms generation, then 4 actions at 100 ms; the request follows the last.
    assert_eq!(sent, [0, 550, 1100]);
    assert!(
        summary
            .rounds
            .iter()
            .all(|r| r.discarded == 0 && r.executed == 4)
    );
    // Idle: 250 ms before the first chunk, then from each due-but-missing action (650, 1200)
    // to the next chunk (800, 1350).
    assert_eq!(summary.idle_us, 250_000 + 2 * 150_000);
    assert_eq!(robot.log().first(), Some(&(250, 0, 0)));
    assert_eq!(robot.log().last(), Some(&(1650, 2, 3)));
}

/// A recorder whose task is finished after `goal` actions.
struct GoalRobot {
    inner: Recorder,
    goal: usize,
}

impl Robot for GoalRobot {
    async fn get_obs(&mut self, now_us: u64) -> Result<Observation, RobotError> {
        self.inner.get_obs(now_us).await
    }

    async fn send_act(&mut self, action: &[f32]) -> Result<(), RobotError> {
        self.inner.send_act(action).await
    }

    fn task_done(&self) -> bool {
        self.inner.log().len() >= self.goal
    }
}

#[tokio::test(start_paused = true)]
async fn a_finished_task_executes_no_action_past_its_goal() {
    // Chunks of 10 at 10 Hz, 350 ms generation, trigger 0.5: the goal (12 actions) is reached
    // inside round 1's chunk; its rest is dropped, not executed.
    let transport = Scripted::new(350, 10);
    let seen = transport.seen.clone();
    let mut robot = GoalRobot {
        inner: Recorder::new(transport.clock),
        goal: 12,
    };
    let mut events = Vec::new();
    let summary = runner(0.5, u64::MAX)
        .run(&mut robot, transport, |event| events.push(event.clone()))
        .await
        .unwrap();
    assert_eq!(robot.inner.log().len(), 12);
    assert_eq!(summary.actions_executed, 12);
    // Actions at 350, 450, ..., 1450 ms: the task ends at its 12th action.
    assert_eq!(summary.latency_us(), 1_450_000);
    // Round 1 (7 executable after 3 discarded) would trigger at its 4th action, the 12th of the
    // task: the goal is reached first, so no round 2 is sent.
    assert_eq!(seen.lock().unwrap().len(), 2);
    assert_eq!(summary.rounds.len(), 2);
    assert!(events.contains(&RunnerEvent::ChunkEnded {
        task: 1,
        round: 1,
        executed: 4,
        dropped: 3
    }));
}

#[tokio::test(start_paused = true)]
async fn a_refused_end_task_is_reported_in_the_summary() {
    let run = |end_error| async move {
        let mut transport = Scripted::new(100, 10);
        transport.end_error = end_error;
        let ended = transport.ended.clone();
        let mut robot = Recorder::new(transport.clock);
        let summary = runner(0.5, 2)
            .run(&mut robot, transport, |_| {})
            .await
            .unwrap();
        assert_eq!(*ended.lock().unwrap(), Some(TaskOutcome::Done));
        summary
    };
    let acknowledged = run(None).await;
    assert!(acknowledged.server_record.is_some());
    assert_eq!(acknowledged.end_error, None);
    let refused = run(Some(ErrorCode::UnknownTask)).await;
    assert!(refused.server_record.is_none());
    let error = refused.end_error.unwrap();
    assert!(error.contains("unknown_task"), "{error}");
}

#[tokio::test(start_paused = true)]
async fn a_refetched_observation_moves_the_alignment_point() {
    let mut transport = Scripted::new(420, 10);
    transport.refetch_round = Some(1);
    let mut robot = Recorder::new(transport.clock);
    let mut refetched = Vec::new();
    let summary = runner(0.5, 2)
        .run(&mut robot, transport, |event| {
            if let RunnerEvent::ObservationRefetched {
                round,
                at_us,
                actions_executed,
                ..
            } = event
            {
                refetched.push((*round, *at_us / 1000, *actions_executed));
            }
        })
        .await
        .unwrap();
    // Round 1 is sent at 820 ms (5 actions after 420); re-fetched at 1030 ms, after the actions
    // at 920 and 1020; it arrives at 1240 after those at 1120 and 1220: 2 slots used since the
    // re-fetch, not 4.
    // 5 actions before the request, 2 more before the re-fetch.
    assert_eq!(refetched, [(1, 1030, 7)]);
    assert_eq!(summary.rounds[1].discarded, 2);
    assert_eq!(summary.rounds[1].refetches, 1);
}

#[tokio::test(start_paused = true)]
async fn a_retryable_failure_requests_again_with_a_new_round() {
    let mut transport = Scripted::new(100, 4);
    transport.fail.insert(1, ErrorCode::Overloaded);
    let seen = transport.seen.clone();
    let mut robot = Recorder::new(transport.clock);
    let summary = runner(0.5, 3)
        .run(&mut robot, transport, |_| {})
        .await
        .unwrap();
    let rounds: Vec<u64> = summary.rounds.iter().map(|r| r.round).collect();
    assert_eq!(rounds, [0, 2, 3]);
    assert_eq!(summary.failed_rounds, 1);
    let seen = seen.lock().unwrap();
    assert_eq!(seen.len(), 4);
    // The retry waited for the server's retry_after (50 ms) after the failure at 300 ms.
    assert_eq!(seen[2].sent_at_ms, 350);
}

#[tokio::test(start_paused = true)]
async fn a_fatal_failure_ends_the_task_as_failed() {
    let mut transport = Scripted::new(100, 4);
    transport.fail.insert(1, ErrorCode::InvalidObservation);
    let ended = transport.ended.clone();
    let mut robot = Recorder::new(transport.clock);
    let error = runner(0.5, 3)
        .run(&mut robot, transport, |_| {})
        .await
        .unwrap_err();
    assert!(
        matches!(error, RunnerError::Round { round: 1, .. }),
        "{error:?}"
    );
    assert_eq!(*ended.lock().unwrap(), Some(TaskOutcome::Failed));
}

#[tokio::test]
async fn simulated_robot_runs_a_task_over_quic() {
    let responder = Responder::start(Behavior {
        horizon: 5,
        chunk_len: 10,
        action_dim: 2,
        generation: Duration::from_millis(20),
        ..Behavior::default()
    });
    let config = ClientConfig::pinned(responder.addr, responder.fingerprint, "secret");
    let client = Client::connect(config).await.unwrap();
    let mut robot = SimulatedRobot::new(2, 1, 8, 8);
    let summary = RobotRunner::new(RunnerConfig {
        control_hz: 100.0,
        rounds: 4,
        ..RunnerConfig::default()
    })
    .run(&mut robot, client.task(11), |_| {})
    .await
    .unwrap();
    assert_eq!(summary.rounds.len(), 4);
    assert_eq!(robot.executed(), summary.actions_executed);
    let executed: u64 = summary.rounds.iter().map(|r| u64::from(r.executed)).sum();
    assert_eq!(executed, summary.actions_executed);
    assert_eq!(summary.server_record.as_ref().unwrap().rounds, 4);
    let seen = responder.seen();
    let rounds: Vec<u64> = seen.submits.iter().map(|s| s.1).collect();
    assert_eq!(rounds, [0, 1, 2, 3]);
    // Every request after the first reported the chunk being executed at 100 Hz.
    assert_eq!(seen.last_exec.len(), 3);
    assert!(
        seen.last_exec
            .iter()
            .all(|(_, info)| info.control_hz == 100.0)
    );
    assert_eq!(seen.ended, [(11, TaskOutcome::Done)]);
}
