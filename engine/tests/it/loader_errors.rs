//! A broken checkpoint is a clear error that names what is wrong, never a panic.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::{Path, PathBuf};

use kairos_engine::smolvla::SmolVlaExpert;
use kairos_engine::{EngineError, EngineOptions, load_model};
use safetensors::tensor::{Dtype, TensorView};

const K_PROJ: &str = "model.vlm_with_expert.lm_expert.layers.1.self_attn.k_proj.weight";

fn golden() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/smolvla_small")
}

/// A copy of the golden checkpoint in a temp dir, with `edit` applied to its tensors.
fn checkpoint_with(
    edit: impl FnOnce(&mut Vec<(String, Dtype, Vec<usize>, Vec<u8>)>),
) -> tempfile::TempDir {
    let bytes = std::fs::read(golden().join("model.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let mut tensors: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = st
        .tensors()
        .into_iter()
        .map(|(k, v)| (k, v.dtype(), v.shape().to_vec(), v.data().to_vec()))
        .collect();
    edit(&mut tensors);
    let views: Vec<(String, TensorView<'_>)> = tensors
        .iter()
        .map(|(k, d, s, b)| (k.clone(), TensorView::new(*d, s.clone(), b).unwrap()))
        .collect();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("model.safetensors"),
        safetensors::serialize(views, None).unwrap(),
    )
    .unwrap();
    for f in ["config.json", "vlm_config.json"] {
        std::fs::copy(golden().join(f), dir.path().join(f)).unwrap();
    }
    dir
}

fn load(dir: &Path) -> EngineError {
    SmolVlaExpert::load(dir, &EngineOptions::default()).unwrap_err()
}

#[test]
fn untouched_copy_loads() {
    let dir = checkpoint_with(|_| {});
    SmolVlaExpert::load(dir.path(), &EngineOptions::default()).unwrap();
}

#[test]
fn missing_tensor_names_the_key() {
    let dir = checkpoint_with(|t| t.retain(|(k, ..)| k != K_PROJ));
    let err = load(dir.path());
    assert!(
        matches!(&err, EngineError::MissingTensor { key } if key == K_PROJ),
        "{err:?}"
    );
    assert!(err.to_string().contains(K_PROJ));
}

#[test]
fn wrong_shape_names_the_key_and_both_shapes() {
    // Layer 1 cross-attends: its k_proj maps the VLM's 32-wide K/V; give it the self-attention shape.
    let dir = checkpoint_with(|t| {
        let e = t.iter_mut().find(|(k, ..)| k == K_PROJ).unwrap();
        e.2 = vec![32, 72];
        e.3 = vec![0u8; 32 * 72 * 4];
    });
    let err = load(dir.path());
    match &err {
        EngineError::ShapeMismatch {
            key,
            expected,
            found,
        } => {
            assert_eq!(key, K_PROJ);
            assert_eq!(expected, &vec![32, 32]);
            assert_eq!(found, &vec![32, 72]);
        }
        other => panic!("expected a shape mismatch, got {other:?}"),
    }
    assert!(err.to_string().contains("[32, 72]"));
}

#[test]
fn wrong_dtype_names_the_key() {
    let dir = checkpoint_with(|t| {
        let e = t.iter_mut().find(|(k, ..)| k == K_PROJ).unwrap();
        e.1 = Dtype::I32;
    });
    let err = load(dir.path());
    assert!(
        matches!(&err, EngineError::DtypeMismatch { key, found, .. } if key == K_PROJ && found == "I32"),
        "{err:?}"
    );
}

#[test]
fn half_precision_checkpoints_load() {
    let dir = checkpoint_with(|t| {
        for (_, dtype, _, bytes) in t.iter_mut() {
            let halves: Vec<u8> = bytes
                .chunks_exact(4)
                .flat_map(|b| {
                    half::bf16::from_f32(f32::from_le_bytes([b[0], b[1], b[2], b[3]])).to_le_bytes()
                })
                .collect();
            *dtype = Dtype::BF16;
            *bytes = halves;
        }
    });
    SmolVlaExpert::load(dir.path(), &EngineOptions::default()).unwrap();
}

#[test]
fn truncated_file_is_a_load_error() {
    let dir = checkpoint_with(|_| {});
    let path = dir.path().join("model.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() - 1000]).unwrap();
    let err = load(dir.path());
    assert!(
        matches!(&err, EngineError::Load { path: p, .. } if p.ends_with("model.safetensors")),
        "{err:?}"
    );
    std::fs::write(&path, &bytes[..5]).unwrap();
    assert!(matches!(load(dir.path()), EngineError::Load { .. }));
}

#[test]
fn missing_files_and_bad_configs_are_load_errors() {
    let dir = checkpoint_with(|_| {});
    std::fs::remove_file(dir.path().join("model.safetensors")).unwrap();
    assert!(matches!(load(dir.path()), EngineError::Load { .. }));

    let dir = checkpoint_with(|_| {});
    std::fs::write(dir.path().join("config.json"), "{ not json").unwrap();
    assert!(matches!(load(dir.path()), EngineError::Load { .. }));

    let dir = checkpoint_with(|_| {});
    std::fs::write(dir.path().join("config.json"), r#"{"type": "pi0_fast"}"#).unwrap();
    let Err(err) = load_model(dir.path()) else {
        panic!("a pi0_fast config must not load")
    };
    assert!(err.to_string().contains("unknown model type"), "{err}");

    // A known family whose files are missing: the first missing file is named.
    let dir = checkpoint_with(|_| {});
    std::fs::write(dir.path().join("config.json"), r#"{"type": "pi0"}"#).unwrap();
    let Err(err) = load_model(dir.path()) else {
        panic!("a pi0 config without its processors must not load")
    };
    assert!(
        err.to_string().contains("policy_preprocessor.json"),
        "{err}"
    );
}
