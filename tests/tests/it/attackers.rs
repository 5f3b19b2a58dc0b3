//! The mixed soak's attackers (`kairos_tests::attacks`, `kairos_tests::hostile_worker`; run by
//! `scripts/soak.sh --mixed` as `kairos-attack` and `kairos-hostile-worker`), each once against
//! a server in this process: what each does reaches the server, the server's guard acts on it,
//! and a well-behaved robot is still served.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use kairos_engine::ActionModel;
use kairos_sdk::tls::ServerTrust;
use kairos_tests::attacks::{AttackCounters, connection_hog, slowloris_quic, slowloris_tcp};
use kairos_tests::harness::{ServerOptions, TestServer, one_round};
use kairos_tests::hostile_worker::{HostileCounters, hostile_register, run_hostile_worker};
use kairos_tests::model::TestFlow;
use kairos_tests::workers::{spawn_worker, worker_token};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Hang guard only: every wait below ends on an event well before it.
const GIVE_UP: Duration = Duration::from_secs(60);

const A: &str = "token-of-robot-a";
const B: &str = "token-of-robot-b";

/// Waits until `counter` reaches `at_least`.
async fn wait_count(what: &str, counter: &AtomicU64, at_least: u64) {
    tokio::time::timeout(GIVE_UP, async {
        while counter.load(Ordering::Relaxed) < at_least {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap_or_else(|_| panic!("{what} never reached {at_least}"));
}

/// GETs `path` on the metrics listener; the whole response.
async fn get(addr: SocketAddr, path: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let request = format!("GET {path} HTTP/1.1\r\nHost: kairos\r\nConnection: close\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    response
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_listener_attacks_are_held_off_and_another_robot_is_served() {
    let server = TestServer::start(ServerOptions {
        robots: vec![("a".into(), A.into()), ("b".into(), B.into())],
        tweak: |config| {
            // Two robots share 8 places: each may hold 4.
            config.connections.max_connections = 8;
            config.connections.hello_timeout_ms = 500;
            config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let openpi = server.server().openpi_addr.unwrap();
    let metrics = server.server().metrics_addr.unwrap();
    let trust = ServerTrust::Pinned(server.pin);
    let (quic_loris, openpi_loris, metrics_loris, hog) = (
        AttackCounters::shared(),
        AttackCounters::shared(),
        AttackCounters::shared(),
        AttackCounters::shared(),
    );
    let attacks = [
        tokio::spawn(slowloris_quic(
            server.addr,
            trust.clone(),
            2,
            quic_loris.clone(),
            None,
        )),
        tokio::spawn({
            let counters = openpi_loris.clone();
            async move {
                slowloris_tcp(openpi, 2, counters, None).await;
                Ok::<(), anyhow::Error>(())
            }
        }),
        tokio::spawn({
            let counters = metrics_loris.clone();
            async move {
                slowloris_tcp(metrics, 2, counters, None).await;
                Ok::<(), anyhow::Error>(())
            }
        }),
        tokio::spawn(connection_hog(
            server.addr,
            trust,
            A.into(),
            hog.clone(),
            None,
        )),
    ];

    // Each listener closes the connections that never finish their first message.
    wait_count("QUIC slowloris closed", &quic_loris.closed_by_server, 2).await;
    wait_count("openpi slowloris closed", &openpi_loris.closed_by_server, 2).await;
    wait_count(
        "metrics slowloris closed",
        &metrics_loris.closed_by_server,
        2,
    )
    .await;
    // The hog got its robot's share and was refused the next place.
    wait_count("hog refused", &hog.refused, 1).await;
    assert_eq!(hog.opened.load(Ordering::Relaxed), 4, "{}", hog.summary());
    assert_eq!(hog.held.load(Ordering::Relaxed), 4, "{}", hog.summary());

    // Meanwhile another robot connects and is served, and the server says it is ready.
    let b = server.connect(B).await.unwrap();
    one_round(&b, 1, 0).await.unwrap();
    b.close().await;
    let ready = get(metrics, "/ready").await;
    assert!(ready.starts_with("HTTP/1.1 200"), "{ready}");
    for attack in attacks {
        attack.abort();
    }
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_hostile_worker_is_removed_and_its_batch_served_by_a_healthy_worker() {
    let server = TestServer::start(ServerOptions {
        engines: 0,
        max_batch: 2,
        tweak: |config| config.metrics.listen = Some("127.0.0.1:0".parse().unwrap()),
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let spec = TestFlow::new().spec().clone();
    let register = hostile_register(&spec, worker_token(&server).unwrap(), 0.001);
    let counters = Arc::new(HostileCounters::default());
    // Rejoins only after the test: one registration, one answer.
    let hostile = tokio::spawn(run_hostile_worker(
        server.addr,
        ServerTrust::Pinned(server.pin),
        register,
        spec,
        Duration::from_secs(3600),
        counters.clone(),
    ));
    wait_count("hostile registered", &counters.registered, 1).await;
    // Alone in the pool, the hostile worker gets the round's batch and answers it with NaN.
    let client = server.connect(&server.token).await.unwrap();
    let round = tokio::spawn(async move {
        let reply = one_round(&client, 1, 0).await;
        client.close().await;
        reply
    });
    wait_count("hostile answered", &counters.answered, 1).await;
    wait_count("hostile removed", &counters.removed, 1).await;
    // A healthy worker joins and runs the batch again: the robot gets finite actions.
    let (stop, healthy) = spawn_worker(&server, "healthy").unwrap();
    let reply = tokio::time::timeout(GIVE_UP, round)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    let actions = reply.reply.actions.to_f32().unwrap();
    assert!(!actions.is_empty() && actions.iter().all(|a| a.is_finite()));
    let text = get(server.server().metrics_addr.unwrap(), "/metrics").await;
    assert!(
        text.contains("kairos_worker_removed_total{reason=\"invalid_answer\"} 1"),
        "{text}"
    );
    hostile.abort();
    let _ = stop.send(());
    healthy.await.unwrap().unwrap();
    server.shutdown().await;
}
