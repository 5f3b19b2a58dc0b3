//! Criterion benches of the engine's hot path.
//!
//! - `smolvla_expert/denoise/{1,4,16}`: the full-size SmolVLA expert (`lerobot/smolvla_base`
//!   shapes: hidden 720, 16 layers, GQA 15/5x64), prefix 177 tokens, chunk 50, 10 Euler steps,
//!   seeded random weights, on the fast CPU kernels with `KAIROS_ENGINE_THREADS` (default: all
//!   cores) threads. The PyTorch comparison is `engine/tools/bench_vs_pytorch.py`.
//! - `flow_head/generate/1`: the built-in default model, one request.
//!
//! `cargo bench -p kairos-engine --bench engine`

use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use kairos_engine::sampler::gaussian_noise;
use kairos_engine::smolvla::{ExpertDims, ExpertWeights, PrefixKv, SmolVlaExpert};
use kairos_engine::{EngineOptions, default_model};

const PREFIX: usize = 177;

fn smolvla_expert(c: &mut Criterion) {
    let dims = ExpertDims::smolvla_base();
    let expert =
        SmolVlaExpert::from_weights(&ExpertWeights::random(&dims, 1), &EngineOptions::default())
            .expect("expert");
    let prefixes: Vec<PrefixKv> = (0..16u64)
        .map(|i| {
            let t = |s: usize| gaussian_noise(100 + i, s, PREFIX * dims.kv_width());
            PrefixKv::new(
                &dims,
                vec![true; PREFIX],
                (0..dims.layers.len()).map(|l| t(2 * l)).collect(),
                (0..dims.layers.len()).map(|l| t(2 * l + 1)).collect(),
            )
            .expect("prefix")
        })
        .collect();
    let mut group = c.benchmark_group("smolvla_expert/denoise");
    group.sample_size(10).warm_up_time(Duration::from_secs(1));
    for batch in [1usize, 4, 16] {
        group.measurement_time(Duration::from_secs(8 * batch as u64));
        let requests: Vec<(&PrefixKv, usize, u64)> = prefixes[..batch]
            .iter()
            .zip(0..)
            .map(|(p, s)| (p, 1, s))
            .collect();
        group.bench_with_input(BenchmarkId::from_parameter(batch), &requests, |b, r| {
            b.iter(|| expert.generate(r).expect("generate"))
        });
    }
    group.finish();
}

fn flow_head(c: &mut Criterion) {
    let model = default_model(&EngineOptions::default()).expect("model");
    let requests = kairos_engine::profile::synthetic_batch(model.as_ref(), 1);
    let mut group = c.benchmark_group("flow_head/generate");
    group.sample_size(20);
    group.bench_function("1", |b| {
        b.iter(|| model.generate(&requests).expect("generate"))
    });
    group.finish();
}

criterion_group!(benches, smolvla_expert, flow_head);
criterion_main!(benches);
