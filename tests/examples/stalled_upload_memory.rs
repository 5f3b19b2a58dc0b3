//! A measurement, not a test (docs/BENCHMARKS.md, "Stalled uploads"): #12 item 4's attack with the
//! default limits against a `kairos serve` process, whose memory is then the server's alone.
//!
//! `KAIROS_BIN=target/debug/kairos cargo run -p kairos-tests --example stalled_upload_memory`

#![allow(clippy::unwrap_used)] // a measurement harness; any failure ends it with the reason

use std::sync::Arc;
use std::time::Duration;

use kairos_sdk::protocol::frame::encode_header;
use kairos_sdk::protocol::{
    Hello, Limits, Message, MessageKind, PROTOCOL_VERSION, read_message, write_message,
};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, client_config};
use quinn::VarInt;

/// Guards against a hang only.
const HANG_GUARD: Duration = Duration::from_secs(60);

/// The server process's `VmRSS` and `VmHWM`, KiB.
fn process_memory_kib(pid: u32) -> Option<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| {
        status
            .lines()
            .find_map(|line| line.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

// A measurement, not a test (docs/BENCHMARKS.md, "Stalled uploads"): the same attack with the
// default limits (16 MiB frames) against a `kairos serve` process, whose memory is then the
// server's alone. `KAIROS_BIN` names the binary, so a build of another commit can be measured
// the same way; `STALL_STREAMS` (default 32) streams each announce a 16 MiB frame and send all of
// it but one byte. Samples the server's RSS for 15 s after the streams are open.
#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    use kairos_server::config::DEFAULT_ROBOT;
    use kairos_server::data_dir::DataDir;

    let bin = std::env::var("KAIROS_BIN").expect("KAIROS_BIN names the kairos binary");
    let streams: usize = std::env::var("STALL_STREAMS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(32);
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let mut child = std::process::Command::new(&bin)
        .args(["serve", "--listen", &addr.to_string(), "--data-dir"])
        .arg(dir.path().join("data"))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let pid = child.id();
    let data_dir = DataDir::new(dir.path().join("data"));
    // Wait for the server to write its pin and token and to answer.
    let connection = tokio::time::timeout(HANG_GUARD, async {
        loop {
            if let (Ok(pin), Ok(token)) = (data_dir.read_pin(), data_dir.token(DEFAULT_ROBOT)) {
                let config =
                    client_config(&ServerTrust::Pinned(pin), &TransportTuning::default()).unwrap();
                let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().unwrap()).unwrap();
                endpoint.set_default_client_config(config);
                if let Ok(connecting) = endpoint.connect(addr, "kairos")
                    && let Ok(connection) = connecting.await
                {
                    let (mut send, mut recv) = connection.open_bi().await.unwrap();
                    let hello = Message::Hello(Hello {
                        protocol: PROTOCOL_VERSION,
                        token,
                        client: "staller".into(),
                    });
                    write_message(&mut send, &hello, u32::MAX).await.unwrap();
                    send.finish().unwrap();
                    if let Ok(Some(Message::Welcome(_))) =
                        read_message(&mut recv, &Limits::default()).await
                    {
                        return (endpoint, connection);
                    }
                }
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await
    .expect("the server starts");
    let (_endpoint, connection) = connection;
    let before = process_memory_kib(pid);

    let frame = Limits::default().max_frame;
    let mut opened = Vec::new();
    for _ in 0..streams {
        let (mut send, recv) = connection.open_bi().await.unwrap();
        send.write_all(&encode_header(MessageKind::Submit, frame))
            .await
            .unwrap();
        opened.push((send, recv));
    }
    let written = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let stopped = Arc::new(std::sync::atomic::AtomicU64::new(0));
    for (mut send, recv) in opened {
        let (written, stopped) = (written.clone(), stopped.clone());
        tokio::spawn(async move {
            let body = vec![0u8; 1 << 20];
            let mut left = frame as usize - 1;
            while left > 0 {
                match send.write(&body[..left.min(body.len())]).await {
                    Ok(n) => {
                        left -= n;
                        written.fetch_add(n as u64, std::sync::atomic::Ordering::Relaxed);
                    }
                    Err(_) => {
                        stopped.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        return;
                    }
                }
            }
            let _ = send.stopped().await;
            stopped.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            drop(recv);
        });
    }
    let mut peak_rss = 0;
    let mut hwm = 0;
    for _ in 0..30 {
        tokio::time::sleep(Duration::from_millis(500)).await;
        if let Some((rss, high)) = process_memory_kib(pid) {
            peak_rss = peak_rss.max(rss);
            hwm = high;
        }
    }
    println!(
        "{bin}: {streams} streams announcing {frame} B: server RSS before {before:?} KiB, peak \
         {peak_rss} KiB, VmHWM {hwm} KiB; client wrote {} B, {} streams stopped",
        written.load(std::sync::atomic::Ordering::Relaxed),
        stopped.load(std::sync::atomic::Ordering::Relaxed),
    );
    connection.close(VarInt::from_u32(0), b"done");
    let _ = child.kill();
    let _ = child.wait();
}
