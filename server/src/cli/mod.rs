//! The `kairos` command line: one module per subcommand, each with a `clap::Args` struct and a
//! `run` function. `main.rs` only parses and dispatches.
pub mod plugin;
pub mod robot;
