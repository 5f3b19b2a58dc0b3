//! Time the default-size SmolVLA expert's denoise loop (`lerobot/smolvla_base` shapes: hidden
//! 720, 16 layers, prefix 177 tokens, chunk 50, 10 steps) with seeded random weights.
//!
//! `cargo run --release -p kairos-engine --example expert_timing -- [--batch 1,4,16]
//! [--iters 5] [--threads 2] [--kernels fast|portable|candle] [--prefix 177] [--precision f32|bf16]`
//!
//! Prints one JSON line per batch size: `{"batch":B,"median_ms":..,"min_ms":..,"runs":[..]}`.
//! `engine/tools/bench_vs_pytorch.py` runs it next to LeRobot's PyTorch denoise.

use std::time::Instant;

use kairos_engine::smolvla::{ExpertDims, ExpertWeights, PrefixKv, SmolVlaExpert};
use kairos_engine::{EngineOptions, Kernels};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut batches = vec![1usize, 4, 16];
    let mut iters = 5usize;
    let mut threads = 0usize;
    let mut kernels = Kernels::Fast;
    let mut prefix_len = 177usize;
    let mut precision = kairos_engine::Precision::F32;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        if flag == "--help" || flag == "-h" {
            println!(
                "Times the SmolVLA expert's denoise loop with seeded random weights.\n\n\
                 Usage: expert_timing [--batch 1,4,16] [--iters 5] [--threads 2] \
                 [--kernels fast|portable|candle] [--prefix 177] [--precision f32|bf16]"
            );
            return Ok(());
        }
        let value = args.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--batch" => batches = value.split(',').map(str::parse).collect::<Result<_, _>>()?,
            "--iters" => iters = value.parse()?,
            "--threads" => threads = value.parse()?,
            "--prefix" => prefix_len = value.parse()?,
            "--precision" => precision = value.parse()?,
            "--kernels" => {
                kernels = match value.as_str() {
                    "fast" => Kernels::Fast,
                    "portable" => Kernels::Portable,
                    "candle" => Kernels::Candle,
                    other => return Err(format!("unknown kernels {other}").into()),
                }
            }
            other => return Err(format!("unknown flag {other}").into()),
        }
    }
    let dims = ExpertDims::smolvla_base();
    let weights = ExpertWeights::random(&dims, 1);
    let expert = SmolVlaExpert::from_weights(
        &weights,
        &EngineOptions {
            kernels,
            threads,
            precision,
            ..Default::default()
        },
    )?;
    eprintln!("{}", expert.description());
    let max_batch = batches.iter().copied().max().unwrap_or(1);
    let prefixes: Vec<PrefixKv> = (0..max_batch)
        .map(|i| {
            let layer = |s: usize| {
                kairos_engine::sampler::gaussian_noise(
                    1000 + i as u64,
                    s,
                    prefix_len * dims.kv_width(),
                )
            };
            PrefixKv::new(
                &dims,
                vec![true; prefix_len],
                (0..dims.layers.len()).map(|l| layer(2 * l)).collect(),
                (0..dims.layers.len()).map(|l| layer(2 * l + 1)).collect(),
            )
        })
        .collect::<Result<_, _>>()?;
    for &b in &batches {
        let requests: Vec<(&PrefixKv, usize, u64)> = prefixes[..b]
            .iter()
            .enumerate()
            .map(|(i, p)| (p, 1, i as u64))
            .collect();
        expert.generate(&requests)?; // warm-up: page in weights, size the workspace
        let mut runs = Vec::with_capacity(iters);
        let cpu0 = kairos_engine::profile::process_cpu_ms();
        for _ in 0..iters {
            let t = Instant::now();
            let out = expert.generate(&requests)?;
            runs.push(t.elapsed().as_secs_f64() * 1e3);
            assert_eq!(out.len(), b);
        }
        let cpu_ms = (kairos_engine::profile::process_cpu_ms() - cpu0) / iters as f64;
        let mut sorted = runs.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted[sorted.len() / 2];
        println!(
            "{{\"batch\":{b},\"median_ms\":{median:.1},\"min_ms\":{:.1},\"cpu_ms_per_run\":{cpu_ms:.0},\"runs\":[{}]}}",
            sorted[0],
            runs.iter()
                .map(|r| format!("{r:.1}"))
                .collect::<Vec<_>>()
                .join(",")
        );
    }
    Ok(())
}
