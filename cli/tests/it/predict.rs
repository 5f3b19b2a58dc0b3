//! `kairos predict` on the `smolvla_tiny` fixture, run as a user runs it: the printed actions are
//! exactly what the engine's `SmolVlaPipeline` computes for the same observation and seed.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::PathBuf;
use std::process::{Command, Output};

use kairos_engine::smolvla::{Observation, SmolVlaPipeline};
use kairos_engine::{EngineOptions, ImageFormat, ImageInput};

use crate::repo_root;

fn fixture() -> PathBuf {
    repo_root().join("engine/tests/fixtures/smolvla_tiny")
}

fn predict(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_kairos"))
        .arg("predict")
        .arg("--model")
        .arg(fixture())
        .args(["--threads", "2"])
        .args(args)
        .output()
        .unwrap()
}

fn parse(output: &Output) -> serde_json::Value {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).unwrap()
}

fn actions(v: &serde_json::Value) -> Vec<Vec<f32>> {
    v["actions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|row| {
            row.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect()
        })
        .collect()
}

fn library(obs: &Observation, seed: u64) -> Vec<Vec<f32>> {
    let options = EngineOptions {
        threads: 2,
        ..Default::default()
    };
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &options).unwrap();
    let (mut out, _) = pipeline
        .predict(std::slice::from_ref(obs), &[seed])
        .unwrap();
    out.remove(0).actions
}

#[test]
fn synthetic_observation_prints_the_chunk() {
    let v = parse(&predict(&[]));
    let (chunk, dim) = (
        v["chunk"].as_u64().unwrap(),
        v["action_dim"].as_u64().unwrap(),
    );
    // The fixture's config: chunk_size 16, a 6-wide action.
    assert_eq!((chunk, dim), (16, 6));
    let got = actions(&v);
    assert_eq!(got.len(), 16);
    for stage in ["preprocess", "prefix", "expert", "postprocess", "total"] {
        assert!(v["timing_ms"][stage].as_f64().unwrap() >= 0.0, "{stage}");
    }
    let options = EngineOptions::default();
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &options).unwrap();
    let obs = pipeline.checkpoint().synthetic_observation();
    assert_eq!(got, library(&obs, 0));
}

#[test]
fn images_state_task_and_seed_from_the_command_line() {
    let png = fixture().join("golden/missing.0.top.png");
    let state = "0.1,-0.2,0.3,0.4,0.5,-0.6,0.7";
    let task = "put the blue block on the plate";
    let v = parse(&predict(&[
        "--image",
        &format!("top={}", png.display()),
        "--state",
        state,
        "--task",
        task,
        "--seed",
        "7",
    ]));
    let obs = Observation {
        images: [(
            "top".to_owned(),
            ImageInput::Encoded {
                format: ImageFormat::Png,
                bytes: std::fs::read(&png).unwrap(),
            },
        )]
        .into_iter()
        .collect(),
        state: state.split(',').map(|s| s.parse().unwrap()).collect(),
        task: task.into(),
    };
    assert_eq!(actions(&v), library(&obs, 7));

    // The same observation as a JSON file.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("obs.json");
    let json = serde_json::json!({
        "task": task,
        "state": obs.state,
        "images": {"top": png},
    });
    std::fs::write(&file, json.to_string()).unwrap();
    let from_file = parse(&predict(&[
        "--json-in",
        file.to_str().unwrap(),
        "--seed",
        "7",
    ]));
    assert_eq!(actions(&from_file), actions(&v));
}

#[test]
fn bad_inputs_fail_with_the_field_named() {
    let out = predict(&["--image", "wrist=/dev/null"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/dev/null"), "{err}");

    let png = fixture().join("golden/missing.0.top.png");
    let out = predict(&["--image", &format!("wrist={}", png.display())]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown camera `wrist`"), "{err}");

    let out = predict(&["--state", "1,2"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("observation.state has 2 values"), "{err}");
}

/// `--cuda-graphs` reaches the engine: on the CPU it is refused at load, saying why.
#[test]
fn cuda_graphs_on_the_cpu_fail_saying_they_need_cuda() {
    let out = predict(&["--cuda-graphs"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("CUDA graphs need a CUDA device"), "{err}");
}

/// `--precision bf16` where the native bf16 kernel may not run (forced here with
/// `KAIROS_DISABLE_BF16`) runs the exact f32 model and says so once on stderr.
#[test]
fn precision_bf16_falls_back_to_f32_with_a_warning() {
    let out = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .env("KAIROS_DISABLE_BF16", "1")
        .arg("predict")
        .arg("--model")
        .arg(fixture())
        .args(["--threads", "2", "--precision", "bf16"])
        .output()
        .unwrap();
    let v = parse(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.matches("precision bf16").count(), 1, "{err}");
    assert!(err.contains("runs in f32"), "{err}");
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &EngineOptions::default()).unwrap();
    let obs = pipeline.checkpoint().synthetic_observation();
    assert_eq!(actions(&v), library(&obs, 0));
    let bad = predict(&["--precision", "fp8"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--precision"));
}

/// `--batch N` predicts N copies of the observation in one batch, copy `i` with seed `seed + i`,
/// each exactly as alone; `--repeat R` adds its timings without changing the actions.
#[test]
fn a_batch_of_copies_and_repeated_timings() {
    let v = parse(&predict(&["--batch", "2", "--seed", "3", "--repeat", "2"]));
    let options = EngineOptions::default();
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &options).unwrap();
    let obs = pipeline.checkpoint().synthetic_observation();
    let batch = v["batch_actions"].as_array().unwrap();
    assert_eq!(batch.len(), 2);
    let chunk = |i: usize| actions(&serde_json::json!({ "actions": batch[i] }));
    assert_eq!(chunk(0), actions(&v));
    assert_eq!(chunk(0), library(&obs, 3));
    assert_eq!(chunk(1), library(&obs, 4));
    assert_eq!(v["batch"], 2);
    assert_eq!(v["runs_ms"].as_array().unwrap().len(), 2);
    assert!(v["cpu_ms_per_run"].as_f64().unwrap() >= 0.0);
    assert!(v["peak_rss_mb"].as_f64().unwrap() > 0.0);
    // Without --batch/--repeat the output keeps its shape.
    let plain = parse(&predict(&[]));
    assert!(plain.get("batch_actions").is_none() && plain.get("runs_ms").is_none());
}

/// `kairos predict --model engine/tests/fixtures/pi05_tiny` (and `pi0_tiny`): the promised JSON,
/// with exactly the library's actions for the synthetic observation; every stage on the fast
/// kernels by default and on Candle ops with `--kernels candle`.
#[test]
fn pi_checkpoints_print_the_chunk() {
    for fixture in ["pi05_tiny", "pi0_tiny"] {
        let dir = repo_root().join("engine/tests/fixtures").join(fixture);
        let run = |extra: &[&str]| {
            let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
                .arg("predict")
                .arg("--model")
                .arg(&dir)
                .args(["--threads", "2", "--seed", "3"])
                .args(extra)
                .output()
                .unwrap();
            parse(&output)
        };
        let v = run(&[]);
        let candle = run(&["--kernels", "candle"]);
        for stage in ["vision", "prefix", "expert"] {
            let path = v["paths"][stage].as_str().unwrap();
            assert!(path.starts_with("fast:"), "{fixture} {stage}: {path}");
            assert_eq!(candle["paths"][stage], "candle:cpu", "{fixture} {stage}");
        }
        assert_eq!(
            (v["chunk"].as_u64(), v["action_dim"].as_u64()),
            (Some(12), Some(6)),
            "{fixture}"
        );
        for stage in ["preprocess", "prefix", "expert", "postprocess", "total"] {
            assert!(
                v["timing_ms"][stage].as_f64().unwrap() >= 0.0,
                "{fixture} {stage}"
            );
        }
        let options = EngineOptions {
            threads: 2,
            ..Default::default()
        };
        let pipeline = kairos_engine::pi::PiPipeline::load(&dir, None, &options).unwrap();
        let obs = pipeline.checkpoint().synthetic_observation();
        let (mut want, _) = pipeline.predict(&[obs], &[3]).unwrap();
        assert_eq!(actions(&v), want.remove(0).actions, "{fixture}");
    }
}

/// π0 / π0.5: the paths `kairos predict` prints are the library's, for the fast kernels and for
/// Candle ops alike.
#[test]
fn pi_paths_printed_are_the_librarys() {
    let dir = repo_root().join("engine/tests/fixtures/pi05_tiny");
    for kernels in ["fast", "candle"] {
        let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
            .arg("predict")
            .arg("--model")
            .arg(&dir)
            .args(["--threads", "2", "--kernels", kernels])
            .output()
            .unwrap();
        let v = parse(&output);
        let options = EngineOptions {
            threads: 2,
            kernels: kernels.parse().unwrap(),
            ..Default::default()
        };
        let pipeline = kairos_engine::pi::PiPipeline::load(&dir, None, &options).unwrap();
        let paths = kairos_engine::ActionModel::paths(&pipeline).unwrap();
        let printed: kairos_engine::StagePaths =
            serde_json::from_value(v["paths"].clone()).unwrap();
        assert_eq!(printed, paths, "{kernels}");
        if kernels == "candle" {
            assert_eq!(paths, kairos_engine::StagePaths::all("candle:cpu"));
        }
    }
}

/// `--kernels candle` moves the whole pipeline: `paths` says `candle:cpu` for every stage, and
/// the chunk equals the fast kernels' within the parity bound. Each path is within
/// `5 e_lr + 16 ulp` of LeRobot's f32 actions (`engine/tests/it/smolvla_processors.rs`; `e_lr`
/// is LeRobot's own f32-vs-f64 error on the fixture's actions, `golden/meta.json`), so the two
/// are within twice that of each other.
#[test]
fn candle_kernels_run_every_stage_on_candle_and_agree_with_the_fast_kernels() {
    let candle = parse(&predict(&["--kernels", "candle"]));
    for stage in ["vision", "prefix", "expert"] {
        assert_eq!(candle["paths"][stage], "candle:cpu", "{stage}");
    }
    let fast = parse(&predict(&["--kernels", "fast"]));
    for stage in ["vision", "prefix", "expert"] {
        let path = fast["paths"][stage].as_str().unwrap();
        assert!(path.starts_with("fast:"), "{stage}: {path}");
    }
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture().join("golden/meta.json")).unwrap())
            .unwrap();
    let e_lr = ["pair.actions", "missing.actions"]
        .iter()
        .map(|k| meta["lerobot_f32_vs_f64"][k]["max_abs"].as_f64().unwrap() as f32)
        .fold(0.0f32, f32::max);
    let (a, b) = (actions(&candle).concat(), actions(&fast).concat());
    let big = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let bound = 2.0 * (5.0 * e_lr + 16.0 * f32::EPSILON * big);
    let diff = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert_eq!(a.len(), b.len());
    assert!(diff <= bound, "|candle - fast| = {diff:e} > {bound:e}");
    assert_ne!(
        a, b,
        "the two paths computed bit-identical results: one path ran twice"
    );
}
