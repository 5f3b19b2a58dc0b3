//! Users' plugins in `kairos bench live` (issue #14 §4): `--priority-plugin F.wasm` is loaded
//! through the same registries as `bench sim`'s, the live replay server schedules with it, and
//! its simulated side-by-side gives the numbers of its native twin. Run `plugins/build.sh` first
//! (CI does); a missing plugin fails the test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use kairos_tests::plugins::{repo_root, shipped_plugin};

/// A CSV file's rows keyed by their `variant` column.
fn rows(path: &Path) -> BTreeMap<String, BTreeMap<String, String>> {
    let csv = std::fs::read_to_string(path).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    lines
        .map(|line| {
            let row: BTreeMap<String, String> = header
                .iter()
                .zip(line.split(','))
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect();
            (row["variant"].clone(), row)
        })
        .collect()
}

#[test]
fn bench_live_runs_a_priority_plugin_beside_its_native_twin() {
    let out = tempfile::tempdir().unwrap();
    let fifo = shipped_plugin("fifo");
    let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .current_dir(repo_root())
        .args([
            "bench",
            "live",
            "-w",
            "workloads/libero-smolvla.toml",
            "--variants",
            "fifo",
            "--tasks",
            "6",
            "--time-scale",
            "8",
            // The simulated side with a free network, so two systems' simulations differ only
            // by their scheduler (the measured network differs between live runs).
            "--sim-network",
            "free",
            "--no-plots",
            "--priority-plugin",
        ])
        .arg(&fifo)
        .arg("--plugin-cache")
        .arg(repo_root().join("plugins/build/cache"))
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "kairos bench live failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    let live = rows(&out.path().join("live.csv"));
    let sim = rows(&out.path().join("sim.csv"));
    for key in ["fifo", "fifo-wasm", "fifo-wasm-dynamic"] {
        let row = live
            .get(key)
            .unwrap_or_else(|| panic!("no live run of {key}: {live:?}"));
        assert_eq!(row["tasks"], "6", "{key}: every task finished live");
    }
    // The plugin ran under its own name in the live server's scheduler.
    assert_eq!(live["fifo-wasm"]["policy"], "fifo-wasm");
    // Simulated through the same registry, the twin gives the native FIFO's numbers.
    for column in [
        "p25_s",
        "mean_s",
        "p95_s",
        "rounds_per_task",
        "mean_batch",
        "events",
    ] {
        assert_eq!(
            sim["fifo"][column], sim["fifo-wasm"][column],
            "simulated fifo vs fifo.wasm: {column}"
        );
    }
    let summary = std::fs::read_to_string(out.path().join("summary.md")).unwrap();
    assert!(summary.contains("fifo.wasm + dyn. horizon"), "{summary}");
}
