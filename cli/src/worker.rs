//! `kairos worker`: a remote engine worker for a scheduler (`kairos serve`). Parses its
//! arguments, loads and profiles the model with the pool's own code (`pool::build_pool`, the
//! same `LocalEngine` and start-up profile as a local engine), then runs `kairos_server::worker` until
//! SIGTERM or Ctrl-C, when it drains and exits 0.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::Context;
use kairos_sdk::protocol::worker::WorkerTier;
use kairos_sdk::tls::{Fingerprint, ServerTrust};

use kairos_core::scheduler::{EngineId, Tier};
use kairos_server::config::EngineConfig;
use kairos_server::data_dir::DataDir;
use kairos_server::pool::build_pool;
use kairos_server::worker::{WorkerOptions, run as run_worker};

/// Serve a scheduler's batches on this machine's engine.
#[derive(clap::Args, Debug, Clone)]
pub struct WorkerArgs {
    /// The scheduler's QUIC address (`kairos serve`'s `listen`), `host:port`: an IP address or
    /// a DNS name (e.g. a Kubernetes Service's), resolved again whenever the worker reconnects.
    #[arg(long, value_name = "HOST:PORT")]
    pub server: String,
    /// The scheduler's data directory, read for the certificate pin and the worker token when
    /// `--pin` or `--worker-token` is not given.
    #[arg(long, default_value = kairos_sdk::data_dir::DEFAULT_DATA_DIR)]
    pub data_dir: PathBuf,
    /// The scheduler's certificate fingerprint, `sha256:<hex>`.
    #[arg(long)]
    pub pin: Option<Fingerprint>,
    /// The worker token (`worker-token.txt` in the scheduler's data directory).
    #[arg(long)]
    pub worker_token: Option<String>,
    /// The model (`builtin`, `builtin:<preset>` or a checkpoint directory); its shapes must be
    /// the site's.
    #[arg(long, default_value = "builtin")]
    pub model: String,
    /// The task tokenizer of a whole SmolVLA checkpoint [default: `tokenizer.json` beside it].
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// The device (`cpu`, `cuda`, `cuda:N`).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// The weight GEMMs' number format: `f32` (exact) or `bf16` (AVX512_BF16; falls back to
    /// f32 with a warning elsewhere).
    #[arg(long, default_value = "f32")]
    pub precision: String,
    /// Edge or cloud; `auto`: the scheduler classifies the worker from its measured round
    /// trip (`[workers] cloud_rtt_ms`), and re-classifies it as that moves.
    #[arg(long, value_enum, default_value = "edge")]
    pub tier: TierArg,
    /// Largest batch to accept (caps the measured saturation batch).
    #[arg(long)]
    pub max_batch: Option<u32>,
    /// A JSON engine profile to use instead of measuring one at start.
    #[arg(long)]
    pub profile: Option<PathBuf>,
    /// Name for logs and metrics (default: `<hostname>-<pid>`).
    #[arg(long)]
    pub worker_id: Option<String>,
    /// Serve `/ready` (200 once the model is loaded, 503 from SIGTERM on) and `/metrics` on this
    /// TCP address (plain HTTP, `server::metrics::http`): the worker's connection state,
    /// batches answered and failed, heartbeats sent, compute time per batch, batch sizes and
    /// its engine's busy time. Its round trip and re-dispatches are the scheduler's to export.
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<std::net::SocketAddr>,
}

/// `--tier`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum TierArg {
    /// Near the robots.
    Edge,
    /// Far from them.
    Cloud,
    /// Classified by the scheduler from the measured round trip.
    Auto,
}

/// Runs `kairos worker` until SIGTERM/Ctrl-C (exit 0 after draining). A lost connection is
/// dialled again with backoff (`kairos_server::worker::run`); a refusal or a first connection that
/// fails ends it with an error.
pub fn run(args: WorkerArgs) -> anyhow::Result<()> {
    super::init_logging("info");
    let data_dir = DataDir::new(&args.data_dir);
    let pin = match args.pin {
        Some(pin) => pin,
        None => data_dir
            .read_pin()
            .context("reading the scheduler's pin (or pass --pin)")?,
    };
    let token = match &args.worker_token {
        Some(token) => token.clone(),
        None => data_dir
            .read_worker_token()
            .context("reading the worker token (or pass --worker-token)")?,
    };
    let engine_config = EngineConfig {
        model: args.model.clone(),
        tokenizer: args.tokenizer.clone(),
        device: args.device.clone(),
        precision: args.precision.clone(),
        tier: Tier::Edge,
        instances: 1,
        max_batch: args.max_batch,
        profile: args.profile.clone(),
        ..EngineConfig::default()
    };
    let pool = build_pool(
        std::slice::from_ref(&engine_config),
        &kairos_bench::horizon_bench::served::schemes(),
        |_| {},
    )
    .context("loading and profiling the model")?;
    let engine = pool
        .get(EngineId(0))
        .cloned()
        .context("the engine did not start")?;
    let profile = engine.profile();
    println!(
        "worker: {} on {}, batches up to {}",
        profile.model, profile.device, profile.max_batch
    );
    let worker_id = args.worker_id.clone().unwrap_or_else(|| {
        let host = std::fs::read_to_string("/etc/hostname").unwrap_or_default();
        format!("{}-{}", host.trim(), std::process::id())
    });
    let options = WorkerOptions {
        server: args.server.clone(),
        trust: ServerTrust::Pinned(pin),
        token,
        worker_id,
        tier: match args.tier {
            TierArg::Edge => WorkerTier::Edge,
            TierArg::Cloud => WorkerTier::Cloud,
            TierArg::Auto => WorkerTier::Auto,
        },
        max_batch: args.max_batch.unwrap_or(u32::MAX),
        metrics: kairos_server::metrics::Metrics::for_worker(),
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let readiness = kairos_server::metrics::Readiness::new();
    let report = runtime.block_on(async {
        if let Some(addr) = args.metrics_listen {
            let listener = kairos_server::metrics::http::bind(addr)
                .await
                .with_context(|| format!("cannot listen for metrics on {addr}"))?;
            tokio::spawn(kairos_server::metrics::http::serve(
                listener,
                options.metrics.clone(),
                readiness.clone(),
                std::future::pending(),
            ));
        }
        readiness.set(true);
        let shutdown = async {
            let mut term =
                match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                    Ok(term) => term,
                    Err(error) => {
                        tracing::error!(%error, "cannot listen for SIGTERM");
                        return std::future::pending().await;
                    }
                };
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
            readiness.set(false);
        };
        anyhow::Ok(run_worker(options, Arc::clone(&engine), shutdown).await?)
    })?;
    println!(
        "worker {} stopped after draining: {} batches answered",
        report.engine, report.batches
    );
    Ok(())
}
