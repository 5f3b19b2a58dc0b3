//! π0 and π0.5 on the Candle path against LeRobot 0.6.1: every intermediate of the
//! `pi0_tiny` and `pi05_tiny` fixtures (written by `engine/tools/pi_fixture.py` with LeRobot's
//! own `save_pretrained`, goldens recorded from LeRobot's own inference).
//!
//! From LeRobot's prepared images, tokens and normalised state, the test compares the SigLIP
//! output and the projected image tokens of every present camera, the prefix embeddings and
//! every layer's keys and values at the valid positions, every Euler step's velocity and the
//! normalised chunk (with LeRobot's noise), for both cases (`pair`: two observations, a resized
//! and a native-size camera plus an empty one, a truncated and a padded task; `missing`: one
//! camera missing), and that a batch gives each observation exactly what it gets alone.
//!
//! Bound (the one `smolvla_vlm.rs` derives): both sides compute in f32 from the same weights and
//! differ only in rounding (summation order, 1-ulp transcendental functions, the RoPE frequency
//! rounded once instead of by PyTorch's `pow`). The fixture records LeRobot's own f32 error
//! against its float64 recomputation per tensor (`e_lr`, meta.json `lerobot_f32_vs_f64`); ours
//! is of the same nature, so both `|ours - lerobot|` and `|ours - f64|` must be within
//! `5 e_lr + 16 ulp(max |value|)`. A wrong mask, position, scale or layer order gives errors of
//! 1e-2..1, orders of magnitude above.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::PathBuf;

use candle_core::{Device, Tensor};
use kairos_engine::pi::{
    PiConfig, PiDims, PiFamily, PiModel, PiObservation, PrefixCache, SampleInput,
};
use kairos_engine::weights::Checkpoint;

use super::smolvla_goldens::Goldens;

/// `engine/tests/fixtures/<name>`.
pub(crate) fn pi_fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The fixture's model on `device`.
pub(crate) fn load_model(name: &str, device: &Device) -> PiModel {
    let dir = pi_fixture(name);
    let cfg: PiConfig =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let family = PiFamily::from_type(&cfg.policy_type).unwrap();
    let ckpt = Checkpoint::open(&dir.join("model.safetensors")).unwrap();
    let dims = PiDims::from_checkpoint(&cfg, family, &ckpt).unwrap();
    PiModel::load(&ckpt, &dims, device).unwrap()
}

/// Assert `ours` matches LeRobot's f32 result and its f64 recomputation within the bound above
/// (`want` are the golden values at the same positions as `ours`).
pub(crate) fn check(g: &Goldens, key: &str, ours: &[f32], want: &[f32], want64: &[f32]) {
    assert_eq!(ours.len(), want.len(), "{key}: length");
    assert_eq!(ours.len(), want64.len(), "{key}: length");
    let (mut d32, mut d64, mut big) = (0.0f32, 0.0f32, 0.0f32);
    for i in 0..ours.len() {
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

/// One golden case as the model's inputs.
pub(crate) struct Case {
    pub(crate) name: String,
    pub(crate) batch: usize,
    pub(crate) slots: usize,
    pub(crate) side: usize,
    /// `[slot]` -> `[batch][3][side][side]`.
    images: Vec<Vec<f32>>,
    /// `[slot]` -> `[batch]`.
    pub(crate) image_mask: Vec<Vec<u8>>,
    tokens: Vec<Vec<u32>>,
    token_mask: Vec<Vec<bool>>,
    /// `[batch]` -> the normalised state.
    pub(crate) state: Vec<Vec<f32>>,
    /// `[batch]` -> `[chunk][max_action_dim]`.
    pub(crate) noise: Vec<Vec<f32>>,
    /// `[batch][prefix_len]`.
    pub(crate) pad_mask: Vec<Vec<bool>>,
}

pub(crate) fn case(g: &Goldens, name: &str) -> Case {
    let c = &g.meta["cases"][name];
    let batch = c["batch"].as_u64().unwrap() as usize;
    let slots = c["image_slots"].as_u64().unwrap() as usize;
    let per_batch = |v: Vec<f32>| -> Vec<Vec<f32>> {
        let n = v.len() / batch;
        v.chunks_exact(n).map(<[f32]>::to_vec).collect()
    };
    let len = g.shape(&format!("{name}.tokens"))[1];
    let plen = g.shape(&format!("{name}.prefix_pad_mask"))[1];
    Case {
        name: name.into(),
        batch,
        slots,
        side: g.shape(&format!("{name}.image.0"))[2],
        images: (0..slots)
            .map(|s| g.f32(&format!("{name}.image.{s}")))
            .collect(),
        image_mask: (0..slots)
            .map(|s| g.u8(&format!("{name}.image_mask.{s}")))
            .collect(),
        tokens: g
            .i64(&format!("{name}.tokens"))
            .chunks_exact(len)
            .map(|r| r.iter().map(|&t| u32::try_from(t).unwrap()).collect())
            .collect(),
        token_mask: g
            .u8(&format!("{name}.token_mask"))
            .chunks_exact(len)
            .map(|r| r.iter().map(|&m| m != 0).collect())
            .collect(),
        state: per_batch(g.f32(&format!("{name}.state_norm"))),
        noise: per_batch(g.f32(&format!("{name}.noise"))),
        pad_mask: g
            .u8(&format!("{name}.prefix_pad_mask"))
            .chunks_exact(plen)
            .map(|r| r.iter().map(|&m| m != 0).collect())
            .collect(),
    }
}

impl Case {
    pub(crate) fn pixels(&self, slot: usize, b: usize) -> &[f32] {
        let n = 3 * self.side * self.side;
        &self.images[slot][b * n..(b + 1) * n]
    }

    pub(crate) fn observation(&self, b: usize) -> PiObservation<'_> {
        PiObservation {
            images: (0..self.slots)
                .map(|s| (self.image_mask[s][b] != 0).then(|| self.pixels(s, b)))
                .collect(),
            tokens: &self.tokens[b],
            token_mask: &self.token_mask[b],
        }
    }

    /// The golden `[batch][len][width]` tensor `key` at observation `b`'s valid prefix positions.
    pub(crate) fn valid_rows(&self, g: &Goldens, key: &str, b: usize) -> (Vec<f32>, Vec<f32>) {
        let shape = g.shape(key);
        let (len, width) = (shape[1], shape[2..].iter().product::<usize>());
        let pick = |v: Vec<f32>| -> Vec<f32> {
            (0..len)
                .filter(|&j| self.pad_mask[b][j])
                .flat_map(|j| v[(b * len + j) * width..(b * len + j + 1) * width].to_vec())
                .collect()
        };
        (pick(g.f32(key)), pick(g.f32(&format!("{key}.f64"))))
    }
}

fn host(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

fn check_case(g: &Goldens, model: &PiModel, c: &Case) {
    let name = &c.name;
    let d = model.dims();
    // Vision and projector: every present camera of the case in one batch.
    for slot in 0..c.slots {
        let present: Vec<usize> = (0..c.batch)
            .filter(|&b| c.image_mask[slot][b] != 0)
            .collect();
        if present.is_empty() {
            continue;
        }
        let pixels: Vec<f32> = present
            .iter()
            .flat_map(|&b| c.pixels(slot, b).to_vec())
            .collect();
        let images =
            Tensor::from_vec(pixels, (present.len(), 3, c.side, c.side), model.device()).unwrap();
        let out = model.vision(&images).unwrap();
        for (key, ours) in [("vision", &out.hidden), ("image_emb", &out.embeddings)] {
            let key = format!("{name}.{key}.{slot}");
            let per = g.f32(&key).len() / c.batch;
            let pick = |v: Vec<f32>| -> Vec<f32> {
                present
                    .iter()
                    .flat_map(|&b| v[b * per..(b + 1) * per].to_vec())
                    .collect()
            };
            check(
                g,
                &key,
                &host(ours),
                &pick(g.f32(&key)),
                &pick(g.f32(&format!("{key}.f64"))),
            );
        }
    }

    // Prefix: embeddings and every layer's keys and values at the valid positions.
    let observations: Vec<PiObservation<'_>> = (0..c.batch).map(|b| c.observation(b)).collect();
    let prefixes = model.prefix(&observations).unwrap();
    for (b, p) in prefixes.iter().enumerate() {
        assert_eq!(
            p.len,
            c.pad_mask[b].iter().filter(|&&m| m).count(),
            "{name}: valid prefix of {b}"
        );
        let key = format!("{name}.prefix_embs");
        let (want, want64) = c.valid_rows(g, &key, b);
        check(g, &key, &host(&p.embeddings), &want, &want64);
        for l in 0..d.vlm.depth {
            for (kind, ours) in [("key", &p.keys[l]), ("value", &p.values[l])] {
                let key = format!("{name}.layer.{l}.{kind}");
                let (want, want64) = c.valid_rows(g, &key, b);
                check(g, &key, &host(ours), &want, &want64);
            }
        }
    }

    // The Euler loop on our prefix, with LeRobot's noise.
    let samples = sample(model, c, &prefixes);
    let (steps, chunk, pad) = (d.steps, d.chunk, d.action_pad);
    let action_dim = g.shape(&format!("{name}.actions_norm"))[2];
    let (v32, v64) = (
        g.f32(&format!("{name}.velocities")),
        g.f32(&format!("{name}.velocities.f64")),
    );
    let (a32, a64) = (
        g.f32(&format!("{name}.actions_norm")),
        g.f32(&format!("{name}.actions_norm.f64")),
    );
    let per = chunk * pad;
    // Golden velocities are [step][batch][chunk][pad]; ours [batch][step][chunk][pad].
    let reorder = |v: &[f32]| -> Vec<f32> {
        (0..c.batch)
            .flat_map(|b| {
                (0..steps).flat_map(move |k| {
                    v[(k * c.batch + b) * per..(k * c.batch + b + 1) * per].to_vec()
                })
            })
            .collect()
    };
    let ours_v: Vec<f32> = samples.iter().flat_map(|s| s.velocities.clone()).collect();
    check(
        g,
        &format!("{name}.velocities"),
        &ours_v,
        &reorder(&v32),
        &reorder(&v64),
    );
    let ours_a: Vec<f32> = samples
        .iter()
        .flat_map(|s| {
            s.actions
                .chunks_exact(pad)
                .flat_map(|a| a[..action_dim].to_vec())
                .collect::<Vec<_>>()
        })
        .collect();
    check(g, &format!("{name}.actions_norm"), &ours_a, &a32, &a64);
}

fn sample(
    model: &PiModel,
    c: &Case,
    prefixes: &[PrefixCache],
) -> Vec<kairos_engine::smolvla::ExpertSample> {
    let noises: Vec<Vec<Vec<f32>>> = c.noise.iter().map(|n| vec![n.clone()]).collect();
    let pi0 = model.dims().family == PiFamily::Pi0;
    let inputs: Vec<SampleInput<'_>> = (0..c.batch)
        .map(|b| SampleInput {
            prefix: &prefixes[b],
            state: pi0.then(|| c.state[b].as_slice()),
            noise: &noises[b],
        })
        .collect();
    model.sample(&inputs).unwrap()
}

fn check_fixture(name: &str, device: &Device) {
    let g = Goldens::open_at(&pi_fixture(name));
    let model = load_model(name, device);
    for case_name in ["pair", "missing"] {
        check_case(&g, &model, &case(&g, case_name));
    }
}

#[test]
fn pi0_matches_lerobot_on_the_candle_path() {
    check_fixture("pi0_tiny", &Device::Cpu);
}

#[test]
fn pi05_matches_lerobot_on_the_candle_path() {
    check_fixture("pi05_tiny", &Device::Cpu);
}

/// Each observation of a batch gets, bit for bit, what it gets alone: prefix and chunk.
fn batch_equals_singles(name: &str, device: &Device) {
    let g = Goldens::open_at(&pi_fixture(name));
    let model = load_model(name, device);
    let c = case(&g, "pair");
    let observations: Vec<PiObservation<'_>> = (0..c.batch).map(|b| c.observation(b)).collect();
    let batched = model.prefix(&observations).unwrap();
    let batched_samples = sample(&model, &c, &batched);
    for b in 0..c.batch {
        let alone = model.prefix(&observations[b..=b]).unwrap();
        for l in 0..model.dims().vlm.depth {
            assert_eq!(
                host(&alone[0].keys[l]),
                host(&batched[b].keys[l]),
                "{name}: keys {l} of {b}"
            );
            assert_eq!(
                host(&alone[0].values[l]),
                host(&batched[b].values[l]),
                "{name}: values {l} of {b}"
            );
        }
        let noise = vec![c.noise[b].clone()];
        let pi0 = model.dims().family == PiFamily::Pi0;
        let one = model
            .sample(&[SampleInput {
                prefix: &alone[0],
                state: pi0.then(|| c.state[b].as_slice()),
                noise: &noise,
            }])
            .unwrap();
        assert_eq!(one[0], batched_samples[b], "{name}: chunk of {b}");
    }
}

#[test]
fn pi0_batch_equals_singles() {
    batch_equals_singles("pi0_tiny", &Device::Cpu);
}

#[test]
fn pi05_batch_equals_singles() {
    batch_equals_singles("pi05_tiny", &Device::Cpu);
}

#[cfg(feature = "cuda")]
mod cuda {
    use super::*;

    fn gpu() -> Device {
        Device::new_cuda(0).unwrap()
    }

    #[test]
    fn pi0_matches_lerobot_on_cuda() {
        check_fixture("pi0_tiny", &gpu());
    }

    #[test]
    fn pi05_matches_lerobot_on_cuda() {
        check_fixture("pi05_tiny", &gpu());
    }

    #[test]
    fn pi05_batch_equals_singles_on_cuda() {
        batch_equals_singles("pi05_tiny", &gpu());
    }
}
