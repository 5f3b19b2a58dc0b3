//! The `kairos` binary: one module per subcommand, each with a `clap::Args` struct and a `run`
//! function that turns the arguments into the libraries' option structs, calls the library
//! (`kairos-server` to serve, `kairos-bench` for the tools, `kairos-engine` to predict) and
//! prints. Nothing here is reused by other code: tests build servers and fleets through the
//! libraries.

mod bench;
mod bench_chunking;
mod bench_horizon;
mod bench_live;
mod demo;
mod plugin;
mod predict;
mod profile;
mod robot;
mod serve;
mod worker;

use clap::{Parser, Subcommand};

/// Kairos: an execution-aware serving system for robot foundation models.
#[derive(Parser, Debug)]
#[command(name = "kairos", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the whole system on built-in defaults: a server with the built-in model and a fleet
    /// of simulated robots over QUIC on loopback, once per scheduler, with a summary and a plot.
    Demo(Box<crate::demo::DemoArgs>),
    /// Serve robots over QUIC (built-in defaults, or `--config kairos.toml`).
    Serve(Box<crate::serve::ServeArgs>),
    /// Measure a model's latency against batch size and write its engine profile.
    Profile(Box<crate::profile::ProfileArgs>),
    /// Predict one action chunk with a LeRobot SmolVLA checkpoint and print it as JSON.
    Predict(Box<crate::predict::PredictArgs>),
    /// Print the protocol version and build information.
    Info,
    /// Policy plugins: check a component, turn a C core module into one, show the WIT.
    Plugin(crate::plugin::PluginArgs),
    /// Run a fleet of simulated robots against a server.
    Robot(Box<crate::robot::RobotArgs>),
    /// Evaluation tools: simulate workloads, generate traces.
    Bench(crate::bench::BenchArgs),
    /// Serve a scheduler's batches on this machine's engine (a remote engine worker).
    Worker(Box<crate::worker::WorkerArgs>),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    pin_candle_threads();
    match cli.command {
        Command::Info => {
            println!("kairos {}", env!("CARGO_PKG_VERSION"));
            println!(
                "protocol v{} (ALPN {})",
                kairos_sdk::protocol::PROTOCOL_VERSION,
                String::from_utf8_lossy(kairos_sdk::protocol::ALPN)
            );
            Ok(())
        }
        Command::Demo(args) => crate::demo::run(*args),
        Command::Serve(args) => crate::serve::run(*args),
        Command::Profile(args) => crate::profile::run(*args),
        Command::Predict(args) => crate::predict::run(*args),
        Command::Plugin(args) => crate::plugin::run(args),
        Command::Robot(args) => crate::robot::run(*args),
        Command::Bench(args) => crate::bench::run(args),
        Command::Worker(args) => crate::worker::run(*args),
    }
}

/// Sets Candle's thread count once, to the value Candle itself would choose, unless the user
/// set it ([`kairos_engine::options::candle_cpu_threads`] says why: Candle otherwise works the
/// count out from sysfs on every CPU matmul).
fn pin_candle_threads() {
    let var = kairos_engine::options::CANDLE_THREADS_VAR;
    if std::env::var_os(var).is_some() {
        return;
    }
    let threads = kairos_engine::options::candle_cpu_threads();
    // SAFETY: `main` calls this right after parsing the arguments, before it starts any thread
    // (clap starts none), so no other thread reads or writes the environment meanwhile.
    unsafe { std::env::set_var(var, threads.to_string()) };
}

/// A policy parameter on the command line, `name=value` with a numeric value (`inf` is one).
fn parse_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = text
        .split_once('=')
        .ok_or_else(|| format!("`{text}` is not key=value"))?;
    let name = name.trim();
    if name.is_empty() {
        return Err(format!("`{text}` has an empty name"));
    }
    let value: f64 = value
        .trim()
        .parse()
        .map_err(|_| format!("{name}: `{value}` is not a number"))?;
    Ok((name.to_owned(), value))
}

/// [`parse_param`], with a finite value.
fn parse_finite_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = parse_param(text)?;
    if !value.is_finite() {
        return Err(format!("{name}: `{text}` must have a finite value"));
    }
    Ok((name, value))
}

/// Logs to stderr (stdout stays free for a command's output), at `RUST_LOG`'s filter or else
/// `default_filter`. A second call is a no-op, so tests may run several commands in one process.
fn init_logging(default_filter: &str) {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter)),
        )
        .with_writer(std::io::stderr)
        .try_init();
}
