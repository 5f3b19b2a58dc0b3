//! Writes a tiny flow-head checkpoint (seeded random weights) for load runs, where the model
//! should cost as little as possible so that what is measured is the server:
//! `cargo run -p kairos-tests --bin kairos-tiny-model -- DIR`, then `[[engine]] model = "DIR"`.
//!
//! Shapes: state 8, actions 16 × 7, 4 flow steps, no cameras, one transformer layer of width 32.
//!
//! `--preset smolvla-base` instead writes a seeded random SmolVLA checkpoint folder of
//! `lerobot/smolvla_base`'s shapes (the files LeRobot's `save_pretrained` writes, 1.2 GB; see
//! `kairos_engine::smolvla::random_checkpoint`), to measure the full-size model where no
//! checkpoint can be downloaded: `kairos predict --model DIR`.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use kairos_engine::EngineOptions;
use kairos_engine::flow_head::{FlowHead, FlowHeadConfig};
use kairos_engine::smolvla::random_checkpoint::RandomCheckpoint;

/// Write a tiny flow-head checkpoint (state 8, actions 16 × 7, 4 flow steps, no cameras, one
/// transformer layer of width 32) for load runs: `[[engine]] model = "DIR"`.
#[derive(Parser, Debug)]
#[command(name = "kairos-tiny-model", version)]
struct Args {
    /// Directory to write the checkpoint into (created if missing).
    dir: PathBuf,
    /// What to write.
    #[arg(long, value_enum, default_value_t = Preset::FlowHead)]
    preset: Preset,
    /// Seed of the weights (`smolvla-base`).
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// The checkpoints this command writes.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Preset {
    /// The tiny flow head for load runs.
    FlowHead,
    /// A random SmolVLA folder of `lerobot/smolvla_base`'s shapes.
    SmolvlaBase,
}

fn main() -> anyhow::Result<()> {
    // Parsing comes first: `--help` and bad arguments end here, before anything is written.
    let Args { dir, preset, seed } = Args::parse();
    if preset == Preset::SmolvlaBase {
        RandomCheckpoint::smolvla_base(seed)
            .write(&dir)
            .with_context(|| format!("writing {}", dir.display()))?;
        println!("wrote {}", dir.display());
        return Ok(());
    }
    let config = FlowHeadConfig {
        name: "flow-head-tiny".into(),
        state_dim: 8,
        action_dim: 7,
        chunk_size: 16,
        num_steps: 4,
        max_images: 0,
        image_grid: 1,
        token_dim: 16,
        hidden: 32,
        layers: 1,
        heads: 2,
        kv_heads: 1,
        head_dim: 16,
        ..FlowHeadConfig::default()
    };
    let model = FlowHead::random(
        config,
        kairos_engine::builtin::DEFAULT_SEED,
        &EngineOptions::default(),
    )
    .context("building the tiny flow head")?;
    model
        .save(&dir)
        .with_context(|| format!("writing {}", dir.display()))?;
    println!("wrote {}", dir.display());
    Ok(())
}
