//! The `kairos` binary.

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
    Demo(Box<kairos_server::demo::DemoArgs>),
    /// Serve robots over QUIC (built-in defaults, or `--config kairos.toml`).
    Serve(Box<kairos_server::cli::serve::ServeArgs>),
    /// Measure a model's latency against batch size and write its engine profile.
    Profile(Box<kairos_server::cli::profile::ProfileArgs>),
    /// Predict one action chunk with a LeRobot SmolVLA checkpoint and print it as JSON.
    Predict(Box<kairos_server::cli::predict::PredictArgs>),
    /// Print the protocol version and build information.
    Info,
    /// Policy plugins: check a component, turn a C core module into one, show the WIT.
    Plugin(kairos_server::cli::plugin::PluginArgs),
    /// Run a fleet of simulated robots against a server.
    Robot(Box<kairos_server::cli::robot::RobotArgs>),
    /// Evaluation tools: simulate workloads, generate traces.
    Bench(kairos_server::cli::bench::BenchArgs),
    /// Serve a scheduler's batches on this machine's engine (a remote engine worker).
    Worker(Box<kairos_server::cli::worker::WorkerArgs>),
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
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
        Command::Demo(args) => kairos_server::cli::demo::run(*args),
        Command::Serve(args) => kairos_server::cli::serve::run(*args),
        Command::Profile(args) => kairos_server::cli::profile::run(*args),
        Command::Predict(args) => kairos_server::cli::predict::run(*args),
        Command::Plugin(args) => kairos_server::cli::plugin::run(args),
        Command::Robot(args) => kairos_server::cli::robot::run(*args),
        Command::Bench(args) => kairos_server::cli::bench::run(args),
        Command::Worker(args) => kairos_server::cli::worker::run(*args),
    }
}
