//! The metrics listener under silent clients, over real TCP (issue #28, finding 9): silent
//! connections held open must not delay a probe of `/ready`, whose Kubernetes timeout is one
//! second. The listener here waits for request heads far longer than the test runs, so nothing in
//! it depends on how fast the machine is: a probe answered while every silent connection is
//! still open was not queued behind them.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::time::Duration;

use kairos_server::metrics::http::{self, ListenerOptions};
use kairos_server::metrics::{Metrics, Readiness};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Head timeout of the listeners here: longer than any run of this test.
const PATIENT: Duration = Duration::from_secs(3600);

/// A scheduler's metrics listener on loopback with `options`, ready; served until the test ends.
async fn listener(options: ListenerOptions) -> (SocketAddr, Metrics) {
    let socket = http::bind("127.0.0.1:0".parse().unwrap()).await.unwrap();
    let addr = socket.local_addr().unwrap();
    let metrics = Metrics::new();
    let ready = Readiness::new();
    ready.set(true);
    tokio::spawn(http::serve_with(
        socket,
        metrics.clone(),
        ready,
        options,
        std::future::pending(),
    ));
    (addr, metrics)
}

/// `GET /ready` as a probe sends it; the status code.
async fn probe(addr: SocketAddr) -> u16 {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(b"GET /ready HTTP/1.1\r\nHost: kairos\r\nUser-Agent: kube-probe/1.32\r\n\r\n")
        .await
        .unwrap();
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await.unwrap();
    let text = String::from_utf8(response).unwrap();
    text.get(9..12).unwrap().parse().unwrap()
}

/// `n` connections that send nothing, or the start of a request head and then nothing.
async fn silent(addr: SocketAddr, n: usize) -> Vec<TcpStream> {
    let mut streams = Vec::new();
    for i in 0..n {
        let mut stream = TcpStream::connect(addr).await.unwrap();
        if i % 2 == 1 {
            stream
                .write_all(b"GET /metrics HTTP/1.1\r\nHo")
                .await
                .unwrap();
        }
        streams.push(stream);
    }
    streams
}

/// What the server did to a silent connection.
#[derive(Debug, PartialEq, Eq)]
enum Fate {
    /// Nothing yet: open, no byte received.
    Open,
    /// Closed (end of stream, or reset) without a byte of answer.
    Closed,
    /// Answered (a 408, say).
    Answered,
}

/// What the server did to `stream` so far.
fn fate(stream: &TcpStream) -> Fate {
    let mut byte = [0u8; 1];
    match stream.try_read(&mut byte) {
        Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => Fate::Open,
        Ok(0) | Err(_) => Fate::Closed,
        Ok(_) => Fate::Answered,
    }
}

/// Waits until the server does something to `stream` (bounded only by a generous give-up
/// time, so that a listener that never acts fails instead of hanging CI).
async fn outcome(stream: &TcpStream) -> Fate {
    tokio::time::timeout(Duration::from_secs(120), async {
        loop {
            stream.readable().await.unwrap();
            match fate(stream) {
                Fate::Open => continue,
                done => return done,
            }
        }
    })
    .await
    .expect("the server acted on the connection")
}

fn sample(metrics: &Metrics, series: &str) -> f64 {
    metrics
        .encode()
        .lines()
        .find_map(|l| l.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(0.0)
}

/// 48 silent connections (more than the 32 the listener once served at once, while the rest
/// waited in the accept queue): the probe is answered, and not one silent connection had to be
/// answered or closed for it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_do_not_delay_a_probe_of_ready() {
    let (addr, _metrics) = listener(ListenerOptions {
        head_timeout: PATIENT,
        ..ListenerOptions::default()
    })
    .await;
    let held = silent(addr, 48).await;
    assert_eq!(probe(addr).await, 200);
    for (i, stream) in held.iter().enumerate() {
        assert_eq!(fate(stream), Fate::Open, "silent connection {i}");
    }
}

/// More silent connections from one address than it may hold: each new connection displaces the
/// oldest silent one, so a probe from that very address is still answered; the displaced
/// connections are closed without an answer, and counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_address_gives_way_to_a_probe_by_evicting_its_oldest_silent_connection() {
    let per_address = 8;
    let (addr, metrics) = listener(ListenerOptions {
        head_timeout: PATIENT,
        max_connections: 64,
        max_connections_per_address: per_address,
    })
    .await;
    let held = silent(addr, per_address + 4).await;
    assert_eq!(probe(addr).await, 200);
    // The 4 beyond the cap and the probe each displaced the oldest: the first 5 are closed
    // without an answer (eviction happens before the next connection is admitted; the close may
    // still be on its way through loopback, hence the wait), the others are untouched.
    for (i, stream) in held.iter().enumerate() {
        if i < 5 {
            assert_eq!(outcome(stream).await, Fate::Closed, "connection {i}");
        } else {
            assert_eq!(fate(stream), Fate::Open, "connection {i}");
        }
    }
    assert_eq!(
        sample(
            &metrics,
            r#"kairos_refusals_total{door="metrics",reason="evicted_idle"}"#
        ),
        5.0
    );
}

/// Sends `bytes`, half-closes unless `keep_open`, and returns the status of the answer.
async fn exchange(addr: SocketAddr, bytes: &[u8], keep_open: bool) -> u16 {
    let mut stream = TcpStream::connect(addr).await.unwrap();
    stream.write_all(bytes).await.unwrap();
    if !keep_open {
        stream.shutdown().await.unwrap();
    }
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await.unwrap();
    let text = String::from_utf8(response).unwrap();
    text.get(9..12).unwrap().parse().unwrap()
}

/// What the listener refuses is answered with its status and counted by reason.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_are_answered_and_counted_by_reason() {
    let (addr, metrics) = listener(ListenerOptions {
        // The silent client below never sends its head; any timeout gives it a 408.
        head_timeout: Duration::from_millis(100),
        ..ListenerOptions::default()
    })
    .await;
    let refused = |reason: &str| {
        sample(
            &metrics,
            &format!("kairos_refusals_total{{door=\"metrics\",reason=\"{reason}\"}}"),
        )
    };
    assert_eq!(exchange(addr, b"NOT HTTP\r\n\r\n", false).await, 400);
    let huge = [
        b"GET /metrics HTTP/1.1\r\nX: ".as_slice(),
        &vec![b'a'; http::MAX_HEAD],
    ]
    .concat();
    // Exactly the most the listener reads, so that nothing is left unread when it closes (which
    // would reset the connection, and could discard the answer before the client reads it).
    assert_eq!(exchange(addr, &huge[..http::MAX_HEAD], false).await, 431);
    assert_eq!(
        exchange(addr, b"GET /metrics HTTP/1.1\r\n", true).await,
        408
    );
    assert_eq!(refused("malformed"), 1.0);
    assert_eq!(refused("head_too_large"), 1.0);
    assert_eq!(refused("head_timeout"), 1.0);
    assert_eq!(refused("evicted_idle"), 0.0);
    assert_eq!(probe(addr).await, 200, "and the listener still answers");
}
