//! Users' plugins in `kairos bench sim`: the shipped twins of native policies, given as plugins,
//! reproduce the natives' rows exactly. `fifo.wasm` as a priority plugin gives the numbers of
//! the built-in FIFO (static horizon) and FIFO + dynamic horizon; `threshold.wasm` as a horizon
//! plugin, with the workload's threshold parameters, gives Kairos's numbers. Run
//! `plugins/build.sh` first (CI does); a missing plugin fails the test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use kairos_tests::plugins::{repo_root, shipped_plugin};

/// Runs `kairos bench sim` on LIBERO at task scale 0.1 with `args`, returns results.csv's rows
/// keyed by (variant, x), each the row's cells by column name.
fn bench_sim(args: &[&str], out: &Path) -> BTreeMap<(String, String), BTreeMap<String, String>> {
    let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .current_dir(repo_root())
        .args([
            "bench",
            "sim",
            "-w",
            "workloads/libero-smolvla.toml",
            "--task-scale",
            "0.1",
            "-e",
            "online",
            "--no-plots",
            "--threads",
            "2",
            "--plugin-cache",
        ])
        .arg(repo_root().join("plugins/build/cache"))
        .arg("--out")
        .arg(out)
        .args(args)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "kairos bench sim {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    let csv = std::fs::read_to_string(out.join("results.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let mut rows = BTreeMap::new();
    for line in lines {
        let row: BTreeMap<String, String> = header
            .iter()
            .zip(line.split(','))
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        rows.insert((row["variant"].clone(), row["x"].clone()), row);
    }
    rows
}

/// Every measured column of `plugin`'s rows equals `native`'s, at every rate.
fn assert_same_numbers(
    rows: &BTreeMap<(String, String), BTreeMap<String, String>>,
    native: &str,
    plugin: &str,
) {
    let measured = [
        "tasks",
        "p25_s",
        "mean_s",
        "p50_s",
        "p95_s",
        "p99_s",
        "max_s",
        "rounds_per_task",
        "mean_batch",
        "refetch_share",
        "mean_queue_s",
        "events",
    ];
    let xs: Vec<&String> = rows
        .keys()
        .filter(|(v, _)| v == native)
        .map(|(_, x)| x)
        .collect();
    assert_eq!(xs.len(), 5, "{native}: one row per rate of the workload");
    for x in xs {
        let a = &rows[&(native.to_string(), x.clone())];
        let b = rows
            .get(&(plugin.to_string(), x.clone()))
            .unwrap_or_else(|| panic!("no row of {plugin} at {x}"));
        for column in measured {
            assert_eq!(
                a[column], b[column],
                "{native} vs {plugin} at {x}: {column}"
            );
        }
    }
}

#[test]
fn a_priority_plugin_twin_gives_the_numbers_of_its_native_policy() {
    let out = tempfile::tempdir().unwrap();
    let fifo = shipped_plugin("fifo");
    let rows = bench_sim(&["--priority-plugin", fifo.to_str().unwrap()], out.path());
    assert_same_numbers(&rows, "fifo", "fifo-wasm");
    assert_same_numbers(&rows, "fifo-dynamic", "fifo-wasm-dynamic");
    // The plugin really ran (a row of its own, under its own policy name), and a different
    // scheduler does not give the same numbers: the comparison can fail.
    let plugin_row = rows
        .iter()
        .find(|((v, _), _)| v == "fifo-wasm")
        .map(|(_, r)| r)
        .unwrap();
    assert_eq!(plugin_row["policy"], "fifo-wasm");
    let peak = rows.keys().map(|(_, x)| x.clone()).max_by(|a, b| {
        a.parse::<f64>()
            .unwrap()
            .total_cmp(&b.parse::<f64>().unwrap())
    });
    let peak = peak.unwrap();
    assert_ne!(
        rows[&("fifo-wasm".to_string(), peak.clone())]["mean_s"],
        rows[&("autellix".to_string(), peak)]["mean_s"]
    );
    let summary = std::fs::read_to_string(out.path().join("summary.md")).unwrap();
    assert!(summary.contains("fifo.wasm + dyn. horizon"), "{summary}");
}

#[test]
fn a_horizon_plugin_twin_records_and_replays_the_native_rule() {
    let out = tempfile::tempdir().unwrap();
    let threshold = shipped_plugin("threshold");
    // LIBERO's dynamic setting: threshold t = 0.4, h_min = 5 (workloads/libero-smolvla.toml).
    let rows = bench_sim(
        &[
            "--horizon-plugin",
            threshold.to_str().unwrap(),
            "--param",
            "t=0.4",
            "--param",
            "h_min=5",
        ],
        out.path(),
    );
    assert_same_numbers(&rows, "kairos", "threshold-wasm");
}
