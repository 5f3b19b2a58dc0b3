//! Admission under abuse (#12 item 3), over real QUIC: clients that never authenticate cannot
//! lock robots out, whether they stop half way through the handshake or finish it and never send
//! `Hello`; and a source that sends wrong tokens is refused before its token is looked at.
//! Refusals are counted in `/metrics` and in the shutdown report.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::sync::Arc;
use std::time::{Duration, Instant};

use kairos_sdk::client::{ClientError, close_code};
use kairos_sdk::protocol::{Hello, Message, PROTOCOL_VERSION};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, client_config};
use kairos_server::transport::refusals::{Door, Reason};
use kairos_tests::harness::{RawConnection, ServerOptions, TestServer, one_round};

use super::auth::application_close_code;
use super::metrics::{get, refusal_samples, sample};

/// Guards against a hang only; every wait below is for an event.
const HANG_GUARD: Duration = Duration::from_secs(60);

/// Sends `count` QUIC Initial packets, each opening a new connection attempt, from one UDP port,
/// and never answers anything the server sends back: half-open handshakes. The packets are real
/// Initials (quinn-proto's client state machine builds them), so the server cannot tell them from
/// a robot's first packet.
fn half_open_flood(server: &TestServer, count: usize) -> std::io::Result<std::net::UdpSocket> {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0")?;
    let config = client_config(
        &ServerTrust::Pinned(server.pin),
        &TransportTuning::default(),
    )
    .unwrap();
    let mut endpoint = quinn_proto::Endpoint::new(
        Arc::new(quinn_proto::EndpointConfig::default()),
        None,
        false,
        None,
    );
    let mut sent = 0;
    let mut buf = Vec::new();
    while sent < count {
        let now = Instant::now();
        let (_, mut connection) = endpoint
            .connect(now, config.clone(), server.addr, "kairos")
            .unwrap();
        buf.clear();
        if let Some(transmit) = connection.poll_transmit(now, 1, &mut buf) {
            socket.send_to(&buf[..transmit.size], transmit.destination)?;
            sent += 1;
        }
        // The connection state is dropped: nothing will ever answer the server.
    }
    Ok(socket)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_half_open_handshakes_does_not_lock_a_robot_out() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.connections.max_connections = 64;
            config.connections.max_unauthenticated = 32;
            // The flood's handshakes never time out during the test.
            config.connections.hello_timeout_ms = 600_000;
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    // Ten times the unauthenticated budget, and more than max_connections, from one port (the
    // probe of #12 filled 4,096 slots this way). Sent in bursts so the server's socket buffer
    // keeps most of them; the test does not depend on how many arrive.
    let mut floods = Vec::new();
    for _ in 0..10 {
        floods.push(half_open_flood(&server, 32).unwrap());
        tokio::task::yield_now().await;
    }

    let robot = tokio::time::timeout(HANG_GUARD, server.connect(&server.token))
        .await
        .expect("hang guard")
        .expect("a robot connects during the flood");
    one_round(&robot, 1, 0).await.unwrap();
    robot.close().await;

    let report = server.shutdown().await;
    assert!(
        report.transport.retried > 0,
        "attempts over half the budget were asked to validate their address: {:?}",
        report.transport
    );
    assert_eq!(report.transport.admitted, 1, "{:?}", report.transport);
    drop(floods);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_handshakes_that_never_say_hello_do_not_take_robots_places() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.connections.max_connections = 50;
            config.connections.hello_timeout_ms = 600_000;
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let mut silent = Vec::new();
    for _ in 0..60 {
        silent.push(RawConnection::open(&server).await.unwrap());
    }

    let robot = tokio::time::timeout(HANG_GUARD, server.connect(&server.token))
        .await
        .expect("hang guard")
        .expect("a robot connects while 60 connections sit before Hello");
    one_round(&robot, 1, 0).await.unwrap();
    for raw in &silent {
        assert!(
            raw.connection.close_reason().is_none(),
            "the silent connections were all still open while the robot was served"
        );
    }
    robot.close().await;
    for raw in silent {
        raw.close().await;
    }
    let report = server.shutdown().await;
    assert_eq!(report.transport.admitted, 1);
    assert_eq!(report.refusals.get(Door::Quic, Reason::AtCapacity), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn max_connections_counts_authenticated_robots_only() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.connections.max_connections = 2;
            config.connections.hello_timeout_ms = 300;
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let a = server.connect(&server.token).await.unwrap();
    let b = server.connect(&server.token).await.unwrap();
    one_round(&a, 1, 0).await.unwrap();
    one_round(&b, 2, 0).await.unwrap();

    // A third robot authenticates and is closed with a reason.
    let third = RawConnection::open(&server).await.unwrap();
    let hello = Message::Hello(Hello {
        protocol: PROTOCOL_VERSION,
        token: server.token.clone(),
        client: "third".into(),
    });
    let _ = third.exchange(&hello.encode(u32::MAX).unwrap(), true).await;
    let (code, reason) = application_close_code(third.connection.closed().await);
    assert_eq!(code, u64::from(close_code::AT_CAPACITY));
    assert!(reason.contains("capacity"), "{reason}");

    // A connection that never says Hello needs no place, and is closed when its time is up.
    let silent = RawConnection::open(&server).await.unwrap();
    let (code, reason) = application_close_code(silent.connection.closed().await);
    assert_eq!(code, u64::from(close_code::PROTOCOL_ERROR));
    assert!(reason.contains("Hello"), "{reason}");

    one_round(&a, 1, 1).await.unwrap();
    // Both refusals are counted where an operator looks: in /metrics while the server runs (issue
    // #28, finding 10), and in the shutdown report.
    let (status, text) = get(server.server().metrics_addr.unwrap(), "/metrics").await;
    assert_eq!(status, 200);
    let refused = |reason: &str| {
        sample(
            &text,
            &format!(r#"kairos_refusals_total{{door="quic",reason="{reason}"}}"#),
        )
    };
    assert_eq!(
        (refused("at_capacity"), refused("hello_timeout")),
        (Some(1.0), Some(1.0)),
        "refusals in /metrics: {:?}",
        refusal_samples(&text)
    );
    a.close().await;
    b.close().await;
    let report = server.shutdown().await;
    assert_eq!(report.transport.admitted, 2);
    assert_eq!(report.refusals.get(Door::Quic, Reason::AtCapacity), 1);
    // The silent connection's missing Hello is counted too.
    assert_eq!(report.refusals.get(Door::Quic, Reason::HelloTimeout), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_source_that_sends_wrong_tokens_is_refused_before_its_token_is_read() {
    let server = TestServer::start(ServerOptions {
        robots: vec![("arm".to_string(), "right-token".to_string())],
        tweak: |config| {
            config.connections.failed_token_burst = 3;
            // No refill during the test: the verdict does not depend on the clock.
            config.connections.failed_tokens_per_minute = 0;
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    for guess in ["guess-1", "guess-2", "guess-3"] {
        match server.connect(guess).await {
            Err(error) => match error.downcast::<ClientError>().unwrap() {
                ClientError::Unauthorized(_) => {}
                other => panic!("expected Unauthorized, got {other}"),
            },
            Ok(_) => panic!("a wrong token was accepted"),
        }
    }
    // The fourth attempt from the same address carries the right token, and is refused at its
    // first packet: the server never gets as far as reading it.
    match server.connect("right-token").await {
        Err(error) => match error.downcast::<ClientError>().unwrap() {
            ClientError::Connection(quinn::ConnectionError::ConnectionClosed(close)) => {
                assert_eq!(
                    close.error_code,
                    quinn_proto::TransportErrorCode::CONNECTION_REFUSED
                );
            }
            other => panic!("expected a refused connection, got {other}"),
        },
        Ok(_) => panic!("a rate-limited source got in"),
    }
    // Another address is not affected (all of 127.0.0.0/8 is loopback).
    let mut config = server.client_config(server.addr, "right-token");
    config.bind = Some("127.0.0.2:0".parse().unwrap());
    let robot = kairos_sdk::client::Client::connect(config)
        .await
        .expect("another source connects");
    one_round(&robot, 1, 0).await.unwrap();
    robot.close().await;
    let report = server.shutdown().await;
    assert_eq!(
        report.refusals.get(Door::Quic, Reason::WrongTokenLimit),
        1,
        "{}",
        report.refusals
    );
    assert_eq!(report.refusals.get(Door::Quic, Reason::Unauthorized), 3);
}
