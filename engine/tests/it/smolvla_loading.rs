//! Loading keeps the VLM's weights as the checkpoint stores them: `smolvla_tiny`'s VLM tensors
//! are bf16 on disk and are packed straight from their bits (see `SmolVlaVlm::load_from`). The
//! prefix this computes must be bit-identical to that of the same checkpoint rewritten with
//! every tensor widened to f32 on disk (which the loader reads as f32, the path that widened
//! before), in f32 and in bf16 compute.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use kairos_engine::Precision;
use kairos_engine::smolvla::{SmolVlaExpert, SmolVlaVlm, VisionImage, VlmObservation};
use kairos_engine::weights::{Checkpoint, StoredTensor, serialize_f32};

use super::smolvla_bf16::options;
use super::smolvla_goldens::{Goldens, fixture};

const EMBED: &str = "model.vlm_with_expert.vlm.model.text_model.embed_tokens.weight";

/// `smolvla_tiny` with every tensor stored as f32, in a temp dir.
fn widened_copy() -> tempfile::TempDir {
    let ckpt = Checkpoint::open(&fixture().join("model.safetensors")).unwrap();
    let tensors: Vec<(String, Vec<usize>, Vec<f32>)> = ckpt
        .keys()
        .into_iter()
        .map(|k| {
            let shape = ckpt.shape(&k).unwrap().to_vec();
            let values = ckpt.tensor(&k, &shape).unwrap();
            (k, shape, values)
        })
        .collect();
    let views: Vec<(String, Vec<usize>, &[f32])> = tensors
        .iter()
        .map(|(k, s, v)| (k.clone(), s.clone(), v.as_slice()))
        .collect();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("model.safetensors"),
        serialize_f32(&views).unwrap(),
    )
    .unwrap();
    for f in ["config.json", "vlm_config.json"] {
        std::fs::copy(fixture().join(f), dir.path().join(f)).unwrap();
    }
    dir
}

#[test]
fn bf16_checkpoint_gives_the_prefix_of_its_f32_widening_bit_for_bit() {
    let ckpt = Checkpoint::open(&fixture().join("model.safetensors")).unwrap();
    let shape = ckpt.shape(EMBED).unwrap().to_vec();
    assert!(
        matches!(
            ckpt.tensor_stored(EMBED, &shape).unwrap(),
            StoredTensor::Bf16(_)
        ),
        "the fixture's VLM must be bf16 on disk for this test to test anything"
    );
    let widened = widened_copy();
    let wide = Checkpoint::open(&widened.path().join("model.safetensors")).unwrap();
    assert!(matches!(
        wide.tensor_stored(EMBED, &shape).unwrap(),
        StoredTensor::F32(_)
    ));

    // LeRobot's prepared `pair` case: two observations, two cameras each, real tokens.
    let g = Goldens::open();
    let side = g.shape("pair.image.0")[2];
    let n = 3 * side * side;
    let images: Vec<Vec<f32>> = (0..2).map(|s| g.f32(&format!("pair.image.{s}"))).collect();
    let len = g.shape("pair.tokens")[1];
    let tokens: Vec<u32> = g
        .i64("pair.tokens")
        .iter()
        .map(|&t| u32::try_from(t).unwrap())
        .collect();
    let mask: Vec<bool> = g.u8("pair.token_mask").iter().map(|&m| m != 0).collect();
    let state = g.f32("pair.state_padded");

    for precision in [Precision::F32, Precision::Bf16] {
        let expert = SmolVlaExpert::load(&fixture(), &options(precision)).unwrap();
        let pad = state.len() / 2;
        let states: Vec<Vec<f32>> = state.chunks_exact(pad).map(<[f32]>::to_vec).collect();
        let state_tokens = expert.embed_state(&states).unwrap();
        let obs: Vec<VlmObservation<'_>> = (0..2)
            .map(|b| VlmObservation {
                images: images
                    .iter()
                    .map(|im| {
                        Some(VisionImage {
                            side,
                            pixels: &im[b * n..(b + 1) * n],
                        })
                    })
                    .collect(),
                tokens: &tokens[b * len..(b + 1) * len],
                token_mask: &mask[b * len..(b + 1) * len],
                state_token: &state_tokens[b],
            })
            .collect();
        let ours = SmolVlaVlm::load(&fixture(), &options(precision)).unwrap();
        let old = SmolVlaVlm::load(widened.path(), &options(precision)).unwrap();
        assert_eq!(
            ours.embed_prefix(&obs).unwrap(),
            old.embed_prefix(&obs).unwrap(),
            "{precision:?}: prefix embeddings"
        );
        let d = expert.dims();
        let (a, b) = (ours.prefix(d, &obs).unwrap(), old.prefix(d, &obs).unwrap());
        for (o, (p, q)) in a.iter().zip(&b).enumerate() {
            assert_eq!(p.valid(), q.valid());
            for l in 0..d.layers.len() {
                assert_eq!(p.keys(l), q.keys(l), "{precision:?} obs {o} layer {l} keys");
                assert_eq!(
                    p.values(l),
                    q.values(l),
                    "{precision:?} obs {o} layer {l} values"
                );
            }
        }
    }
}
