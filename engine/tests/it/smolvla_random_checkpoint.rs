//! The random checkpoint writer (`smolvla::random_checkpoint`): shaped like the `smolvla_tiny`
//! fixture, which LeRobot's `save_pretrained` wrote, it writes the same tensors (names, dtypes,
//! shapes); its folder loads and predicts; the same seed writes the same bytes.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::collections::BTreeMap;
use std::path::Path;

use kairos_engine::smolvla::random_checkpoint::RandomCheckpoint;
use kairos_engine::smolvla::{SmolVlaPipeline, VlmConfig};
use kairos_engine::{EngineOptions, Kernels};
use safetensors::SafeTensors;

use crate::smolvla_goldens::fixture;

/// The fixture's shapes.
fn like_fixture(seed: u64) -> RandomCheckpoint {
    RandomCheckpoint {
        vlm: VlmConfig::from_file(&fixture().join("vlm_config.json")).unwrap(),
        num_vlm_layers: 4,
        state_dim: 7,
        action_dim: 6,
        cameras: 2,
        image_side: 96,
        chunk: 16,
        tokenizer_max_length: 16,
        seed,
    }
}

/// Name -> (dtype, shape) of a safetensors file.
fn tensors(path: &Path) -> BTreeMap<String, (String, Vec<usize>)> {
    let bytes = std::fs::read(path).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    st.tensors()
        .into_iter()
        .map(|(name, t)| (name, (format!("{:?}", t.dtype()), t.shape().to_vec())))
        .collect()
}

#[test]
fn it_writes_the_tensors_lerobot_saves() {
    let dir = tempfile::tempdir().unwrap();
    like_fixture(1).write(dir.path()).unwrap();
    let ours = tensors(&dir.path().join("model.safetensors"));
    let lerobot = tensors(&fixture().join("model.safetensors"));
    assert_eq!(ours, lerobot);
    for name in [
        "config.json",
        "vlm_config.json",
        "tokenizer.json",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
        "policy_preprocessor_step_5_normalizer_processor.safetensors",
        "policy_postprocessor_step_0_unnormalizer_processor.safetensors",
    ] {
        assert!(dir.path().join(name).is_file(), "{name}");
    }
}

#[test]
fn its_folder_loads_and_predicts_on_both_paths() {
    let dir = tempfile::tempdir().unwrap();
    like_fixture(2).write(dir.path()).unwrap();
    let mut results = Vec::new();
    for kernels in [Kernels::Fast, Kernels::Candle] {
        let options = EngineOptions {
            kernels,
            threads: 2,
            ..Default::default()
        };
        let pipeline = SmolVlaPipeline::load(dir.path(), None, &options).unwrap();
        assert_eq!(pipeline.checkpoint().camera_keys().len(), 2);
        let obs = pipeline.checkpoint().synthetic_observation();
        let (out, _) = pipeline.predict(&[obs], &[5]).unwrap();
        let actions = out[0].actions.concat();
        assert_eq!(actions.len(), 16 * 6);
        assert!(actions.iter().all(|a| a.is_finite()));
        results.push(actions);
    }
    let diff = results[0]
        .iter()
        .zip(&results[1])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let big = results[0].iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(diff <= 1e-3 * big.max(1.0), "fast vs candle: {diff:e}");
}

#[test]
fn the_same_seed_writes_the_same_bytes() {
    let (a, b, c) = (
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
    );
    like_fixture(3).write(a.path()).unwrap();
    like_fixture(3).write(b.path()).unwrap();
    like_fixture(4).write(c.path()).unwrap();
    let read = |d: &Path| std::fs::read(d.join("model.safetensors")).unwrap();
    assert_eq!(read(a.path()), read(b.path()));
    assert_ne!(read(a.path()), read(c.path()));
}

/// `smolvla_base`'s shape is what the engine knows as SmolVLM2-500M with 16 text layers and a
/// 720-wide expert (the config only: the full folder is 1.2 GB).
#[test]
fn the_smolvla_base_preset_has_the_base_shapes() {
    let base = RandomCheckpoint::smolvla_base(0);
    assert_eq!(base.vlm, VlmConfig::smolvlm2_500m());
    assert_eq!(
        (
            base.num_vlm_layers,
            base.chunk,
            base.image_side,
            base.cameras
        ),
        (16, 50, 512, 2)
    );
}
