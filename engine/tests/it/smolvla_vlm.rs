//! The SmolVLA VLM side (SigLIP vision tower, connector, prefix embeddings, SmolLM2 prefix
//! layers -> `PrefixKv`) and then the whole model against LeRobot 0.6.1.
//!
//! `engine/tests/fixtures/smolvla_tiny/` was written by `engine/tools/smolvla_fixture.py`: a small
//! random SmolVLA saved with LeRobot's own `save_pretrained` (VLM tensors in bf16), and LeRobot's
//! intermediates for two cases: `pair` (two observations, two cameras of odd sizes plus one empty
//! camera, a truncated and a short task) and `missing` (one camera missing). The test feeds
//! LeRobot's prepared images, tokens and padded state to our VLM and compares the vision output,
//! the connector output, the prefix embeddings and every layer's K/V at the valid positions, and
//! then, with the existing expert on our prefix and LeRobot's noise, the normalised actions.
//!
//! Tolerance, as in `smolvla_parity.rs`: both sides compute in f32 from the same (bf16-rounded)
//! weights and differ only in rounding. The fixture records, per tensor, LeRobot's own f32 error
//! against its f64 recomputation (`e_lr`, meta.json `lerobot_f32_vs_f64`; ~1e-6 on values of
//! magnitude ~4, 2e-5 on prefix embeddings of magnitude ~40). Our error against f64 is of the
//! same nature, so `|ours - lerobot| <= |ours - f64| + e_lr` should be a few `e_lr`; the test
//! asserts `|ours - lerobot| <= 5 e_lr` and `|ours - f64| <= 5 e_lr`, each plus a floor of 16 f32
//! ulps of the largest value (measured 2026-11-25: at most 2.3 e_lr, e.g. 4.8e-6 on layer 3's
//! keys, 4.6e-5 on the prefix embeddings, 1.4e-6 on the actions). A real mismatch (a wrong mask,
//! position, scale, shuffle order or layer) shows up as errors of order 1e-2..1, four orders
//! above.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::PathBuf;

use kairos_engine::smolvla::{ExpertInput, SmolVlaExpert, SmolVlaVlm, VisionImage, VlmObservation};
use kairos_engine::weights::Checkpoint;
use kairos_engine::{DeviceKind, EngineOptions, Kernels};

use super::smolvla_goldens::{Goldens, fixture};

fn cpu(kernels: Kernels) -> EngineOptions {
    EngineOptions {
        device: DeviceKind::Cpu,
        kernels,
        threads: 2,
        ..Default::default()
    }
}

/// Assert `ours` matches LeRobot's f32 result and its f64 recomputation within the bound above,
/// on the positions where `keep` is true.
fn check(g: &Goldens, key: &str, ours: &[f32], keep: &dyn Fn(usize) -> bool) {
    let want = g.f32(key);
    let want64 = g.f32(&format!("{key}.f64"));
    assert_eq!(ours.len(), want.len(), "{key}: length");
    let (mut d32, mut d64, mut big) = (0.0f32, 0.0f32, 0.0f32);
    for i in (0..ours.len()).filter(|&i| keep(i)) {
        d32 = d32.max((ours[i] - want[i]).abs());
        d64 = d64.max((ours[i] - want64[i]).abs());
        big = big.max(want[i].abs());
    }
    let bound = 5.0 * g.e_lr(key) + 16.0 * f32::EPSILON * big;
    eprintln!("{key}: |ours-lerobot| {d32:.3e}, |ours-f64| {d64:.3e}, bound {bound:.3e}");
    assert!(
        d32 <= bound,
        "{key}: |ours - lerobot| = {d32:e} > {bound:e}"
    );
    assert!(d64 <= bound, "{key}: |ours - f64| = {d64:e} > {bound:e}");
}

struct Case {
    batch: usize,
    slots: usize,
    side: usize,
    images: Vec<Vec<f32>>,
    image_mask: Vec<Vec<u8>>,
    tokens: Vec<Vec<u32>>,
    token_mask: Vec<Vec<bool>>,
    state: Vec<Vec<f32>>,
}

fn case(g: &Goldens, name: &str) -> Case {
    let c = &g.meta["cases"][name];
    let batch = c["batch"].as_u64().unwrap() as usize;
    let slots = c["image_slots"].as_u64().unwrap() as usize;
    let images: Vec<Vec<f32>> = (0..slots)
        .map(|s| g.f32(&format!("{name}.image.{s}")))
        .collect();
    let side = g.shape(&format!("{name}.image.0"))[2];
    let image_mask = (0..slots)
        .map(|s| g.u8(&format!("{name}.image_mask.{s}")))
        .collect();
    let len = g.shape(&format!("{name}.tokens"))[1];
    let tokens = g.i64(&format!("{name}.tokens"));
    let mask = g.u8(&format!("{name}.token_mask"));
    let state = g.f32(&format!("{name}.state_padded"));
    let pad = state.len() / batch;
    Case {
        batch,
        slots,
        side,
        images,
        image_mask,
        tokens: tokens
            .chunks_exact(len)
            .map(|r| r.iter().map(|&t| u32::try_from(t).unwrap()).collect())
            .collect(),
        token_mask: mask
            .chunks_exact(len)
            .map(|r| r.iter().map(|&m| m != 0).collect())
            .collect(),
        state: state.chunks_exact(pad).map(<[f32]>::to_vec).collect(),
    }
}

impl Case {
    fn image(&self, slot: usize, b: usize) -> VisionImage<'_> {
        let n = 3 * self.side * self.side;
        VisionImage {
            side: self.side,
            pixels: &self.images[slot][b * n..(b + 1) * n],
        }
    }

    fn observations<'a>(&'a self, state_tokens: &'a [Vec<f32>]) -> Vec<VlmObservation<'a>> {
        (0..self.batch)
            .map(|b| VlmObservation {
                images: (0..self.slots)
                    .map(|s| (self.image_mask[s][b] != 0).then(|| self.image(s, b)))
                    .collect(),
                tokens: &self.tokens[b],
                token_mask: &self.token_mask[b],
                state_token: &state_tokens[b],
            })
            .collect()
    }
}

fn models(kernels: Kernels) -> (SmolVlaVlm, SmolVlaExpert) {
    models_with(&cpu(kernels))
}

fn models_with(options: &EngineOptions) -> (SmolVlaVlm, SmolVlaExpert) {
    let vlm = SmolVlaVlm::load(&fixture(), options).unwrap();
    let expert = SmolVlaExpert::load(&fixture(), options).unwrap();
    (vlm, expert)
}

fn parity(kernels: Kernels, name: &str) {
    parity_with(&Goldens::open(), &cpu(kernels), name);
}

fn parity_with(g: &Goldens, options: &EngineOptions, name: &str) {
    let (vlm, expert) = models_with(options);
    let c = case(g, name);
    let d = expert.dims().clone();

    // Vision tower and connector on every slot's image (the empty camera's all -1 image too).
    for s in 0..c.slots {
        let images: Vec<VisionImage<'_>> = (0..c.batch).map(|b| c.image(s, b)).collect();
        let out = vlm.embed_images(&images).unwrap();
        let cat = |v: &[Vec<f32>]| -> Vec<f32> { v.concat() };
        check(g, &format!("{name}.vision.{s}"), &cat(&out.hidden), &|_| {
            true
        });
        check(
            g,
            &format!("{name}.connector.{s}"),
            &cat(&out.embeddings),
            &|_| true,
        );
    }

    // Prefix embeddings and K/V at the valid positions.
    let state_tokens = expert.embed_state(&c.state).unwrap();
    let obs = c.observations(&state_tokens);
    let embedded = vlm.embed_prefix(&obs).unwrap();
    let pad = g.u8(&format!("{name}.prefix_pad_mask"));
    let len = pad.len() / c.batch;
    for (b, e) in embedded.iter().enumerate() {
        let want: Vec<bool> = pad[b * len..(b + 1) * len]
            .iter()
            .map(|&m| m != 0)
            .collect();
        assert_eq!(e.valid, want, "{name}: pad mask of observation {b}");
    }
    let h = vlm.config().text_config.hidden_size;
    let flat: Vec<f32> = embedded.iter().flat_map(|e| e.embeddings.clone()).collect();
    check(g, &format!("{name}.prefix_embs"), &flat, &|i| {
        pad[i / h] != 0
    });

    let prefixes = vlm.prefix(&d, &obs).unwrap();
    let kvw = d.kv_width();
    for l in 0..d.layers.len() {
        let keys: Vec<f32> = prefixes.iter().flat_map(|p| p.keys(l).to_vec()).collect();
        let values: Vec<f32> = prefixes.iter().flat_map(|p| p.values(l).to_vec()).collect();
        check(g, &format!("{name}.layer.{l}.key"), &keys, &|i| {
            pad[i / kvw] != 0
        });
        check(g, &format!("{name}.layer.{l}.value"), &values, &|i| {
            pad[i / kvw] != 0
        });
    }

    // The whole model: our prefix, LeRobot's noise, the existing expert.
    let noise = g.f32(&format!("{name}.noise"));
    let per = d.chunk * d.action_pad;
    let noises: Vec<Vec<Vec<f32>>> = noise.chunks_exact(per).map(|n| vec![n.to_vec()]).collect();
    let inputs: Vec<ExpertInput<'_>> = prefixes
        .iter()
        .zip(&noises)
        .map(|(prefix, noise)| ExpertInput { prefix, noise })
        .collect();
    // With CUDA graphs the first run captures the loop and the second replays it: both are
    // checked.
    let runs = if options.cuda_graphs { 2 } else { 1 };
    for _ in 0..runs {
        let out = expert.sample(&inputs).unwrap();
        let actions: Vec<f32> = out
            .iter()
            .flat_map(|o| {
                o.actions
                    .chunks_exact(d.action_pad)
                    .flat_map(|a| a[..d.action_dim].to_vec())
                    .collect::<Vec<_>>()
            })
            .collect();
        check(g, &format!("{name}.actions_norm"), &actions, &|_| true);
    }
    if let Some(stats) = expert.cuda_graph_stats() {
        assert_eq!((stats.captured, stats.replays), (1, 1), "{name}: {stats:?}");
    }
}

#[test]
fn two_cameras_and_an_empty_one_match_lerobot() {
    parity(Kernels::Fast, "pair");
}

#[test]
fn a_missing_camera_matches_lerobot() {
    parity(Kernels::Fast, "missing");
}

#[test]
fn portable_kernels_match_lerobot() {
    parity(Kernels::Portable, "pair");
}

/// The Candle path (vision tower, connector, text layers and expert in Candle ops) on the CPU,
/// the reference for CUDA: the same bound.
#[test]
fn candle_path_matches_lerobot() {
    parity(Kernels::Candle, "pair");
    parity(Kernels::Candle, "missing");
}

/// The same on the first GPU (`scripts/run-cuda-tests.sh`): the same f32 bound, as for the
/// expert alone (`smolvla_parity.rs`: Candle keeps cuBLAS's f32 products at full precision).
#[cfg(feature = "cuda")]
#[test]
fn cuda_path_matches_lerobot() {
    let options = EngineOptions {
        device: DeviceKind::Cuda(0),
        kernels: Kernels::Candle,
        ..Default::default()
    };
    let g = Goldens::open();
    for name in ["pair", "missing"] {
        parity_with(&g, &options, name);
    }
}

/// The same with the Euler loop replayed as a CUDA graph (`EngineOptions::cuda_graphs`): the
/// run that captures and the run that replays each match LeRobot within the same bound.
#[cfg(feature = "cuda")]
#[test]
fn cuda_graphs_path_matches_lerobot() {
    let options = EngineOptions {
        device: DeviceKind::Cuda(0),
        kernels: Kernels::Candle,
        cuda_graphs: true,
        ..Default::default()
    };
    let g = Goldens::open();
    for name in ["pair", "missing"] {
        parity_with(&g, &options, name);
    }
}

/// A batch mixing both cases (different cameras and text lengths) gives every observation
/// bit-identical prefixes to running it alone.
#[test]
fn batched_prefixes_are_bit_identical_to_single() {
    let g = Goldens::open();
    let (vlm, expert) = models(Kernels::Fast);
    let d = expert.dims().clone();
    let pair = case(&g, "pair");
    let missing = case(&g, "missing");
    let pair_states = expert.embed_state(&pair.state).unwrap();
    let missing_states = expert.embed_state(&missing.state).unwrap();
    let mut batch = pair.observations(&pair_states);
    batch.extend(missing.observations(&missing_states));
    // Reverse order, so that positions in the batch differ from the single runs too.
    batch.reverse();
    let together = vlm.prefix(&d, &batch).unwrap();
    assert_eq!(together.len(), 3);
    assert_ne!(together[0].len(), together[1].len());
    for (obs, batched) in batch.iter().zip(&together) {
        let alone = vlm.prefix(&d, std::slice::from_ref(obs)).unwrap();
        assert_eq!(&alone[0], batched);
    }
}

/// Errors name what is wrong instead of panicking.
#[test]
fn bad_observations_are_errors() {
    let g = Goldens::open();
    let (vlm, expert) = models(Kernels::Fast);
    let d = expert.dims().clone();
    let c = case(&g, "missing");
    let states = expert.embed_state(&c.state).unwrap();
    let good = c.observations(&states).remove(0);

    let mut o = good.clone();
    o.images = vec![None, None];
    let e = vlm.prefix(&d, &[o]).unwrap_err().to_string();
    assert!(e.contains("every camera is missing"), "{e}");

    let bad_tokens: Vec<u32> = vec![100_000; good.tokens.len()];
    let mut o = good.clone();
    o.tokens = &bad_tokens;
    let e = vlm.prefix(&d, &[o]).unwrap_err().to_string();
    assert!(e.contains("token id 100000"), "{e}");

    let short = vec![0.0f32; 5];
    let mut o = good.clone();
    o.images = vec![Some(VisionImage {
        side: 2,
        pixels: &short,
    })];
    let e = vlm.prefix(&d, &[o]).unwrap_err().to_string();
    assert!(e.contains("images[0]"), "{e}");

    let mut o = good.clone();
    o.state_token = &short;
    let e = vlm.prefix(&d, &[o]).unwrap_err().to_string();
    assert!(e.contains("state token has 5 values"), "{e}");
}

/// A checkpoint lacking a VLM tensor names it.
#[test]
fn missing_vlm_tensor_is_named() {
    let dir = tempfile::tempdir().unwrap();
    for f in ["config.json", "vlm_config.json"] {
        std::fs::copy(fixture().join(f), dir.path().join(f)).unwrap();
    }
    let ckpt = Checkpoint::open(&fixture().join("model.safetensors")).unwrap();
    let dropped = "model.vlm_with_expert.vlm.model.vision_model.encoder.layers.1.mlp.fc2.bias";
    assert!(ckpt.contains(dropped));
    let shapes: Vec<(String, Vec<usize>)> = ckpt
        .keys()
        .into_iter()
        .filter(|k| k != dropped)
        .map(|k| {
            let s = ckpt.shape(&k).unwrap().to_vec();
            (k, s)
        })
        .collect();
    let data: Vec<Vec<f32>> = shapes
        .iter()
        .map(|(k, s)| ckpt.tensor(k, s).unwrap())
        .collect();
    let tensors: Vec<(String, Vec<usize>, &[f32])> = shapes
        .iter()
        .zip(&data)
        .map(|((k, s), d)| (k.clone(), s.clone(), d.as_slice()))
        .collect();
    std::fs::write(
        dir.path().join("model.safetensors"),
        kairos_engine::weights::serialize_f32(&tensors).unwrap(),
    )
    .unwrap();
    let e = SmolVlaVlm::load(dir.path(), &cpu(Kernels::Fast))
        .unwrap_err()
        .to_string();
    assert!(e.contains(dropped), "{e}");
}

/// A real LeRobot SmolVLA checkpoint (e.g. `lerobot/smolvla_base` downloaded by hand), at the path
/// in `KAIROS_SMOLVLA_CHECKPOINT`: every VLM tensor loads under its LeRobot name and shape, and
/// one observation (a mid-grey image for every camera the config names, 12 tokens, zero state)
/// gives a prefix of the expected length with finite K/V. Opt-in: run with
/// `KAIROS_SMOLVLA_CHECKPOINT=DIR cargo test -p kairos-engine --test it -- --ignored real_checkpoint`.
#[test]
#[ignore = "needs a real SmolVLA checkpoint in KAIROS_SMOLVLA_CHECKPOINT"]
fn real_checkpoint_builds_a_prefix() {
    let dir = PathBuf::from(
        std::env::var("KAIROS_SMOLVLA_CHECKPOINT")
            .expect("set KAIROS_SMOLVLA_CHECKPOINT to a SmolVLA checkpoint directory"),
    );
    let options = cpu(Kernels::Fast);
    let vlm = SmolVlaVlm::load(&dir, &options).unwrap();
    let expert = SmolVlaExpert::load(&dir, &options).unwrap();
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let cameras = cfg["input_features"]
        .as_object()
        .unwrap()
        .values()
        .filter(|f| f["type"] == "VISUAL")
        .count()
        .max(1);
    let side = cfg["resize_imgs_with_padding"][0].as_u64().unwrap_or(512) as usize;
    let grey = vec![0.0f32; 3 * side * side];
    let tokens: Vec<u32> = (1..=12).collect();
    let mask = vec![true; tokens.len()];
    let state = expert.embed_state(&[vec![0.0]]).unwrap();
    let obs = VlmObservation {
        images: (0..cameras)
            .map(|_| {
                Some(VisionImage {
                    side,
                    pixels: &grey,
                })
            })
            .collect(),
        tokens: &tokens,
        token_mask: &mask,
        state_token: &state[0],
    };
    let prefix = vlm.prefix(expert.dims(), &[obs]).unwrap().remove(0);
    assert_eq!(
        prefix.len(),
        cameras * vlm.tokens_per_image(side) + tokens.len() + 1
    );
    assert_eq!(prefix.valid_len(), prefix.len());
}

/// `prefix_length` pads the prefix at the end (LeRobot's `pad_tensor`): the valid tokens' K/V are
/// unchanged, the extra positions are padding; `add_image_special_tokens` is refused by name.
#[test]
fn prefix_length_pads_at_the_end() {
    use kairos_engine::smolvla::{SmolVlaConfig, VlmConfig, VlmWeights};
    let g = Goldens::open();
    let (vlm, expert) = models(Kernels::Fast);
    let d = expert.dims().clone();
    let c = case(&g, "pair");
    let states = expert.embed_state(&c.state).unwrap();
    let obs = c.observations(&states);
    let plain = vlm.prefix(&d, &obs).unwrap();

    let mut cfg: SmolVlaConfig =
        serde_json::from_str(&std::fs::read_to_string(fixture().join("config.json")).unwrap())
            .unwrap();
    let vlm_cfg = VlmConfig::for_checkpoint(&fixture(), &cfg).unwrap();
    let ckpt = Checkpoint::open(&fixture().join("model.safetensors")).unwrap();
    let weights = VlmWeights::load(&ckpt, &vlm_cfg, cfg.num_vlm_layers).unwrap();
    cfg.prefix_length = 60;
    let padded_vlm = SmolVlaVlm::from_weights(&weights, &cfg, &cpu(Kernels::Fast)).unwrap();
    let padded = padded_vlm.prefix(&d, &obs).unwrap();
    for (p, q) in plain.iter().zip(&padded) {
        assert_eq!(q.len(), 60);
        assert_eq!(&q.valid()[..p.len()], p.valid());
        assert!(q.valid()[p.len()..].iter().all(|v| !v));
        let w = d.kv_width();
        for l in 0..d.layers.len() {
            assert_eq!(&q.keys(l)[..p.len() * w], p.keys(l));
            assert_eq!(&q.values(l)[..p.len() * w], p.values(l));
        }
    }

    cfg.add_image_special_tokens = true;
    let e = SmolVlaVlm::from_weights(&weights, &cfg, &cpu(Kernels::Fast))
        .unwrap_err()
        .to_string();
    assert!(e.contains("add_image_special_tokens"), "{e}");
}
