//! The `kairos` binary.

use clap::{Parser, Subcommand};

/// Kairos: an execution-aware serving system for robot foundation models.
#[derive(Parser, Debug)]
#[command(name = "kairos", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the protocol version and build information.
    Info,
    /// Policy plugins: check a component, turn a C core module into one, show the WIT.
    Plugin(kairos_server::cli::plugin::PluginArgs),
    /// Run a fleet of simulated robots against a server.
    Robot(kairos_server::cli::robot::RobotArgs),
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
        Command::Plugin(args) => kairos_server::cli::plugin::run(args),
        Command::Robot(args) => kairos_server::cli::robot::run(args),
    }
}
