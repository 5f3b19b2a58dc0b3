//! `kairos serve`: run the server.
//!
//! With no arguments it listens on `127.0.0.1:4433`, keeps its state in `./kairos-data` (a
//! self-signed certificate, its fingerprint, and a generated token for the robot `default`) and
//! serves the engine crate's built-in model, profiled at start. `--config kairos.toml` sets the
//! rest (see `docs/SERVER.md`). Ctrl-C shuts down gracefully: no new connections or rounds, the
//! rounds already accepted are answered. If the driver dies, the server stops the same way by
//! itself and the command exits with an error.

use std::collections::BTreeMap;
use std::future::Future;
use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};

use kairos_server::config::{Config, DEFAULT_ROBOT, Overrides};
use kairos_server::pool::{BuildEvent, EnginePool, build_pool};

use kairos_bench::horizon_bench::served;
use kairos_server::transport::launch::{Policies, RunningServer, ServerReport, start};

/// Serve robots over QUIC.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct ServeArgs {
    /// Configuration file (kairos.toml); without it every setting has its default.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Listen address, overriding the file's `listen`.
    #[arg(long)]
    pub listen: Option<std::net::SocketAddr>,
    /// Also serve openpi clients (`openpi-client`'s `WebsocketClientPolicy`) on this TCP
    /// address, overriding the file's `[openpi] listen` (docs/SERVER.md, "openpi endpoint").
    #[arg(long, value_name = "ADDR")]
    pub openpi_listen: Option<std::net::SocketAddr>,
    /// Serve Prometheus metrics (`GET /metrics`) and readiness (`GET /ready`) over plain HTTP
    /// on this TCP address, overriding the file's `[metrics] listen` (docs/SERVER.md,
    /// "Metrics and readiness").
    #[arg(long, value_name = "ADDR")]
    pub metrics_listen: Option<std::net::SocketAddr>,
    /// Data directory, overriding the file's `data_dir`.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// The engine's model (`builtin`, `builtin:smolvla-random`, a checkpoint directory, or
    /// `horizon-flow:DIR`: the closed-loop bench's policy), overriding the file's. Its profile is then measured at start. With several `[[engine]]`
    /// tables in the file, set it there instead.
    #[arg(long)]
    pub model: Option<String>,
    /// The task tokenizer (`tokenizer.json`) of a whole SmolVLA checkpoint, overriding the
    /// file's; same rules as `--model` [default: `tokenizer.json` beside the checkpoint].
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// The engine's device (`cpu`, `cuda`, `cuda:N`), overriding the file's; same rules as
    /// `--model`. CUDA needs a `kairos` built with `--features cuda`.
    #[arg(long)]
    pub device: Option<String>,
    /// The engine's weight GEMMs: `f32` or `bf16` (AVX512_BF16; falls back to f32 elsewhere),
    /// overriding the file's `precision`; same rules as `--model`.
    #[arg(long)]
    pub precision: Option<String>,
    /// Replay SmolVLA's Euler loop as a CUDA graph per batch shape (CUDA only), overriding the
    /// file's `cuda_graphs`; same rules as `--model`.
    #[arg(long)]
    pub cuda_graphs: bool,
    /// Local engine instances of the model (default: the file's `instances`, else 1). `0` runs a
    /// scheduler with no local engine, served only by remote workers (`kairos worker`); the
    /// model then only fixes the shapes workers must match.
    #[arg(long, value_name = "N")]
    pub local_engines: Option<u32>,
    /// A horizon-policy plugin (`.wasm` component), registered under its file stem and made
    /// the default horizon policy; robots may still select another by name.
    #[arg(long, value_name = "FILE.wasm")]
    pub horizon_plugin: Option<PathBuf>,
    /// Parameters of the default horizon policy, `key=value,...` (e.g. `t=0.4,h_min=8`).
    #[arg(long, value_name = "K=V,...", value_parser = parse_params)]
    pub horizon_params: Option<BTreeMap<String, f64>>,
    /// A priority-policy plugin (`.wasm` component), registered under its file stem and made
    /// the scheduler's policy.
    #[arg(long, value_name = "FILE.wasm")]
    pub priority_plugin: Option<PathBuf>,
    /// Parameters of the priority plugin, `key=value,...`.
    #[arg(long, value_name = "K=V,...", requires = "priority_plugin")]
    pub priority_params: Option<String>,
}

/// `key=value,...` with finite numeric values.
fn parse_params(s: &str) -> Result<BTreeMap<String, f64>, String> {
    s.split(',')
        .filter(|kv| !kv.trim().is_empty())
        .map(crate::parse_finite_param)
        .collect()
}

impl ServeArgs {
    /// The flags as the library's overrides.
    fn overrides(&self) -> Overrides {
        Overrides {
            listen: self.listen,
            openpi_listen: self.openpi_listen,
            metrics_listen: self.metrics_listen,
            data_dir: self.data_dir.clone(),
            model: self.model.clone(),
            tokenizer: self.tokenizer.clone(),
            device: self.device.clone(),
            precision: self.precision.clone(),
            cuda_graphs: self.cuda_graphs,
            local_engines: self.local_engines,
            horizon_plugin: self.horizon_plugin.clone(),
            horizon_params: self.horizon_params.clone(),
            priority_plugin: self.priority_plugin.clone(),
            priority_params: self.priority_params.clone(),
        }
    }
}

/// The configuration the arguments describe.
pub fn config(args: &ServeArgs) -> anyhow::Result<Config> {
    Config::load_with(args.config.as_deref(), &args.overrides()).context("invalid settings")
}

/// Runs `kairos serve` until Ctrl-C.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    crate::init_logging("info");
    let config = config(&args)?;
    let pool = start_engines(&config)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let report = runtime.block_on(serve(&config, pool, async {
        if let Err(error) = tokio::signal::ctrl_c().await {
            tracing::error!(%error, "cannot listen for Ctrl-C; stopping");
        }
    }))?;
    println!(
        "stopped: {} connections ({} openpi), {} rounds answered ({} from the reply cache), {} failed, {} tasks ended",
        report.transport.admitted + report.openpi.connections,
        report.openpi.connections,
        report.driver.replies,
        report.driver.cached_replies,
        report.driver.failed,
        report.driver.tasks_ended
    );
    println!(
        "  refused: {} ({} of {} logged); {} QUIC Retry answers",
        report.refusals,
        report.refusals.logged,
        report.refusals.total(),
        report.transport.retried
    );
    let latency = |name: &str, s: kairos_server::driver::LatencySummary| {
        println!(
            "  {name:<34} p50 {:>7.3} ms  p99 {:>7.3} ms  max {:>7.3} ms  ({} replies)",
            s.p50_us as f64 / 1e3,
            s.p99_us as f64 / 1e3,
            s.max_us as f64 / 1e3,
            s.count
        );
    };
    latency("server-added (total - inference)", report.driver.overhead);
    latency(
        "  of it processing (- queue, refetch)",
        report.driver.processing,
    );
    // A non-zero exit, so that an orchestrator restarts the server.
    if let Some(failure) = report.driver_failure {
        anyhow::bail!("the server stopped because its driver died: {failure}");
    }
    Ok(())
}

/// Loads and profiles the configured engines, showing progress.
pub fn start_engines(config: &Config) -> anyhow::Result<EnginePool> {
    let bar = ProgressBar::new_spinner();
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg}")
            .context("progress bar template")?,
    );
    let pool = build_pool(&config.engines, &served::schemes(), |event| match event {
        BuildEvent::Loading { index, model } => {
            bar.set_message(format!("engine {index}: loading {model}"));
        }
        BuildEvent::Measured {
            index,
            batch,
            done,
            total,
        } => {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            bar.set_message(format!("engine {index}: profiling batch {batch}"));
        }
        BuildEvent::Ready {
            index,
            profile,
            paths,
        } => bar.suspend(|| {
            let paths = paths.map(|p| format!(" [{p}]")).unwrap_or_default();
            println!(
                "engine {index}: {} on {}{paths}, batches up to {} ({})",
                profile.model,
                profile.device,
                profile.max_batch,
                profile
                    .points
                    .iter()
                    .map(|p| format!("batch {}: {:.2} ms", p.batch, p.latency_ms))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }),
    })
    .context("starting the engines")?;
    bar.finish_and_clear();
    Ok(pool)
}

/// Serves until `shutdown` resolves or the driver dies, printing where to connect; then drains.
pub async fn serve(
    config: &Config,
    pool: EnginePool,
    shutdown: impl Future<Output = ()>,
) -> anyhow::Result<ServerReport> {
    let server = start(config, pool, Policies::default())
        .await
        .context("starting the server")?;
    print_banner(config, &server);
    tokio::select! {
        () = shutdown => println!("shutting down: answering the rounds already accepted..."),
        // The server has begun to stop by itself; wait for its drain.
        reason = server.failed() => eprintln!("{reason}: the server is not ready and stops"),
    }
    Ok(server.shutdown().await)
}

fn print_banner(config: &Config, server: &RunningServer) {
    let data_dir = &config.data_dir;
    println!(
        "kairos {} serving {}",
        env!("CARGO_PKG_VERSION"),
        server.model.name
    );
    println!(
        "  listening on   {} (QUIC, TLS 1.3, ALPN kairos/1)",
        server.local_addr
    );
    if let Some(addr) = server.openpi_addr {
        println!("  openpi         ws://{addr} (openpi-client; Api-Key = a robot token)");
    }
    if let Some(addr) = server.metrics_addr {
        println!(
            "  metrics        http://{addr}/metrics, readiness http://{addr}/ready, fleet page http://{addr}/"
        );
    }
    println!(
        "  certificate    {}{}",
        server.fingerprint,
        if server.generated_certificate {
            " (generated now)"
        } else {
            ""
        }
    );
    println!(
        "  pin file       {}",
        kairos_server::data_dir::DataDir::new(data_dir)
            .fingerprint()
            .display()
    );
    match &server.tokens_file {
        Some(path) => println!(
            "  robot tokens   {} (robot `{DEFAULT_ROBOT}`; keep it private)",
            path.display()
        ),
        None => println!(
            "  robot tokens   {} robots from the config (token hashes)",
            config.robots.len()
        ),
    }
    println!(
        "  connect with   kairos robot --server {} --data-dir {}",
        server.local_addr,
        data_dir.display()
    );
    if config.workers.enabled {
        let local: u32 = config.engines.iter().map(|e| e.instances).sum();
        println!(
            "  workers        kairos worker --server {} --data-dir {} (ALPN kairos-worker/1; token {}){}",
            server.local_addr,
            data_dir.display(),
            kairos_server::data_dir::DataDir::new(data_dir)
                .worker_token()
                .display(),
            if local == 0 && !config.engines.is_empty() {
                "; no local engine: rounds wait for a worker"
            } else {
                ""
            }
        );
    }
}

#[cfg(test)]
mod tests {
    use kairos_server::config::PluginConfig;

    use super::*;

    #[test]
    fn arguments_override_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("kairos.toml");
        std::fs::write(&file, "listen = \"127.0.0.1:5000\"\ndata_dir = \"state\"\n").unwrap();
        let from_file = config(&ServeArgs {
            config: Some(file.clone()),
            ..ServeArgs::default()
        })
        .unwrap();
        assert_eq!(from_file.listen.port(), 5000);
        assert_eq!(from_file.data_dir, dir.path().join("state"));
        let overridden = config(&ServeArgs {
            config: Some(file),
            listen: Some("127.0.0.1:6000".parse().unwrap()),
            data_dir: Some(PathBuf::from("/tmp/x")),
            ..ServeArgs::default()
        })
        .unwrap();
        assert_eq!(overridden.listen.port(), 6000);
        assert_eq!(overridden.data_dir, PathBuf::from("/tmp/x"));
        assert_eq!(overridden.openpi.listen, None);
        assert_eq!(overridden.metrics.listen, None);
        let metrics = config(&ServeArgs {
            metrics_listen: Some("0.0.0.0:9464".parse().unwrap()),
            ..ServeArgs::default()
        })
        .unwrap();
        assert_eq!(
            metrics.metrics.listen,
            Some("0.0.0.0:9464".parse().unwrap())
        );
        let openpi = config(&ServeArgs {
            openpi_listen: Some("127.0.0.1:8000".parse().unwrap()),
            ..ServeArgs::default()
        })
        .unwrap();
        assert_eq!(
            openpi.openpi.listen,
            Some("127.0.0.1:8000".parse().unwrap())
        );
        assert_eq!(config(&ServeArgs::default()).unwrap(), Config::default());
        let missing = config(&ServeArgs {
            config: Some(dir.path().join("nope.toml")),
            ..ServeArgs::default()
        })
        .unwrap_err();
        assert!(format!("{missing:#}").contains("nope.toml"), "{missing:#}");
    }

    #[test]
    fn plugin_flags_register_the_plugin_and_select_it() {
        let args = ServeArgs {
            horizon_plugin: Some(PathBuf::from("plugins/build/threshold.wasm")),
            horizon_params: Some(parse_params("t=0.3, h_min=6").unwrap()),
            priority_plugin: Some(PathBuf::from("plugins/build/plas.wasm")),
            priority_params: Some("levels=4".into()),
            ..ServeArgs::default()
        };
        let resolved = config(&args).unwrap();
        let names: Vec<String> = resolved.plugins.iter().map(PluginConfig::name).collect();
        assert_eq!(names, ["threshold", "plas"]);
        assert_eq!(resolved.horizon.policy, "threshold");
        assert_eq!(resolved.horizon.params.get("h_min"), Some(&6.0));
        assert_eq!(resolved.scheduler.policy.to_string(), "plas:levels=4");
        assert!(parse_params("t").unwrap_err().contains("key=value"));
        assert!(parse_params("t=x").unwrap_err().contains("not a number"));
        // The same file twice is one name twice: refused with the key.
        let twice = config(&ServeArgs {
            horizon_plugin: Some(PathBuf::from("a/p.wasm")),
            priority_plugin: Some(PathBuf::from("b/p.wasm")),
            ..ServeArgs::default()
        })
        .unwrap_err();
        assert!(format!("{twice:#}").contains("listed twice"), "{twice:#}");
    }

    #[test]
    fn model_and_device_flags_configure_the_one_engine() {
        let dir = tempfile::tempdir().unwrap();
        let one = dir.path().join("one.toml");
        std::fs::write(
            &one,
            "[[engine]]\nmodel = \"builtin\"\nprofile = \"p.json\"\nthreads = 1\n",
        )
        .unwrap();
        let resolved = config(&ServeArgs {
            config: Some(one),
            model: Some("builtin:smolvla-random".into()),
            device: Some("cuda:1".into()),
            ..ServeArgs::default()
        })
        .unwrap();
        let engine = &resolved.engines[0];
        assert_eq!(engine.model, "builtin:smolvla-random");
        assert_eq!(engine.device, "cuda:1");
        assert_eq!(engine.threads, 1, "the file's other settings stay");
        assert_eq!(engine.profile, None, "a profile is per model and device");

        // No [[engine]] in the file: the flags configure the default engine.
        let resolved = config(&ServeArgs {
            device: Some("cpu".into()),
            ..ServeArgs::default()
        })
        .unwrap();
        assert_eq!(resolved.engines.len(), 1);
        assert_eq!(resolved.engines[0].model, "builtin");

        let bad = config(&ServeArgs {
            device: Some("tpu".into()),
            ..ServeArgs::default()
        })
        .unwrap_err();
        assert!(format!("{bad:#}").contains("engine[0].device"), "{bad:#}");

        let two = dir.path().join("two.toml");
        std::fs::write(&two, "[[engine]]\n[[engine]]\ntier = \"cloud\"\n").unwrap();
        let ambiguous = config(&ServeArgs {
            config: Some(two),
            model: Some("builtin".into()),
            ..ServeArgs::default()
        })
        .unwrap_err();
        assert!(
            format!("{ambiguous:#}").contains("2 [[engine]] tables"),
            "{ambiguous:#}"
        );
    }
}
