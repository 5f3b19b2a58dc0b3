//! Interoperability: the Python client in `sdk/examples/python/`, written from docs/PROTOCOL.md
//! alone, against the Rust protocol responder over real QUIC/TLS.
//!
//! Ignored by default because it needs a Python with `aioquic`, `msgpack` and `numpy`:
//! `KAIROS_PYTHON=/path/to/python cargo test -p kairos-sdk --test it python_client:: -- --ignored`

#![allow(clippy::unwrap_used)] // helpers outside #[test] fns

use crate::support::{Behavior, Responder};
use kairos_sdk::protocol::TaskOutcome;

/// Runs the example client with `args` and returns its output.
async fn run_client(args: Vec<String>) -> std::process::Output {
    let python = std::env::var("KAIROS_PYTHON").unwrap_or_else(|_| "python3".to_owned());
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/examples/python/kairos_client.py"
    );
    tokio::task::spawn_blocking(move || {
        std::process::Command::new(python)
            .arg(script)
            .args(args)
            .output()
            .unwrap()
    })
    .await
    .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs python3 with aioquic, msgpack and numpy (set KAIROS_PYTHON)"]
async fn python_client_speaks_the_protocol() {
    let responder = Responder::start(Behavior {
        fetch_observation: true,
        ..Behavior::default()
    });
    let addr = responder.addr.to_string();
    let output = run_client(vec![
        addr.clone(),
        responder.fingerprint.to_string(),
        "secret".to_owned(),
        "3".to_owned(),
    ])
    .await;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "stdout:\n{stdout}\nstderr:\n{stderr}"
    );
    assert!(
        stdout.contains("round 2: H=4 of N=8 actions[4, 2]"),
        "{stdout}"
    );
    {
        let seen = responder.seen();
        let rounds: Vec<(u64, u32)> = seen.submits.iter().map(|s| (s.1, s.2)).collect();
        assert_eq!(rounds, [(0, 0), (1, 0), (2, 0)]);
        assert_eq!(seen.fresh.len(), 3, "every FetchObservation was answered");
        assert_eq!(seen.last_exec.len(), 2);
        assert_eq!(seen.ended.len(), 1);
        assert_eq!(seen.ended[0].1, TaskOutcome::Done);
    }

    // A wrong pin is refused by the Python client before it sends its token.
    let wrong = format!("sha256:{}", "00".repeat(32));
    let refused = run_client(vec![addr, wrong, "secret".to_owned()]).await;
    assert_eq!(refused.status.code(), Some(2));
}
