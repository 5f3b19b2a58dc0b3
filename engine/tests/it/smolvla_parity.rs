//! The SmolVLA expert against LeRobot 0.6.1's own `SmolVLAPolicy`.
//!
//! `engine/tests/golden/smolvla_small/` was written by `engine/tools/reference.py`: LeRobot's
//! policy with a small random config (4 layers: 2 self-, 2 cross-attention; GQA 6/2 heads of
//! 16; chunk 16) ran `predict_action_chunk` on 3 observations whose prefixes have 21, 16 and 12
//! valid tokens (padding in the middle of the prefix, as short instructions give). The file
//! holds LeRobot's prefix KV cache, the noise, every step's velocity and the chunk, in float32
//! and recomputed in float64.
//!
//! Tolerance. Both implementations compute in f32 and differ only in rounding (summation order,
//! exp/rsqrt approximations of ~1 ulp). Against the f64 recomputation, LeRobot's own f32 result
//! is off by `e_lr` (in meta.json: ~4e-6 on velocities of magnitude ~3, ~1e-6 on actions). Ours
//! has an error of the same nature, so `|ours - lerobot| <= |ours - f64| + |lerobot - f64|`
//! should be a small multiple of `e_lr`. The test asserts `|ours - lerobot| <= 5 e_lr` (with a
//! floor of 64 f32 ulps of the largest value), and separately that our own error against f64 is
//! no worse than 4 e_lr: a real mismatch (a wrong mask, position, scale or layer order) shows up
//! as errors of order 1e-2..1, three orders above.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::path::PathBuf;

use kairos_engine::smolvla::{ExpertDims, ExpertInput, ExpertSample, PrefixKv, SmolVlaExpert};
use kairos_engine::weights::Checkpoint;
use kairos_engine::{DeviceKind, EngineOptions, Kernels};

fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/smolvla_small")
}

struct Golden {
    prefixes: Vec<PrefixKv>,
    noise: Vec<Vec<f32>>,
    state: Vec<Vec<f32>>,
    state_emb: Vec<f32>,
    velocities: Vec<f32>,
    velocities_f64: Vec<f32>,
    actions: Vec<f32>,
    actions_f64: Vec<f32>,
    err_velocity: f32,
    err_actions: f32,
}

fn f64_tensor(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Vec<f32> {
    ckpt.tensor(key, shape).unwrap()
}

fn load_golden(expert: &SmolVlaExpert) -> Golden {
    let d = expert.dims();
    let io = Checkpoint::open(&golden_dir().join("io.safetensors")).unwrap();
    let mask_shape = io.shape("prefix_pad_mask").unwrap().to_vec();
    let (b, len) = (mask_shape[0], mask_shape[1]);
    let (n, a, k) = (d.chunk, d.action_pad, d.steps);
    let mask = io.tensor_u8("prefix_pad_mask", &[b, len]).unwrap();
    let prefixes = golden_prefixes(d, &io, &mask, b, len, |l, kv| format!("prefix.{l}.{kv}"));
    let noise = io.tensor("noise", &[b, n, a]).unwrap();
    let state = io.tensor("state", &[b, d.state_pad]).unwrap();
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden_dir().join("meta.json")).unwrap())
            .unwrap();
    Golden {
        prefixes,
        noise: noise.chunks_exact(n * a).map(<[f32]>::to_vec).collect(),
        state: state
            .chunks_exact(d.state_pad)
            .map(<[f32]>::to_vec)
            .collect(),
        state_emb: io.tensor("state_emb", &[b, d.vlm_hidden]).unwrap(),
        velocities: io.tensor("velocities", &[k, b, n, a]).unwrap(),
        velocities_f64: f64_tensor(&io, "velocities_f64", &[k, b, n, a]),
        actions: io.tensor("actions", &[b, n, a]).unwrap(),
        actions_f64: f64_tensor(&io, "actions_f64", &[b, n, a]),
        err_velocity: meta["lerobot_f32_vs_f64_max_abs_velocity"]
            .as_f64()
            .unwrap() as f32,
        err_actions: meta["lerobot_f32_vs_f64_max_abs_actions"].as_f64().unwrap() as f32,
    }
}

/// One `PrefixKv` per batch row from golden K/V tensors `[b, len, kv_heads, head_dim]` (post-RoPE,
/// LeRobot's layout) named `name(layer, "key" | "value")`, and the `[b, len]` pad mask.
pub(crate) fn golden_prefixes(
    d: &ExpertDims,
    ckpt: &Checkpoint,
    mask: &[u8],
    b: usize,
    len: usize,
    name: impl Fn(usize, &str) -> String,
) -> Vec<PrefixKv> {
    let kv = [b, len, d.kv_heads, d.head_dim];
    let per = len * d.kv_width();
    let layers: Vec<(Vec<f32>, Vec<f32>)> = (0..d.layers.len())
        .map(|l| {
            (
                ckpt.tensor(&name(l, "key"), &kv).unwrap(),
                ckpt.tensor(&name(l, "value"), &kv).unwrap(),
            )
        })
        .collect();
    (0..b)
        .map(|i| {
            PrefixKv::new(
                d,
                mask[i * len..(i + 1) * len]
                    .iter()
                    .map(|&m| m != 0)
                    .collect(),
                layers
                    .iter()
                    .map(|(k, _)| k[i * per..(i + 1) * per].to_vec())
                    .collect(),
                layers
                    .iter()
                    .map(|(_, v)| v[i * per..(i + 1) * per].to_vec())
                    .collect(),
            )
            .unwrap()
        })
        .collect()
}

pub(crate) fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn floor_of(values: &[f32]) -> f32 {
    64.0 * f32::EPSILON * values.iter().fold(0.0f32, |m, v| m.max(v.abs()))
}

/// The options of a CPU test: `kernels` on two threads.
fn cpu(kernels: Kernels) -> EngineOptions {
    EngineOptions {
        device: DeviceKind::Cpu,
        kernels,
        threads: 2,
        ..Default::default()
    }
}

/// The options of a GPU test: Candle on the first CUDA device.
#[cfg(feature = "cuda")]
pub(crate) fn cuda() -> EngineOptions {
    EngineOptions {
        device: DeviceKind::Cuda(0),
        kernels: Kernels::Candle,
        threads: 0,
        ..Default::default()
    }
}

/// What the tests name a run by, e.g. `Cpu/Fast`.
fn label(options: &EngineOptions) -> String {
    format!("{:?}/{:?}", options.device, options.kernels)
}

fn check(options: EngineOptions) {
    let kernels = label(&options);
    let expert = SmolVlaExpert::load(&golden_dir(), &options).unwrap();
    let g = load_golden(&expert);

    let emb = expert.embed_state(&g.state).unwrap().concat();
    assert!(
        max_abs_diff(&emb, &g.state_emb) <= 1e-5,
        "{kernels}: state_proj differs"
    );

    let inputs = golden_inputs(&g);
    let out = expert.sample(&inputs).unwrap();
    assert_matches_lerobot(&kernels, &g, expert.dims(), &out);
}

/// One request per golden observation, with LeRobot's noise.
fn golden_inputs(g: &Golden) -> Vec<ExpertInput<'_>> {
    g.prefixes
        .iter()
        .zip(&g.noise)
        .map(|(prefix, noise)| ExpertInput {
            prefix,
            noise: std::slice::from_ref(noise),
        })
        .collect()
}

/// `out` (the samples of [`golden_inputs`]) is LeRobot's result within the bound above.
fn assert_matches_lerobot(kernels: &str, g: &Golden, d: &ExpertDims, out: &[ExpertSample]) {
    let (b, k, len) = (g.prefixes.len(), d.steps, d.chunk * d.action_pad);
    // Ours: [request][K][N][A]; LeRobot's: [K][request][N][A].
    let mut velocities = vec![0.0f32; k * b * len];
    for (i, o) in out.iter().enumerate() {
        for step in 0..k {
            velocities[(step * b + i) * len..(step * b + i + 1) * len]
                .copy_from_slice(&o.velocities[step * len..(step + 1) * len]);
        }
    }
    let actions: Vec<f32> = out.iter().flat_map(|o| o.actions.iter().copied()).collect();

    let tol_v = (5.0 * g.err_velocity).max(floor_of(&g.velocities));
    let tol_a = (5.0 * g.err_actions).max(floor_of(&g.actions));
    let dv = max_abs_diff(&velocities, &g.velocities);
    let da = max_abs_diff(&actions, &g.actions);
    let dv64 = max_abs_diff(&velocities, &g.velocities_f64);
    let da64 = max_abs_diff(&actions, &g.actions_f64);
    println!(
        "{kernels}: |v - lerobot| {dv:.2e} (tol {tol_v:.2e}), |x - lerobot| {da:.2e} (tol {tol_a:.2e}); \
         vs f64: {dv64:.2e} / {da64:.2e} (lerobot's own: {:.2e} / {:.2e})",
        g.err_velocity, g.err_actions
    );
    assert!(
        dv <= tol_v,
        "{kernels}: velocities differ from LeRobot by {dv}"
    );
    assert!(da <= tol_a, "{kernels}: chunk differs from LeRobot by {da}");
    assert!(
        dv64 <= (4.0 * g.err_velocity).max(tol_v),
        "{kernels}: velocity error vs f64 {dv64}"
    );
    assert!(
        da64 <= (4.0 * g.err_actions).max(tol_a),
        "{kernels}: chunk error vs f64 {da64}"
    );
}

#[test]
fn fast_kernels_match_lerobot() {
    check(cpu(Kernels::Fast));
}

#[test]
fn portable_kernels_match_lerobot() {
    check(cpu(Kernels::Portable));
}

#[test]
fn candle_matches_lerobot() {
    check(cpu(Kernels::Candle));
}

/// Candle on the first GPU. The same f32 tolerance holds: Candle keeps cuBLAS's f32 GEMMs at full
/// precision unless told otherwise (no TF32), so only the summation order differs. Compiled by
/// `scripts/check-cuda-build.sh`; runs with `cargo test -p kairos-engine --features cuda` on a
/// machine with a GPU.
#[cfg(feature = "cuda")]
#[test]
fn cuda_matches_lerobot() {
    check(cuda());
}

/// LeRobot's batch has prefixes of 21, 16 and 12 valid tokens (padded to 21): each row must get
/// what it gets alone. The fast kernels drop padding and compute every row in a fixed order, so
/// they agree bit for bit; Candle pads and masks like LeRobot, so it agrees to rounding.
fn batch_equals_singles(options: EngineOptions, exact: bool) {
    let kernels = label(&options);
    let expert = SmolVlaExpert::load(&golden_dir(), &options).unwrap();
    let g = load_golden(&expert);
    let inputs: Vec<ExpertInput<'_>> = g
        .prefixes
        .iter()
        .zip(&g.noise)
        .map(|(prefix, noise)| ExpertInput {
            prefix,
            noise: std::slice::from_ref(noise),
        })
        .collect();
    let batched = expert.sample(&inputs).unwrap();
    for (input, b) in inputs.iter().zip(&batched) {
        let single = expert
            .sample(std::slice::from_ref(input))
            .unwrap()
            .remove(0);
        if exact {
            assert_eq!(b, &single, "{kernels}");
        } else {
            assert!(
                max_abs_diff(&b.velocities, &single.velocities) < 1e-5,
                "{kernels}"
            );
        }
    }
}

#[test]
fn fast_batch_equals_singles() {
    batch_equals_singles(cpu(Kernels::Fast), true);
}

#[test]
fn candle_batch_equals_singles() {
    batch_equals_singles(cpu(Kernels::Candle), false);
}

#[cfg(feature = "cuda")]
#[test]
fn cuda_batch_equals_singles() {
    batch_equals_singles(cuda(), false);
}

/// CUDA graphs are a CUDA feature: asking for them on the CPU is an error at load, whichever
/// kernels run there.
#[test]
fn cuda_graphs_on_the_cpu_are_refused_at_load() {
    for kernels in [Kernels::Auto, Kernels::Candle] {
        let options = EngineOptions {
            cuda_graphs: true,
            ..cpu(kernels)
        };
        let e = SmolVlaExpert::load(&golden_dir(), &options)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("CUDA graphs need a CUDA device"),
            "{kernels:?}: {e}"
        );
    }
}

/// The Euler loop replayed as a CUDA graph (`EngineOptions::cuda_graphs`) gives the uncaptured
/// loop's bits. A shape's first call runs uncaptured and captures the graph; every later call of
/// that shape copies its inputs into the graph's and replays it. Checked: the replay matches
/// LeRobot within `cuda_matches_lerobot`'s bound; two replays with different noise each equal
/// the uncaptured expert's result bit for bit (the graph reads the new input); another batch
/// size captures a graph of its own and replays it bit for bit too; and the counters show that
/// every call after a shape's first was a replay.
#[cfg(feature = "cuda")]
#[test]
fn cuda_graphs_replay_the_uncaptured_loop_bit_for_bit() {
    use kairos_engine::smolvla::CudaGraphStats;
    let graphs = EngineOptions {
        cuda_graphs: true,
        ..cuda()
    };
    let expert = SmolVlaExpert::load(&golden_dir(), &graphs).unwrap();
    let uncaptured = SmolVlaExpert::load(&golden_dir(), &cuda()).unwrap();
    assert!(expert.path().ends_with("+graphs"), "{}", expert.path());
    assert_eq!(uncaptured.cuda_graph_stats(), None);
    let stats = || expert.cuda_graph_stats().unwrap();
    assert_eq!(stats(), CudaGraphStats::default());
    let g = load_golden(&expert);
    let inputs = golden_inputs(&g);
    let want = uncaptured.sample(&inputs).unwrap();

    // The first call of three rows captures; the second replays.
    let first = expert.sample(&inputs).unwrap();
    assert_eq!(
        stats(),
        CudaGraphStats {
            captured: 1,
            uncaptured: 0,
            replays: 0
        }
    );
    let replayed = expert.sample(&inputs).unwrap();
    assert_eq!(stats().replays, 1);
    assert_eq!(first, want);
    assert_eq!(replayed, want);
    assert_matches_lerobot("Cuda(0)/Candle, graph replay", &g, expert.dims(), &replayed);

    // Same shape, other noise: a replay, and the uncaptured loop's bits for that noise.
    let other_noise: Vec<Vec<f32>> = (0..inputs.len() as u64)
        .map(|i| kairos_engine::sampler::gaussian_noise(7 + i, 0, g.noise[0].len()))
        .collect();
    let other: Vec<ExpertInput<'_>> = g
        .prefixes
        .iter()
        .zip(&other_noise)
        .map(|(prefix, noise)| ExpertInput {
            prefix,
            noise: std::slice::from_ref(noise),
        })
        .collect();
    let replayed_other = expert.sample(&other).unwrap();
    assert_eq!(stats().replays, 2);
    assert_eq!(replayed_other, uncaptured.sample(&other).unwrap());
    assert_ne!(replayed_other[0].actions, replayed[0].actions);

    // One row: a shape of its own, captured on its first call, replayed on the second.
    let one = &other[1..2];
    let want_one = uncaptured.sample(one).unwrap();
    assert_eq!(expert.sample(one).unwrap(), want_one);
    assert_eq!(
        stats(),
        CudaGraphStats {
            captured: 2,
            uncaptured: 0,
            replays: 2
        }
    );
    assert_eq!(expert.sample(one).unwrap(), want_one);
    assert_eq!(stats().replays, 3);
    // And the three-row graph still replays the first batch's bits.
    assert_eq!(expert.sample(&inputs).unwrap(), want);
    assert_eq!(stats().replays, 4);
}
