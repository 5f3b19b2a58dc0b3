//! Stalled uploads cannot pin memory (#12 item 4), over real QUIC: a robot that opens many
//! streams, announces a large frame on each and then stalls can make the server hold no more
//! than its connection's budget (`upload_buffer_frames` frames partly read, plus a QUIC receive
//! window of the same size), and every stalled stream is stopped once it falls under the minimum
//! upload rate, and counted (`too_slow` in `/metrics` and in the shutdown report). Meanwhile
//! another robot is served.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::sync::Arc;
use std::time::Duration;

use kairos_sdk::client::STREAM_REFUSED;
use kairos_sdk::protocol::frame::encode_header;
use kairos_sdk::protocol::{
    ErrorCode, HEADER_LEN, Hello, Limits, Message, MessageKind, PROTOCOL_VERSION, read_message,
    write_message,
};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, client_config};
use kairos_server::transport::refusals::{Door, Reason};
use kairos_tests::harness::{ServerOptions, TestServer, one_round};
use quinn::VarInt;

use super::metrics::{get, refusal_samples, sample};

/// Guards against a hang only; every wait below is for an event.
const HANG_GUARD: Duration = Duration::from_secs(60);
/// The test server's frame limit.
const MAX_FRAME: u32 = 1 << 20;
/// Frames a connection may have partly read (the server's `upload_buffer_frames`).
const BUFFER_FRAMES: u32 = 2;
/// Streams the attacker opens.
const STREAMS: usize = 16;
/// The attacker's own send buffer: bytes it can have written but not yet had acknowledged.
const SEND_WINDOW: u64 = 64 << 10;

/// Reads the resident set of this process from /proc (Linux), KiB.
fn rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
}

/// What one attacking stream managed: bytes the server let it write, and the code it was stopped
/// with.
struct StreamOutcome {
    written: u64,
    stopped: Option<u64>,
    error: Option<ErrorCode>,
}

/// Bytes every attacking stream has written so far, and their sum when the first stop was seen.
#[derive(Default)]
struct Tally {
    written: Vec<u64>,
    at_first_stop: Option<u64>,
}

/// After the frame header (already written), writes all but the last byte of a `MAX_FRAME` body
/// as fast as the server lets it; never finishes. Returns when the server stops the stream.
async fn stall(
    index: usize,
    tally: Arc<std::sync::Mutex<Tally>>,
    mut send: quinn::SendStream,
    mut recv: quinn::RecvStream,
) -> StreamOutcome {
    let frame = vec![0u8; MAX_FRAME as usize - 1];
    let mut written = HEADER_LEN as u64;
    let mut stopped = None;
    let first_stop = || {
        let mut tally = tally.lock().unwrap();
        let sum = tally.written.iter().sum();
        tally.at_first_stop.get_or_insert(sum);
    };
    while (written as usize - HEADER_LEN) < frame.len() {
        match send.write(&frame[written as usize - HEADER_LEN..]).await {
            Ok(n) => {
                written += n as u64;
                tally.lock().unwrap().written[index] = written;
            }
            Err(quinn::WriteError::Stopped(code)) => {
                stopped = Some(code.into_inner());
                break;
            }
            Err(other) => panic!("write failed: {other}"),
        }
    }
    if stopped.is_none() {
        // Everything went out: only a stop from the server ends the stall.
        stopped = tokio::time::timeout(HANG_GUARD, send.stopped())
            .await
            .ok()
            .and_then(|stop| stop.ok().flatten())
            .map(VarInt::into_inner);
    }
    first_stop();
    let error = match read_message(&mut recv, &Limits::default()).await {
        Ok(Some(Message::Error(error))) => Some(error.code),
        _ => None,
    };
    StreamOutcome {
        written,
        stopped,
        error,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_uploads_are_bounded_by_the_connection_budget_and_stopped() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.limits.max_frame = MAX_FRAME;
            config.limits.max_image_bytes = MAX_FRAME / 2;
            config.connections.upload_buffer_frames = BUFFER_FRAMES;
            config.connections.min_upload_bytes_per_s = 1 << 20;
            config.connections.upload_grace_ms = 500;
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
        },
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let rss_before = rss_kib();

    // The attacker: a robot with a valid token, and a small send buffer so that what it has
    // written is what the server's flow control let through (plus SEND_WINDOW).
    let mut config = client_config(
        &ServerTrust::Pinned(server.pin),
        &TransportTuning::default(),
    )
    .unwrap();
    let mut transport = TransportTuning::default().build();
    transport
        .max_concurrent_bidi_streams(VarInt::from_u32(0))
        .max_concurrent_uni_streams(VarInt::from_u32(0))
        .send_window(SEND_WINDOW);
    config.transport_config(Arc::new(transport));
    let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
    endpoint.set_default_client_config(config);
    let connection = endpoint
        .connect(server.addr, "kairos")
        .unwrap()
        .await
        .unwrap();
    let (mut send, mut recv) = connection.open_bi().await.unwrap();
    let hello = Message::Hello(Hello {
        protocol: PROTOCOL_VERSION,
        token: server.token.clone(),
        client: "staller".into(),
    });
    write_message(&mut send, &hello, u32::MAX).await.unwrap();
    send.finish().unwrap();
    match read_message(&mut recv, &Limits::default()).await.unwrap() {
        Some(Message::Welcome(_)) => {}
        other => panic!("expected Welcome, got {other:?}"),
    }

    // Every stream announces its frame before any body byte goes out, so the server sees all of
    // them at once (a stream whose first bytes flow control held back would be a later wave).
    let mut streams = Vec::new();
    for _ in 0..STREAMS {
        let (mut send, recv) = connection.open_bi().await.unwrap();
        send.write_all(&encode_header(MessageKind::Submit, MAX_FRAME))
            .await
            .unwrap();
        streams.push((send, recv));
    }
    let tally = Arc::new(std::sync::Mutex::new(Tally {
        written: vec![HEADER_LEN as u64; STREAMS],
        at_first_stop: None,
    }));
    let mut stalls = tokio::task::JoinSet::new();
    for (index, (send, recv)) in streams.into_iter().enumerate() {
        stalls.spawn(stall(index, tally.clone(), send, recv));
    }

    // Another robot is served while the attack holds its streams.
    let robot = server.connect(&server.token).await.unwrap();
    one_round(&robot, 1, 0).await.unwrap();

    let mut outcomes = Vec::new();
    let all = async {
        while let Some(outcome) = stalls.join_next().await {
            outcomes.push(outcome.unwrap());
        }
    };
    tokio::time::timeout(HANG_GUARD, all)
        .await
        .expect("every stalled stream was stopped");
    let rss_after = rss_kib();

    let written: u64 = outcomes.iter().map(|o| o.written).sum();
    let in_at_first_stop = tally
        .lock()
        .unwrap()
        .at_first_stop
        .expect("a stream was stopped");
    let budget = u64::from(BUFFER_FRAMES) * u64::from(MAX_FRAME);
    // Until the server stops a stream, flow control lets in at most the partly read frames (the
    // budget), the QUIC receive window (as large) and what the client itself buffers, plus the
    // headers. A stop returns its stream's bytes to the window, and the client may spend that
    // credit on other streams before its task for the stopped stream runs: one more stream
    // window (`MAX_FRAME`) of slack. (After the stops the total keeps growing with the credit
    // they free, which is why the snapshot is taken at the first one; what the server *holds*
    // stays bounded, see the process measurement below.)
    let bound = 2 * budget + SEND_WINDOW + (STREAMS * HEADER_LEN) as u64 + u64::from(MAX_FRAME);
    println!(
        "stalled upload: {STREAMS} streams announcing {MAX_FRAME} B each had written \
         {in_at_first_stop} B when the first was stopped (bound {bound} B, unbounded {} B), \
         {written} B in all; process RSS {rss_before:?} -> {rss_after:?} KiB",
        STREAMS as u64 * (u64::from(MAX_FRAME) + HEADER_LEN as u64 - 1)
    );
    assert!(
        in_at_first_stop <= bound,
        "the server let {in_at_first_stop} bytes of stalled uploads in, over {bound}"
    );
    for outcome in &outcomes {
        assert_eq!(
            outcome.stopped,
            Some(u64::from(STREAM_REFUSED)),
            "every stalled stream is stopped"
        );
    }
    assert!(
        outcomes
            .iter()
            .any(|outcome| outcome.error == Some(ErrorCode::TooSlow)),
        "the stopped streams are told why"
    );
    // Every stop is counted where an operator looks: in /metrics while the server runs (issue
    // #28, finding 10), and in the shutdown report below.
    let (status, text) = get(server.server().metrics_addr.unwrap(), "/metrics").await;
    assert_eq!(status, 200);
    assert_eq!(
        sample(
            &text,
            r#"kairos_refusals_total{door="quic",reason="too_slow"}"#
        ),
        Some(STREAMS as f64),
        "refusals in /metrics: {:?}",
        refusal_samples(&text)
    );

    // The server still serves.
    one_round(&robot, 1, 1).await.unwrap();
    robot.close().await;
    connection.close(VarInt::from_u32(0), b"done");
    let report = server.shutdown().await;
    assert_eq!(
        report.refusals.get(Door::Quic, Reason::TooSlow),
        STREAMS as u64
    );
}
