//! End to end over real QUIC on loopback: one server, 20 concurrent robots, each running a
//! multi-round task with asynchronous inference. Every round is answered exactly once, and the
//! G/E records the server keeps match what each robot did.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;

use kairos_sdk::protocol::HorizonSelection;
use kairos_tests::harness::{
    RecordError, RobotPlan, ServerOptions, TestServer, compare_records, run_fleet,
};

const ROBOTS: u64 = 20;
const ROUNDS: u64 = 6;

/// Timing tolerance for matching the server's records with the robots' logs, µs.
///
/// The server maps robot clocks onto its own per connection (min over recent messages of
/// `server_read − sent_at`, minus RTT/2). On loopback the least-delayed message's one-way delay
/// is tens of µs, but with 20 robots, the server and the test sharing 2 cores, a message can wait
/// a few ms for a thread, and the smoothed RTT moves between requests; 5 ms bounds both with a
/// margin while still catching any real bookkeeping error (a wrong round's interval, a missing
/// `remaining / control_hz`, a unit slip: those are tens of ms or more at 200 Hz).
const TOLERANCE_US: u64 = 5_000;

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
        worst = worst.max(compare_records(log).unwrap());
        // Server side: one generation per (task, round).
        server.assert_generated_once(log.task, ROUNDS).await;
    }
    println!("largest record error vs robot logs: {worst:?}");
    assert!(worst.generation_outside_us <= TOLERANCE_US, "{worst:?}");
    assert!(worst.exec_start_us <= TOLERANCE_US, "{worst:?}");
    assert!(worst.exec_end_us <= TOLERANCE_US, "{worst:?}");

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
    use kairos_server::cli::serve::{ServeArgs, config, start_engines};
    use kairos_server::config::{DEFAULT_ROBOT, TokensFile};
    use kairos_server::transport::launch::{Policies, start};

    let dir = tempfile::tempdir().unwrap();
    let args = ServeArgs {
        config: None,
        listen: Some("127.0.0.1:0".parse().unwrap()),
        data_dir: Some(dir.path().join("kairos-data")),
        ..ServeArgs::default()
    };
    let config = config(&args).unwrap();
    let pool = tokio::task::spawn_blocking({
        let config = config.clone();
        move || start_engines(&config)
    })
    .await
    .unwrap()
    .unwrap();
    let server = start(&config, pool, Policies::default()).await.unwrap();
    assert_eq!(server.model.name, "flow-head-small");

    let data_dir = dir.path().join("kairos-data");
    let pin = std::fs::read_to_string(data_dir.join("fingerprint.txt")).unwrap();
    let token = TokensFile::read(&data_dir.join("tokens.toml"))
        .unwrap()
        .token(DEFAULT_ROBOT)
        .unwrap()
        .to_string();
    let client = Client::connect(ClientConfig::pinned(
        server.local_addr,
        pin.trim().parse().unwrap(),
        token,
    ))
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
