//! End to end over real QUIC on loopback: one server, 20 concurrent robots, each running a
//! multi-round task with asynchronous inference. Every round is answered exactly once, and the
//! G/E records the server keeps match what each robot did.

use std::collections::BTreeMap;

use kairos_sdk::protocol::HorizonSelection;
use kairos_server::scheduler::TaskId;
use kairos_tests::harness::{RecordError, RobotPlan, ServerOptions, TestServer, compare_records, run_task};

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

    let mut robots = Vec::new();
    for i in 0..ROBOTS {
        let client = server.connect(&server.token).await.unwrap();
        let plan = RobotPlan {
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
        };
        robots.push(tokio::spawn(async move {
            let log = run_task(&client, &plan, None).await;
            client.close().await;
            log
        }));
    }
    let mut logs = Vec::new();
    for robot in robots {
        logs.push(robot.await.unwrap().unwrap());
    }

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
        let snapshot = server
            .server()
            .driver
            .snapshot(TaskId(log.task))
            .await
            .unwrap()
            .unwrap();
        assert!(snapshot.ended);
        let expected: BTreeMap<u64, u32> = (0..ROUNDS).map(|r| (r, 1)).collect();
        assert_eq!(snapshot.generated, expected, "task {}", log.task);
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
