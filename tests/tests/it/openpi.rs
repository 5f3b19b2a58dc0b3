//! The openpi-compatible endpoint (`[openpi] listen`) against the real, unmodified
//! `openpi-client==0.1.2` from PyPI, driven by `tests/python/openpi_check.py`.
//!
//! Ignored by default because it needs a Python with `openpi-client` installed (scripts/test.sh
//! makes one in `.venv-openpi` and runs these with `--include-ignored`):
//! `KAIROS_OPENPI_PYTHON=.venv-openpi/bin/python cargo test -p kairos-tests --test it openpi:: -- --ignored`

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::sync::{Arc, Mutex, mpsc};

use kairos_engine::{ActionChunk, ActionModel, ActionRequest, EngineError, ModelSpec};
use kairos_server::config::Config;
use kairos_server::transport::refusals::{Door, Reason};
use kairos_tests::harness::{ServerOptions, TestServer};
use kairos_tests::model::TestFlow;
use serde_json::Value;

/// The openpi endpoint on an ephemeral port, and a small frame limit for the too-large case.
fn with_openpi(config: &mut Config) {
    config.openpi.listen = Some("127.0.0.1:0".parse().unwrap());
    config.limits.max_frame = MAX_FRAME;
}

const MAX_FRAME: u32 = 256 << 10;

fn robots() -> ServerOptions {
    ServerOptions {
        robots: vec![
            ("arm-1".to_string(), "token-one".to_string()),
            ("arm-2".to_string(), "token-two".to_string()),
        ],
        tweak: with_openpi,
        ..ServerOptions::default()
    }
}

/// Runs `openpi_check.py MODE HOST PORT ARGS...` and parses the JSON it prints.
async fn check(server: &TestServer, mode: &str, args: &[&str]) -> Value {
    let python = std::env::var("KAIROS_OPENPI_PYTHON")
        .expect("KAIROS_OPENPI_PYTHON: a python with openpi-client==0.1.2 (scripts/test.sh)");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/python/openpi_check.py");
    let addr = server.server().openpi_addr.expect("openpi endpoint on");
    let mut command = std::process::Command::new(python);
    command
        .arg(script)
        .arg(mode)
        .arg(addr.ip().to_string())
        .arg(addr.port().to_string())
        .args(args);
    let output = tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "{mode}: stdout:\n{stdout}\nstderr:\n{stderr}"
    );
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("{mode}: {e}: {stdout}"))
}

/// Waits until the server has ended `count` tasks (the websocket closes reach it after the
/// client process exits). The bound only turns a hang into a failure; it is not a timing margin.
async fn wait_tasks_ended(server: &TestServer, count: u64) {
    let ended = async {
        loop {
            let stats = server.server().driver.stats().await.unwrap();
            if stats.tasks_ended >= count {
                return;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    };
    tokio::time::timeout(std::time::Duration::from_secs(120), ended)
        .await
        .unwrap_or_else(|_| panic!("the server never ended {count} tasks"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a python with openpi-client==0.1.2 (set KAIROS_OPENPI_PYTHON)"]
async fn openpi_client_gets_metadata_and_chunks_of_the_model_shape() {
    let server = TestServer::start(robots()).await.unwrap();
    let out = check(&server, "basic", &["token-one", "3"]).await;

    let metadata = &out["metadata"];
    assert_eq!(metadata["model"], "test-flow");
    assert_eq!(metadata["robot"], "arm-1");
    assert_eq!(metadata["chunk_len"], 16);
    assert_eq!(metadata["action_dim"], 4);
    assert_eq!(metadata["state_dim"], 6);
    assert_eq!(metadata["keys"]["state"][0], "observation/state");
    let task = metadata["task"].as_u64().unwrap();

    let replies = out["replies"].as_array().unwrap();
    assert_eq!(replies.len(), 3);
    for (round, reply) in replies.iter().enumerate() {
        // The whole chunk by default: openpi clients choose how much of it to execute.
        assert_eq!(reply["shape"], serde_json::json!([16, 4]), "{reply}");
        assert_eq!(reply["dtype"], "float32");
        assert_eq!(reply["finite"], true);
        assert!(reply["server_timing"]["infer_ms"].as_f64().unwrap() >= 0.0);
        assert!(reply["policy_timing"]["infer_ms"].as_f64().is_some());
        assert_eq!(reply["server_timing"]["batch_size"], 1);
        assert_eq!(reply["kairos"]["task"].as_u64(), Some(task));
        assert_eq!(reply["kairos"]["round"].as_u64(), Some(round as u64));
        // openpi's own server reports the previous cycle's total from the second reply on.
        assert_eq!(
            reply["server_timing"].get("prev_total_ms").is_some(),
            round > 0
        );
    }

    // The connection was one task of the scheduler, with one round per request, ended when the
    // websocket closed, and with the execution intervals the call timing implies.
    wait_tasks_ended(&server, 1).await;
    let snapshot = server
        .server()
        .driver
        .snapshot(kairos_core::scheduler::TaskId(task))
        .await
        .unwrap()
        .expect("the task is known");
    assert!(snapshot.ended);
    assert_eq!(snapshot.rounds_completed, 3);
    let executed: Vec<bool> = snapshot
        .history
        .iter()
        .map(|r| r.execution.is_some())
        .collect();
    assert_eq!(executed, [true, true, true], "{:?}", snapshot.history);
    let report = server.shutdown().await;
    assert_eq!(report.openpi.connections, 1);
}

/// Holds the engine on its first batch until the test releases it, so that the other clients'
/// requests queue meanwhile: batching shown by an event, not by timing.
struct FirstBatchGate {
    inner: TestFlow,
    entered: Mutex<Option<tokio::sync::oneshot::Sender<()>>>,
    release: Mutex<mpsc::Receiver<()>>,
}

impl ActionModel for FirstBatchGate {
    fn spec(&self) -> &ModelSpec {
        self.inner.spec()
    }

    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError> {
        let first = self.entered.lock().unwrap().take();
        if let Some(entered) = first {
            let _ = entered.send(());
            let _ = self.release.lock().unwrap().recv();
        }
        self.inner.generate(batch)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a python with openpi-client==0.1.2 (set KAIROS_OPENPI_PYTHON)"]
async fn eight_concurrent_openpi_clients_are_batched_together() {
    const CLIENTS: usize = 8;
    const ROUNDS: usize = 2;
    let (entered_tx, entered) = tokio::sync::oneshot::channel();
    let (release, release_rx) = mpsc::channel();
    let model = Arc::new(FirstBatchGate {
        inner: TestFlow::new(),
        entered: Mutex::new(Some(entered_tx)),
        release: Mutex::new(release_rx),
    });
    let server = Arc::new(TestServer::start_with_model(robots(), model).await.unwrap());
    let run = {
        let server = server.clone();
        tokio::spawn(async move {
            check(
                &server,
                "concurrent",
                &["token-two", &CLIENTS.to_string(), &ROUNDS.to_string()],
            )
            .await
        })
    };
    // The first request is on the engine; wait until every client's first round is queued.
    let queued = async {
        entered.await.unwrap();
        loop {
            let stats = server.server().driver.stats().await.unwrap();
            if stats.accepted >= CLIENTS as u64 {
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(5)).await;
        }
    };
    // A bound against a hang (say, a client that failed to connect), not a timing margin.
    tokio::time::timeout(std::time::Duration::from_secs(120), queued)
        .await
        .unwrap_or_else(|_| panic!("the {CLIENTS} first rounds never queued"));
    release.send(()).unwrap();
    let out = run.await.unwrap();

    assert_eq!(out["errors"], serde_json::json!([]), "{out}");
    let clients = out["clients"].as_array().unwrap();
    assert_eq!(clients.len(), CLIENTS);
    let mut tasks: Vec<u64> = clients
        .iter()
        .map(|c| c["task"].as_u64().unwrap())
        .collect();
    tasks.sort_unstable();
    tasks.dedup();
    assert_eq!(tasks.len(), CLIENTS, "one task per connection");
    let first_round: Vec<u64> = clients
        .iter()
        .map(|c| {
            c["replies"][0]["server_timing"]["batch_size"]
                .as_u64()
                .unwrap()
        })
        .collect();
    // One client's request was alone on the engine; the seven that queued behind it were
    // served together, not one after another.
    assert_eq!(
        first_round.iter().filter(|&&b| b == 1).count(),
        1,
        "{first_round:?}"
    );
    assert!(
        first_round.iter().filter(|&&b| b > 1).count() == CLIENTS - 1,
        "{first_round:?}"
    );
    for client in clients {
        for reply in client["replies"].as_array().unwrap() {
            assert_eq!(reply["shape"], serde_json::json!([16, 4]));
        }
    }
    wait_tasks_ended(&server, CLIENTS as u64).await;
    let stats = server.server().driver.stats().await.unwrap();
    assert_eq!(stats.replies, (CLIENTS * ROUNDS) as u64);
    assert!(
        stats.batches < stats.replies,
        "{} batches for {} replies",
        stats.batches,
        stats.replies
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a python with openpi-client==0.1.2 (set KAIROS_OPENPI_PYTHON)"]
async fn a_wrong_or_missing_key_is_refused_before_any_observation() {
    let server = TestServer::start(robots()).await.unwrap();
    let out = check(&server, "auth", &[]).await;
    assert_eq!(out["wrong_key"], 401, "{out}");
    assert_eq!(out["no_key"], 401, "{out}");
    let stats = server.server().driver.stats().await.unwrap();
    assert_eq!(
        stats.accepted + stats.refused,
        0,
        "no round reached the driver"
    );
    // The right key still works.
    let ok = check(&server, "basic", &["token-two", "1"]).await;
    assert_eq!(ok["metadata"]["robot"], "arm-2");
    let report = server.shutdown().await;
    assert_eq!(report.refusals.get(Door::Openpi, Reason::Unauthorized), 2);
    assert_eq!(report.openpi.connections, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs a python with openpi-client==0.1.2 (set KAIROS_OPENPI_PYTHON)"]
async fn garbage_frames_get_an_error_and_a_close_while_another_client_keeps_working() {
    let server = TestServer::start(robots()).await.unwrap();
    let out = check(&server, "garbage", &["token-one"]).await;
    let cases = &out["cases"];
    let expect = |case: &str, code: u64, text: &str| {
        let result = &cases[case];
        assert_eq!(result["close_code"], code, "{case}: {result}");
        let reply = result["reply"].as_str().unwrap();
        assert!(reply.contains(text), "{case}: {reply}");
    };
    expect("not_msgpack", 1008, "not msgpack");
    expect("truncated", 1008, "ends inside a value");
    expect("not_a_map", 1008, "expected a msgpack map");
    expect("wrong_state_len", 1008, "observation.state");
    expect("wrong_image_shape", 1008, "observation/image");
    expect("string_state", 1008, "dtype `<U1`");
    expect("text_frame", 1003, "expected a binary msgpack message");
    expect("too_large", 1009, "too_large");
    let client_error = out["client_error"].as_str().unwrap();
    assert!(
        client_error.contains("Error in inference server") && client_error.contains("state"),
        "{client_error}"
    );
    assert_eq!(out["before"]["shape"], serde_json::json!([16, 4]));
    assert_eq!(out["after"]["shape"], serde_json::json!([16, 4]));
    assert_eq!(
        out["after"]["kairos"]["round"], 1,
        "the good client's task went on"
    );
    server.shutdown().await;
}
