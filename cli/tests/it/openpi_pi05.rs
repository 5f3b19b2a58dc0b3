//! `kairos serve --model engine/tests/fixtures/pi05_tiny --openpi-listen ADDR`, as a user runs
//! it, answering the real, unmodified `openpi-client==0.1.2` (driven by
//! `tests/python/openpi_check.py basic`): metadata with the π0.5 checkpoint's shapes and chunks
//! of `[chunk, action_dim]` finite float32 actions.
//!
//! Ignored by default because it needs a Python with `openpi-client` installed (scripts/test.sh
//! makes one in `.venv-openpi` and runs the ignored tests):
//! `KAIROS_OPENPI_PYTHON=.venv-openpi/bin/python cargo test -p kairos-cli --test it openpi_pi05 -- --ignored`

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::repo_root;

/// Kills the server when the test ends, however it ends.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A port nothing listens on now (the OS's next ephemeral one).
fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

#[test]
#[ignore = "needs a python with openpi-client==0.1.2 (set KAIROS_OPENPI_PYTHON)"]
fn openpi_client_gets_pi05_chunks_from_kairos_serve() {
    let python = std::env::var("KAIROS_OPENPI_PYTHON")
        .expect("KAIROS_OPENPI_PYTHON: a python with openpi-client==0.1.2 (scripts/test.sh)");
    let data = tempfile::tempdir().unwrap();
    let openpi: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
    let mut server = Server(
        Command::new(env!("CARGO_BIN_EXE_kairos"))
            .arg("serve")
            .arg("--model")
            .arg(repo_root().join("engine/tests/fixtures/pi05_tiny"))
            .args(["--listen", "127.0.0.1:0", "--openpi-listen"])
            .arg(openpi.to_string())
            .arg("--data-dir")
            .arg(data.path())
            .env("KAIROS_ENGINE_THREADS", "2")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    // Ready when the openpi port accepts; the server generates the robot token before that.
    let give_up = Instant::now() + Duration::from_secs(300);
    while TcpStream::connect(openpi).is_err() {
        if let Some(status) = server.0.try_wait().unwrap() {
            panic!("kairos serve exited with {status}");
        }
        assert!(
            Instant::now() < give_up,
            "the openpi endpoint never came up"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let tokens = std::fs::read_to_string(data.path().join("tokens.toml")).unwrap();
    let token = tokens
        .lines()
        .find_map(|l| l.trim().strip_prefix("token = "))
        .map(|t| t.trim_matches('"').to_owned())
        .unwrap_or_else(|| panic!("no token in tokens.toml:\n{tokens}"));

    let output = Command::new(python)
        .arg(repo_root().join("tests/python/openpi_check.py"))
        .args([
            "basic",
            "127.0.0.1",
            &openpi.port().to_string(),
            &token,
            "2",
        ])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "stdout:\n{stdout}\nstderr:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let out: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let metadata = &out["metadata"];
    assert_eq!(metadata["model"], "pi05");
    assert_eq!(metadata["chunk_len"], 12);
    assert_eq!(metadata["action_dim"], 6);
    assert_eq!(metadata["state_dim"], 7);
    let replies = out["replies"].as_array().unwrap();
    assert_eq!(replies.len(), 2);
    for reply in replies {
        assert_eq!(reply["shape"], serde_json::json!([12, 6]), "{reply}");
        assert_eq!(reply["dtype"], "float32");
        assert_eq!(reply["finite"], true);
    }
}
