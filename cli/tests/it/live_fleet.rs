//! A live fleet as an operator runs one, for the tests that look at it from outside (the fleet
//! page in a browser, Prometheus): `kairos serve --local-engines 0` (the scheduler of the
//! Kubernetes manifests) with a horizon plugin and a priority plugin, its metrics listener on
//! loopback; two `kairos worker` processes registered to it, which run every batch; a
//! `kairos robot` fleet sending rounds until it is stopped. Every
//! wait is for an event seen through the metrics listener (workers registered, robots connected,
//! rounds answered), bounded only by a generous give-up time.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::repo_root;

/// Give-up time for any one wait (a hung run fails instead of blocking CI).
pub const GIVE_UP: Duration = Duration::from_secs(300);

/// The processes of a fleet; killed when dropped, however the test ends.
pub struct LiveFleet {
    /// The data directory shared by the server, the workers and the robots.
    pub dir: tempfile::TempDir,
    /// The server's metrics listener.
    pub metrics: SocketAddr,
    serve: Child,
    workers: Vec<Child>,
    fleet: Option<Child>,
    /// Everything `kairos serve` printed.
    output: Arc<Mutex<Vec<String>>>,
}

impl Drop for LiveFleet {
    fn drop(&mut self) {
        let children = std::iter::once(&mut self.serve)
            .chain(self.workers.iter_mut())
            .chain(self.fleet.iter_mut());
        for child in children {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A fixed profile for the workers, so they start without measuring one.
fn write_profile(dir: &Path) -> PathBuf {
    let path = dir.join("profile.json");
    std::fs::write(
        &path,
        r#"{"model":"flow-head-small","device":"cpu (test profile)","points":[{"batch":1,"latency_ms":30.0},{"batch":4,"latency_ms":60.0}],"max_batch":4}"#,
    )
    .unwrap();
    path
}

fn kairos() -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_kairos"));
    command.env("KAIROS_ENGINE_THREADS", "1");
    command
}

/// `GET path` on `addr`: (status, body).
pub fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    write!(stream, "GET {path} HTTP/1.1\r\nHost: kairos\r\n\r\n").unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let (head, body) = response.split_once("\r\n\r\n").unwrap();
    let status = head.get(9..12).unwrap().parse().unwrap();
    (status, body.to_string())
}

impl LiveFleet {
    /// Starts the server and its workers, then `robots` robots; returns once every robot is
    /// connected and the fleet has answered rounds on both workers' side of the pool.
    pub fn start(robots: u64) -> LiveFleet {
        let dir = tempfile::tempdir().unwrap();
        let plugins = repo_root().join("plugins/build");
        for plugin in ["threshold.wasm", "kairos.wasm"] {
            assert!(
                plugins.join(plugin).exists(),
                "{} is missing: build the plugins first (KAIROS_BIN=target/debug/kairos bash \
                 plugins/build.sh; scripts/test.sh does)",
                plugins.join(plugin).display()
            );
        }
        let mut serve = kairos()
            .args(["serve", "--listen", "127.0.0.1:0"])
            .args(["--metrics-listen", "127.0.0.1:0", "--local-engines", "0"])
            .arg("--data-dir")
            .arg(dir.path().join("data"))
            .arg("--horizon-plugin")
            .arg(plugins.join("threshold.wasm"))
            .arg("--priority-plugin")
            .arg(plugins.join("kairos.wasm"))
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let output = Arc::new(Mutex::new(Vec::new()));
        let (found, addresses) = std::sync::mpsc::channel();
        let stdout = serve.stdout.take().unwrap();
        let lines = output.clone();
        std::thread::spawn(move || {
            let (mut quic, mut metrics) = (None, None);
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let word = |prefix: &str| {
                    let rest = line.trim_start().strip_prefix(prefix)?;
                    let addr = rest.split_whitespace().next()?;
                    let addr = addr.trim_start_matches("http://");
                    let addr = addr.split('/').next()?;
                    addr.parse::<SocketAddr>().ok()
                };
                quic = quic.or_else(|| word("listening on"));
                metrics = metrics.or_else(|| word("metrics"));
                lines.lock().unwrap().push(line);
                if let (Some(q), Some(m)) = (quic, metrics) {
                    let _ = found.send((q, m));
                    quic = None;
                    metrics = None;
                }
            }
        });
        let Ok((quic, metrics)) = addresses.recv_timeout(GIVE_UP) else {
            let _ = serve.kill();
            panic!(
                "kairos serve did not print its addresses:\n{}",
                output.lock().unwrap().join("\n")
            );
        };
        let mut fleet = LiveFleet {
            metrics,
            serve,
            workers: Vec::new(),
            fleet: None,
            output,
            dir,
        };
        let profile = write_profile(fleet.dir.path());
        for id in ["w0", "w1"] {
            let worker = kairos()
                .args(["worker", "--server", &quic.to_string()])
                .arg("--data-dir")
                .arg(fleet.dir.path().join("data"))
                .arg("--profile")
                .arg(&profile)
                .args(["--worker-id", id, "--max-batch", "4"])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap();
            fleet.workers.push(worker);
        }
        fleet.wait_for("both workers registered", |s| {
            s["engines"].as_array().is_some_and(|e| e.len() == 2)
        });
        let robots_fleet = kairos()
            .args(["robot", "--server", &quic.to_string()])
            .arg("--data-dir")
            .arg(fleet.dir.path().join("data"))
            .args(["--robots", &robots.to_string(), "--rounds", "1000000"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        fleet.fleet = Some(robots_fleet);
        fleet.wait_for("every robot connected and rounds answered", |s| {
            s["robots"]["connected"] == robots && s["window"]["rounds"].as_u64() >= Some(robots * 3)
        });
        fleet
    }

    /// The fleet snapshot now (`GET /api/fleet`).
    pub fn snapshot(&self) -> serde_json::Value {
        let (status, body) = http_get(self.metrics, "/api/fleet");
        assert_eq!(status, 200, "{body}");
        serde_json::from_str(&body).unwrap()
    }

    /// Polls the snapshot until `done` holds.
    pub fn wait_for(&self, what: &str, done: impl Fn(&serde_json::Value) -> bool) {
        let started = Instant::now();
        loop {
            let snapshot = self.snapshot();
            if done(&snapshot) {
                return;
            }
            if started.elapsed() > GIVE_UP {
                panic!(
                    "gave up waiting for {what}; last snapshot {snapshot}\nkairos serve:\n{}",
                    self.output.lock().unwrap().join("\n")
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Kills worker `index` (0 or 1) without a word, as a crash would.
    pub fn kill_worker(&mut self, index: usize) {
        let worker = &mut self.workers[index];
        worker.kill().unwrap();
        worker.wait().unwrap();
    }
}
