//! The served models through `ActionModel`: batching, samples, seeds, updates, checkpoints.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use kairos_engine::flow_head::{FlowHead, FlowHeadConfig};
use kairos_engine::smolvla::SmolVlaExpert;
use kairos_engine::smolvla::serving::SmolVlaStandIn;
use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineOptions, ImageFormat, ImageInput, Kernels,
    load_model,
};

/// A narrower flow head than the default (test time), same chunk, steps and I/O shapes.
fn small_head(kernels: Kernels) -> FlowHead {
    small_head_with(&EngineOptions {
        kernels,
        threads: 2,
        ..Default::default()
    })
}

/// [`small_head`] with any options (same seed, so the same weights).
fn small_head_with(options: &EngineOptions) -> FlowHead {
    let config = FlowHeadConfig {
        hidden: 128,
        layers: 2,
        heads: 2,
        kv_heads: 1,
        token_dim: 64,
        ..Default::default()
    };
    FlowHead::random(config, 7, options).unwrap()
}

fn image(seed: u8, side: usize) -> ImageInput {
    let data = (0..side * side * 3)
        .map(|i| (i as u8).wrapping_mul(seed).wrapping_add(seed))
        .collect();
    ImageInput::RawU8 {
        height: side,
        width: side,
        channels: 3,
        data,
    }
}

fn png(seed: u8) -> ImageInput {
    let ImageInput::RawU8 { data, .. } = image(seed, 16) else {
        unreachable!()
    };
    let img = image::RgbImage::from_raw(16, 16, data).unwrap();
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
    ImageInput::Encoded {
        format: ImageFormat::Png,
        bytes: bytes.into_inner(),
    }
}

/// Requests that differ in state, camera count (so prefix length), samples and seed.
fn requests(state_dim: usize) -> Vec<ActionRequest> {
    let state = |k: f32| {
        (0..state_dim)
            .map(|i| (i as f32 * 0.3 + k).sin())
            .collect::<Vec<_>>()
    };
    vec![
        ActionRequest {
            cameras: Vec::new(),
            state: state(0.0),
            images: vec![image(3, 20), png(5)],
            instruction: "pick".into(),
            samples: 1,
            seed: 11,
            guidance: None,
        },
        ActionRequest {
            cameras: Vec::new(),
            state: state(1.0),
            images: vec![],
            instruction: "place the cube".into(),
            samples: 3,
            seed: 12,
            guidance: None,
        },
        ActionRequest {
            cameras: Vec::new(),
            state: state(2.0),
            images: vec![image(9, 7)],
            instruction: String::new(),
            samples: 2,
            seed: 13,
            guidance: None,
        },
    ]
}

fn assert_updates_sum_to_chunk(c: &ActionChunk) {
    let (n, d, k) = (c.chunk_len, c.action_dim, c.steps);
    assert_eq!(c.updates.len(), c.samples * k * n * d, "U is [S][K][N][D]");
    assert_eq!(c.actions.len(), c.samples * n * d);
    assert_eq!(c.noise.len(), c.samples * n * d);
    for s in 0..c.samples {
        let u = c.sample_updates(s);
        for i in 0..n * d {
            let mut x = c.noise[s * n * d + i];
            for step in 0..k {
                x += u[step * n * d + i];
            }
            assert_eq!(
                x,
                c.sample_actions(s)[i],
                "noise + sum(U) must be the chunk (sample {s}, value {i})"
            );
        }
    }
    assert!(c.actions.iter().all(|v| v.is_finite()));
}

fn batch_matches_singles(model: &dyn ActionModel, exact: bool) {
    let reqs = requests(model.spec().state_dim);
    let batched = model.generate(&reqs).unwrap();
    assert_eq!(batched.len(), reqs.len());
    for (r, b) in reqs.iter().zip(&batched) {
        let single = model.generate(std::slice::from_ref(r)).unwrap().remove(0);
        assert_eq!(
            (b.samples, b.steps, b.chunk_len, b.action_dim),
            (r.samples, 10, 50, model.spec().action_dim)
        );
        if exact {
            assert_eq!(
                b, &single,
                "a request must get the same chunk alone and in a batch"
            );
        } else {
            let diff = b
                .actions
                .iter()
                .zip(&single.actions)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            assert!(diff < 1e-4, "batched vs single differ by {diff}");
        }
        assert_updates_sum_to_chunk(b);
    }
}

#[test]
fn flow_head_batch_equals_singles_bit_for_bit() {
    batch_matches_singles(&small_head(Kernels::Fast), true);
}

#[test]
fn flow_head_candle_batch_equals_singles() {
    batch_matches_singles(&small_head(Kernels::Candle), false);
}

#[test]
fn flow_head_fast_and_candle_agree() {
    let reqs = requests(8);
    let fast = small_head(Kernels::Fast).generate(&reqs).unwrap();
    let candle = small_head(Kernels::Candle).generate(&reqs).unwrap();
    for (f, c) in fast.iter().zip(&candle) {
        assert_eq!(f.noise, c.noise);
        let diff = f
            .actions
            .iter()
            .zip(&c.actions)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(diff < 1e-4, "fast vs candle differ by {diff}");
    }
}

/// The flow head on the first GPU (Candle's CUDA kernels) against the fast CPU kernels, and its
/// batches against single requests. Compiled by `scripts/check-cuda-build.sh`; runs with
/// `cargo test -p kairos-engine --features cuda` on a machine with a GPU.
#[cfg(feature = "cuda")]
#[test]
fn flow_head_on_cuda_matches_the_cpu() {
    let cuda = small_head_with(&EngineOptions {
        device: kairos_engine::DeviceKind::Cuda(0),
        kernels: Kernels::Auto,
        threads: 0,
        ..Default::default()
    });
    let reqs = requests(8);
    let on_gpu = cuda.generate(&reqs).unwrap();
    let on_cpu = small_head(Kernels::Fast).generate(&reqs).unwrap();
    for (g, c) in on_gpu.iter().zip(&on_cpu) {
        assert_eq!(g.noise, c.noise, "the noise is drawn on the host");
        assert_updates_sum_to_chunk(g);
        let diff = g
            .actions
            .iter()
            .zip(&c.actions)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(diff < 1e-4, "cuda vs cpu differ by {diff}");
    }
    batch_matches_singles(&cuda, false);
}

#[test]
fn samples_share_the_observation_and_follow_the_seed() {
    let head = small_head(Kernels::Fast);
    let mut r = requests(8).remove(0);
    r.samples = 4;
    let four = head.generate(std::slice::from_ref(&r)).unwrap().remove(0);
    r.samples = 1;
    let one = head.generate(std::slice::from_ref(&r)).unwrap().remove(0);
    // Sample 0 of four is the single sample; the others differ (different noise).
    assert_eq!(four.sample_actions(0), one.sample_actions(0));
    assert_ne!(four.sample_actions(1), four.sample_actions(0));
    // Same seed, same chunk; another seed, another chunk.
    assert_eq!(head.generate(std::slice::from_ref(&r)).unwrap()[0], one);
    r.seed += 1;
    assert_ne!(
        head.generate(std::slice::from_ref(&r)).unwrap()[0].actions,
        one.actions
    );
}

#[test]
fn observation_changes_the_chunk() {
    let head = small_head(Kernels::Fast);
    let base = requests(8).remove(0);
    let out = |r: &ActionRequest| {
        head.generate(std::slice::from_ref(r))
            .unwrap()
            .remove(0)
            .actions
    };
    let a = out(&base);
    let mut other_state = base.clone();
    other_state.state[0] += 1.0;
    let mut other_image = base.clone();
    other_image.images[0] = image(200, 20);
    let mut no_images = base.clone();
    no_images.images.clear();
    assert_ne!(a, out(&other_state));
    assert_ne!(a, out(&other_image));
    assert_ne!(a, out(&no_images));
}

#[test]
fn bad_requests_are_rejected() {
    let head = small_head(Kernels::Fast);
    let good = requests(8).remove(0);
    let mut short = good.clone();
    short.state.pop();
    let mut many = good.clone();
    many.images = vec![image(1, 4); 3];
    let mut zero = good.clone();
    zero.samples = 0;
    let mut nan = good.clone();
    nan.state[1] = f32::NAN;
    let mut broken = good.clone();
    broken.images[0] = ImageInput::Encoded {
        format: ImageFormat::Jpeg,
        bytes: vec![0xff, 0xd8, 0],
    };
    for bad in [short, many, zero, nan, broken] {
        let err = head.generate(&[good.clone(), bad]).unwrap_err();
        assert!(err.to_string().contains("invalid input"), "{err}");
    }
    assert!(head.generate(&[]).unwrap().is_empty());
}

#[test]
fn flow_head_checkpoint_round_trip() {
    let head = small_head(Kernels::Fast);
    let dir = tempfile::tempdir().unwrap();
    head.save(dir.path()).unwrap();
    let loaded = load_model(dir.path()).unwrap();
    assert_eq!(loaded.spec(), head.spec());
    let reqs = requests(8);
    assert_eq!(
        loaded.generate(&reqs).unwrap(),
        head.generate(&reqs).unwrap()
    );
    let via_config = load_model(&dir.path().join("config.json")).unwrap();
    assert_eq!(via_config.spec().name, "flow-head-small");
}

#[test]
fn default_model_spec() {
    let model = kairos_engine::default_model(&EngineOptions::default()).unwrap();
    let spec = model.spec();
    assert_eq!(
        (
            spec.chunk_len,
            spec.action_dim,
            spec.state_dim,
            spec.steps,
            spec.max_images
        ),
        (50, 7, 8, 10, 2)
    );
    // Seeded: two instances give the same chunk.
    let again = kairos_engine::default_model(&EngineOptions::default()).unwrap();
    let r = requests(8);
    assert_eq!(
        model.generate(&r[..1]).unwrap(),
        again.generate(&r[..1]).unwrap()
    );
}

#[test]
fn smolvla_stand_in_serves_the_golden_checkpoint() {
    let dir =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/smolvla_small");
    let model = load_model(&dir).unwrap();
    let spec = model.spec().clone();
    assert_eq!(
        (
            spec.chunk_len,
            spec.action_dim,
            spec.state_dim,
            spec.max_images
        ),
        (16, 6, 7, 2)
    );
    assert!(spec.name.contains("stand-in"));
    let mut reqs = requests(7);
    for r in &mut reqs {
        r.images.truncate(2);
    }
    let out = model.generate(&reqs).unwrap();
    for (r, c) in reqs.iter().zip(&out) {
        assert_eq!((c.samples, c.chunk_len, c.action_dim), (r.samples, 16, 6));
        assert_eq!(c, &model.generate(std::slice::from_ref(r)).unwrap()[0]);
        assert_updates_sum_to_chunk(c);
    }
    // Same expert, stand-in prefix made by hand: the adapter adds nothing else.
    let expert = SmolVlaExpert::load(&dir, &EngineOptions::default()).unwrap();
    let stand_in = SmolVlaStandIn::new(expert, 2);
    assert_eq!(stand_in.prefix_len(), 2 * 64 + 48 + 1);
    let state = stand_in
        .expert()
        .embed_state(&[reqs[0].state.clone()])
        .unwrap();
    let prefix = stand_in.stand_in_prefix(&reqs[0], &state[0]).unwrap();
    assert_eq!(prefix.valid_len(), 2 * 64 + "pick".len() + 1);
    let direct = stand_in
        .expert()
        .generate(&[(&prefix, 1, reqs[0].seed)])
        .unwrap();
    assert_eq!(direct[0], out[0]);
}
