//! `Precision::Bf16` on the `smolvla_tiny` fixture: the whole pipeline (processors, vision
//! tower, text layers, expert, 10 Euler steps) with every weight GEMM in bf16, against
//! LeRobot's f32 final actions, on the fast kernels and on the Candle path (bf16 weight
//! products, f32 norms, softmax and residuals; attention's products in f32).
//!
//! Bound: each bf16 GEMM output is off by at most about `2^-8 * sum |a||b|` (both operands
//! rounded to 8 significand bits; see `kernels::gemm`'s `bf16_gemm_is_within_its_rounding_bound`),
//! and those errors pass through every vision, text and expert layer and 10 Euler steps.
//! No useful worst case composes from that, so the bound is a relative one on the final
//! actions, `BF16_BOUND x max |action|`, about 4.6x the largest measured (2026-11-25, Zen 4:
//! `pair` 2.6e-3, `missing` 4.3e-3 of max |action|; max abs 0.041 / 0.048 on actions up to
//! 15.6 / 11.0); an f32 run shows ~1e-6, a broken kernel O(1). The Candle path rounds the same
//! operands (weights and the activations entering each weight product) to bf16, so the same
//! bound holds for it.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use kairos_engine::kernels::Isa;
use kairos_engine::smolvla::SmolVlaPipeline;
use kairos_engine::{EngineOptions, Kernels, Precision};

use crate::smolvla_goldens::{Goldens, fixture};
use crate::smolvla_processors::{max_abs_diff, observations};

/// Largest `|bf16 - LeRobot f32| / max |action|` accepted on the fixture's final actions.
const BF16_BOUND: f32 = 0.02;

/// The fast CPU kernels on 2 threads, in `precision`.
pub(crate) fn options(precision: Precision) -> EngineOptions {
    EngineOptions {
        kernels: Kernels::Fast,
        threads: 2,
        precision,
        ..Default::default()
    }
}

#[test]
fn bf16_pipeline_stays_within_its_bound_of_the_f32_goldens() {
    let g = Goldens::open();
    let exact = SmolVlaPipeline::load(&fixture(), None, &options(Precision::F32)).unwrap();
    let bf16 = SmolVlaPipeline::load(&fixture(), None, &options(Precision::Bf16)).unwrap();
    // Where the native kernel cannot run (no AVX512_BF16, or KAIROS_DISABLE_BF16 set), the
    // model falls back to f32 and must then equal it exactly.
    let native = Precision::Bf16.resolve(Isa::detect()) == Precision::Bf16;
    for name in ["pair", "missing"] {
        let obs = observations(&g, name);
        let noise = g.f32(&format!("{name}.noise"));
        let per = noise.len() / obs.len();
        let noises: Vec<Vec<f32>> = noise.chunks_exact(per).map(<[f32]>::to_vec).collect();
        let run = |p: &SmolVlaPipeline| -> Vec<f32> {
            let (out, _) = p.predict_with_noise(&obs, &noises).unwrap();
            out.iter().flat_map(|p| p.actions.concat()).collect()
        };
        let (ours, ours_f32) = (run(&bf16), run(&exact));
        let want = g.f32(&format!("{name}.actions"));
        let big = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let d = max_abs_diff(&ours, &want);
        let rel = d / big;
        eprintln!(
            "{name}: bf16 native {native}: max |bf16 - lerobot f32| {d:.3e}, / max|action| {big:.3e} = {rel:.3e}"
        );
        if native {
            assert!(rel <= BF16_BOUND, "{name}: {rel:e} > {BF16_BOUND:e}");
            assert_ne!(ours, ours_f32, "{name}: the bf16 model computed in f32");
        } else {
            assert_eq!(ours, ours_f32, "{name}: the f32 fallback differs from f32");
        }
    }
    // Batched == single, bit for bit, in bf16 too.
    let obs = observations(&g, "pair");
    let (both, _) = bf16.predict(&obs, &[3, 4]).unwrap();
    let (one, _) = bf16.predict(&obs[1..], &[4]).unwrap();
    assert_eq!(both[1], one[0]);
}

/// The Candle path in bf16 (any CPU: Candle's bf16 products need no AVX512_BF16), against
/// LeRobot's f32 actions with the same bound, and not computed in f32.
#[test]
fn bf16_candle_pipeline_stays_within_its_bound_of_the_f32_goldens() {
    let g = Goldens::open();
    let candle = |precision| EngineOptions {
        kernels: Kernels::Candle,
        precision,
        ..Default::default()
    };
    let exact = SmolVlaPipeline::load(&fixture(), None, &candle(Precision::F32)).unwrap();
    let bf16 = SmolVlaPipeline::load(&fixture(), None, &candle(Precision::Bf16)).unwrap();
    let paths = bf16.paths();
    assert_eq!(
        [&paths.vision, &paths.prefix, &paths.expert],
        ["candle:cpu-bf16"; 3]
    );
    for name in ["pair", "missing"] {
        let obs = observations(&g, name);
        let noise = g.f32(&format!("{name}.noise"));
        let per = noise.len() / obs.len();
        let noises: Vec<Vec<f32>> = noise.chunks_exact(per).map(<[f32]>::to_vec).collect();
        let run = |p: &SmolVlaPipeline| -> Vec<f32> {
            let (out, _) = p.predict_with_noise(&obs, &noises).unwrap();
            out.iter().flat_map(|p| p.actions.concat()).collect()
        };
        let (ours, ours_f32) = (run(&bf16), run(&exact));
        let want = g.f32(&format!("{name}.actions"));
        let big = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let rel = max_abs_diff(&ours, &want) / big;
        eprintln!("{name}: candle bf16: max |bf16 - lerobot f32| / max|action| = {rel:.3e}");
        assert!(rel <= BF16_BOUND, "{name}: {rel:e} > {BF16_BOUND:e}");
        assert!(
            max_abs_diff(&ours, &ours_f32) > 0.0,
            "{name}: the bf16 model computed in f32"
        );
    }
}
