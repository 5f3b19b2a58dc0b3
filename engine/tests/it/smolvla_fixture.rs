//! The `smolvla_tiny` fixture: a LeRobot 0.6.1 SmolVLA checkpoint directory and LeRobot's golden
//! intermediates on it (`engine/tools/smolvla_fixture.py` writes both; see docs/ENGINE.md).
//!
//! These tests check that the fixture is what the other parity tests assume: the checkpoint has
//! every file LeRobot's `save_pretrained` writes (stats files found through `state_file`, never
//! by name), every golden tensor that `golden/meta.json` describes is there with its shape and
//! dtype, the shapes agree with each other and with the configs, the PNGs hold the raw images,
//! and the engine's existing expert, fed LeRobot's prefix K/V from the goldens, reproduces
//! LeRobot's velocities and normalised actions. The processors, the vision tower and the VLM
//! prefix are checked against the same goldens in their own modules.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use kairos_engine::smolvla::{ExpertInput, SmolVlaConfig, SmolVlaExpert, VlmTextConfig};
use kairos_engine::weights::Checkpoint;
use kairos_engine::{DeviceKind, EngineOptions, Kernels};
use safetensors::SafeTensors;
use safetensors::tensor::Dtype;
use serde_json::Value;

use crate::smolvla_parity::{golden_prefixes, max_abs_diff};

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/smolvla_tiny")
}

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn meta() -> Value {
    json(&fixture().join("golden/meta.json"))
}

fn dim(meta: &Value, key: &str) -> usize {
    meta["dims"][key].as_u64().unwrap() as usize
}

/// `golden/goldens.safetensors`, parsed once per test.
struct Goldens {
    bytes: Vec<u8>,
}

impl Goldens {
    fn load() -> Self {
        Goldens {
            bytes: std::fs::read(fixture().join("golden/goldens.safetensors")).unwrap(),
        }
    }

    fn view(&self) -> SafeTensors<'_> {
        SafeTensors::deserialize(&self.bytes).unwrap()
    }

    fn shape(&self, key: &str) -> Vec<usize> {
        self.view()
            .tensor(key)
            .unwrap_or_else(|_| panic!("{key} missing"))
            .shape()
            .to_vec()
    }

    fn i64s(&self, key: &str) -> Vec<i64> {
        let view = self.view();
        let t = view.tensor(key).unwrap();
        assert_eq!(t.dtype(), Dtype::I64, "{key}");
        t.data()
            .chunks_exact(8)
            .map(|b| i64::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }

    fn u8s(&self, key: &str) -> Vec<u8> {
        let view = self.view();
        let t = view.tensor(key).unwrap();
        assert_eq!(t.dtype(), Dtype::U8, "{key}");
        t.data().to_vec()
    }

    fn f32s(&self, key: &str) -> Vec<f32> {
        let view = self.view();
        let t = view.tensor(key).unwrap();
        assert_eq!(t.dtype(), Dtype::F32, "{key}");
        t.data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    }
}

#[test]
fn checkpoint_has_lerobots_files_and_is_small() {
    let dir = fixture();
    for name in [
        "config.json",
        "model.safetensors",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
        "tokenizer.json",
        "vlm_config.json",
        "golden/goldens.safetensors",
        "golden/meta.json",
    ] {
        assert!(dir.join(name).is_file(), "{name} missing");
    }
    // Every stats file is the one a step names through `state_file`.
    let mut stats = Vec::new();
    for pipeline in ["policy_preprocessor.json", "policy_postprocessor.json"] {
        let p = json(&dir.join(pipeline));
        for step in p["steps"].as_array().unwrap() {
            if let Some(file) = step["state_file"].as_str() {
                let ckpt = Checkpoint::open(&dir.join(file)).unwrap();
                assert!(
                    ckpt.contains("action.q01") && ckpt.contains("action.q99"),
                    "{file}: the action is QUANTILES-normalised"
                );
                stats.push(file.to_string());
            }
        }
    }
    assert_eq!(stats.len(), 2, "one normaliser and one unnormaliser");
    let pre = json(&dir.join("policy_preprocessor.json"));
    let steps: Vec<&str> = pre["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["registry_name"].as_str().unwrap())
        .collect();
    assert_eq!(
        steps,
        [
            "rename_observations_processor",
            "to_batch_processor",
            "smolvla_new_line_processor",
            "tokenizer_processor",
            "device_processor",
            "normalizer_processor"
        ]
    );
    let m = meta();
    let tok = &pre["steps"][3]["config"];
    assert_eq!(tok["max_length"], m["tokenizer"]["max_length"]);
    assert_eq!(tok["padding"], "longest");
    assert_eq!(
        pre["steps"][0]["config"]["rename_map"]["observation.images.top"],
        "observation.images.camera1"
    );

    // The budget for the committed fixture.
    let total: u64 = walk(&dir).iter().map(|p| p.metadata().unwrap().len()).sum();
    assert!(total < 5_000_000, "fixture is {total} bytes");
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn model_file_is_mixed_bf16_and_f32_with_the_configs_shapes() {
    let dir = fixture();
    let bytes = std::fs::read(dir.join("model.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut dtypes = BTreeMap::new();
    for (name, t) in st.tensors() {
        let vlm = name.starts_with("model.vlm_with_expert.vlm.");
        assert_eq!(
            t.dtype(),
            if vlm { Dtype::BF16 } else { Dtype::F32 },
            "{name}"
        );
        *dtypes.entry(format!("{:?}", t.dtype())).or_insert(0) += 1;
    }
    assert!(dtypes.len() == 2, "{dtypes:?}");

    let m = meta();
    let cfg: SmolVlaConfig =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let text = VlmTextConfig::from_vlm_config_file(&dir.join("vlm_config.json")).unwrap();
    assert_eq!(cfg.num_vlm_layers, dim(&m, "num_vlm_layers"));
    assert!(
        text.num_hidden_layers > cfg.num_vlm_layers,
        "the checkpoint keeps only the first num_vlm_layers text layers"
    );
    let h = dim(&m, "text_hidden");
    let layers = (0..text.num_hidden_layers)
        .filter(|l| {
            st.tensor(&format!(
                "model.vlm_with_expert.vlm.model.text_model.layers.{l}.self_attn.q_proj.weight"
            ))
            .is_ok()
        })
        .count();
    assert_eq!(layers, cfg.num_vlm_layers);
    let vlm: Value = json(&dir.join("vlm_config.json"));
    let (vh, patch, size, sf) = (
        dim(&m, "vision_hidden"),
        dim(&m, "patch_size"),
        dim(&m, "image_size"),
        dim(&m, "scale_factor"),
    );
    assert_eq!(vlm["scale_factor"].as_u64().unwrap() as usize, sf);
    assert_eq!(
        vlm["vision_config"]["image_size"].as_u64().unwrap() as usize,
        size
    );
    let shape = |k: &str| st.tensor(k).unwrap().shape().to_vec();
    let v = "model.vlm_with_expert.vlm.model.";
    assert_eq!(
        shape(&format!(
            "{v}vision_model.embeddings.patch_embedding.weight"
        )),
        [vh, 3, patch, patch]
    );
    assert_eq!(
        shape(&format!(
            "{v}vision_model.embeddings.position_embedding.weight"
        )),
        [(size / patch) * (size / patch), vh]
    );
    assert_eq!(
        shape(&format!("{v}connector.modality_projection.proj.weight")),
        [h, vh * sf * sf]
    );
    assert_eq!(
        shape(&format!("{v}text_model.embed_tokens.weight"))[1],
        h,
        "embedding width"
    );
}

#[test]
fn goldens_match_their_description_and_each_other() {
    let m = meta();
    let g = Goldens::load();
    let described = m["tensors"].as_object().unwrap();
    for (key, d) in described {
        let shape: Vec<usize> = d["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        assert_eq!(g.shape(key), shape, "{key}");
        let dtype = format!("{:?}", g.view().tensor(key).unwrap().dtype());
        let want = match d["dtype"].as_str().unwrap() {
            "float32" => "F32",
            "float64" => "F64",
            "int64" => "I64",
            "uint8" => "U8",
            other => panic!("{key}: unexpected dtype {other}"),
        };
        assert_eq!(dtype, want, "{key}");
    }
    assert_eq!(g.view().len(), described.len(), "undescribed tensors");

    let (chunk, action, state, per_cam, size) = (
        dim(&m, "chunk"),
        dim(&m, "action"),
        dim(&m, "state"),
        dim(&m, "tokens_per_camera"),
        dim(&m, "image_size"),
    );
    let max_len = m["tokenizer"]["max_length"].as_u64().unwrap() as usize;
    for (case, c) in m["cases"].as_object().unwrap() {
        let b = c["batch"].as_u64().unwrap() as usize;
        let slots = c["image_slots"].as_u64().unwrap() as usize;
        let len = g.shape(&format!("{case}.tokens"))[1];
        assert!(len <= max_len, "{case}: tokens longer than max_length");
        let prefix = slots * per_cam + len + 1;
        assert_eq!(c["prefix_len"].as_u64().unwrap() as usize, prefix, "{case}");
        assert_eq!(g.shape(&format!("{case}.prefix_embs"))[..2], [b, prefix]);
        assert_eq!(g.shape(&format!("{case}.actions")), [b, chunk, action]);
        assert_eq!(g.shape(&format!("{case}.state_norm")), [b, state]);
        for s in 0..slots {
            assert_eq!(g.shape(&format!("{case}.image.{s}")), [b, 3, size, size]);
        }

        // The prefix pad mask is [camera slots x image mask ; token mask ; 1], position ids
        // count the valid tokens, and the state token alone opens a new attention block.
        let token_mask = g.u8s(&format!("{case}.token_mask"));
        let pad = g.u8s(&format!("{case}.prefix_pad_mask"));
        let att = g.u8s(&format!("{case}.prefix_att_mask"));
        let pos = g.i64s(&format!("{case}.prefix_positions"));
        for i in 0..b {
            let mut want = Vec::with_capacity(prefix);
            for s in 0..slots {
                let m = g.u8s(&format!("{case}.image_mask.{s}"))[i];
                want.extend(std::iter::repeat_n(m, per_cam));
            }
            want.extend_from_slice(&token_mask[i * len..(i + 1) * len]);
            want.push(1);
            assert_eq!(&pad[i * prefix..(i + 1) * prefix], &want[..], "{case}[{i}]");
            let mut count = -1i64;
            for (j, &p) in want.iter().enumerate() {
                count += i64::from(p);
                assert_eq!(pos[i * prefix + j], count, "{case}[{i}] position {j}");
                assert_eq!(att[i * prefix + j], u8::from(j == prefix - 1));
            }
            let valid = want.iter().filter(|&&p| p == 1).count();
            assert_eq!(c["prefix_valid"][i].as_u64().unwrap() as usize, valid);
        }
        // A missing camera is an all -1 image.
        for s in 0..slots {
            let mask = g.u8s(&format!("{case}.image_mask.{s}"));
            let img = g.f32s(&format!("{case}.image.{s}"));
            for (i, &m) in mask.iter().enumerate() {
                let one = &img[i * 3 * size * size..(i + 1) * 3 * size * size];
                if m == 0 {
                    assert!(one.iter().all(|&v| v == -1.0), "{case} slot {s}");
                } else {
                    assert!(one.iter().all(|&v| (-1.0..=1.0).contains(&v)));
                }
            }
        }
    }
    // What the cases are for: a truncated task, a padded one, and a missing camera.
    let pair_mask = g.u8s("pair.token_mask");
    assert_eq!(g.shape("pair.tokens")[1], max_len);
    assert!(pair_mask[..max_len].iter().all(|&v| v == 1), "truncated");
    assert!(pair_mask[max_len..].contains(&0), "padded");
    let pad_id = m["tokenizer"]["pad_id"].as_i64().unwrap();
    let tokens = g.i64s("pair.tokens");
    for (t, mask) in tokens.iter().zip(&pair_mask) {
        if *mask == 0 {
            assert_eq!(*t, pad_id);
        }
    }
    assert_eq!(g.u8s("missing.image_mask.1"), [0]);
}

#[test]
fn pngs_hold_the_raw_images() {
    let m = meta();
    let g = Goldens::load();
    for (case, c) in m["cases"].as_object().unwrap() {
        for png in c["pngs"].as_array().unwrap() {
            let name = png.as_str().unwrap();
            // `{case}.{batch index}.{camera}.png`, camera as sent (before the rename map).
            let parts: Vec<&str> = name.trim_end_matches(".png").split('.').collect();
            let (i, cam) = (parts[1].parse::<usize>().unwrap(), parts[2]);
            let img = image::open(fixture().join("golden").join(name))
                .unwrap()
                .to_rgb8();
            let key = format!("{case}.raw.observation.images.{cam}");
            let shape = g.shape(&key);
            let (h, w) = (shape[1], shape[2]);
            assert_eq!((img.height() as usize, img.width() as usize), (h, w));
            let raw = g.u8s(&key);
            assert_eq!(
                img.as_raw()[..],
                raw[i * h * w * 3..(i + 1) * h * w * 3],
                "{name}"
            );
        }
    }
}

/// The engine's expert (unchanged) on LeRobot's prefix K/V of each case reproduces LeRobot's
/// velocities and normalised actions. Bound as in `smolvla_parity.rs`: 5x LeRobot's own f32
/// error against its f64 run (`meta.json` -> `lerobot_f32_vs_f64`), floor 64 ulps of the largest
/// value. That error includes the VLM's rounding, which the expert here does not redo, so the
/// bound is loose; a wrong mask or position is still orders of magnitude above it.
#[test]
fn expert_reproduces_lerobot_from_the_golden_prefix() {
    let options = EngineOptions {
        device: DeviceKind::Cpu,
        kernels: Kernels::Fast,
        threads: 2,
        ..Default::default()
    };
    let expert = SmolVlaExpert::load(&fixture(), &options).unwrap();
    let d = expert.dims().clone();
    let m = meta();
    let g = Goldens::load();
    let ckpt = Checkpoint::open(&fixture().join("golden/goldens.safetensors")).unwrap();
    for (case, c) in m["cases"].as_object().unwrap() {
        let b = c["batch"].as_u64().unwrap() as usize;
        let len = c["prefix_len"].as_u64().unwrap() as usize;
        let mask = g.u8s(&format!("{case}.prefix_pad_mask"));
        let prefixes = golden_prefixes(&d, &ckpt, &mask, b, len, |l, kv| {
            format!("{case}.layer.{l}.{kv}")
        });
        let (n, a) = (d.chunk, d.action_pad);
        let noise = ckpt.tensor(&format!("{case}.noise"), &[b, n, a]).unwrap();
        let noise: Vec<Vec<f32>> = noise.chunks_exact(n * a).map(<[f32]>::to_vec).collect();
        let inputs: Vec<ExpertInput<'_>> = prefixes
            .iter()
            .zip(&noise)
            .map(|(prefix, noise)| ExpertInput {
                prefix,
                noise: std::slice::from_ref(noise),
            })
            .collect();
        let out = expert.sample(&inputs).unwrap();

        let k = d.steps;
        let want_v = ckpt
            .tensor(&format!("{case}.velocities"), &[k, b, n, a])
            .unwrap();
        let want_x = ckpt
            .tensor(&format!("{case}.actions_norm"), &[b, n, d.action_dim])
            .unwrap();
        // Ours: [request][K][N][A] and [request][N][A]; LeRobot's: [K][request][N][A] and the
        // chunk cut to the action dim.
        let mut v = vec![0.0f32; k * b * n * a];
        let mut x = Vec::with_capacity(b * n * d.action_dim);
        for (i, o) in out.iter().enumerate() {
            for s in 0..k {
                v[(s * b + i) * n * a..(s * b + i + 1) * n * a]
                    .copy_from_slice(&o.velocities[s * n * a..(s + 1) * n * a]);
            }
            for row in o.actions.chunks_exact(a) {
                x.extend_from_slice(&row[..d.action_dim]);
            }
        }
        let err = |key: &str| {
            m["lerobot_f32_vs_f64"][format!("{case}.{key}")]["max_abs"]
                .as_f64()
                .unwrap() as f32
        };
        let floor = |w: &[f32]| 64.0 * f32::EPSILON * w.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let tol_v = (5.0 * err("velocities")).max(floor(&want_v));
        let tol_x = (5.0 * err("actions_norm")).max(floor(&want_x));
        let dv = max_abs_diff(&v, &want_v);
        let dx = max_abs_diff(&x, &want_x);
        println!(
            "{case}: |v - lerobot| {dv:.2e} (tol {tol_v:.2e}), |x - lerobot| {dx:.2e} (tol {tol_x:.2e})"
        );
        assert!(dv <= tol_v, "{case}: velocities differ by {dv}");
        assert!(dx <= tol_x, "{case}: normalised actions differ by {dx}");
    }
}
