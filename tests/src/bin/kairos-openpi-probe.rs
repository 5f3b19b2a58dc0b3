//! `kairos-openpi-probe`: the hostile openpi clients of docs/RELIABILITY.md, at full scale,
//! against a running `kairos serve --openpi-listen ADDR` (the regression tests in
//! `tests/tests/it/openpi_guards.rs` play the same attacks small). It prints what the attack
//! achieved and, given the server's pid, the server's resident memory:
//!
//! ```text
//! kairos-openpi-probe stalls   ADDR KEY PID [connections=40] [mib=15] [hold_s=90]
//! kairos-openpi-probe upgrades ADDR KEY PID [connections=4200] [seconds=25] [sources=1]
//! kairos-openpi-probe keys     ADDR KEY PID [count=300]
//! kairos-openpi-probe chw      ADDR KEY PID [images=32]
//! ```
//!
//! - `stalls`: connections with a valid key each announce a `mib` MiB message, send all of it but
//!   one byte as fast as the server takes it, and stall; held `hold_s` seconds. Reports the
//!   server's peak RSS growth and when (if) each connection was cut.
//! - `upgrades`: for `seconds`, keeps `connections` TCP connections open from `sources` loopback
//!   addresses (127.0.0.2 and up), each with half an upgrade and no key, reopening any the server
//!   closes; meanwhile 16 clients from 127.0.0.1 connect one after another with `KEY` and ask one
//!   round each. Reports how many of the 16 were served.
//! - `keys`: `count` upgrades with wrong keys from 127.0.0.2, as fast as they go, then one with
//!   `KEY` from the same address. Reports the statuses.
//! - `chw`: `images` connections at once, each sending one `[3, 2048, 2100]` `uint8` image
//!   (channel-first, over the default `max_image_bytes` and `max_image_pixels`). Reports the
//!   server's peak RSS growth and the time until every one was refused.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use kairos_server::openpi::msgpack::Writer;
use kairos_tests::openpi_wire::{
    connect_from, frame, frame_header, opcode, read_frame, read_until_close, upgrade,
    upgrade_request,
};
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;

/// A `/proc/PID/status` field, KiB.
fn status_kib(pid: u32, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|line| line.strip_prefix(field))
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// The `n`th optional argument after the four fixed ones, or `default`.
fn arg(args: &[String], n: usize, default: u64) -> anyhow::Result<u64> {
    match args.get(4 + n) {
        Some(text) => text.parse().with_context(|| format!("argument `{text}`")),
        None => Ok(default),
    }
}

/// A request with the default keys for the built-in model (a state of 8) and `image`.
fn request(image: (&[usize], &[u8])) -> Vec<u8> {
    let mut w = Writer::new();
    w.map(2);
    w.str("observation/state").ndarray_f32(&[8], &[0.0; 8]);
    w.str("observation/image")
        .ndarray_raw(image.0, "|u1", image.1);
    w.finish()
}

/// Connects with `key` from `source` and reads the metadata.
async fn connected(source: &str, addr: SocketAddr, key: &str) -> anyhow::Result<TcpStream> {
    let (status, head, mut stream) = upgrade(source, addr, Some(key)).await?;
    if status != 101 {
        bail!("upgrade refused: {}", head.lines().next().unwrap_or(""));
    }
    let (kind, _) = read_frame(&mut stream).await?;
    if kind != opcode::BINARY {
        bail!("no metadata");
    }
    Ok(stream)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [probe, addr, key, pid, ..] = args.as_slice() else {
        bail!("usage: kairos-openpi-probe stalls|upgrades|keys|chw ADDR KEY PID [ARGS...]");
    };
    let addr: SocketAddr = addr.parse()?;
    let pid: u32 = pid.parse()?;
    match probe.as_str() {
        "stalls" => stalls(addr, key, pid, &args).await,
        "upgrades" => upgrades(addr, key, &args).await,
        "keys" => keys(addr, key).await,
        "chw" => chw(addr, key, pid, &args).await,
        other => bail!("unknown probe `{other}`"),
    }
}

async fn stalls(addr: SocketAddr, key: &str, pid: u32, args: &[String]) -> anyhow::Result<()> {
    let connections = arg(args, 0, 40)? as usize;
    let size = arg(args, 1, 15)? << 20;
    let hold = Duration::from_secs(arg(args, 2, 90)?);
    let rss_before = status_kib(pid, "VmRSS:").unwrap_or(0);
    let started = Instant::now();
    let written = Arc::new(AtomicU64::new(0));
    let mut tasks = tokio::task::JoinSet::new();
    for _ in 0..connections {
        let stream = connected("127.0.0.1", addr, key).await?;
        let (mut read, mut write) = stream.into_split();
        let written = written.clone();
        tasks.spawn(async move {
            let writer = tokio::spawn(async move {
                let _ = write
                    .write_all(&frame_header(opcode::BINARY, size, [9, 9, 9, 9]))
                    .await;
                let chunk = vec![0u8; 64 << 10];
                let mut sent = 0u64;
                while sent + 1 < size {
                    let n = (size - 1 - sent).min(chunk.len() as u64) as usize;
                    if write.write_all(&chunk[..n]).await.is_err() {
                        break;
                    }
                    sent += n as u64;
                    written.fetch_add(n as u64, Ordering::Relaxed);
                }
                // Stall: keep the write half open.
                std::future::pending::<()>().await;
            });
            let ending = read_until_close(&mut read, Duration::from_secs(86_400)).await;
            writer.abort();
            (
                started.elapsed(),
                ending.map(|e| e.texts).unwrap_or_default(),
            )
        });
    }
    let mut peak = rss_before;
    let mut cut = Vec::new();
    let deadline = started + hold;
    while Instant::now() < deadline && cut.len() < connections {
        tokio::select! {
            Some(done) = tasks.join_next() => cut.push(done?),
            () = tokio::time::sleep(Duration::from_millis(200)) => {}
        }
        peak = peak.max(status_kib(pid, "VmRSS:").unwrap_or(0));
    }
    let too_slow = cut
        .iter()
        .filter(|(_, texts)| texts.iter().any(|t| t.starts_with("too_slow")))
        .count();
    let last_cut = cut.iter().map(|(at, _)| *at).max();
    println!(
        "stalls: {connections} connections announcing {} MiB; client wrote {:.1} MiB in all",
        size >> 20,
        written.load(Ordering::Relaxed) as f64 / (1 << 20) as f64
    );
    println!(
        "  server RSS {:.1} MiB before, peak {:.1} MiB within {} s: +{:.1} MiB",
        mib(rss_before),
        mib(peak),
        hold.as_secs(),
        mib(peak.saturating_sub(rss_before))
    );
    println!(
        "  cut by the server within {} s: {} ({} told too_slow), the last at {:?}",
        hold.as_secs(),
        cut.len(),
        too_slow,
        last_cut
    );
    tasks.abort_all();
    Ok(())
}

async fn upgrades(addr: SocketAddr, key: &str, args: &[String]) -> anyhow::Result<()> {
    let connections = arg(args, 0, 4200)? as usize;
    let seconds = arg(args, 1, 25)?;
    let sources = arg(args, 2, 1)?.clamp(1, 250) as usize;
    let until = Instant::now() + Duration::from_secs(seconds);
    let opened = Arc::new(AtomicU64::new(0));
    let half = upgrade_request(addr, None);
    let half = half.as_bytes()[..half.len() / 2].to_vec();
    let mut attackers = tokio::task::JoinSet::new();
    for i in 0..connections {
        let source = format!("127.0.0.{}", 2 + i % sources);
        let opened = opened.clone();
        let half = half.clone();
        attackers.spawn(async move {
            while Instant::now() < until {
                let Ok(mut stream) = connect_from(&source, addr).await else {
                    tokio::time::sleep(Duration::from_millis(10)).await;
                    continue;
                };
                opened.fetch_add(1, Ordering::Relaxed);
                if stream.write_all(&half).await.is_err() {
                    continue;
                }
                // Held until the server closes it (or the flood ends).
                let left = until.saturating_duration_since(Instant::now());
                let _ = tokio::time::timeout(left, read_frame(&mut stream)).await;
            }
        });
    }
    // Sixteen real clients, spread over the flood.
    let mut served = 0;
    let mut failures = BTreeMap::<String, u32>::new();
    let step = Duration::from_millis(seconds * 1000 / 17);
    for _ in 0..16 {
        tokio::time::sleep(step).await;
        let round = async {
            let mut stream = connected("127.0.0.1", addr, key).await?;
            stream
                .write_all(&frame(opcode::BINARY, &request((&[8, 8, 3], &[9; 192]))))
                .await?;
            let (kind, reply) = read_frame(&mut stream).await?;
            anyhow::ensure!(
                kind == opcode::BINARY,
                "no reply: {}",
                String::from_utf8_lossy(&reply)
            );
            anyhow::Ok(())
        };
        match tokio::time::timeout(Duration::from_secs(10), round).await {
            Ok(Ok(())) => served += 1,
            Ok(Err(error)) => *failures.entry(format!("{error:#}")).or_default() += 1,
            Err(_) => *failures.entry("no answer within 10 s".into()).or_default() += 1,
        }
    }
    attackers.abort_all();
    println!(
        "upgrades: {connections} half-sent upgrades held from {sources} address(es) for {seconds} s \
         ({} connections opened in all)",
        opened.load(Ordering::Relaxed)
    );
    println!("  legitimate clients served: {served} of 16; failures: {failures:?}");
    Ok(())
}

async fn keys(addr: SocketAddr, key: &str) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut statuses = BTreeMap::<u16, u32>::new();
    for i in 0..300 {
        let (status, _, _) = upgrade("127.0.0.2", addr, Some(&format!("wrong-{i}"))).await?;
        *statuses.entry(status).or_default() += 1;
    }
    let elapsed = started.elapsed();
    let (right, _, _) = upgrade("127.0.0.2", addr, Some(key)).await?;
    println!("keys: 300 wrong keys in {elapsed:?} from one address: statuses {statuses:?}");
    println!("  then the right key from that address: {right}");
    Ok(())
}

async fn chw(addr: SocketAddr, key: &str, pid: u32, args: &[String]) -> anyhow::Result<()> {
    let images = arg(args, 0, 32)? as usize;
    let shape = [3usize, 2048, 2100];
    let pixels = vec![7u8; shape.iter().product()];
    let message = Arc::new(frame(opcode::BINARY, &request((&shape, &pixels))));
    drop(pixels);
    let rss_before = status_kib(pid, "VmRSS:").unwrap_or(0);
    let peak = Arc::new(AtomicU64::new(rss_before));
    let sampler = {
        let peak = peak.clone();
        tokio::spawn(async move {
            loop {
                peak.fetch_max(status_kib(pid, "VmRSS:").unwrap_or(0), Ordering::Relaxed);
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };
    let started = Instant::now();
    let mut tasks = tokio::task::JoinSet::new();
    for _ in 0..images {
        let stream = connected("127.0.0.1", addr, key).await?;
        let message = message.clone();
        tasks.spawn(async move {
            let (mut read, mut write) = stream.into_split();
            // Written beside the read: a cut upload may never finish writing.
            let writer = tokio::spawn(async move { write.write_all(&message).await });
            let ending = read_until_close(&mut read, Duration::from_secs(600)).await;
            writer.abort();
            ending
        });
    }
    let mut answers = BTreeMap::<String, u32>::new();
    while let Some(done) = tasks.join_next().await {
        let code = match done? {
            Ok(ending) => ending
                .texts
                .first()
                .and_then(|t| t.split(':').next())
                .unwrap_or("closed without text")
                .to_string(),
            Err(error) => format!("{error:#}"),
        };
        *answers.entry(code).or_default() += 1;
    }
    let elapsed = started.elapsed();
    sampler.abort();
    let peak = peak.load(Ordering::Relaxed);
    println!(
        "chw: {images} channel-first {shape:?} uint8 images ({:.1} MB each) at once: answers \
         {answers:?} in {elapsed:?}",
        message.len() as f64 / 1e6
    );
    println!(
        "  server RSS {:.1} MiB before, peak {:.1} MiB (sampled every 20 ms): +{:.1} MiB",
        mib(rss_before),
        mib(peak),
        mib(peak.saturating_sub(rss_before))
    );
    Ok(())
}
