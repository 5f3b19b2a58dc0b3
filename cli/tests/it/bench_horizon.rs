//! `kairos bench horizon`: the quick run with the committed policy writes pareto.csv with the
//! documented columns and one row per policy, `--task contact` runs with its own committed
//! model, and `--train` still trains (a few steps) and writes a model the bench loads.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::process::Command;

use kairos_tests::plugins::{repo_root, shipped_plugin};

fn kairos(args: &[&str], out: &std::path::Path) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .current_dir(repo_root())
        .args(["bench", "horizon"])
        .args(args)
        .arg(out)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "kairos bench horizon {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

#[test]
fn the_quick_run_writes_one_pareto_row_per_policy() {
    let out = tempfile::tempdir().unwrap();
    // Fewer episodes than --quick's 40 keep the test short; the columns and rows are the same.
    // The shipped twin of the §3.1 rule rides along as a user's plugin (plugins/build.sh builds
    // it; CI runs that first).
    let twin = shipped_plugin("threshold");
    let cache = repo_root().join("plugins/build/cache");
    kairos(
        &[
            "--quick",
            "--episodes",
            "12",
            "--horizon-plugin",
            twin.to_str().unwrap(),
            "--param",
            "t=0.4",
            "--plugin-cache",
            cache.to_str().unwrap(),
            "--out",
        ],
        out.path(),
    );
    let csv = std::fs::read_to_string(out.path().join("pareto.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(
        header[..7],
        [
            "policy",
            "params",
            "mean_horizon",
            "success_rate",
            "ci_low",
            "ci_high",
            "episodes"
        ]
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    // --quick: static H in {1, 4, 16}, the threshold rule at two thresholds, spread and steady
    // at one setting each, and the plugin.
    assert_eq!(rows.len(), 8, "{csv}");
    assert!(rows.iter().any(|r| r[0] == "steady"), "{csv}");
    // The plugin is a row of its own, and the twin of the native rule decides exactly as it
    // does, episode for episode: every measured column is the same.
    let native = rows
        .iter()
        .find(|r| r[0] == "threshold" && r[1] == "t=0.4")
        .unwrap();
    let plugin = rows.iter().find(|r| r[0] == "threshold.wasm").unwrap();
    assert_eq!(plugin[1], "t=0.4");
    assert_eq!(plugin[2..], native[2..], "{csv}");
    let statics: Vec<&Vec<&str>> = rows.iter().filter(|r| r[0] == "static").collect();
    assert_eq!(statics.len(), 3);
    for (row, h) in statics.iter().zip([1.0, 4.0, 16.0]) {
        assert_eq!(row[1], format!("h={h}"));
        // A static horizon executes h actions per chunk, except where an episode ends inside
        // one.
        let mean: f64 = row[2].parse().unwrap();
        assert!(
            mean <= h && mean > h * 0.6,
            "static h={h}: mean executed {mean}"
        );
    }
    for row in &rows {
        let (p, lo, hi): (f64, f64, f64) = (
            row[3].parse().unwrap(),
            row[4].parse().unwrap(),
            row[5].parse().unwrap(),
        );
        assert!(
            lo <= p && p <= hi && (0.0..=1.0).contains(&lo) && hi <= 1.0,
            "{row:?}"
        );
        assert_eq!(row[6], "12");
    }
    assert!(out.path().join("pareto.png").exists());
    assert!(out.path().join("pareto.svg").exists());
    let summary = std::fs::read_to_string(out.path().join("summary.md")).unwrap();
    assert!(summary.contains("| threshold | t=0.4 |"), "{summary}");
}

#[test]
fn training_runs_a_few_steps_and_writes_a_loadable_model() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model");
    let stdout = kairos(
        &["--train", "--iterations", "3", "--demos", "4", "--model"],
        &model,
    );
    assert!(stdout.contains("3 steps"), "{stdout}");
    assert!(model.join("model.safetensors").exists());
    let config = std::fs::read_to_string(model.join("config.json")).unwrap();
    assert!(config.contains("\"iterations\": 3"), "{config}");
    // The bench runs with it.
    let out = dir.path().join("out");
    kairos(
        &[
            "--quick",
            "--episodes",
            "2",
            "--no-plots",
            "--model",
            model.to_str().unwrap(),
            "--out",
        ],
        &out,
    );
    assert!(out.join("pareto.csv").exists());
}

#[test]
fn live_and_in_process_episodes_agree() {
    // The same policies and seeds, once in-process and once served over loopback QUIC by a real
    // server (two robots at once, so rounds are batched): every episode must have the same
    // outcome, length, inference calls and executed horizons. Each round carries the in-process
    // sampler seed; a wire path that changed the observation, the noise, the policy's inputs or
    // the reply's actions would change an episode. The plugin twin of the §3.1 rule runs in the
    // server's registry.
    let twin = shipped_plugin("threshold");
    let cache = repo_root().join("plugins/build/cache");
    let run = |live: bool| {
        let out = tempfile::tempdir().unwrap();
        let mut args = vec![
            "--policy",
            "static:h=4",
            "--policy",
            "threshold:t=0.4",
            "--policy",
            "spread:threshold=0.3,samples=4",
            "--horizon-plugin",
            twin.to_str().unwrap(),
            "--param",
            "t=0.2",
            "--plugin-cache",
            cache.to_str().unwrap(),
            "--episodes",
            "6",
            "--seed",
            "41",
            "--threads",
            "2",
            "--no-plots",
        ];
        if live {
            args.push("--live");
        }
        args.push("--out");
        kairos(&args, out.path());
        let read = |f: &str| std::fs::read_to_string(out.path().join(f)).unwrap();
        (read("episodes.csv"), read("pareto.csv"), read("summary.md"))
    };
    let (episodes, pareto, summary) = run(false);
    let (live_episodes, live_pareto, live_summary) = run(true);
    assert!(summary.contains("Mode: in-process"), "{summary}");
    assert!(live_summary.contains("Mode: live"), "{live_summary}");
    assert!(
        live_summary.contains(" 0 fallback decisions"),
        "{live_summary}"
    );
    let rows: Vec<&str> = episodes.lines().skip(1).collect();
    assert_eq!(rows.len(), 4 * 6, "{episodes}");
    assert!(
        rows.iter()
            .any(|r| r.starts_with("threshold.wasm,t=0.2,41,"))
    );
    // The policies chose differently (the comparison is not between identical trivia).
    let horizons: std::collections::BTreeSet<&str> =
        rows.iter().map(|r| r.rsplit(',').next().unwrap()).collect();
    assert!(horizons.len() > 4, "{episodes}");
    assert_eq!(live_episodes, episodes);
    assert_eq!(live_pareto, pareto);
}

#[test]
fn the_contact_task_runs_quick_with_its_own_model_and_refuses_the_other_tasks() {
    let out = tempfile::tempdir().unwrap();
    let stdout = kairos(
        &[
            "--task",
            "contact",
            "--quick",
            "--episodes",
            "4",
            "--no-plots",
            "--out",
        ],
        out.path(),
    );
    assert!(stdout.contains("--task contact --quick"), "{stdout}");
    let csv = std::fs::read_to_string(out.path().join("pareto.csv")).unwrap();
    // --quick's built-in rows and the contact-aware rule (alone, and through releases 8
    // samples agree on), all on the contact model.
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 9, "{csv}");
    assert!(
        rows.iter()
            .any(|r| r[0] == "contact" && r[1] == "margin=1;slow=0.7"),
        "{csv}"
    );
    assert!(
        rows.iter()
            .any(|r| r[0] == "contact S=8" && r[1] == "margin=0;quorum=6;release=4;slow=0.8"),
        "{csv}"
    );
    // A model trained on the uniform task is refused for the contact task.
    let refused = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .current_dir(repo_root())
        .args([
            "bench",
            "horizon",
            "--task",
            "contact",
            "--quick",
            "--episodes",
            "1",
        ])
        .args(["--model", "workloads/horizon/model", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("trained on the uniform task"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
}
