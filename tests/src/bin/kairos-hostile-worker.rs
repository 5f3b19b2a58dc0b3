//! A misbehaving remote worker for the mixed soak (`scripts/soak.sh --mixed`): it registers with
//! the real worker token and a fast profile of the built-in model's shapes, answers every batch
//! unusably (NaN actions, one result too many, 100,000-byte error texts, in turn) and registers
//! again after each removal (`kairos_tests::hostile_worker`). Runs until SIGINT/SIGTERM or
//! `--seconds`, then prints what it did.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use kairos_engine::EngineOptions;
use kairos_sdk::tls::ServerTrust;
use kairos_server::data_dir::DataDir;
use kairos_tests::hostile_worker::{HostileCounters, hostile_register, run_hostile_worker};

/// A worker that answers every batch unusably and registers again after each removal.
#[derive(Parser, Debug)]
#[command(name = "kairos-hostile-worker", version)]
struct Args {
    /// The scheduler's QUIC address.
    #[arg(long)]
    server: SocketAddr,
    /// The scheduler's data directory: its certificate pin and worker token.
    #[arg(long)]
    data_dir: PathBuf,
    /// The latency the profile declares at batch 1, ms (fast, so batches come to it).
    #[arg(long, default_value_t = 1.0)]
    latency_ms: f64,
    /// Pause after a removal before registering again, ms.
    #[arg(long, default_value_t = 100)]
    rejoin_ms: u64,
    /// Stop after this long (default: at SIGINT/SIGTERM).
    #[arg(long)]
    seconds: Option<u64>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let data_dir = DataDir::new(&args.data_dir);
    let pin = data_dir.read_pin().context("reading the scheduler's pin")?;
    let token = data_dir
        .read_worker_token()
        .context("reading the worker token")?;
    // The site's shapes: the built-in model's, as `kairos serve` serves it by default.
    let model = kairos_engine::default_model(&EngineOptions::default())
        .context("building the built-in model for its shapes")?;
    let spec = model.spec().clone();
    drop(model);
    let register = hostile_register(&spec, token, args.latency_ms);
    let counters = std::sync::Arc::new(HostileCounters::default());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    runtime.block_on(async {
        let worker = run_hostile_worker(
            args.server,
            ServerTrust::Pinned(pin),
            register,
            spec,
            Duration::from_millis(args.rejoin_ms),
            counters.clone(),
        );
        tokio::select! {
            () = worker => {}
            () = kairos_tests::attacks::until_stopped(args.seconds) => {}
        }
    });
    println!("hostile worker: {}", counters.summary());
    Ok(())
}
