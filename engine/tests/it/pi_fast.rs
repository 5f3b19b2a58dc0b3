//! π0 and π0.5 on the engine's fast CPU kernels against LeRobot 0.6.1: the same intermediates
//! of the `pi0_tiny` and `pi05_tiny` fixtures as `pi_parity.rs` checks on the Candle path
//! (SigLIP output and image tokens of every present camera, prefix embeddings, every layer's
//! keys and values at the valid positions, every Euler step's velocity, the normalised chunk),
//! that a batch gives each observation bit for bit what it gets alone, and bf16 weight GEMMs
//! within their bound of the f32 goldens.
//!
//! f32 bound: the one `pi_parity.rs` derives, `5 e_lr + 16 ulp(max |value|)` against both
//! LeRobot's f32 result and its f64 recomputation. The fast kernels compute in f32 from the
//! same weights; they differ from PyTorch only in rounding: summation order (fixed FMA order),
//! `exp` to ~1 ulp (softmax, SiLU, tanh-GELU), the RoPE frequency rounded once, and
//! `action_time_mlp_in`'s two input halves summed in two GEMMs. Those are errors of the same
//! nature as LeRobot's own f32 error, so the Candle path's bound holds unchanged; a wrong mask,
//! position, scale or layer order gives errors of 1e-2..1.
//!
//! bf16 bound: each bf16 GEMM rounds its weights and its activations to 8 significand bits
//! (2^-9 relative each); as `smolvla_bf16.rs` notes, no useful worst case composes through
//! every layer and ten Euler steps. These tiny random networks amplify rounding strongly (their
//! weights are f32, not bf16-rounded as SmolVLA's fixture's are): rounding only the weights
//! to bf16, in an otherwise exact f32 run, already moves the chunk by 1-4 % of its largest
//! value. So the test measures that weights-only error `d_w` on a bf16-rounded copy of the
//! checkpoint and bounds the bf16 path's error by `BF16_FACTOR x d_w`: the activations' rounding
//! is of the same size and independent, so about `2 d_w` is expected (measured 2026-11-28 on an
//! AVX512_BF16 CPU: 0.87-3.15 d_w over both fixtures and cases; the kernels are deterministic,
//! so every such CPU gets those bits). A broken kernel moves the chunk by the order of its
//! largest value, 30 d_w and more.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use kairos_engine::Precision;
use kairos_engine::kernels::{Isa, Pool};
use kairos_engine::pi::{
    FastPiModel, FastPrefix, FastSampleInput, PiConfig, PiDims, PiFamily, PiObservation,
};
use kairos_engine::weights::{Checkpoint, serialize_f32};

use super::pi_parity::{Case, case, check, pi_fixture};
use super::smolvla_goldens::Goldens;

/// Largest `|bf16 - f32|` accepted on the normalised chunk, in units of the error that rounding
/// only the weights to bf16 gives (see the module's doc).
const BF16_FACTOR: f32 = 6.0;

/// The fixture's model on the fast kernels (2 threads, the best ISA) in `precision`.
fn load_fast(name: &str, precision: Precision) -> FastPiModel {
    let dir = pi_fixture(name);
    let cfg: PiConfig =
        serde_json::from_str(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
    let family = PiFamily::from_type(&cfg.policy_type).unwrap();
    let ckpt = Checkpoint::open(&dir.join("model.safetensors")).unwrap();
    let dims = PiDims::from_checkpoint(&cfg, family, &ckpt).unwrap();
    FastPiModel::load(&ckpt, &dims, Pool::new(2).unwrap(), precision).unwrap()
}

fn sample(
    model: &FastPiModel,
    c: &Case,
    prefixes: &[FastPrefix],
) -> Vec<kairos_engine::smolvla::ExpertSample> {
    let noises: Vec<Vec<Vec<f32>>> = c.noise.iter().map(|n| vec![n.clone()]).collect();
    let pi0 = model.dims().family == PiFamily::Pi0;
    let inputs: Vec<FastSampleInput<'_>> = (0..c.batch)
        .map(|b| FastSampleInput {
            prefix: &prefixes[b],
            state: pi0.then(|| c.state[b].as_slice()),
            noise: &noises[b],
        })
        .collect();
    model.sample(&inputs).unwrap()
}

/// Golden velocities are `[step][batch][chunk][pad]`; samples give `[batch][step][..]`.
fn reorder(v: &[f32], batch: usize, steps: usize, per: usize) -> Vec<f32> {
    (0..batch)
        .flat_map(|b| {
            (0..steps)
                .flat_map(move |k| v[(k * batch + b) * per..(k * batch + b + 1) * per].to_vec())
        })
        .collect()
}

/// The normalised actions cut to the action dim, `[batch][chunk][action_dim]`.
fn cut_actions(
    samples: &[kairos_engine::smolvla::ExpertSample],
    pad: usize,
    dim: usize,
) -> Vec<f32> {
    samples
        .iter()
        .flat_map(|s| {
            s.actions
                .chunks_exact(pad)
                .flat_map(|a| a[..dim].to_vec())
                .collect::<Vec<_>>()
        })
        .collect()
}

fn check_case(g: &Goldens, model: &FastPiModel, c: &Case) {
    let name = &c.name;
    let d = model.dims();
    for slot in 0..c.slots {
        let present: Vec<usize> = (0..c.batch)
            .filter(|&b| c.image_mask[slot][b] != 0)
            .collect();
        if present.is_empty() {
            continue;
        }
        let images: Vec<&[f32]> = present.iter().map(|&b| c.pixels(slot, b)).collect();
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
                &ours.concat(),
                &pick(g.f32(&key)),
                &pick(g.f32(&format!("{key}.f64"))),
            );
        }
    }
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
        check(g, &key, &p.embeddings, &want, &want64);
        for l in 0..d.vlm.depth {
            for (kind, ours) in [("key", &p.keys[l]), ("value", &p.values[l])] {
                let key = format!("{name}.layer.{l}.{kind}");
                let (want, want64) = c.valid_rows(g, &key, b);
                check(g, &key, ours, &want, &want64);
            }
        }
    }
    let samples = sample(model, c, &prefixes);
    let (steps, per) = (d.steps, d.chunk * d.action_pad);
    let ours_v: Vec<f32> = samples.iter().flat_map(|s| s.velocities.clone()).collect();
    check(
        g,
        &format!("{name}.velocities"),
        &ours_v,
        &reorder(&g.f32(&format!("{name}.velocities")), c.batch, steps, per),
        &reorder(
            &g.f32(&format!("{name}.velocities.f64")),
            c.batch,
            steps,
            per,
        ),
    );
    let action_dim = g.shape(&format!("{name}.actions_norm"))[2];
    check(
        g,
        &format!("{name}.actions_norm"),
        &cut_actions(&samples, d.action_pad, action_dim),
        &g.f32(&format!("{name}.actions_norm")),
        &g.f32(&format!("{name}.actions_norm.f64")),
    );
}

fn check_fixture(name: &str) {
    let g = Goldens::open_at(&pi_fixture(name));
    let model = load_fast(name, Precision::F32);
    for case_name in ["pair", "missing"] {
        check_case(&g, &model, &case(&g, case_name));
    }
}

#[test]
fn pi0_matches_lerobot_on_the_fast_kernels() {
    check_fixture("pi0_tiny");
}

#[test]
fn pi05_matches_lerobot_on_the_fast_kernels() {
    check_fixture("pi05_tiny");
}

/// Each observation of a batch gets, bit for bit, what it gets alone: vision, prefix and chunk.
fn batch_equals_singles(name: &str, precision: Precision) {
    let g = Goldens::open_at(&pi_fixture(name));
    let model = load_fast(name, precision);
    let c = case(&g, "pair");
    let observations: Vec<PiObservation<'_>> = (0..c.batch).map(|b| c.observation(b)).collect();
    let batched = model.prefix(&observations).unwrap();
    let batched_samples = sample(&model, &c, &batched);
    let pi0 = model.dims().family == PiFamily::Pi0;
    for b in 0..c.batch {
        let alone = model.prefix(&observations[b..=b]).unwrap();
        assert_eq!(alone[0], batched[b], "{name} {precision:?}: prefix of {b}");
        let noise = vec![c.noise[b].clone()];
        let one = model
            .sample(&[FastSampleInput {
                prefix: &alone[0],
                state: pi0.then(|| c.state[b].as_slice()),
                noise: &noise,
            }])
            .unwrap();
        assert_eq!(
            one[0], batched_samples[b],
            "{name} {precision:?}: chunk of {b}"
        );
    }
}

#[test]
fn pi0_batch_equals_singles_on_the_fast_kernels() {
    batch_equals_singles("pi0_tiny", Precision::F32);
    batch_equals_singles("pi0_tiny", Precision::Bf16);
}

#[test]
fn pi05_batch_equals_singles_on_the_fast_kernels() {
    batch_equals_singles("pi05_tiny", Precision::F32);
    batch_equals_singles("pi05_tiny", Precision::Bf16);
}

/// The fixture's checkpoint with every tensor rounded to bf16 (and stored as f32).
fn bf16_rounded_checkpoint(name: &str) -> Checkpoint {
    let ckpt = Checkpoint::open(&pi_fixture(name).join("model.safetensors")).unwrap();
    let tensors: Vec<(String, Vec<usize>, Vec<f32>)> = ckpt
        .keys()
        .into_iter()
        .map(|k| {
            let shape = ckpt.shape(&k).unwrap().to_vec();
            let values = ckpt.tensor(&k, &shape).unwrap();
            let rounded = values
                .into_iter()
                .map(|x| half::bf16::from_f32(x).to_f32())
                .collect();
            (k, shape, rounded)
        })
        .collect();
    let views: Vec<(String, Vec<usize>, &[f32])> = tensors
        .iter()
        .map(|(k, s, v)| (k.clone(), s.clone(), v.as_slice()))
        .collect();
    Checkpoint::from_bytes("bf16-rounded", serialize_f32(&views).unwrap()).unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()))
}

/// bf16 weight GEMMs against our f32 chunk, within `BF16_FACTOR` times the error of rounding
/// only the weights to bf16 (an exact f32 run on a rounded copy of the checkpoint, measured
/// here), and not equal to the f32 chunk (the bf16 kernels ran). Where the native kernel cannot
/// run (no AVX512_BF16, or `KAIROS_DISABLE_BF16`), the model falls back to f32 and must equal
/// it.
fn bf16_within_bound(name: &str) {
    let g = Goldens::open_at(&pi_fixture(name));
    let exact = load_fast(name, Precision::F32);
    let bf16 = load_fast(name, Precision::Bf16);
    let rounded = {
        let dims = exact.dims().clone();
        FastPiModel::load(
            &bf16_rounded_checkpoint(name),
            &dims,
            Pool::new(2).unwrap(),
            Precision::F32,
        )
        .unwrap()
    };
    let native = Precision::Bf16.resolve(Isa::detect()) == Precision::Bf16;
    assert_eq!(bf16.precision() == Precision::Bf16, native);
    for case_name in ["pair", "missing"] {
        let c = case(&g, case_name);
        let observations: Vec<PiObservation<'_>> = (0..c.batch).map(|b| c.observation(b)).collect();
        let run = |m: &FastPiModel| -> Vec<f32> {
            let prefixes = m.prefix(&observations).unwrap();
            sample(m, &c, &prefixes)
                .into_iter()
                .flat_map(|s| s.actions)
                .collect()
        };
        let (ours, ours_f32, weights_only) = (run(&bf16), run(&exact), run(&rounded));
        let (d, d_weights) = (
            max_abs_diff(&ours, &ours_f32),
            max_abs_diff(&weights_only, &ours_f32),
        );
        let big = ours_f32.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        eprintln!(
            "{name} {case_name}: |bf16 - f32| {d:.3e} ({:.3e} of max |action| {big:.3}), \
             weights rounded only {d_weights:.3e}, ratio {:.2}",
            d / big,
            d / d_weights
        );
        if native {
            assert!(
                d_weights > 0.0,
                "{name} {case_name}: rounding changed nothing"
            );
            assert!(
                d <= BF16_FACTOR * d_weights,
                "{name} {case_name}: {d} > {BF16_FACTOR} x {d_weights}"
            );
            assert_ne!(ours, ours_f32, "{name} {case_name}: bf16 ran as f32");
        } else {
            assert_eq!(ours, ours_f32, "{name} {case_name}: the f32 fallback");
        }
    }
}

#[test]
fn pi0_bf16_stays_within_its_bound_of_the_f32_goldens() {
    bf16_within_bound("pi0_tiny");
}

#[test]
fn pi05_bf16_stays_within_its_bound_of_the_f32_goldens() {
    bf16_within_bound("pi05_tiny");
}

/// Inputs the fast model cannot take are errors that say what is wrong, never panics.
#[test]
fn bad_inputs_are_named_errors_on_the_fast_kernels() {
    let g = Goldens::open_at(&pi_fixture("pi0_tiny"));
    let model = load_fast("pi0_tiny", Precision::F32);
    let c = case(&g, "pair");
    let prefix_err = |obs: PiObservation<'_>| model.prefix(&[obs]).unwrap_err().to_string();
    let short = vec![0.0f32; 10];
    let mut obs = c.observation(0);
    obs.images[0] = Some(&short);
    let e = prefix_err(obs);
    assert!(
        e.contains("camera slot 0") && e.contains("10 values"),
        "{e}"
    );
    let mut obs = c.observation(0);
    let tokens = vec![10_000u32; obs.tokens.len()];
    obs.tokens = &tokens;
    assert!(prefix_err(obs).contains("vocabulary"));
    let mut obs = c.observation(0);
    obs.token_mask = &obs.token_mask[1..];
    assert!(prefix_err(obs).contains("mask values"));

    let prefixes = model.prefix(&[c.observation(0)]).unwrap();
    let sample_err = |state: Option<&[f32]>, noise: &[Vec<f32>]| {
        model
            .sample(&[FastSampleInput {
                prefix: &prefixes[0],
                state,
                noise,
            }])
            .unwrap_err()
            .to_string()
    };
    let noise = vec![c.noise[0].clone()];
    let state = c.state[0].as_slice();
    assert!(sample_err(None, &noise).contains("needs the state"));
    assert!(sample_err(Some(&[0.0; 100]), &noise).contains("state has 100 values"));
    assert!(sample_err(Some(state), &[vec![0.0; 3]]).contains("noise has 3 values"));
    assert!(sample_err(Some(state), &[]).contains("no sample"));
}
