//! `kairos bench sim -e scale` end to end, at a size a test can run: 200 and 400 robots at 20
//! per worker. Every robot's task completes, every round submitted is answered, the worker count
//! follows the fleet, and the outputs (scale.csv, the summary's table, the plot) are written.
//! No timing is asserted: the timings depend on the machine.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;
use std::process::Command;

use kairos_tests::plugins::repo_root;

#[test]
fn scale_experiment_serves_every_round_and_writes_its_outputs() {
    let out = tempfile::tempdir().unwrap();
    let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .current_dir(repo_root())
        .args([
            "bench",
            "sim",
            "-w",
            "workloads/libero-smolvla.toml",
            "-e",
            "scale",
            "--scale-robots",
            "200,400",
            "--robots-per-worker",
            "20",
            "--out",
        ])
        .arg(out.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "kairos bench sim -e scale failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );

    let csv = std::fs::read_to_string(out.path().join("scale.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let rows: Vec<BTreeMap<&str, &str>> = lines
        .map(|l| header.iter().copied().zip(l.split(',')).collect())
        .collect();
    assert_eq!(rows.len(), 2, "{csv}");
    let num = |row: &BTreeMap<&str, &str>, k: &str| -> f64 { row[k].parse().unwrap() };
    for (row, (robots, workers)) in rows.iter().zip([(200.0, 10.0), (400.0, 20.0)]) {
        assert_eq!(row["workload"], "libero-smolvla");
        assert_eq!(num(row, "robots"), robots);
        assert_eq!(num(row, "workers"), workers);
        assert_eq!(num(row, "tasks"), robots, "every robot finished its task");
        assert!(num(row, "rounds") >= robots);
        assert_eq!(
            num(row, "answered"),
            num(row, "rounds"),
            "every round answered"
        );
        // LIBERO/SmolVLA's edge instances take batches of at most 16.
        assert!(num(row, "batches") * 16.0 >= num(row, "rounds"));
        assert!(num(row, "decisions") >= 1.0);
        assert!(num(row, "makespan_s") > 0.0);
    }

    // The same runs in results.csv, as the other experiments' rows.
    let results = std::fs::read_to_string(out.path().join("results.csv")).unwrap();
    assert_eq!(
        results
            .lines()
            .filter(|l| l.starts_with("libero-smolvla,scale,"))
            .count(),
        2
    );
    let summary = std::fs::read_to_string(out.path().join("summary.md")).unwrap();
    assert!(summary.contains("## Scale: one scheduler, 20 robots per engine instance"));
    assert!(summary.contains("| 200 | 10 |") && summary.contains("| 400 | 20 |"));
    assert!(out.path().join("scale.png").is_file());
}
