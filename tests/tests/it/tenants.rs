//! Fairness between tenants, over real QUIC: one robot cannot take every connection place
//! (`[connections] max_connections_per_robot`, by default an equal share of
//! `max_connections` per configured robot), flood the scheduler with rounds (per-robot and
//! per-connection round rates), or take a shared plugin from the others by making it trap
//! (quarantine is per robot first).

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;
use std::time::Duration;

use kairos_sdk::client::{Client, ClientError, close_code};
use kairos_sdk::protocol::{ErrorCode, Hello, HorizonSelection, Message, PROTOCOL_VERSION};
use kairos_server::config::PluginConfig;
use kairos_server::plugin::PluginKind;
use kairos_server::plugin::componentize::componentize;
use kairos_tests::harness::{
    RawConnection, RobotPlan, ServerOptions, TestServer, one_round, run_task,
};

/// Hang guard only: every wait below ends on an event well before it.
const GIVE_UP: Duration = Duration::from_secs(60);

const A: &str = "tenant-a-token";
const B: &str = "tenant-b-token";

fn two_robots() -> Vec<(String, String)> {
    vec![("a".into(), A.into()), ("b".into(), B.into())]
}

/// The close code and reason of a connection the server closed.
fn application_close(error: quinn::ConnectionError) -> (u64, String) {
    match error {
        quinn::ConnectionError::ApplicationClosed(close) => (
            close.error_code.into_inner(),
            String::from_utf8_lossy(&close.reason).into_owned(),
        ),
        other => panic!("not closed by the server: {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_robot_cannot_take_every_connection_place() {
    let server = TestServer::start(ServerOptions {
        robots: two_robots(),
        tweak: |config| {
            // Two robots share 8 places: by default each may hold 4, its fair share.
            config.connections.max_connections = 8;
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let mut held = Vec::new();
    for _ in 0..4 {
        held.push(server.connect(A).await.unwrap());
    }
    // The fifth connection of the same token is closed with a reason.
    let fifth = RawConnection::open(&server).await.unwrap();
    let hello = Message::Hello(Hello {
        protocol: PROTOCOL_VERSION,
        token: A.into(),
        client: "fifth".into(),
    });
    let _ = fifth.exchange(&hello.encode(u32::MAX).unwrap(), true).await;
    let closed = tokio::time::timeout(GIVE_UP, fifth.connection.closed())
        .await
        .expect("the fifth connection is closed");
    let (code, reason) = application_close(closed);
    assert_eq!(code, u64::from(close_code::AT_CAPACITY), "{reason}");
    assert!(reason.contains("max_connections_per_robot"), "{reason}");

    // Another robot still gets in and is served.
    let b = server.connect(B).await.unwrap();
    one_round(&b, 2, 0).await.unwrap();
    // A place given back is a place robot `a` can take again.
    held.pop().unwrap().close().await;
    let again = tokio::time::timeout(GIVE_UP, async {
        loop {
            match Client::connect(server.client_config(server.addr, A)).await {
                Ok(client) => return client,
                // The server may not have seen the close yet.
                Err(ClientError::Connection(_)) => {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
                Err(other) => panic!("{other}"),
            }
        }
    })
    .await
    .unwrap();
    one_round(&again, 1, 0).await.unwrap();
    for client in held.into_iter().chain([again, b]) {
        client.close().await;
    }
    let report = server.shutdown().await;
    assert_eq!(report.transport.refused, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rounds_are_rate_limited_per_connection_and_per_robot() {
    let server = TestServer::start(ServerOptions {
        robots: two_robots(),
        tweak: |config| {
            // Refilled once in 100 s: nothing refills while the test runs.
            config.connections.rounds_per_s_per_connection = 0.01;
            config.connections.round_burst_per_connection = 2;
            config.connections.rounds_per_s_per_robot = 0.01;
            config.connections.round_burst_per_robot = 3;
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let refused = |result: Result<_, ClientError>| match result {
        Err(ClientError::Server(reply)) => {
            assert_eq!(reply.code, ErrorCode::Overloaded, "{reply:?}");
            assert!(reply.retryable);
            assert!(reply.retry_after_ms.is_some_and(|ms| ms > 0), "{reply:?}");
            reply.message
        }
        other => panic!("expected a rate-limit refusal, got {other:?}"),
    };
    let a1 = server.connect(A).await.unwrap();
    let a2 = server.connect(A).await.unwrap();
    one_round(&a1, 1, 0).await.unwrap();
    one_round(&a1, 1, 1).await.unwrap();
    // The connection's burst is spent.
    let message = refused(one_round(&a1, 1, 2).await);
    assert!(message.contains("connection"), "{message}");
    // The robot's burst allows one more round, on its other connection.
    one_round(&a2, 2, 0).await.unwrap();
    let message = refused(one_round(&a2, 2, 1).await);
    assert!(message.contains("robot"), "{message}");
    // Another robot is not affected.
    let b = server.connect(B).await.unwrap();
    for round in 0..2 {
        one_round(&b, 3, round).await.unwrap();
    }
    for client in [a1, a2, b] {
        client.close().await;
    }
    server.shutdown().await;
}

/// A horizon plugin that traps whenever the round passes it parameters, and answers `h_max`
/// otherwise: one robot's requests (with a parameter) make it trap, another's do not.
fn trapping_plugin(dir: &std::path::Path) -> PluginConfig {
    // The `kairos:policy@0.1.0` `choose` signature: locals 14-15 are the parameters' list.
    let module = wat::parse_str(
        r#"(module
  (memory (export "memory") 1)
  (global $heap (mut i32) (i32.const 1024))
  (func (export "cabi_realloc") (param i32 i32 i32 i32) (result i32)
    (local $p i32)
    ;; Aligned bump allocation; `post-return` resets the heap.
    (local.set $p
      (i32.and
        (i32.add (global.get $heap) (i32.sub (local.get 2) (i32.const 1)))
        (i32.xor (i32.sub (local.get 2) (i32.const 1)) (i32.const -1))))
    (global.set $heap (i32.add (local.get $p) (local.get 3)))
    (local.get $p))
  (func (export "kairos:policy/horizon@0.1.0#choose")
    (param i32 i32 i32 i32 i32 i32 i32 i32 i32 i32 f32 i64 i32 i32 i32 i32) (result i32)
    (if (local.get 15) (then unreachable))
    (i32.store8 (i32.const 0) (i32.const 0))
    (i32.store (i32.const 4) (local.get 9))
    (i32.const 0))
  (func (export "cabi_post_kairos:policy/horizon@0.1.0#choose") (param i32)
    (global.set $heap (i32.const 1024))))"#,
    )
    .unwrap();
    let component = componentize(&module, PluginKind::Horizon).unwrap();
    let path = dir.join("trappy.wasm");
    std::fs::write(&path, component).unwrap();
    PluginConfig {
        name: Some("trappy".into()),
        // Generous: a loaded machine must not turn a slow call into a failure.
        deadline_ms: Some(2_000),
        ..PluginConfig::file(path)
    }
}

fn asks_for_trappy(task: u64, rounds: u64, params: BTreeMap<String, f64>) -> RobotPlan {
    RobotPlan {
        horizon: Some(HorizonSelection {
            policy: "trappy".into(),
            params,
            samples: 1,
        }),
        ..RobotPlan::static_horizon(task, rounds, 4)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_robots_plugin_traps_do_not_take_the_plugin_from_another_robot() {
    let dir = tempfile::tempdir().unwrap();
    let server = TestServer::start(ServerOptions {
        robots: two_robots(),
        plugins: vec![trapping_plugin(dir.path())],
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    // Robot `a` makes the plugin trap on every round: after 3 traps it is quarantined for `a`.
    let a = server.connect(A).await.unwrap();
    let boom = BTreeMap::from([("boom".to_string(), 1.0)]);
    let log = run_task(&a, &asks_for_trappy(1, 5, boom), None)
        .await
        .unwrap();
    let answered: Vec<&str> = log.rounds.iter().map(|r| r.policy.as_str()).collect();
    assert_eq!(
        answered, ["threshold"; 5],
        "the native fallback answers `a`"
    );
    // Robot `b` still gets the plugin on every round.
    let b = server.connect(B).await.unwrap();
    let log = run_task(&b, &asks_for_trappy(2, 5, BTreeMap::new()), None)
        .await
        .unwrap();
    let answered: Vec<&str> = log.rounds.iter().map(|r| r.policy.as_str()).collect();
    assert_eq!(answered, ["trappy"; 5], "the plugin answers `b`");
    a.close().await;
    b.close().await;
    server.shutdown().await;
}
