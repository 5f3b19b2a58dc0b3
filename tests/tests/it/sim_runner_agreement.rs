//! The simulator's robots follow the SDK runner's execution rules: a task run by the real
//! `RobotRunner` (virtual time, a scripted server with a fixed generation latency) and recorded
//! with `RunnerTraceRecorder`, then replayed alone in the simulator against an engine with that
//! latency, comes back with the same rounds and the same end-to-end latency.

#![allow(clippy::unwrap_used)] // helpers outside #[test] fns

use std::collections::BTreeMap;
use std::time::Duration;

use kairos_bench::sim::{Load, SimConfig, SimNetwork, simulate};
use kairos_core::scheduler::{EngineSpec, SchedulerConfig, Tier};
use kairos_core::time::Timestamp;
use kairos_engine::{EngineProfile, ProfilePoint};
use kairos_sdk::client::{ClientError, Clock, ObservationSource, RoundReply, RoundRequest};
use kairos_sdk::protocol::{LastExecInfo, Reply, TaskEnded, TaskOutcome, Tensor, Timing};
use kairos_sdk::robot::{RobotRunner, RoundTransport, RunnerConfig, SimulatedRobot};
use kairos_sdk::trace::{HorizonSetting, RecordSetup, RunnerTraceRecorder, TraceSet};

const HZ: f32 = 10.0;
const TASK: u64 = 9;

/// Answers every round after `latency` with `horizon` actions, in virtual time.
struct Scripted {
    clock: Clock,
    next_round: u64,
    latency: Duration,
    horizon: u32,
}

impl RoundTransport for Scripted {
    fn task_id(&self) -> u64 {
        TASK
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
        _source: &mut S,
    ) -> Result<RoundReply, ClientError> {
        let round = self.next_round;
        self.next_round += 1;
        let sent_at_us = self.clock.now_us();
        tokio::time::sleep(self.latency).await;
        let values = vec![0.0f32; self.horizon as usize * 2];
        Ok(RoundReply {
            reply: Reply {
                task: TASK,
                round,
                horizon: self.horizon,
                chunk_len: self.horizon,
                actions: Tensor::from_f32(vec![self.horizon, 2], &values).unwrap(),
                policy: "static".to_owned(),
                timing: Timing {
                    inference_us: self.latency.as_micros() as u64,
                    ..Timing::default()
                },
                start: None,
                delay: None,
                chunking: None,
            },
            sent_at_us,
            received_at_us: self.clock.now_us(),
            attempts: 1,
            refetches: 0,
            observation_captured_at_us: request.observation.captured_at_us,
        })
    }

    async fn end(
        self,
        _outcome: TaskOutcome,
        _last_exec: Option<LastExecInfo>,
    ) -> Result<TaskEnded, ClientError> {
        Ok(TaskEnded {
            task: TASK,
            rounds: self.next_round as u32,
            wait_us: 0,
            attained_service_us: 0,
            history: vec![],
        })
    }
}

fn engine(latency_ms: f64) -> EngineSpec {
    let point = |batch| ProfilePoint { batch, latency_ms };
    EngineSpec {
        name: "edge".into(),
        tier: Tier::Edge,
        profile: EngineProfile {
            model: "scripted".into(),
            device: "virtual".into(),
            points: vec![point(1), point(8)],
            max_batch: 8,
        },
        rtt: Duration::ZERO,
    }
}

async fn agree(latency_ms: u64, horizon: u32, trigger: f32, rounds: u64) {
    let transport = Scripted {
        clock: Clock::start(),
        next_round: 0,
        latency: Duration::from_millis(latency_ms),
        horizon,
    };
    let mut recorder = RunnerTraceRecorder::new(
        Vec::new(),
        RecordSetup {
            setting: "static".into(),
            horizon: HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), f64::from(horizon))]),
            },
            control_hz: HZ,
            obs_bytes: 0,
        },
    )
    .unwrap();
    let mut robot = SimulatedRobot::new(2, 0, 0, 0);
    let runner = RobotRunner::new(RunnerConfig {
        control_hz: HZ,
        trigger,
        rounds,
        ..RunnerConfig::default()
    });
    let summary = runner
        .run(&mut robot, transport, |event| {
            recorder.on_event(event).unwrap()
        })
        .await
        .unwrap();
    let live = TraceSet::read(recorder.finish().unwrap().as_slice()).unwrap();
    let recorded = &live.tasks[0];
    assert_eq!(recorded.rounds.len() as u64, rounds);
    for (r, s) in recorded.rounds.iter().zip(&summary.rounds) {
        assert_eq!((r.horizon, r.executed), (s.horizon, s.executed));
    }

    let sim = simulate(
        &live,
        &SimConfig {
            engines: vec![engine(latency_ms as f64)],
            scheduler: SchedulerConfig::default(),
            policy: "fifo".parse().unwrap(),
            setting: "static".into(),
            network: SimNetwork {
                robot_rtt: Duration::ZERO,
                robot_uplink_mbps: 1000.0,
                wan_mbps: 1000.0,
            },
            hints: false,
            load: Load::Explicit(vec![(Timestamp::ZERO, TASK)]),
            seed: 1,
            record: true,
            policies: Default::default(),
            replay_horizon: None,
        },
    )
    .unwrap();
    let replayed = &sim.recorded[0];
    let key = |t: &kairos_sdk::trace::TaskTrace| {
        t.rounds
            .iter()
            .map(|r| (r.issued_at_action, r.horizon, r.executed, r.round_trip_us))
            .collect::<Vec<_>>()
    };
    assert_eq!(
        key(replayed),
        key(recorded),
        "latency {latency_ms} ms, H {horizon}"
    );
    let sim_latency_us = (sim.tasks[0].latency_s * 1e6).round() as u64;
    assert_eq!(sim_latency_us, summary.latency_us(), "end-to-end latency");
}

#[tokio::test(start_paused = true)]
async fn a_runner_recording_replays_identically_in_the_simulator() {
    // Asynchronous inference: the next request after half the chunk; replies land between ticks
    // with chunks partly overlapping (discards) ...
    agree(350, 10, 0.5, 5).await;
    // ... replies slower than the lead time (the robot idles, chunks start at once) ...
    agree(730, 8, 0.5, 4).await;
    // ... and synchronous inference.
    agree(120, 6, 1.0, 3).await;
}
