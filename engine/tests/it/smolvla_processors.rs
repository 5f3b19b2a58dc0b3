//! The processors of a SmolVLA checkpoint (rename map, newline + tokenizer, normaliser, image
//! preparation, unnormaliser) and the whole pipeline from raw inputs, against LeRobot 0.6.1 on
//! the `smolvla_tiny` fixture (see `smolvla_vlm.rs` for the fixture and the model's bounds).
//!
//! Bounds:
//! - tokens and masks: exact (LeRobot pads a batch to its longest task; its padding positions
//!   must hold the pad id with a false mask, ours have none);
//! - normalised state: the same f32 operations in the same order as LeRobot's
//!   `(x - mean) / (std + eps)`, so bit-identical (asserted exactly);
//! - prepared images: [`prepared_pixel_bound`] of the longer input side (derived there:
//!   rounding of the 7 bilinear operations plus a possibly fused source-coordinate computation;
//!   `6.3e-5` for the 131-pixel camera; measured 2026-11-25: at most 2.6e-6);
//! - unnormalised actions from LeRobot's normalised ones: the same f32 operations as LeRobot's
//!   QUANTILES inverse, bit-identical (asserted exactly);
//! - the whole pipeline's final actions: the model's bound from `smolvla_vlm.rs` (`5 e_lr` of
//!   LeRobot's own f32-vs-f64 error plus 16 ulps of the largest value), since the processors
//!   add nothing measurable to the model's rounding.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::{Path, PathBuf};

use crate::smolvla_goldens::{Goldens, fixture};
use kairos_engine::smolvla::images::prepared_pixel_bound;
use kairos_engine::smolvla::{Observation, SmolVlaCheckpoint, SmolVlaPipeline};
use kairos_engine::weights::Checkpoint;
use kairos_engine::{DeviceKind, EngineError, EngineOptions, ImageFormat, ImageInput, Kernels};

/// The raw observations of case `name`, keyed as the robot sends them.
pub(crate) fn observations(g: &Goldens, name: &str) -> Vec<Observation> {
    let case = &g.meta["cases"][name];
    let batch = case["batch"].as_u64().unwrap() as usize;
    let state = g.f32(&format!("{name}.raw.state"));
    let dim = state.len() / batch;
    (0..batch)
        .map(|b| {
            let images = case["raw_cameras"]
                .as_object()
                .unwrap()
                .iter()
                .map(|(key, hw)| {
                    let (h, w) = (
                        hw[0].as_u64().unwrap() as usize,
                        hw[1].as_u64().unwrap() as usize,
                    );
                    let all = g.u8(&format!("{name}.raw.{key}"));
                    let n = h * w * 3;
                    let image = ImageInput::RawU8 {
                        height: h,
                        width: w,
                        channels: 3,
                        data: all[b * n..(b + 1) * n].to_vec(),
                    };
                    (key.clone(), image)
                })
                .collect();
            Observation {
                images,
                state: state[b * dim..(b + 1) * dim].to_vec(),
                task: case["tasks"][b].as_str().unwrap().to_owned(),
            }
        })
        .collect()
}

fn cpu() -> EngineOptions {
    EngineOptions {
        device: DeviceKind::Cpu,
        kernels: Kernels::Auto,
        threads: 2,
        ..Default::default()
    }
}

pub(crate) fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn preprocessing_matches(name: &str) {
    let g = Goldens::open();
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    let pad_id = g.meta["tokenizer"]["pad_id"].as_u64().unwrap() as u32;
    let observations = observations(&g, name);
    let batch = observations.len();
    let tokens = g.i64(&format!("{name}.tokens"));
    let token_mask = g.u8(&format!("{name}.token_mask"));
    let token_len = tokens.len() / batch;
    let state_norm = g.f32(&format!("{name}.state_norm"));
    let slots = g.meta["cases"][name]["image_slots"].as_u64().unwrap() as usize;
    let longest_side = g.meta["cases"][name]["raw_cameras"]
        .as_object()
        .unwrap()
        .values()
        .flat_map(|hw| hw.as_array().unwrap().iter().map(|v| v.as_u64().unwrap()))
        .max()
        .unwrap() as usize;
    let bound = prepared_pixel_bound(longest_side);
    for (b, obs) in observations.iter().enumerate() {
        let p = ck.prepare(obs).unwrap();

        // Tokens: exactly LeRobot's real tokens; LeRobot's batch padding is pad ids, masked.
        let want = &tokens[b * token_len..(b + 1) * token_len];
        let mask = &token_mask[b * token_len..(b + 1) * token_len];
        let real: Vec<u32> = want
            .iter()
            .zip(mask)
            .filter(|(_, m)| **m != 0)
            .map(|(&t, _)| t as u32)
            .collect();
        assert_eq!(p.tokens.ids, real, "{name}[{b}]: token ids");
        assert!(p.tokens.mask.iter().all(|&m| m), "{name}[{b}]: mask");
        for (&t, &m) in want.iter().zip(mask).skip(real.len()) {
            assert_eq!((t as u32, m), (pad_id, 0), "{name}[{b}]: LeRobot's padding");
        }

        // State: bit-identical.
        let dim = p.state.len();
        assert_eq!(
            p.state,
            state_norm[b * dim..(b + 1) * dim],
            "{name}[{b}]: state"
        );

        // Images: every slot, mask and pixels.
        assert_eq!(p.images.len(), slots, "{name}[{b}]: camera slots");
        for (s, img) in p.images.iter().enumerate() {
            let mask = g.u8(&format!("{name}.image_mask.{s}"));
            assert_eq!(img.present, mask[b] != 0, "{name}[{b}]: mask of slot {s}");
            let all = g.f32(&format!("{name}.image.{s}"));
            let n = all.len() / batch;
            let d = max_abs_diff(&img.pixels, &all[b * n..(b + 1) * n]);
            eprintln!("{name}[{b}] image {s}: |ours - lerobot| {d:.3e} (bound {bound:.3e})");
            assert!(d <= bound, "{name}[{b}] image {s}: {d:e} > {bound:e}");
        }
    }
}

#[test]
fn two_cameras_a_truncated_task_and_state_match_lerobot() {
    let g = Goldens::open();
    // The case exercises what it claims: the first task is cut to max_length.
    let max = g.meta["tokenizer"]["max_length"].as_u64().unwrap() as usize;
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    let long = &observations(&g, "pair")[0].task;
    assert_eq!(
        ck.tokenizer()
            .encode(&format!("{long}\n"))
            .unwrap()
            .ids
            .len(),
        max
    );
    preprocessing_matches("pair");
}

#[test]
fn a_missing_camera_becomes_an_empty_one_like_lerobot() {
    preprocessing_matches("missing");
}

#[test]
fn unnormalised_actions_match_lerobot_exactly() {
    let g = Goldens::open();
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    for name in ["pair", "missing"] {
        let norm = g.f32(&format!("{name}.actions_norm"));
        let want = g.f32(&format!("{name}.actions"));
        let dim = ck.action_dim();
        let ours: Vec<f32> = ck.finish_actions(&norm, dim).unwrap().concat();
        assert_eq!(ours, want, "{name}: unnormalised actions");
    }
    // A padded model output (max_action_dim wide) is cut first.
    let norm = g.f32("missing.actions_norm");
    let pad = ck.config().max_action_dim;
    let padded: Vec<f32> = norm
        .chunks_exact(ck.action_dim())
        .flat_map(|row| {
            let mut r = row.to_vec();
            r.resize(pad, 9.0);
            r
        })
        .collect();
    assert_eq!(
        ck.finish_actions(&padded, pad).unwrap().concat(),
        g.f32("missing.actions")
    );
}

#[test]
fn the_whole_pipeline_matches_lerobot_from_raw_inputs() {
    whole_pipeline_matches_lerobot(&cpu());
}

/// The same through the Candle path: every stage in Candle ops, as on CUDA.
#[test]
fn the_whole_candle_pipeline_matches_lerobot_from_raw_inputs() {
    let options = EngineOptions {
        kernels: Kernels::Candle,
        ..cpu()
    };
    let pipeline = whole_pipeline_matches_lerobot(&options);
    let paths = pipeline.paths();
    assert_eq!(
        [&paths.vision, &paths.prefix, &paths.expert],
        ["candle:cpu"; 3]
    );
}

fn whole_pipeline_matches_lerobot(options: &EngineOptions) -> SmolVlaPipeline {
    let g = Goldens::open();
    let pipeline = SmolVlaPipeline::load(&fixture(), None, options).unwrap();
    for name in ["pair", "missing"] {
        let observations = observations(&g, name);
        let noise = g.f32(&format!("{name}.noise"));
        let per = noise.len() / observations.len();
        let noises: Vec<Vec<f32>> = noise.chunks_exact(per).map(<[f32]>::to_vec).collect();
        let (out, _) = pipeline.predict_with_noise(&observations, &noises).unwrap();
        let ours: Vec<f32> = out.iter().flat_map(|p| p.actions.concat()).collect();
        let want = g.f32(&format!("{name}.actions"));
        let want64 = g.f32(&format!("{name}.actions.f64"));
        let big = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let key = format!("{name}.actions");
        let bound = 5.0 * g.e_lr(&key) + 16.0 * f32::EPSILON * big;
        let (d32, d64) = (max_abs_diff(&ours, &want), max_abs_diff(&ours, &want64));
        eprintln!("{key}: |ours-lerobot| {d32:.3e}, |ours-f64| {d64:.3e}, bound {bound:.3e}");
        assert!(
            d32 <= bound && d64 <= bound,
            "{key}: {d32:e} / {d64:e} > {bound:e}"
        );
        assert_eq!(out[0].actions.len(), pipeline.chunk());
        assert_eq!(out[0].actions[0].len(), pipeline.action_dim());
    }
    // Batched == single, bit for bit, through the processors too.
    let observations = observations(&g, "pair");
    let (both, _) = pipeline.predict(&observations, &[3, 4]).unwrap();
    let (one, _) = pipeline.predict(&observations[1..], &[4]).unwrap();
    if options.kernels == Kernels::Candle {
        // Candle pads the batch to its longest prefix and masks it: equal up to rounding.
        let (a, b) = (both[1].actions.concat(), one[0].actions.concat());
        assert!(max_abs_diff(&a, &b) <= 1e-4, "{}", max_abs_diff(&a, &b));
    } else {
        assert_eq!(both[1], one[0]);
    }
    pipeline
}

#[test]
fn png_and_raw_inputs_prepare_identically() {
    let g = Goldens::open();
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    let raw = &observations(&g, "missing")[0];
    let mut png = raw.clone();
    png.images.insert(
        "observation.images.top".into(),
        ImageInput::Encoded {
            format: ImageFormat::Png,
            bytes: std::fs::read(fixture().join("golden/missing.0.top.png")).unwrap(),
        },
    );
    // The short camera name and the full key resolve to the same (renamed) camera.
    let mut short = raw.clone();
    let img = short.images.remove("observation.images.top").unwrap();
    short.images.insert("top".into(), img);
    let want = ck.prepare(raw).unwrap();
    assert_eq!(ck.prepare(&png).unwrap(), want);
    assert_eq!(ck.prepare(&short).unwrap(), want);
}

#[test]
fn synthetic_observation_covers_every_camera() {
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    let obs = ck.synthetic_observation();
    // camera1 and camera2; empty_camera_0 is LeRobot's placeholder for a missing camera.
    assert_eq!(
        obs.images.keys().collect::<Vec<_>>(),
        vec!["observation.images.camera1", "observation.images.camera2"]
    );
    assert_eq!(obs.state, vec![0.0; 7]);
    assert_eq!(obs.task, "pick up the cube");
    // Both cameras, then the one empty camera the config asks for (LeRobot's slot order).
    let p = ck.prepare(&obs).unwrap();
    let present: Vec<bool> = p.images.iter().map(|i| i.present).collect();
    assert_eq!(present, vec![true, true, false]);
}

/// A copy of the fixture to break.
fn copy_fixture() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(fixture()).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, dir.path().join(path.file_name().unwrap())).unwrap();
        }
    }
    dir
}

fn edit_json(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(path, serde_json::to_string(&v).unwrap()).unwrap();
}

fn open_err(dir: &Path) -> String {
    SmolVlaCheckpoint::open(dir, None).unwrap_err().to_string()
}

/// The normaliser's stats file, rewritten with `edit` applied to its tensors.
fn edit_stats(dir: &Path, edit: impl FnOnce(&mut Vec<(String, Vec<usize>, Vec<f32>)>)) -> String {
    let name = "policy_preprocessor_step_5_normalizer_processor.safetensors";
    let ck = Checkpoint::open(&dir.join(name)).unwrap();
    let mut tensors: Vec<(String, Vec<usize>, Vec<f32>)> = ck
        .keys()
        .into_iter()
        .map(|k| {
            let shape = ck.shape(&k).unwrap().to_vec();
            let v = ck.tensor(&k, &shape).unwrap();
            (k, shape, v)
        })
        .collect();
    edit(&mut tensors);
    let views: Vec<(String, Vec<usize>, &[f32])> = tensors
        .iter()
        .map(|(k, s, v)| (k.clone(), s.clone(), v.as_slice()))
        .collect();
    let bytes = kairos_engine::weights::serialize_f32(&views).unwrap();
    std::fs::write(dir.join(name), bytes).unwrap();
    name.to_owned()
}

#[test]
fn missing_files_are_named() {
    for file in [
        "config.json",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
        "policy_postprocessor_step_0_unnormalizer_processor.safetensors",
        "tokenizer.json",
    ] {
        let dir = copy_fixture();
        std::fs::remove_file(dir.path().join(file)).unwrap();
        let err = open_err(dir.path());
        assert!(
            err.contains("missing file") && err.contains(file),
            "{file}: {err}"
        );
    }
    let dir = copy_fixture();
    std::fs::remove_file(dir.path().join("model.safetensors")).unwrap();
    let err = SmolVlaPipeline::load(dir.path(), None, &cpu())
        .unwrap_err()
        .to_string();
    assert!(err.contains("model.safetensors"), "{err}");
    // An explicit tokenizer path that does not exist is named too.
    let err = SmolVlaCheckpoint::open(&fixture(), Some(Path::new("/nonexistent/tok.json")))
        .unwrap_err()
        .to_string();
    assert!(err.contains("/nonexistent/tok.json"), "{err}");
}

#[test]
fn the_state_file_is_followed_not_guessed() {
    // Renaming the stats file and pointing the JSON at the new name still loads.
    let dir = copy_fixture();
    let old = "policy_preprocessor_step_5_normalizer_processor.safetensors";
    let new = "stats_somewhere_else.safetensors";
    std::fs::rename(dir.path().join(old), dir.path().join(new)).unwrap();
    edit_json(&dir.path().join("policy_preprocessor.json"), |v| {
        for step in v["steps"].as_array_mut().unwrap() {
            if step.get("state_file").is_some() {
                step["state_file"] = new.into();
            }
        }
    });
    let ck = SmolVlaCheckpoint::open(dir.path(), None).unwrap();
    let want = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    assert_eq!(ck.preprocessor(), want.preprocessor());
}

#[test]
fn missing_and_misshapen_stats_are_named() {
    // A stat the mode needs is missing: named with its file.
    let dir = copy_fixture();
    let file = edit_stats(dir.path(), |t| {
        t.retain(|(k, _, _)| k != "observation.state.std")
    });
    let err = open_err(dir.path());
    assert!(
        err.contains("observation.state.std") && err.contains(&file),
        "{err}"
    );
    // A stat of the wrong length.
    let dir = copy_fixture();
    edit_stats(dir.path(), |t| {
        for (k, s, v) in t.iter_mut() {
            if k == "observation.state.mean" {
                v.push(0.0);
                s[0] += 1;
            }
        }
    });
    let err = open_err(dir.path());
    assert!(err.contains("observation.state.mean"), "{err}");
    // A stat of a dtype that is not a float.
    let dir = copy_fixture();
    let name = "policy_postprocessor_step_0_unnormalizer_processor.safetensors";
    let ck = Checkpoint::open(&dir.path().join(name)).unwrap();
    let mut tensors = std::collections::BTreeMap::new();
    let mut store: Vec<(String, Vec<usize>, Vec<u8>, safetensors::Dtype)> = Vec::new();
    for k in ck.keys() {
        let shape = ck.shape(&k).unwrap().to_vec();
        let v = ck.tensor(&k, &shape).unwrap();
        if k == "action.q01" {
            store.push((
                k,
                shape,
                v.iter()
                    .map(|&x| x as i32)
                    .flat_map(i32::to_le_bytes)
                    .collect(),
                safetensors::Dtype::I32,
            ));
        } else {
            store.push((
                k,
                shape,
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                safetensors::Dtype::F32,
            ));
        }
    }
    for (k, s, b, d) in &store {
        tensors.insert(
            k.clone(),
            safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
        );
    }
    std::fs::write(
        dir.path().join(name),
        safetensors::serialize(tensors, None).unwrap(),
    )
    .unwrap();
    let err = open_err(dir.path());
    assert!(
        err.contains("action.q01") && err.contains("I32") && err.contains(name),
        "{err}"
    );
}

#[test]
fn a_feature_without_stats_passes_through() {
    let dir = copy_fixture();
    edit_stats(dir.path(), |t| {
        t.retain(|(k, _, _)| !k.starts_with("observation.state."))
    });
    let ck = SmolVlaCheckpoint::open(dir.path(), None).unwrap();
    let normalizer = ck.preprocessor().normalizer.as_ref().unwrap();
    assert_eq!(normalizer.unnormalised(), ["observation.state".to_owned()]);
    let g = Goldens::open();
    let obs = &observations(&g, "missing")[0];
    assert_eq!(ck.prepare(obs).unwrap().state, obs.state);
}

#[test]
fn an_unknown_normalisation_mode_is_named() {
    let dir = copy_fixture();
    edit_json(&dir.path().join("policy_postprocessor.json"), |v| {
        v["steps"][0]["config"]["norm_map"]["ACTION"] = "LOG_SCALE".into();
    });
    let err = open_err(dir.path());
    assert!(
        err.contains("LOG_SCALE")
            && err.contains("ACTION")
            && err.contains("policy_postprocessor.json"),
        "{err}"
    );
    // An unknown step is refused by name rather than skipped.
    let dir = copy_fixture();
    edit_json(&dir.path().join("policy_preprocessor.json"), |v| {
        v["steps"]
            .as_array_mut()
            .unwrap()
            .push(serde_json::json!({"registry_name": "delta_action_processor", "config": {}}));
    });
    let err = open_err(dir.path());
    assert!(err.contains("delta_action_processor"), "{err}");
}

#[test]
fn bad_observations_are_named_errors() {
    let ck = SmolVlaCheckpoint::open(&fixture(), None).unwrap();
    let g = Goldens::open();
    let good = observations(&g, "missing").remove(0);

    let mut obs = good.clone();
    let img = obs.images.remove("observation.images.top").unwrap();
    obs.images.insert("wrist".into(), img);
    let err = ck.prepare(&obs).unwrap_err();
    assert!(matches!(err, EngineError::UnknownCamera { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("wrist") && msg.contains("observation.images.camera1"),
        "{msg}"
    );

    let mut obs = good.clone();
    obs.state.push(1.0);
    let err = ck.prepare(&obs).unwrap_err().to_string();
    assert!(
        err.contains("observation.state") && err.contains('8') && err.contains('7'),
        "{err}"
    );

    let mut obs = good.clone();
    obs.state[2] = f32::NAN;
    assert!(
        ck.prepare(&obs)
            .unwrap_err()
            .to_string()
            .contains("observation.state[2]")
    );

    let mut obs = good.clone();
    obs.images.insert(
        "camera2".into(),
        ImageInput::Encoded {
            format: ImageFormat::Png,
            bytes: b"not a png".to_vec(),
        },
    );
    let err = ck.prepare(&obs).unwrap_err().to_string();
    assert!(err.contains("observation.images.camera2"), "{err}");

    let mut obs = good;
    obs.images.clear();
    assert!(ck.prepare(&obs).is_err());
}

/// A real LeRobot SmolVLA checkpoint (e.g. a fine-tuned `lerobot/smolvla_base`), opt-in:
/// `KAIROS_SMOLVLA_CHECKPOINT=DIR [KAIROS_SMOLVLA_TOKENIZER=tokenizer.json] cargo test -p
/// kairos-engine --test it real_checkpoint -- --ignored`. It loads every file, predicts from the
/// synthetic observation and checks the chunk's shape, that it is finite, and that batching and
/// the seed behave.
#[test]
#[ignore = "needs a real checkpoint: set KAIROS_SMOLVLA_CHECKPOINT and run with --ignored"]
fn real_checkpoint_predicts() {
    let dir = PathBuf::from(
        std::env::var("KAIROS_SMOLVLA_CHECKPOINT")
            .expect("set KAIROS_SMOLVLA_CHECKPOINT to a LeRobot SmolVLA checkpoint directory"),
    );
    let tokenizer = std::env::var("KAIROS_SMOLVLA_TOKENIZER")
        .ok()
        .map(PathBuf::from);
    let pipeline = SmolVlaPipeline::load(&dir, tokenizer.as_deref(), &cpu()).unwrap();
    let obs = pipeline.checkpoint().synthetic_observation();
    let (out, times) = pipeline
        .predict(&[obs.clone(), obs.clone()], &[0, 1])
        .unwrap();
    eprintln!("{}: {times:?}", dir.display());
    for p in &out {
        assert_eq!(p.actions.len(), pipeline.chunk());
        assert!(p.actions.iter().all(|a| a.len() == pipeline.action_dim()));
        assert!(p.actions.iter().flatten().all(|v| v.is_finite()));
    }
    assert_ne!(out[0], out[1], "different seeds, same chunk");
    let (alone, _) = pipeline.predict(&[obs], &[1]).unwrap();
    assert_eq!(alone[0], out[1]);
}

/// The directory served through `ActionModel` (what `kairos serve --model DIR` loads): the whole
/// policy, sample 0 of a request equal to `predict` with the request's seed, in robot units, with
/// `noise + sum(updates)` equal to the actions up to rounding.
#[test]
fn the_checkpoint_serves_as_an_action_model() {
    let g = Goldens::open();
    let model = kairos_engine::load_model_with(&fixture(), &cpu()).unwrap();
    let spec = model.spec().clone();
    assert_eq!(
        (
            spec.name.as_str(),
            spec.chunk_len,
            spec.action_dim,
            spec.state_dim,
            spec.max_images
        ),
        ("smolvla", 16, 6, 7, 2)
    );
    let obs = observations(&g, "missing").remove(0);
    let request = kairos_engine::ActionRequest {
        cameras: Vec::new(),
        state: obs.state.clone(),
        images: obs.images.values().cloned().collect(),
        instruction: obs.task.clone(),
        samples: 2,
        seed: 5,
        guidance: None,
    };
    let chunk = model
        .generate(std::slice::from_ref(&request))
        .unwrap()
        .remove(0);
    let pipeline = SmolVlaPipeline::load(&fixture(), None, &cpu()).unwrap();
    let (want, _) = pipeline.predict(&[obs], &[5]).unwrap();
    assert_eq!(chunk.sample_actions(0), want[0].actions.concat().as_slice());
    assert_ne!(chunk.sample_actions(0), chunk.sample_actions(1));
    let (n, k) = (spec.chunk_len * spec.action_dim, spec.steps);
    for s in 0..2 {
        let mut x = chunk.noise[s * n..(s + 1) * n].to_vec();
        for step in chunk.sample_updates(s).chunks_exact(n).take(k) {
            for (xi, u) in x.iter_mut().zip(step) {
                *xi += u;
            }
        }
        let d = max_abs_diff(&x, chunk.sample_actions(s));
        let big = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(
            d <= 1e-5 * big.max(1.0),
            "sample {s}: noise + sum U off by {d}"
        );
    }
    // Too many images for the model's cameras are refused by the spec.
    let mut three = request;
    three.images.push(three.images[0].clone());
    three.images.push(three.images[0].clone());
    assert!(model.generate(&[three]).is_err());
}

/// The served policy matches a request's images to its cameras by name: the spec lists the
/// cameras and every other name a robot may use (the rename map's `top`, the short `camera2`),
/// and a named request in any order gets the chunk of the positional one in the model's order.
/// A name the model lacks is refused by the spec, naming it and the model's cameras.
#[test]
fn named_cameras_match_in_any_order() {
    let g = Goldens::open();
    let model = kairos_engine::load_model_with(&fixture(), &cpu()).unwrap();
    let spec = model.spec().clone();
    assert_eq!(
        spec.cameras,
        ["observation.images.camera1", "observation.images.camera2"]
    );
    for (alias, camera) in [
        ("top", "observation.images.camera1"),
        ("observation.images.top", "observation.images.camera1"),
        ("camera2", "observation.images.camera2"),
        ("observation.images.camera1", "observation.images.camera1"),
    ] {
        assert_eq!(spec.camera(alias), Some(camera), "{alias}");
    }
    assert_eq!(spec.camera("wrist"), None);
    let obs = observations(&g, "pair").remove(0);
    let keys: Vec<String> = obs.images.keys().cloned().collect();
    assert_eq!(keys.len(), 2);
    let positional = kairos_engine::ActionRequest {
        cameras: Vec::new(),
        state: obs.state.clone(),
        images: spec
            .cameras
            .iter()
            .map(|c| {
                let key = keys.iter().find(|k| spec.camera(k) == Some(c)).unwrap();
                obs.images[key].clone()
            })
            .collect(),
        instruction: obs.task.clone(),
        samples: 1,
        seed: 9,
        guidance: None,
    };
    let reversed = kairos_engine::ActionRequest {
        cameras: keys.iter().rev().cloned().collect(),
        images: keys.iter().rev().map(|k| obs.images[k].clone()).collect(),
        ..positional.clone()
    };
    let chunks = model.generate(&[positional.clone(), reversed]).unwrap();
    assert_eq!(chunks[0], chunks[1]);
    let unknown = kairos_engine::ActionRequest {
        cameras: vec![keys[0].clone(), "wrist".into()],
        images: positional.images.clone(),
        ..positional
    };
    let err = spec
        .check_request(&unknown, &Default::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("images[1].camera")
            && err.contains("`wrist`")
            && err.contains("observation.images.camera1, observation.images.camera2"),
        "{err}"
    );
    assert!(model.generate(&[unknown]).is_err());
}

/// `model.safetensors` rewritten with `edit` applied to its (raw, mixed bf16/f32) tensors.
fn edit_weights(
    dir: &Path,
    edit: impl FnOnce(&mut Vec<(String, safetensors::Dtype, Vec<usize>, Vec<u8>)>),
) {
    let path = dir.join("model.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut tensors: Vec<(String, safetensors::Dtype, Vec<usize>, Vec<u8>)> = file
        .tensors()
        .into_iter()
        .map(|(k, v)| (k, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
        .collect();
    edit(&mut tensors);
    let views: std::collections::BTreeMap<String, safetensors::tensor::TensorView<'_>> = tensors
        .iter()
        .map(|(k, d, s, b)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
            )
        })
        .collect();
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
}

/// A VLM tensor missing from the whole checkpoint, or of the wrong shape, fails the load with
/// its key named (the expert's are covered by `loader_errors`); nothing panics.
#[test]
fn a_missing_or_misshapen_vlm_tensor_is_named() {
    const CONNECTOR: &str =
        "model.vlm_with_expert.vlm.model.connector.modality_projection.proj.weight";
    const PATCH: &str =
        "model.vlm_with_expert.vlm.model.vision_model.embeddings.patch_embedding.bias";
    let load = |dir: &Path| SmolVlaPipeline::load(dir, None, &cpu()).unwrap_err();
    let dir = copy_fixture();
    edit_weights(dir.path(), |t| t.retain(|(k, ..)| k != PATCH));
    let err = load(dir.path());
    assert!(err.to_string().contains(PATCH), "{err}");
    let dir = copy_fixture();
    edit_weights(dir.path(), |t| {
        for (k, _, shape, _) in t.iter_mut() {
            if k == CONNECTOR {
                shape.reverse();
            }
        }
    });
    let err = load(dir.path());
    assert!(
        matches!(&err, EngineError::ShapeMismatch { key, .. } if key.contains(CONNECTOR)),
        "{err}"
    );
}
