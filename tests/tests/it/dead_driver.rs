//! A dead driver is a dead server: when the driver thread ends for any reason, a panic
//! included, `/ready` answers 503, `/metrics` shows `kairos_driver_alive 0`, the server stops
//! admitting and drains on its own, and its report says why (so `kairos serve` exits non-zero
//! and Kubernetes restarts it).
//!
//! The driver is killed the way a real bug would kill it: the scheduler's priority policy,
//! which the driver calls on its own thread for every decision, panics. The policy is
//! registered in code through `Policies`, the API a deployment uses for native policies, so
//! the server carries no hook that exists only for this test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::time::Duration;

use kairos_core::scheduler::{PendingView, PolicyError, PriorityPolicy};
use kairos_core::time::Timestamp;
use kairos_sdk::client::ClientError;
use kairos_sdk::protocol::ErrorCode;
use kairos_server::transport::launch::Policies;
use kairos_tests::harness::{ServerOptions, TestServer, one_round};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Hang guard only: every wait below ends on an event well before it.
const GIVE_UP: Duration = Duration::from_secs(60);

/// A priority policy with a bug: it panics on its first decision.
struct PanicsOnItsFirstDecision;

impl PriorityPolicy for PanicsOnItsFirstDecision {
    fn name(&self) -> &str {
        "panics"
    }

    fn order(
        &mut self,
        _now: Timestamp,
        _pending: &[PendingView],
        _order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        panic!("a priority policy bug, on purpose");
    }
}

/// GETs `path`; the status code and the body.
async fn get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(format!("GET {path} HTTP/1.1\r\nHost: kairos\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    let status = response
        .strip_prefix("HTTP/1.1 ")
        .and_then(|rest| rest.get(..3))
        .and_then(|code| code.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {response:?}"));
    (status, response)
}

fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_driver_that_panics_makes_the_server_unready_and_stop() {
    let mut policies = Policies::default();
    policies.priority.register("panics", |_spec| {
        Ok(Box::new(PanicsOnItsFirstDecision) as Box<dyn PriorityPolicy>)
    });
    let server = TestServer::start(ServerOptions {
        policies,
        tweak: |config| {
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
            config.scheduler.policy = "panics".parse().unwrap();
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let metrics = server.server().metrics_addr.unwrap();
    let (status, text) = get(metrics, "/ready").await;
    assert_eq!(status, 200, "{text}");
    let (_, text) = get(metrics, "/metrics").await;
    assert_eq!(sample(&text, "kairos_driver_alive"), Some(1.0), "{text}");

    // The first round makes the scheduler decide: the driver thread panics. The robot reads
    // the server's refusal; the connection's close as the server stops does not overtake it
    // (it did under load: the robot saw a lost connection and spent its reconnect attempts,
    // about a minute, on a server going away).
    let client = server.connect(&server.token).await.unwrap();
    let failed = one_round(&client, 1, 0).await;
    match &failed {
        Err(ClientError::Server(reply)) => {
            assert_eq!(reply.code, ErrorCode::ShuttingDown, "{reply:?}");
            assert!(reply.retryable, "{reply:?}");
        }
        other => panic!("expected the server's shutting_down refusal, got {other:?}"),
    }
    assert_eq!(
        client.stats().resent_rounds,
        0,
        "the round was not sent again"
    );

    // Probes see it: not ready, and why.
    tokio::time::timeout(GIVE_UP, async {
        while get(metrics, "/ready").await.0 != 503 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .expect("/ready turns 503 once the driver is dead");
    let (_, text) = get(metrics, "/metrics").await;
    assert_eq!(sample(&text, "kairos_driver_alive"), Some(0.0), "{text}");

    // The server stops by itself, without being told, and says why.
    let reason = tokio::time::timeout(GIVE_UP, server.server().failed())
        .await
        .expect("the server noticed its driver died");
    assert!(reason.contains("on purpose"), "{reason}");
    client.close().await;
    let report = tokio::time::timeout(GIVE_UP, server.stopped())
        .await
        .expect("the server drains and stops on its own");
    let failure = report.driver_failure.expect("the report names the failure");
    assert!(failure.contains("on purpose"), "{failure}");
}
