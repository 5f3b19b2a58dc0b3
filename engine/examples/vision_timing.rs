//! Time SmolVLA's VLM side on `lerobot/smolvla_base` shapes with seeded random weights: the
//! SigLIP vision tower + connector (SmolVLM2-500M: 12 layers, hidden 768, 512x512 images in 16x16
//! patches, ~212 GFLOP per camera) and, with `--prefix`, the whole prefix (vision, 48 language
//! tokens, state token, 16 SmolLM2 layers -> `PrefixKv`).
//!
//! `cargo run --release -p kairos-engine --example vision_timing -- [--cameras 1] [--iters 3]
//! [--threads 2] [--kernels fast|portable] [--side 512] [--prefix] [--precision f32|bf16]`
//! (`KAIROS_ISA=avx2` runs the AVX2 kernels on an AVX-512 CPU, for comparison)
//!
//! Prints one JSON line: `{"what":..,"cameras":N,"median_ms":..,"min_ms":..,"gflop":..,
//! "gflops":..,"runs":[..]}` (GFLOP counts the vision tower's multiply-adds x 2).

use std::time::Instant;

use kairos_engine::smolvla::{
    ExpertDims, SmolVlaConfig, SmolVlaVlm, VisionImage, VlmConfig, VlmObservation, VlmWeights,
};
use kairos_engine::{EngineOptions, Kernels};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut cameras = 1usize;
    let mut iters = 3usize;
    let mut threads = 0usize;
    let mut kernels = Kernels::Fast;
    let mut side = 512usize;
    let mut prefix = false;
    let mut precision = kairos_engine::Precision::F32;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        match flag.as_str() {
            "--help" | "-h" => {
                println!(
                    "Times SmolVLA's vision tower (or, with --prefix, the whole VLM prefix) on \
                     smolvla_base shapes with seeded random weights.\n\n\
                     Usage: vision_timing [--cameras 1] [--iters 3] [--threads 2] \
                     [--kernels fast|portable] [--side 512] [--prefix] [--precision f32|bf16]"
                );
                return Ok(());
            }
            "--prefix" => {
                prefix = true;
                continue;
            }
            _ => {}
        }
        let value = args.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--cameras" => cameras = value.parse()?,
            "--iters" => iters = value.parse()?,
            "--threads" => threads = value.parse()?,
            "--side" => side = value.parse()?,
            "--precision" => precision = value.parse()?,
            "--kernels" => {
                kernels = match value.as_str() {
                    "fast" => Kernels::Fast,
                    "portable" => Kernels::Portable,
                    other => return Err(format!("unknown kernels {other}").into()),
                }
            }
            other => return Err(format!("unknown flag {other}").into()),
        }
    }
    let config = VlmConfig::smolvlm2_500m();
    let cfg = SmolVlaConfig::default();
    let layers = if prefix { cfg.num_vlm_layers } else { 1 };
    let t0 = Instant::now();
    let weights = VlmWeights::random(&config, layers, 7)?;
    let options = EngineOptions {
        kernels,
        threads,
        precision,
        ..Default::default()
    };
    let vlm = SmolVlaVlm::from_weights(&weights, &cfg, &options)?;
    drop(weights);
    eprintln!(
        "weights ready in {:.1} s: {:?}",
        t0.elapsed().as_secs_f64(),
        vlm
    );
    let pixels: Vec<Vec<f32>> = (0..cameras)
        .map(|c| {
            kairos_engine::sampler::gaussian_noise(100 + c as u64, 0, 3 * side * side)
                .into_iter()
                .map(|v| (0.5 * v).clamp(-1.0, 1.0))
                .collect()
        })
        .collect();
    let images: Vec<VisionImage<'_>> = pixels
        .iter()
        .map(|p| VisionImage { side, pixels: p })
        .collect();
    let dims = ExpertDims::smolvla_base();
    let tokens: Vec<u32> = (0..48).map(|i| 100 + 37 * i).collect();
    let mask = vec![true; tokens.len()];
    let state_token = vec![0.1f32; config.text_config.hidden_size];
    let run = || -> Result<(), kairos_engine::EngineError> {
        if prefix {
            let obs = VlmObservation {
                images: images.iter().copied().map(Some).collect(),
                tokens: &tokens,
                token_mask: &mask,
                state_token: &state_token,
            };
            vlm.prefix(&dims, &[obs]).map(|_| ())
        } else {
            vlm.embed_images(&images).map(|_| ())
        }
    };
    run()?; // warm-up
    let mut runs = Vec::with_capacity(iters);
    let cpu0 = kairos_engine::profile::process_cpu_ms();
    for _ in 0..iters {
        let t = Instant::now();
        run()?;
        runs.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cpu_ms = (kairos_engine::profile::process_cpu_ms() - cpu0) / iters as f64;
    let mut sorted = runs.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let gflop = cameras as f64 * vision_gflop(&config, side);
    println!(
        "{{\"what\":\"{}\",\"cameras\":{cameras},\"side\":{side},\"median_ms\":{median:.1},\"min_ms\":{:.1},\"gflop\":{gflop:.1},\"gflops\":{:.1},\"cpu_ms_per_run\":{cpu_ms:.0},\"runs\":[{}]}}",
        if prefix { "prefix" } else { "vision" },
        sorted[0],
        gflop / (median / 1e3),
        runs.iter()
            .map(|r| format!("{r:.1}"))
            .collect::<Vec<_>>()
            .join(",")
    );
    Ok(())
}

/// Multiply-adds x 2 of the vision tower and connector for one `side x side` image.
fn vision_gflop(c: &VlmConfig, side: usize) -> f64 {
    let v = &c.vision_config;
    let n = ((side / v.patch_size) * (side / v.patch_size)) as f64;
    let (h, i, p) = (
        v.hidden_size as f64,
        v.intermediate_size as f64,
        v.patch_size as f64,
    );
    let patch = n * 3.0 * p * p * h;
    let layer = n * (4.0 * h * h + 2.0 * h * i) + 2.0 * n * n * h;
    let s2 = (c.scale_factor * c.scale_factor) as f64;
    let connector = n / s2 * h * s2 * c.text_config.hidden_size as f64;
    2.0 * (patch + v.num_hidden_layers as f64 * layer + connector) / 1e9
}
