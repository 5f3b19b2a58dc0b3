//! The binaries of this crate, run as a user runs them: `--help` prints help and touches nothing.

use std::process::Command;

/// `kairos-tiny-model --help` used to take `--help` for its output directory and create it.
#[test]
fn tiny_model_help_prints_help_and_creates_nothing() {
    let cwd = tempfile::tempdir().unwrap();
    for flag in ["--help", "-h"] {
        let output = Command::new(env!("CARGO_BIN_EXE_kairos-tiny-model"))
            .arg(flag)
            .current_dir(cwd.path())
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&output.stdout);
        assert!(output.status.success(), "{flag}: {output:?}");
        assert!(
            stdout.contains("Usage: kairos-tiny-model"),
            "{flag}: {stdout}"
        );
        assert!(stdout.contains("<DIR>"), "{flag}: {stdout}");
        let created: Vec<_> = std::fs::read_dir(cwd.path()).unwrap().collect();
        assert!(created.is_empty(), "{flag} created {created:?}");
    }
    // An unknown option is refused, not taken for a directory.
    let output = Command::new(env!("CARGO_BIN_EXE_kairos-tiny-model"))
        .arg("--out")
        .current_dir(cwd.path())
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert_eq!(std::fs::read_dir(cwd.path()).unwrap().count(), 0);
}

/// With a directory it writes a checkpoint the engine loads.
#[test]
fn tiny_model_writes_a_loadable_checkpoint() {
    let cwd = tempfile::tempdir().unwrap();
    let status = Command::new(env!("CARGO_BIN_EXE_kairos-tiny-model"))
        .arg("tiny")
        .current_dir(cwd.path())
        .status()
        .unwrap();
    assert!(status.success());
    let model = kairos_engine::flow_head::FlowHead::load(
        &cwd.path().join("tiny"),
        &kairos_engine::EngineOptions::default(),
    )
    .unwrap();
    let spec = kairos_engine::ActionModel::spec(&model);
    assert_eq!(
        (spec.state_dim, spec.chunk_len, spec.action_dim),
        (8, 16, 7)
    );
}
