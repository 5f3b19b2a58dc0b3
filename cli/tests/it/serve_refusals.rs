//! Guards are visible (`kairos serve` as users run it): clients a guard turns away are counted in
//! `/metrics` (`kairos_refusals_total{door, reason}`), logged at warn level a few lines per reason
//! however many there are, and summed in the report `kairos serve` prints when it stops. The
//! flood here is wrong keys and tokens on both endpoints, from their own loopback addresses.
//! Every wait is for an event (a line printed, a process exited); `GIVE_UP` only turns a hang
//! into a failure.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use kairos_sdk::client::{Client, ClientConfig};
use kairos_sdk::tls::Fingerprint;
use kairos_tests::openpi_wire::upgrade;

const GIVE_UP: Duration = Duration::from_secs(240);
/// Wrong openpi keys sent from one address.
const WRONG_KEYS: usize = 60;
/// Wrong QUIC tokens sent from another address.
const WRONG_TOKENS: usize = 5;
/// `failed_token_burst`: wrong tokens an address may send before it is limited.
const BURST: usize = 3;

/// The server process, killed if the test ends early.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn write_config(dir: &Path) -> std::path::PathBuf {
    std::fs::write(
        dir.join("profile.json"),
        r#"{"model":"flow-head-small","device":"cpu (test profile)","points":[{"batch":1,"latency_ms":30.0},{"batch":4,"latency_ms":60.0}],"max_batch":4}"#,
    )
    .unwrap();
    let config = dir.join("kairos.toml");
    std::fs::write(
        &config,
        format!(
            r#"listen = "127.0.0.1:0"
data_dir = "data"

[[engine]]
model = "builtin"
profile = "profile.json"

[openpi]
listen = "127.0.0.1:0"

[metrics]
listen = "127.0.0.1:0"

[connections]
failed_token_burst = {BURST}
failed_tokens_per_minute = 1
"#
        ),
    )
    .unwrap();
    config
}

/// The address after `marker` on the first stdout line that has it (`ws://ADDR`, `http://ADDR/`).
fn address(line: &str, marker: &str) -> Option<SocketAddr> {
    let rest = line.split_once(marker)?.1;
    let end = rest.find(['/', ' ']).unwrap_or(rest.len());
    rest[..end].parse().ok()
}

/// `GET /metrics`, the body.
fn scrape(addr: SocketAddr) -> String {
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: kairos\r\n\r\n")
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    response
}

fn sample(metrics: &str, door: &str, reason: &str) -> Option<u64> {
    let series = format!(r#"kairos_refusals_total{{door="{door}",reason="{reason}"}} "#);
    metrics
        .lines()
        .find_map(|line| line.strip_prefix(series.as_str())?.parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_are_counted_logged_sparingly_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_config(dir.path());
    let mut child = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .args(["serve", "--config"])
        .arg(&config)
        .env_remove("RUST_LOG")
        .env("KAIROS_ENGINE_THREADS", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let server = Server(child);
    let stderr = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = stderr.read_to_string(&mut text);
        text
    });
    let (lines_tx, lines) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if lines_tx.send(line).is_err() {
                break;
            }
        }
    });
    let (mut quic, mut openpi, mut metrics) = (None, None, None);
    let mut printed = Vec::new();
    while quic.is_none() || openpi.is_none() || metrics.is_none() {
        let line = lines
            .recv_timeout(GIVE_UP)
            .unwrap_or_else(|_| panic!("no banner from kairos serve: {printed:?}"));
        quic = quic.or(address(&line, "listening on   "));
        openpi = openpi.or(address(&line, "ws://"));
        metrics = metrics.or(address(&line, "http://"));
        printed.push(line);
    }
    let (quic, openpi, metrics) = (quic.unwrap(), openpi.unwrap(), metrics.unwrap());

    // Wrong openpi keys from one address...
    for i in 0..WRONG_KEYS {
        let (status, head, _) = upgrade("127.0.0.2", openpi, Some(&format!("guess-{i}")))
            .await
            .unwrap();
        assert!(matches!(status, 401 | 429), "{head}");
    }
    // ...and wrong QUIC tokens from another.
    let pin: Fingerprint = std::fs::read_to_string(dir.path().join("data/fingerprint.txt"))
        .unwrap()
        .parse()
        .unwrap();
    for i in 0..WRONG_TOKENS {
        let mut config = ClientConfig::pinned(quic, pin, format!("guess-{i}"));
        config.bind = Some("127.0.0.3:0".parse().unwrap());
        assert!(
            Client::connect(config).await.is_err(),
            "a wrong token got in"
        );
    }

    let text = scrape(metrics);
    let limited = (WRONG_KEYS - BURST) as u64;
    assert_eq!(
        sample(&text, "openpi", "unauthorized"),
        Some(BURST as u64),
        "{text}"
    );
    assert_eq!(sample(&text, "openpi", "wrong_token_limit"), Some(limited));
    assert_eq!(sample(&text, "quic", "unauthorized"), Some(BURST as u64));
    assert_eq!(
        sample(&text, "quic", "wrong_token_limit"),
        Some((WRONG_TOKENS - BURST) as u64)
    );

    // Ctrl-C: the report counts the refusals.
    let stopped = Command::new("kill")
        .args(["-INT", &server.0.id().to_string()])
        .status()
        .unwrap();
    assert!(stopped.success());
    let mut report = None;
    while let Ok(line) = lines.recv_timeout(GIVE_UP) {
        if line.trim_start().starts_with("refused:") {
            report = Some(line);
        }
    }
    let report = report.unwrap_or_else(|| panic!("no refusals in the report"));
    assert!(
        report.contains(&format!("quic: 2 wrong_token_limit, {BURST} unauthorized"))
            && report.contains(&format!(
                "openpi: {limited} wrong_token_limit, {BURST} unauthorized"
            )),
        "{report}"
    );
    let stderr = stderr.join().unwrap();
    // One line per endpoint and reason within the flood's few seconds (a new one at most every
    // 10 s), not one per refusal.
    let logged = stderr
        .lines()
        .filter(|line| line.contains("connection refused"))
        .count();
    assert!(
        (4..=8).contains(&logged),
        "{logged} log lines for {} refusals:\n{stderr}",
        WRONG_KEYS + WRONG_TOKENS
    );
    assert!(
        stderr
            .lines()
            .filter(|line| line.contains("connection refused"))
            .all(|line| line.contains("WARN")),
        "{stderr}"
    );
    drop(server);
}
