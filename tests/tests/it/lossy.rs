//! Robots behind a lossy link: 5% loss each way, delay with jitter that reorders packets, a few
//! duplicates, and every robot rebinding to a new local port in the middle of its task (a Wi-Fi
//! roam). Every round of every robot completes exactly once.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use kairos_tests::harness::{Hook, RobotPlan, ServerOptions, TestServer, run_task};
use kairos_tests::proxy::{Impairment, Proxy, ProxyConfig};

const ROBOTS: u64 = 8;
const ROUNDS: u64 = 10;
const REBIND_AFTER_ROUND: u64 = 4;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_round_completes_exactly_once_through_loss_reordering_and_rebinding() {
    let server = TestServer::start(ServerOptions::default()).await.unwrap();
    let link = Impairment {
        loss: 0.05,
        delay: Duration::from_millis(2),
        jitter: Duration::from_millis(4),
        duplicate: 0.01,
    };
    let proxy = Proxy::start(server.addr, ProxyConfig::symmetric(link, 2026))
        .await
        .unwrap();

    let rebind: Hook = Arc::new(|client, round| {
        if round == REBIND_AFTER_ROUND {
            let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("a fresh local port");
            client.rebind(socket).expect("rebind");
        }
    });
    let mut robots = Vec::new();
    for i in 0..ROBOTS {
        let client =
            kairos_sdk::client::Client::connect(server.client_config(proxy.addr(), &server.token))
                .await
                .unwrap();
        let plan = RobotPlan::static_horizon(500 + i, ROUNDS, 6);
        let hook = rebind.clone();
        robots.push(tokio::spawn(async move {
            let before = client.local_addr().unwrap();
            let log = run_task(&client, &plan, Some(hook)).await;
            let after = client.local_addr().unwrap();
            client.close().await;
            (log, before, after)
        }));
    }

    let mut resent = 0;
    for robot in robots {
        let (log, before, after) = robot.await.unwrap();
        let log = log.unwrap();
        assert_ne!(before.port(), after.port(), "task {} rebound", log.task);
        let rounds: Vec<u64> = log.rounds.iter().map(|r| r.round).collect();
        assert_eq!(rounds, (0..ROUNDS).collect::<Vec<_>>(), "task {}", log.task);
        resent += log.rounds.iter().filter(|r| r.attempts > 1).count();
        assert_eq!(u64::from(log.ended.rounds), ROUNDS, "task {}", log.task);
        server.assert_generated_once(log.task, ROUNDS).await;
    }

    let stats = proxy.stats();
    let lost_up = stats.to_server.lost.load(Ordering::Relaxed);
    let lost_down = stats.to_client.lost.load(Ordering::Relaxed);
    let reordered = stats.to_server.reordered.load(Ordering::Relaxed)
        + stats.to_client.reordered.load(Ordering::Relaxed);
    println!(
        "proxy: {} packets up ({lost_up} lost), {} down ({lost_down} lost), {reordered} reordered, \
         {} flows; {resent} rounds re-sent",
        stats.to_server.received.load(Ordering::Relaxed),
        stats.to_client.received.load(Ordering::Relaxed),
        stats.flows.load(Ordering::Relaxed),
    );
    assert!(
        lost_up > 0 && lost_down > 0,
        "the link lost packets both ways"
    );
    assert!(reordered > 0, "the link reordered packets");
    assert!(
        stats.flows.load(Ordering::Relaxed) >= 2 * ROBOTS,
        "every robot appeared from a second address"
    );

    let report = server.shutdown().await;
    assert_eq!(
        report.driver.replies,
        ROBOTS * ROUNDS,
        "one generation per round"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_lost_mid_round_resumes_without_a_second_generation() {
    // A forward pass of 200 ms (emulated by the test model) keeps each round in flight long
    // enough for the connection to drop, the client to reconnect (50 ms backoff) and re-send.
    let model = Arc::new(kairos_tests::model::TestFlow::with_latency(
        Duration::from_millis(200),
    ));
    let server = TestServer::start_with_model(ServerOptions::default(), model)
        .await
        .unwrap();
    let link = Impairment {
        loss: 0.05,
        delay: Duration::from_millis(1),
        jitter: Duration::from_millis(2),
        duplicate: 0.0,
    };
    let proxy = Proxy::start(server.addr, ProxyConfig::symmetric(link, 7))
        .await
        .unwrap();
    const DROP_AFTER: u64 = 1;
    // After round 1 the next request leaves (200 Hz, 6 actions, 3 sent ahead) 15 ms into the
    // chunk; 40 ms in, that round is generating on the server.
    let drop_mid_round: Hook = Arc::new(|client, round| {
        if round == DROP_AFTER {
            let client = client.clone();
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_millis(40)).await;
                client.drop_connection().await;
            });
        }
    });
    let mut robots = Vec::new();
    for i in 0..4u64 {
        let client =
            kairos_sdk::client::Client::connect(server.client_config(proxy.addr(), &server.token))
                .await
                .unwrap();
        let plan = RobotPlan::static_horizon(700 + i, 4, 6);
        let hook = drop_mid_round.clone();
        robots.push(tokio::spawn(async move {
            let log = run_task(&client, &plan, Some(hook)).await;
            let stats = client.stats();
            client.close().await;
            (log, stats)
        }));
    }
    for robot in robots {
        let (log, stats) = robot.await.unwrap();
        let log = log.unwrap();
        assert_eq!(log.rounds.len(), 4);
        assert!(
            log.rounds[DROP_AFTER as usize + 1].attempts > 1,
            "task {}: round {} was re-sent on a new connection",
            log.task,
            DROP_AFTER + 1
        );
        assert!(stats.connects >= 2, "task {} reconnected", log.task);
        server.assert_generated_once(log.task, 4).await;
    }
    // A re-sent round found its first copy queued (withdrawn when the old connection died, then
    // accepted again), running (attached) or answered (cached reply) — or, when the loss ate the
    // first copy before it arrived, nothing. Never a second generation: every extra acceptance
    // is a withdrawal.
    let stats = server.server().driver.stats().await.unwrap();
    assert_eq!(stats.accepted, 16 + stats.cancelled, "{stats:?}");
    assert!(
        stats.attached + stats.cached_replies + stats.cancelled >= 1,
        "no re-sent round met its first copy: {stats:?}"
    );
    println!("driver after the drops: {stats:?}");
    let report = server.shutdown().await;
    assert_eq!(report.driver.replies, 16);
}
