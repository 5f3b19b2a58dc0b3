//! Chunking strategies over real QUIC: two robots of one server ask for different strategies in
//! the same rounds, and each gets exactly the chunk its strategy makes (recomputed in-process
//! from the server's own start index), with the server's predicted `d` and start in the reply.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::sync::Arc;

use kairos_bench::horizon_bench::env::{ACTION_DIM, Env, EnvConfig, OBS_DIM};
use kairos_bench::horizon_bench::model::{FlowPolicy, ModelConfig, SavedConfig, TrainConfig};
use kairos_bench::horizon_bench::served::HorizonFlowModel;
use kairos_sdk::client::{NoRefetch, RoundRequest, Task};
use kairos_sdk::protocol::{
    ChunkingSelection, ChunkingStrategy, HorizonSelection, LastExecInfo, Observation, Reply,
    TaskOutcome, Tensor,
};
use kairos_tests::harness::{ServerOptions, TestServer};

/// A tiny policy saved to `dir` (random weights: what matters is that server and test sample
/// with the same ones).
fn tiny_policy(dir: &std::path::Path) {
    let model = ModelConfig {
        chunk_len: 16,
        hidden: 16,
        depth: 2,
        steps: 4,
    };
    let policy = FlowPolicy::new(model.clone()).unwrap();
    let saved = SavedConfig {
        train: TrainConfig {
            model,
            ..TrainConfig::default()
        },
        pairs: 0,
        final_loss: 0.0,
        kairos_version: "test".into(),
    };
    policy.save(dir, &saved).unwrap();
}

/// The robots' control rate: ticks 200 ms apart, far more than any gap between an
/// observation's capture and its round's send.
const HZ: f32 = 5.0;
const TICK_US: u64 = 200_000;

fn request(
    captured_at_us: u64,
    obs: &[f32; OBS_DIM],
    seed: u64,
    last_exec: Option<LastExecInfo>,
    chunking: Option<ChunkingSelection>,
) -> RoundRequest {
    RoundRequest {
        observation: Observation {
            captured_at_us,
            state: Tensor::from_f32(vec![OBS_DIM as u32], obs).unwrap(),
            images: Vec::new(),
            instruction: String::new(),
        },
        last_exec,
        // The whole chunk, so the test sees every action the strategy made.
        horizon: Some(HorizonSelection {
            policy: "static".into(),
            params: [("h".to_string(), 16.0)].into(),
            samples: 1,
        }),
        remaining: None,
        control_hz: Some(HZ),
        seed: Some(seed),
        chunking,
    }
}

async fn round(task: &mut Task, request: RoundRequest) -> Reply {
    task.submit(request, &mut NoRefetch).await.unwrap().reply
}

/// The robot has executed `executed` actions of `reply` since it started it at `started_us`.
fn exec_of(reply: &Reply, started_us: u64, executed: u32) -> LastExecInfo {
    LastExecInfo {
        exec_started_at_us: started_us,
        actions_remaining: reply.horizon - executed,
        control_hz: HZ,
        round: Some(reply.round),
        delay: Some(0),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_robots_with_different_strategies_each_get_what_they_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    tiny_policy(dir.path());
    let served = HorizonFlowModel::load(dir.path()).unwrap();
    let (policy, _) = FlowPolicy::load(dir.path()).unwrap();
    let server = TestServer::start_with_model(ServerOptions::default(), Arc::new(served))
        .await
        .unwrap();
    let (a, b) = (
        server.connect(&server.token).await.unwrap(),
        server.connect(&server.token).await.unwrap(),
    );
    let (mut task_a, mut task_b) = (a.task(1), b.task(2));
    let env_a = Env::new(EnvConfig::default(), 3);
    let env_b = Env::new(EnvConfig::default(), 4);
    let (obs_a, obs_b) = (env_a.observe(), env_b.observe());

    // Round 0: nothing committed yet, both plain.
    let (first_a, first_b) = tokio::join!(
        round(&mut task_a, request(a.now_us(), &obs_a, 10, None, None)),
        round(&mut task_b, request(b.now_us(), &obs_b, 20, None, None)),
    );
    // The server's default; with nothing committed it plans from the observation as is.
    assert_eq!(
        first_a.chunking.as_deref(),
        Some(
            kairos_core::chunking::ChunkingDefaults::default()
                .strategy
                .as_str()
        )
    );
    assert_eq!((first_a.start, first_b.start), (Some(0), Some(0)));
    assert_eq!(
        first_a.actions.to_f32().unwrap(),
        policy.sample(&obs_a, 1, 10).unwrap().sample_actions(0)
    );

    // Round 1: A asks for rtc, B for arrival_state with its own forecast. Each observation was
    // captured `AGE_US` before it is sent. Each robot started its first chunk at a tick one
    // period less a millisecond before the capture; its next tick falls a millisecond after the
    // capture, before the round is even sent: 2 actions executed at the send, 14 left, and the
    // 15 from the capture on are committed. So at least one of them is executed before any
    // reply can arrive (d >= 1, whatever the machine's load).
    const AGE_US: u64 = 20_000;
    // (The clients' clocks start at their connection: wait until that tick exists on both.)
    while a.now_us() <= TICK_US + AGE_US || b.now_us() <= TICK_US + AGE_US {
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    let (capture_a, capture_b) = (a.now_us() - AGE_US, b.now_us() - AGE_US);
    let exec_a = exec_of(&first_a, capture_a - TICK_US + 1_000, 2);
    let exec_b = exec_of(&first_b, capture_b - TICK_US + 1_000, 2);
    let committed_b = &first_b.actions.to_f32().unwrap()[ACTION_DIM..];
    let forecast: Vec<Vec<f32>> =
        kairos_bench::chunking_bench::episode::forecast(&env_b, committed_b);
    let selection_b = ChunkingSelection {
        forecast: Some(
            Tensor::from_f32(
                vec![forecast.len() as u32, OBS_DIM as u32],
                &forecast.concat(),
            )
            .unwrap(),
        ),
        ..ChunkingSelection::new(ChunkingStrategy::ArrivalState)
    };
    let (second_a, second_b) = tokio::join!(
        round(
            &mut task_a,
            request(
                capture_a,
                &obs_a,
                11,
                Some(exec_a),
                Some(ChunkingSelection::new(ChunkingStrategy::Rtc))
            )
        ),
        round(
            &mut task_b,
            request(capture_b, &obs_b, 21, Some(exec_b), Some(selection_b))
        ),
    );

    // A: LeRobot's guidance toward the 15 actions committed from the capture on, with the server's
    // start index as the inference delay; the chunk is the model's, bit for bit.
    assert_eq!(second_a.chunking.as_deref(), Some("rtc"));
    let start_a = second_a.start.unwrap() as usize;
    assert!(
        start_a >= 1 && second_a.delay.unwrap() as usize >= start_a,
        "start {:?}, delay {:?}, b: {:?} {:?}",
        second_a.start,
        second_a.delay,
        second_b.start,
        second_b.delay
    );
    let prefix_a = first_a.actions.to_f32().unwrap()[ACTION_DIM..].to_vec();
    let guidance = kairos_engine::Guidance {
        mode: kairos_engine::GuidanceMode::Rtc,
        prefix: prefix_a,
        delay: start_a,
        execution_horizon: 10,
        schedule: kairos_engine::PrefixSchedule::Linear,
        max_guidance_weight: 10.0,
    };
    let expected_a = policy
        .sample_guided(&obs_a, 1, 11, Some(&guidance))
        .unwrap();
    assert_eq!(
        second_a.actions.to_f32().unwrap(),
        expected_a.sample_actions(0)
    );
    assert_ne!(
        second_a.actions.to_f32().unwrap(),
        policy.sample(&obs_a, 1, 11).unwrap().sample_actions(0),
        "guidance changed the chunk"
    );

    // B: the committed actions first, then the chunk planned from its forecast after them.
    assert_eq!(second_b.chunking.as_deref(), Some("arrival_state"));
    let start_b = second_b.start.unwrap() as usize;
    assert!(start_b >= 1);
    let got_b = second_b.actions.to_f32().unwrap();
    assert_eq!(
        &got_b[..start_b * ACTION_DIM],
        &committed_b[..start_b * ACTION_DIM]
    );
    let from_state: [f32; OBS_DIM] = forecast[start_b - 1].as_slice().try_into().unwrap();
    let planned = policy.sample(&from_state, 1, 21).unwrap();
    let keep = 16 - start_b;
    assert_eq!(
        &got_b[start_b * ACTION_DIM..],
        &planned.sample_actions(0)[..keep * ACTION_DIM]
    );
    assert_eq!(
        second_b.horizon as usize, 16,
        "committed + the chunk, cut to N"
    );

    // The robots' next rounds tell the server the actual d; it scores its predictions.
    let mut third = exec_of(&second_a, a.now_us(), 0);
    third.delay = Some(second_a.delay.unwrap());
    round(
        &mut task_a,
        request(a.now_us(), &obs_a, 12, Some(third), None),
    )
    .await;
    let snapshot = server
        .server()
        .driver
        .snapshot(kairos_core::scheduler::TaskId(1))
        .await
        .unwrap()
        .unwrap();
    assert_eq!(snapshot.delay_errors.rounds, 2);
    assert_eq!(
        snapshot.delay_errors.max_abs_error, 0,
        "told exactly what it predicted"
    );
    task_a.end(TaskOutcome::Done, None).await.unwrap();
    task_b.end(TaskOutcome::Done, None).await.unwrap();
    server.shutdown().await;
}

/// A strategy the model cannot apply is refused before the round is queued, saying why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_strategy_the_model_cannot_apply_is_refused_with_the_reason() {
    // The test flow model does not sample with the shared sampler: no guidance.
    let server = TestServer::start(ServerOptions::default()).await.unwrap();
    let client = server.connect(&server.token).await.unwrap();
    let mut task = client.task(9);
    let state = Tensor::from_f32(vec![6], &[0.0; 6]).unwrap();
    let mut request = RoundRequest::new(Observation {
        captured_at_us: client.now_us(),
        state,
        images: Vec::new(),
        instruction: String::new(),
    });
    request.chunking = Some(ChunkingSelection::new(ChunkingStrategy::Inpaint));
    let error = task
        .submit(request, &mut NoRefetch)
        .await
        .expect_err("refused");
    let text = error.to_string();
    assert!(
        text.contains("invalid_request")
            && text.contains("chunking.strategy")
            && text.contains("inpaint"),
        "{text}"
    );
    server.shutdown().await;
}
