//! The metrics endpoint of a served instance, over real TCP: `/metrics` shows every Kairos
//! family, a round moves the latency histogram, `/ready` flips to 503 when the server drains,
//! and malformed or unknown requests get 4xx.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;

use kairos_tests::harness::{ServerOptions, TestServer, one_round};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Sends `request` raw and returns the status code and the whole response.
async fn exchange(addr: SocketAddr, request: &[u8]) -> (u16, String) {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream.write_all(request).await.unwrap();
    // Half-close: the server sees the end of a truncated request instead of waiting for more.
    stream.shutdown().await.unwrap();
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await.unwrap();
    let text = String::from_utf8(response).unwrap();
    let status = text
        .strip_prefix("HTTP/1.1 ")
        .and_then(|rest| rest.get(..3))
        .and_then(|code| code.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {text:?}"));
    (status, text)
}

/// `GET path`: the status code and the whole response.
pub(super) async fn get(addr: SocketAddr, path: &str) -> (u16, String) {
    exchange(
        addr,
        format!("GET {path} HTTP/1.1\r\nHost: kairos\r\n\r\n").as_bytes(),
    )
    .await
}

/// The value of the sample `series` (name and labels, exactly as exported).
pub(super) fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

/// The `kairos_refusals_total` samples in `text`, for failure messages.
pub(super) fn refusal_samples(text: &str) -> Vec<&str> {
    text.lines()
        .filter(|line| line.starts_with("kairos_refusals_total"))
        .collect()
}

async fn server_with_metrics() -> TestServer {
    TestServer::start(ServerOptions {
        tweak: |config| config.metrics.listen = Some("127.0.0.1:0".parse().unwrap()),
        ..ServerOptions::default()
    })
    .await
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_a_round_and_ready_flips_on_shutdown() {
    let server = server_with_metrics().await;
    let addr = server
        .server()
        .metrics_addr
        .expect("metrics endpoint bound");

    let (status, before) = get(addr, "/metrics").await;
    assert_eq!(status, 200, "{before}");
    assert!(
        before.contains("Content-Type: application/openmetrics-text; version=1.0.0"),
        "{before}"
    );
    for family in [
        "kairos_queue_depth gauge",
        "kairos_workers gauge",
        "kairos_round_latency_seconds histogram",
        "kairos_batch_size histogram",
        "kairos_deadline_misses counter",
        "kairos_engine_busy_seconds counter",
        "kairos_engine_busy_ratio gauge",
    ] {
        assert!(
            before.contains(&format!("# TYPE {family}")),
            "{family}:\n{before}"
        );
    }
    // Labelled families appear with their first series (a worker, a configured plugin); this
    // server has none, and prometheus-client writes no empty family. The re-dispatch reasons
    // are declared at zero by the driver from the start.
    for family in ["kairos_worker_rtt_seconds", "kairos_plugin_fallbacks"] {
        assert!(!before.contains(family), "{family}:\n{before}");
    }
    for reason in [
        "connection_lost",
        "stream_reset",
        "invalid_answer",
        "deadline",
        "gone",
    ] {
        let series = format!("kairos_redispatch_total{{reason=\"{reason}\"}}");
        assert_eq!(sample(&before, &series), Some(0.0), "{series}:\n{before}");
    }
    assert_eq!(
        sample(&before, r#"kairos_workers{tier="edge",state="ready"}"#),
        Some(1.0)
    );
    assert_eq!(
        sample(&before, "kairos_round_latency_seconds_count"),
        Some(0.0)
    );
    assert!(before.contains(r#"kairos_engine_busy_seconds_total{engine="edge-0"}"#));

    // One round: the reply is sent after the driver recorded it.
    let client = server.connect(&server.token).await.unwrap();
    one_round(&client, 7, 0).await.unwrap();
    let (_, after) = get(addr, "/metrics").await;
    assert_eq!(
        sample(&after, "kairos_round_latency_seconds_count"),
        Some(1.0),
        "{after}"
    );
    assert_eq!(
        sample(&after, "kairos_batch_size_count"),
        Some(1.0),
        "{after}"
    );
    assert_eq!(sample(&after, "kairos_queue_depth"), Some(0.0), "{after}");
    assert!(sample(&after, "kairos_round_latency_seconds_sum").unwrap() > 0.0);

    let (status, _) = get(addr, "/ready").await;
    assert_eq!(status, 200);
    server.server().begin_shutdown();
    let (status, body) = get(addr, "/ready").await;
    assert_eq!(status, 503, "a draining server is not ready: {body}");
    client.close().await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_4xx_and_the_endpoint_keeps_serving() {
    let server = server_with_metrics().await;
    let addr = server.server().metrics_addr.unwrap();
    // Exactly the bound without the blank line: the server reads all of it (no unread bytes to
    // reset the connection) and refuses it as too large.
    let prefix = "GET /metrics HTTP/1.1\r\nX: ";
    let oversized = format!("{prefix}{}", "a".repeat(8 * 1024 - prefix.len()));
    for (request, expected) in [
        (&b"GET /nope HTTP/1.1\r\n\r\n"[..], 404),
        (b"DELETE /metrics HTTP/1.1\r\n\r\n", 405),
        (b"\x16\x03\x01\x00\xa5\x01\r\n\r\n", 400),
        (b"GET /metrics\r\n\r\n", 400),
        (b"GET /metrics HTTP/1.1\r\n", 400), // closed before the blank line
        (oversized.as_bytes(), 431),
    ] {
        let (status, text) = exchange(addr, request).await;
        assert_eq!(
            status,
            expected,
            "{:?} -> {text}",
            String::from_utf8_lossy(request)
        );
    }
    let (status, _) = get(addr, "/metrics").await;
    assert_eq!(status, 200, "still serving after bad requests");
    server.shutdown().await;
}
