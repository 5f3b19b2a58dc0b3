//! The openpi endpoint holds what the QUIC endpoint holds, over the real websocket endpoint, each
//! attack played as a hostile client plays it (raw TCP, `kairos_tests::openpi_wire`):
//! - uploads that stall are cut once they fall under the minimum rate, and one robot's stalls
//!   cannot hold more than its budget nor hurt another robot;
//! - half-sent upgrades without a key cannot lock openpi clients out;
//! - wrong keys are rate-limited per source, before they are looked at, by the same limiter the
//!   QUIC endpoint uses;
//! - a channel-first image over the limits is refused from its shape, before it is copied or
//!   transposed (peak memory measured in a child process).
//!
//! Every wait is for an event; the durations below only turn a hang into a failure.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::time::Duration;

use kairos_server::config::Config;
use kairos_server::openpi::msgpack::Writer;
use kairos_tests::harness::{ServerOptions, TestServer};
use kairos_tests::openpi_wire::{
    self, Ending, connect_from, frame, frame_header, opcode, read_frame, read_until_close, upgrade,
};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

/// Turns a hang into a failure; never a timing margin.
const HANG_GUARD: Duration = Duration::from_secs(60);

fn robots(tweak: fn(&mut Config)) -> ServerOptions {
    ServerOptions {
        robots: vec![
            ("arm-1".to_string(), "token-one".to_string()),
            ("arm-2".to_string(), "token-two".to_string()),
        ],
        tweak,
        ..ServerOptions::default()
    }
}

fn openpi_addr(server: &TestServer) -> SocketAddr {
    server.server().openpi_addr.expect("openpi endpoint on")
}

/// A LIBERO-like request for the test model (state of 6, one 8x8 RGB image).
fn request() -> Vec<u8> {
    let mut w = Writer::new();
    w.map(3);
    w.str("observation/state")
        .ndarray_f32(&[6], &[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
    w.str("observation/image")
        .ndarray_raw(&[8, 8, 3], "|u1", &[100; 8 * 8 * 3]);
    w.str("prompt").str("pick up the cup");
    w.finish()
}

/// Connects with `key` from `source`, reads the metadata and returns the open connection.
async fn connected(source: &str, server: SocketAddr, key: &str) -> TcpStream {
    let (status, head, mut stream) = upgrade(source, server, Some(key)).await.unwrap();
    assert_eq!(status, 101, "{head}");
    let (kind, _) = read_frame(&mut stream).await.unwrap();
    assert_eq!(kind, opcode::BINARY, "the metadata comes first");
    stream
}

/// One round on an open connection: the reply is a binary message.
async fn one_round(stream: &mut TcpStream) {
    stream
        .write_all(&frame(opcode::BINARY, &request()))
        .await
        .unwrap();
    let (kind, reply) = tokio::time::timeout(HANG_GUARD, read_frame(stream))
        .await
        .expect("a reply")
        .unwrap();
    assert_eq!(kind, opcode::BINARY, "{}", String::from_utf8_lossy(&reply));
}

/// `kairos_refusals_total{door="openpi",reason=...}` in the server's metrics, if exported.
fn refusals(server: &TestServer, reason: &str) -> Option<u64> {
    let series = format!(r#"kairos_refusals_total{{door="openpi",reason="{reason}"}} "#);
    server
        .server()
        .metrics
        .encode()
        .lines()
        .find_map(|line| line.strip_prefix(series.as_str())?.parse().ok())
}

const MAX_FRAME: u32 = 1 << 20;
const STALLERS: usize = 8;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_openpi_uploads_are_cut_and_do_not_hurt_another_robot() {
    let server = TestServer::start(robots(|config| {
        config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
        config.limits.max_frame = MAX_FRAME;
        config.connections.upload_buffer_frames = 2;
        config.connections.min_upload_bytes_per_s = 1 << 20;
        config.connections.upload_grace_ms = 500;
    }))
    .await
    .unwrap();
    let addr = openpi_addr(&server);

    // arm-1 opens connections, announces a whole frame on each, sends a quarter of it and
    // stalls. The writers run as tasks: the server may hold them back (its budget) until it
    // cuts them. Each keeps its write half open, so the server sees a stall, not an end.
    let mut stallers = Vec::new();
    let mut writers = tokio::task::JoinSet::new();
    for _ in 0..STALLERS {
        let stream = connected("127.0.0.1", addr, "token-one").await;
        let (read, mut write) = stream.into_split();
        writers.spawn(async move {
            let header = frame_header(opcode::BINARY, u64::from(MAX_FRAME), [1, 2, 3, 4]);
            let _ = write.write_all(&header).await;
            let _ = write.write_all(&vec![0u8; MAX_FRAME as usize / 4]).await;
            write
        });
        stallers.push(read);
    }

    // Another robot is served while they stall.
    let mut other = connected("127.0.0.1", addr, "token-two").await;
    one_round(&mut other).await;

    // Every stalled upload is cut, and told why.
    for (i, stream) in stallers.iter_mut().enumerate() {
        let ending = read_until_close(stream, HANG_GUARD)
            .await
            .unwrap_or_else(|_| panic!("stalled upload {i} was never cut"));
        assert!(
            ending.texts.iter().any(|t| t.starts_with("too_slow")),
            "upload {i}: {ending:?}"
        );
        assert_eq!(ending.close_code, Some(1008), "upload {i}: {ending:?}");
    }
    assert_eq!(refusals(&server, "too_slow"), Some(STALLERS as u64));
    let write_halves = writers.join_all().await;

    // The robot whose uploads stalled is served again, and so is the other.
    let mut again = connected("127.0.0.1", addr, "token-one").await;
    one_round(&mut again).await;
    one_round(&mut other).await;
    drop((again, other, write_halves));
    server.shutdown().await;
}

const ATTACKERS: usize = 200;
const PER_SOURCE: usize = 16;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_sent_upgrades_without_a_key_do_not_lock_openpi_clients_out() {
    let server = TestServer::start(robots(|config| {
        config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
        // Few places, so that the flood outnumbers them many times over; a handshake deadline
        // longer than the test, so that no attacker's place is freed by its timeout.
        config.connections.max_connections = 32;
        config.connections.max_unauthenticated = 64;
        config.connections.max_unauthenticated_per_source = PER_SOURCE;
        config.connections.hello_timeout_ms = 600_000;
    }))
    .await
    .unwrap();
    let addr = openpi_addr(&server);

    // 127.0.0.2 opens connection after connection, each with half an upgrade and no key.
    let mut attackers = Vec::new();
    for _ in 0..ATTACKERS {
        let mut stream = connect_from("127.0.0.2", addr).await.unwrap();
        let request = openpi_wire::upgrade_request(addr, None);
        let _ = stream
            .write_all(&request.as_bytes()[..request.len() / 2])
            .await;
        attackers.push(stream);
    }

    // Sixteen openpi clients from another address connect and are served.
    for _ in 0..16 {
        let mut client = connected("127.0.0.1", addr, "token-one").await;
        one_round(&mut client).await;
    }
    // The flood held its share of the handshake places; every other attempt was refused at once.
    assert_eq!(
        refusals(&server, "source_handshakes"),
        Some((ATTACKERS - PER_SOURCE) as u64)
    );
    drop(attackers);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_openpi_keys_are_rate_limited_before_they_are_looked_at() {
    let server = TestServer::start(robots(|config| {
        config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
        config.connections.failed_token_burst = 3;
        config.connections.failed_tokens_per_minute = 1;
    }))
    .await
    .unwrap();
    let addr = openpi_addr(&server);

    let mut statuses = Vec::new();
    for i in 0..30 {
        let (status, head, _) = upgrade("127.0.0.2", addr, Some(&format!("guess-{i}")))
            .await
            .unwrap();
        if status == 429 {
            assert!(
                head.contains("retry-after") || head.contains("Retry-After"),
                "{head}"
            );
        }
        statuses.push(status);
    }
    let mut expected = vec![401; 3];
    expected.extend([429; 27]);
    assert_eq!(statuses, expected);

    // The right key from that address is refused too: the key is never looked at.
    let (status, _, _) = upgrade("127.0.0.2", addr, Some("token-one")).await.unwrap();
    assert_eq!(status, 429);
    // The limiter is the server's, not the endpoint's: QUIC refuses the address as well.
    let mut config = server.client_config(server.addr, "token-one");
    config.bind = Some("127.0.0.2:0".parse().unwrap());
    assert!(
        kairos_sdk::client::Client::connect(config).await.is_err(),
        "a QUIC robot from a source out of wrong tokens got in"
    );
    // Another address is not affected.
    let mut client = connected("127.0.0.1", addr, "token-one").await;
    one_round(&mut client).await;
    assert_eq!(refusals(&server, "unauthorized"), Some(3));
    assert_eq!(refusals(&server, "wrong_token_limit"), Some(28));
    drop(client);
    server.shutdown().await;
}

/// Set in the child process of the test below.
const RSS_CHILD: &str = "KAIROS_OPENPI_CHW_RSS_CHILD";
/// Large channel-first images sent, one connection each (an error closes the connection).
const CHW_IMAGES: usize = 4;
/// `[3, 2048, 2100]` `uint8`: 12.9 MB, within the frame limit, over `max_image_bytes` and
/// `max_image_pixels`.
const CHW_SHAPE: [usize; 3] = [3, 2048, 2100];

/// The peak resident set of this process (Linux `VmHWM`), KiB.
fn peak_rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmHWM:"))
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
}

/// Runs in a child process, so that no other test's allocations move the high-water mark: a
/// server with the default limits, and a client that sends `CHW_IMAGES` channel-first images
/// over `max_image_bytes`. The child reports how much the peak grew while the server refused
/// them. Before the fix the server transposed each image (building an index of eight bytes per
/// value, then the copy) before checking its size.
#[test]
fn a_channel_first_image_over_the_limits_is_refused_before_it_is_copied() {
    if std::env::var_os(RSS_CHILD).is_some() {
        chw_child();
        return;
    }
    let exe = std::env::current_exe().unwrap();
    let name = match module_path!().split_once("::") {
        Some((_, module)) => {
            format!(
                "{module}::a_channel_first_image_over_the_limits_is_refused_before_it_is_copied"
            )
        }
        None => "a_channel_first_image_over_the_limits_is_refused_before_it_is_copied".into(),
    };
    let out = std::process::Command::new(exe)
        .args(["--exact", name.as_str(), "--nocapture", "--test-threads=1"])
        .env(RSS_CHILD, "1")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let value = |key: &str| {
        stdout
            .lines()
            .find_map(|l| l.split_once(key).map(|(_, value)| value.trim().to_owned()))
            .unwrap_or_else(|| panic!("no {key} in {stdout}"))
    };
    let growth = value("rss-growth-kib:");
    if growth == "unavailable" {
        // No procfs (not Linux): the refusals were still checked in the child.
        return;
    }
    let growth: u64 = growth.parse().unwrap();
    eprintln!(
        "{CHW_IMAGES} channel-first images of {CHW_SHAPE:?} refused in {} ms, peak RSS growth {growth} KiB",
        value("refusal-ms:")
    );
    // Each image is received whole (12.9 MB) before it can be looked at; what must not happen
    // is a transpose or copy on top of that.
    assert!(
        growth < 48 * 1024,
        "peak RSS grew by {growth} KiB refusing {CHW_IMAGES} oversized images"
    );
}

fn chw_child() {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let server = TestServer::start(robots(|config| {
            config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
        }))
        .await
        .unwrap();
        let addr = openpi_addr(&server);
        // Warm up the endpoint and the engine with a normal round.
        let mut warm = connected("127.0.0.1", addr, "token-one").await;
        one_round(&mut warm).await;
        drop(warm);
        // Built before the baseline: the client's own frame is not the server's growth.
        let pixels: usize = CHW_SHAPE.iter().product();
        let mut w = Writer::new();
        w.map(2);
        w.str("observation/state").ndarray_f32(&[6], &[0.0; 6]);
        w.str("observation/image")
            .ndarray_raw(&CHW_SHAPE, "|u1", &vec![7u8; pixels]);
        let message = frame(opcode::BINARY, &w.finish());
        let Some(before) = peak_rss_kib() else {
            println!("rss-growth-kib: unavailable");
            return;
        };
        let started = std::time::Instant::now();
        for _ in 0..CHW_IMAGES {
            let mut stream = connected("127.0.0.1", addr, "token-one").await;
            stream.write_all(&message).await.unwrap();
            let ending: Ending = read_until_close(&mut stream, HANG_GUARD).await.unwrap();
            assert!(
                ending.texts.iter().any(|t| t.starts_with("too_large")),
                "{ending:?}"
            );
        }
        let elapsed = started.elapsed();
        let after = peak_rss_kib().unwrap_or(u64::MAX);
        println!("refusal-ms: {}", elapsed.as_millis());
        println!("rss-growth-kib: {}", after.saturating_sub(before));
        server.shutdown().await;
    });
}
