//! End to end over real QUIC on loopback: one server, 20 concurrent robots, each running a
//! multi-round task with asynchronous inference. Every round is answered exactly once, and the
//! G/E records the server keeps match what each robot did.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;

use kairos_sdk::protocol::HorizonSelection;
use kairos_tests::harness::{
    RecordError, RobotPlan, ServerOptions, TaskLog, TestServer, check_exact_records,
    compare_records, run_fleet,
};

const ROBOTS: u64 = 20;
const ROUNDS: u64 = 6;

/// How far the server's records may be from the robots' logs: the uncertainty of the clock
/// mapping, which the run itself measures, not a fixed margin that a loaded machine outgrows.
///
/// The server maps a robot's clock onto its own per connection: offset = min over messages of
/// `server_read − sent_at`, minus RTT/2 (`server::validation`). Its error is at most the least
/// one-way delay (≤ any round trip the robot saw) one way and RTT/2 (≤ the largest round trip:
/// every application round trip contains a transport one) the other, so a `G` mapped back to the
/// robot's clock is off by at most the largest round trip `rt_max` the fleet saw, and an `E`
/// (mapped in with one estimate, back out with a later one) by at most `2 · rt_max`. On a quiet
/// machine `rt_max` is a few ms and this still catches a real bookkeeping error (a wrong round's
/// interval, a missing `remaining / control_hz`, a unit slip: tens of ms or more at 200 Hz); on a
/// loaded one the bound grows with the delays that loosen the mapping, instead of failing.
fn clock_uncertainty_us(logs: &[TaskLog]) -> u64 {
    logs.iter()
        .flat_map(|log| &log.rounds)
        .map(|round| round.received_at_us.saturating_sub(round.sent_at_us))
        .max()
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_robots_complete_multi_round_tasks_and_records_match() {
    let server = TestServer::start(ServerOptions {
        max_batch: 8,
        ..ServerOptions::default()
    })
    .await
    .unwrap();

    let plans = (0..ROBOTS)
        .map(|i| RobotPlan {
            task: 1_000 + i,
            rounds: ROUNDS,
            control_hz: 200.0,
            send_ahead: 3,
            // Half the fleet asks for a static horizon, half uses the server's default (§3.1
            // threshold); `state1` varies where the threshold cuts.
            horizon: (i % 2 == 0).then(|| HorizonSelection {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), 6.0)]),
                samples: 1,
            }),
            state1: 0.05 * (i % 5) as f32,
        })
        .collect();
    let logs = run_fleet(&server, plans).await.unwrap();

    let mut worst = RecordError::default();
    for log in &logs {
        assert_eq!(log.rounds.len() as u64, ROUNDS);
        for (i, round) in log.rounds.iter().enumerate() {
            assert_eq!(round.round, i as u64, "round ids in order");
            assert_eq!(round.attempts, 1, "no resends on loopback");
            assert!(round.horizon >= 1 && round.horizon <= 16);
            if log.task % 2 == 0 {
                assert_eq!((round.horizon, round.policy.as_str()), (6, "static"));
            } else {
                assert_eq!(round.policy, "threshold");
            }
        }
        check_exact_records(log).unwrap();
        worst = worst.max(compare_records(log).unwrap());
        // Server side: one generation per (task, round).
        server.assert_generated_once(log.task, ROUNDS).await;
    }
    let rt_max = clock_uncertainty_us(&logs);
    println!("largest record error vs robot logs: {worst:?}; largest round trip {rt_max} µs");
    assert!(
        worst.generation_outside_us <= rt_max,
        "{worst:?}, rt_max {rt_max} µs"
    );
    assert!(
        worst.exec_start_us <= 2 * rt_max,
        "{worst:?}, rt_max {rt_max} µs"
    );
    assert!(
        worst.exec_end_us <= 2 * rt_max,
        "{worst:?}, rt_max {rt_max} µs"
    );

    let report = server.shutdown().await;
    assert_eq!(report.driver.replies, ROBOTS * ROUNDS);
    assert_eq!(report.driver.cached_replies, 0);
    assert_eq!(report.driver.tasks_ended, ROBOTS);
    assert_eq!(report.transport.admitted, ROBOTS);
}

/// `kairos serve` with no config file: built-in model (profiled at start), generated certificate
/// and `default` robot token in the data dir, found there the way `kairos robot` finds them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_with_defaults_answers_a_robot_that_reads_the_data_dir() {
    use kairos_sdk::client::{Client, ClientConfig, NoRefetch, RoundRequest};
    use kairos_sdk::protocol::{Observation, Tensor};
    use kairos_server::config::{Config, DEFAULT_ROBOT, Overrides};
    use kairos_server::data_dir::DataDir;
    use kairos_server::pool::{ModelSchemes, build_pool};
    use kairos_server::transport::launch::{Policies, start};

    let dir = tempfile::tempdir().unwrap();
    let overrides = Overrides {
        listen: Some("127.0.0.1:0".parse().unwrap()),
        data_dir: Some(dir.path().join("kairos-data")),
        ..Overrides::default()
    };
    let config = Config::load_with(None, &overrides).unwrap();
    let pool = tokio::task::spawn_blocking({
        let config = config.clone();
        move || build_pool(&config.engines, &ModelSchemes::new(), |_| {})
    })
    .await
    .unwrap()
    .unwrap();
    let server = start(&config, pool, Policies::default()).await.unwrap();
    assert_eq!(server.model.name, "flow-head-small");

    let data_dir = DataDir::new(dir.path().join("kairos-data"));
    let pin = data_dir.read_pin().unwrap();
    let token = data_dir.token(DEFAULT_ROBOT).unwrap();
    let client = Client::connect(ClientConfig::pinned(server.local_addr, pin, token))
        .await
        .unwrap();
    let spec = &server.model;
    let mut task = client.task(1);
    let observation = Observation {
        captured_at_us: client.now_us(),
        state: Tensor::from_f32(vec![spec.state_dim], &vec![0.1; spec.state_dim as usize]).unwrap(),
        images: Vec::new(),
        instruction: "pick up the cube".into(),
    };
    let reply = task
        .submit(RoundRequest::new(observation), &mut NoRefetch)
        .await
        .unwrap();
    assert!(reply.reply.horizon >= 1 && reply.reply.horizon <= spec.chunk_len);
    assert_eq!(
        reply.reply.policy, "threshold",
        "the default horizon policy"
    );
    assert_eq!(
        reply.reply.actions.shape,
        vec![reply.reply.horizon, spec.action_dim]
    );
    client.close().await;
    server.shutdown().await;
}
