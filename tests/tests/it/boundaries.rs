//! The architecture's boundaries, as Cargo sees them: a crate that must not reach a layer cannot
//! have it in its dependency tree. A change that adds such a dependency fails here, not in review.
//!
//! - `kairos-core` (the pure logic) has no async runtime, transport, plugin host, command line,
//!   plots, progress bars or Candle, in any of its dependency kinds.
//! - `kairos-server` (serving) has no command line, plots or progress bars, and never depends on
//!   the tools (`kairos-bench`) or the binary (`kairos-cli`). With its default features it has
//!   no `candle-nn` either: the engine composes RMSNorm, LayerNorm, softmax and RoPE from
//!   candle-core, and only its `cuda` feature brings `candle-nn`'s fused kernels, through the
//!   engine and nothing else.
//! - `kairos-engine` and the SDK know nothing of serving.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeSet;
use std::process::Command;

/// The crate names in `cargo tree` for `args` (offline, from the lock file).
fn tree(args: &[&str]) -> BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let output = Command::new(cargo)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args([
            "tree",
            "--locked",
            "--offline",
            "--prefix",
            "none",
            "-f",
            "{p}",
        ])
        .args(args)
        .output()
        .expect("cargo runs");
    assert!(
        output.status.success(),
        "cargo tree {args:?}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .filter_map(|line| line.split_whitespace().next())
        .map(str::to_string)
        .collect()
}

fn assert_none_of(crate_name: &str, found: &BTreeSet<String>, forbidden: &[&str]) {
    let hits: Vec<&&str> = forbidden.iter().filter(|f| found.contains(**f)).collect();
    assert!(hits.is_empty(), "{crate_name} depends on {hits:?}");
}

#[test]
fn the_core_has_no_io_runtime_plugin_host_cli_or_candle() {
    // Every dependency kind: normal, build and dev.
    let core = tree(&["-p", "kairos-core", "-e", "normal,build,dev"]);
    assert!(core.contains("kairos-protocol"), "{core:?}");
    assert_none_of(
        "kairos-core",
        &core,
        &[
            "tokio",
            "quinn",
            "wasmtime",
            "clap",
            "plotters",
            "indicatif",
            "candle-core",
            "candle-nn",
            "kairos-engine",
            "kairos-sdk",
            "kairos-server",
            "kairos-bench",
        ],
    );
}

#[test]
fn serving_has_no_tooling_and_candle_nn_only_in_a_cuda_build() {
    let server = tree(&["-p", "kairos-server", "-e", "normal"]);
    assert!(
        server.contains("kairos-core") && server.contains("quinn"),
        "{server:?}"
    );
    assert_none_of(
        "kairos-server",
        &server,
        &[
            "clap",
            "plotters",
            "indicatif",
            "candle-nn",
            "kairos-bench",
            "kairos-cli",
        ],
    );
    // With the `cuda` feature the fused kernels come in, and only through the engine.
    let dependents = tree(&[
        "-p",
        "kairos-server",
        "-e",
        "normal",
        "--features",
        "cuda",
        "-i",
        "candle-nn",
        "--depth",
        "1",
    ]);
    let expected: BTreeSet<String> = ["candle-nn", "kairos-engine"].map(String::from).into();
    assert_eq!(dependents, expected);
    // Its tests do not reach for the tools either (criterion, a dev-dependency, has its own
    // command line: that one is allowed).
    let with_dev = tree(&["-p", "kairos-server", "-e", "normal,dev"]);
    assert_none_of(
        "kairos-server (dev)",
        &with_dev,
        &["kairos-bench", "kairos-cli", "indicatif"],
    );
}

#[test]
fn the_engine_and_the_sdk_know_nothing_of_serving() {
    let engine = tree(&["-p", "kairos-engine", "-e", "normal"]);
    assert_none_of(
        "kairos-engine",
        &engine,
        &[
            "kairos-core",
            "kairos-sdk",
            "kairos-server",
            "tokio",
            "quinn",
            "wasmtime",
        ],
    );
    let sdk = tree(&["-p", "kairos-sdk", "-e", "normal"]);
    assert_none_of(
        "kairos-sdk",
        &sdk,
        &[
            "kairos-core",
            "kairos-engine",
            "kairos-server",
            "wasmtime",
            "candle-core",
        ],
    );
    let protocol = tree(&["-p", "kairos-protocol", "-e", "normal"]);
    assert_none_of("kairos-protocol", &protocol, &["tokio", "quinn"]);
}
