//! Remote engine workers as a user runs them: a scheduler with no local engine
//! (`--local-engines 0`'s pool, in this process so its counters can be read) served by `kairos
//! worker` processes on loopback, driven by a `kairos robot` fleet process. Nothing here waits
//! on a wall-clock margin: every wait is for an event (a worker registered, a worker busy, a
//! process exited), bounded only by a generous give-up time.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::io::Read;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use kairos_bench::fleet::LocalServer;
use kairos_engine::EngineOptions;
use kairos_server::config::Config;
use kairos_server::driver::EngineView;
use kairos_server::pool::EnginePool;
use kairos_server::transport::launch::Policies;

/// Give-up time for any one wait (a hung run fails instead of blocking CI).
const GIVE_UP: Duration = Duration::from_secs(240);

/// Child processes killed when the test ends, however it ends.
struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for child in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A scheduler serving the built-in model's shapes with no local engine.
async fn scheduler(dir: &Path) -> LocalServer {
    scheduler_for(dir, "builtin").await
}

/// A scheduler serving model `model`'s shapes with no local engine, data in `dir/data`.
async fn scheduler_for(dir: &Path, model: &str) -> LocalServer {
    let model = kairos_engine::resolve_model(model, &EngineOptions::default()).unwrap();
    let config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: dir.join("data"),
        ..Config::default()
    };
    let pool = EnginePool::with_spec(model.spec().clone(), Vec::new()).unwrap();
    assert!(pool.is_empty());
    LocalServer::start(&config, pool, Policies::default())
        .await
        .unwrap()
}

/// A fixed profile for the workers, so they start without measuring one.
fn write_profile(dir: &Path) -> std::path::PathBuf {
    let path = dir.join("profile.json");
    std::fs::write(
        &path,
        r#"{"model":"flow-head-small","device":"cpu (test profile)","points":[{"batch":1,"latency_ms":30.0},{"batch":4,"latency_ms":60.0}],"max_batch":4}"#,
    )
    .unwrap();
    path
}

fn worker(server: &LocalServer, dir: &Path, id: &str) -> Child {
    Command::new(env!("CARGO_BIN_EXE_kairos"))
        .args(["worker", "--server"])
        .arg(server.addr().to_string())
        .arg("--data-dir")
        .arg(dir.join("data"))
        .arg("--profile")
        .arg(dir.join("profile.json"))
        .args(["--worker-id", id, "--max-batch", "4"])
        .env("KAIROS_ENGINE_THREADS", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn robots(server: &LocalServer, dir: &Path, robots: u32, rounds: u32) -> Child {
    Command::new(env!("CARGO_BIN_EXE_kairos"))
        .args(["robot", "--server"])
        .arg(server.addr().to_string())
        .arg("--data-dir")
        .arg(dir.join("data"))
        .args([
            "--robots",
            &robots.to_string(),
            "--rounds",
            &rounds.to_string(),
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// Polls the scheduler's engines until `done` holds (the event waited for).
async fn wait_engines(server: &LocalServer, what: &str, done: impl Fn(&[EngineView]) -> bool) {
    let waited = tokio::time::timeout(GIVE_UP, async {
        loop {
            let engines = server.server.driver.engines().await.unwrap();
            if done(&engines) {
                return engines;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    })
    .await;
    assert!(waited.is_ok(), "gave up waiting for {what}");
}

/// The `kairos robot` summary line: (asked, answered, lost, answered twice, retried).
fn account(output: &str) -> (u64, u64, u64, u64, u64) {
    let line = output
        .lines()
        .find(|l| l.starts_with("rounds: asked"))
        .unwrap_or_else(|| panic!("no summary in {output}"));
    let numbers: Vec<u64> = line
        .split(|c: char| !c.is_ascii_digit())
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().unwrap())
        .collect();
    (numbers[0], numbers[1], numbers[2], numbers[3], numbers[4])
}

async fn wait_exit(child: &mut Child) -> (std::process::ExitStatus, String) {
    let waited = tokio::time::timeout(GIVE_UP, async {
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                return status;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let status = waited.unwrap_or_else(|_| panic!("process {} did not exit", child.id()));
    let mut out = String::new();
    if let Some(stdout) = child.stdout.as_mut() {
        let _ = stdout.read_to_string(&mut out);
    }
    (status, out)
}

/// The index in `ids` of a live worker that runs a batch now.
fn busy_worker(engines: &[EngineView], ids: &[&str]) -> Option<usize> {
    let name = &engines.iter().find(|e| e.live && e.busy)?.name;
    ids.iter()
        .position(|id| name.starts_with(&format!("worker:{id}@")))
}

/// Waits until one of the workers `ids` runs a batch; returns its index.
async fn wait_busy(server: &LocalServer, ids: &[&str]) -> usize {
    tokio::time::timeout(GIVE_UP, async {
        loop {
            let engines = server.server.driver.engines().await.unwrap();
            if let Some(index) = busy_worker(&engines, ids) {
                return index;
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await
    .expect("a worker was busy")
}

/// A scheduler with no local engine and a `kairos worker` process per id, all registered.
async fn scheduler_and_workers(dir: &Path, ids: &[&str]) -> (LocalServer, Procs) {
    let server = scheduler(dir).await;
    write_profile(dir);
    let procs = Procs(ids.iter().map(|id| worker(&server, dir, id)).collect());
    wait_engines(&server, "the workers", |e| {
        e.iter().filter(|e| e.live).count() == ids.len()
    })
    .await;
    (server, procs)
}

/// `--local-engines 0` plus two workers: robots complete. A worker killed with SIGKILL in the
/// middle of a batch: its rounds go back to the queue and run on the other worker, every round
/// is answered exactly once and none fails; the re-dispatch is counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_workers_serve_and_a_killed_workers_batch_is_redispatched() {
    let dir = tempfile::tempdir().unwrap();
    let ids = ["w0", "w1"];
    let (server, mut procs) = scheduler_and_workers(dir.path(), &ids).await;

    // Both workers serve a first fleet.
    let mut fleet = robots(&server, dir.path(), 4, 6);
    let (status, out) = wait_exit(&mut fleet).await;
    assert!(status.success(), "{out}");
    assert_eq!(account(&out), (24, 24, 0, 0, 0), "{out}");
    let stats = server.server.driver.stats().await.unwrap();
    assert_eq!(stats.failed, 0);
    assert_eq!(stats.redispatched.total(), 0, "no worker was lost yet");

    // Kill a worker while it runs a batch.
    let mut fleet = robots(&server, dir.path(), 4, 8);
    let victim = wait_busy(&server, &ids).await;
    // SIGKILL: the worker vanishes mid-batch without a word.
    procs.0[victim].kill().unwrap();
    procs.0[victim].wait().unwrap();
    let (status, out) = wait_exit(&mut fleet).await;
    assert!(status.success(), "{out}");
    let (asked, answered, lost, twice, retried) = account(&out);
    assert_eq!((asked, answered, lost, twice), (32, 32, 0, 0), "{out}");
    assert_eq!(retried, 0, "no round got an error: {out}");
    let stats = server.server.driver.stats().await.unwrap();
    assert_eq!(stats.failed, 0, "{stats:?}");
    assert_eq!(stats.redispatch_given_up, 0, "{stats:?}");
    assert!(
        stats.redispatched.total() >= 1,
        "the killed batch's rounds ran again: {stats:?}"
    );
    // ... and so does `/metrics` (`kairos_redispatch_total{reason}`), with the workers by state.
    let exported = server.server.metrics.encode();
    let sample = |series: &str| {
        exported
            .lines()
            .find_map(|l| {
                l.strip_prefix(series)?
                    .strip_prefix(' ')?
                    .parse::<f64>()
                    .ok()
            })
            .unwrap_or(0.0)
    };
    let redispatched: f64 = [
        "connection_lost",
        "stream_reset",
        "invalid_answer",
        "deadline",
        "gone",
    ]
    .iter()
    .map(|r| sample(&format!("kairos_redispatch_total{{reason=\"{r}\"}}")))
    .sum();
    assert_eq!(
        redispatched,
        stats.redispatched.total() as f64,
        "{exported}"
    );
    assert_eq!(
        sample(r#"kairos_workers{tier="edge",state="ready"}"#),
        1.0,
        "{exported}"
    );
    let engines = server.server.driver.engines().await.unwrap();
    // The killed worker left the pool; once its batch came back the scheduler forgot it.
    let dead = format!("worker:{}@", ids[victim]);
    assert!(
        engines
            .iter()
            .all(|e| !e.name.starts_with(&dead) || !e.live),
        "the killed worker left the pool: {engines:?}"
    );
    assert_eq!(engines.iter().filter(|e| e.live).count(), 1);
    drop(procs);
    let report = server.shutdown().await;
    assert_eq!(report.driver.failed, 0);
}

/// SIGTERM to a busy worker: it sends `Drain`, finishes its batch, exits 0; no round gets an
/// error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sigterm_drains_the_worker_without_failing_a_round() {
    let dir = tempfile::tempdir().unwrap();
    let ids = ["d0", "d1"];
    let (server, mut procs) = scheduler_and_workers(dir.path(), &ids).await;
    let mut fleet = robots(&server, dir.path(), 4, 8);
    let index = wait_busy(&server, &ids).await;
    let pid = procs.0[index].id().to_string();
    let killed = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
    assert!(killed.success());
    let (status, _) = wait_exit(&mut procs.0[index]).await;
    assert!(status.success(), "a drained worker exits 0: {status:?}");
    let (status, out) = wait_exit(&mut fleet).await;
    assert!(status.success(), "{out}");
    assert_eq!(account(&out), (32, 32, 0, 0, 0), "{out}");
    let stats = server.server.driver.stats().await.unwrap();
    assert_eq!(stats.failed, 0, "{stats:?}");
    let engines = server.server.driver.engines().await.unwrap();
    assert_eq!(engines.iter().filter(|e| e.live).count(), 1, "{engines:?}");
    drop(procs);
    server.shutdown().await;
}

/// `kairos worker --model DIR --tokenizer FILE` serves a whole SmolVLA checkpoint saved the way
/// LeRobot saves one, without the task tokenizer beside it (the engine's `smolvla_tiny` fixture,
/// copied without its `tokenizer.json`), here in bf16 (f32 with a warning on a CPU without
/// AVX512_BF16). Without `--tokenizer` the worker refuses to start, naming the file it looked
/// for and the flag; with it, it registers and a `kairos robot` fleet sending two cameras gets
/// every round answered by it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_serves_a_smolvla_checkpoint_with_a_tokenizer_from_elsewhere() {
    let dir = tempfile::tempdir().unwrap();
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../engine/tests/fixtures/smolvla_tiny");
    let model = dir.path().join("my_smolvla");
    std::fs::create_dir(&model).unwrap();
    for entry in std::fs::read_dir(&fixture).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() && path.file_name().is_some_and(|n| n != "tokenizer.json") {
            std::fs::copy(&path, model.join(path.file_name().unwrap())).unwrap();
        }
    }
    // The scheduler serves the checkpoint's shapes with no local engine.
    let server = scheduler_for(dir.path(), fixture.to_str().unwrap()).await;
    assert_eq!(server.server.model.name, "smolvla");
    let profile = dir.path().join("profile.json");
    std::fs::write(
        &profile,
        r#"{"model":"smolvla","device":"cpu (test profile)","points":[{"batch":1,"latency_ms":30.0},{"batch":2,"latency_ms":50.0}],"max_batch":2}"#,
    )
    .unwrap();
    let worker = |tokenizer: Option<&Path>| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_kairos"));
        command
            .args(["worker", "--server"])
            .arg(server.addr().to_string())
            .arg("--data-dir")
            .arg(dir.path().join("data"))
            .arg("--profile")
            .arg(&profile)
            .arg("--model")
            .arg(&model)
            .args(["--precision", "bf16", "--worker-id", "vla"])
            .env("KAIROS_ENGINE_THREADS", "1")
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        if let Some(file) = tokenizer {
            command.arg("--tokenizer").arg(file);
        }
        command
    };

    let refused = tokio::task::spawn_blocking({
        let mut command = worker(None);
        move || command.output().unwrap()
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{stderr}");
    assert!(
        stderr.contains(&model.join("tokenizer.json").display().to_string())
            && stderr.contains("--tokenizer"),
        "{stderr}"
    );

    let procs = Procs(vec![
        worker(Some(&fixture.join("tokenizer.json")))
            .spawn()
            .unwrap(),
    ]);
    wait_engines(&server, "the SmolVLA worker", |e| {
        e.iter()
            .any(|e| e.live && e.name.starts_with("worker:vla@"))
    })
    .await;
    let mut fleet = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .args(["robot", "--server"])
        .arg(server.addr().to_string())
        .arg("--data-dir")
        .arg(dir.path().join("data"))
        .args([
            "--robots",
            "2",
            "--rounds",
            "3",
            "--cameras",
            "2",
            "--image",
            "40x56",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let (status, out) = wait_exit(&mut fleet).await;
    assert!(status.success(), "{out}");
    assert_eq!(account(&out), (6, 6, 0, 0, 0), "{out}");
    let stats = server.server.driver.stats().await.unwrap();
    assert_eq!(stats.failed, 0, "{stats:?}");
    drop(procs);
    server.shutdown().await;
}
