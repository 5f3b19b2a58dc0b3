//! The `kairos` command line: one module per subcommand, each with a `clap::Args` struct and a
//! `run` function. `main.rs` only parses and dispatches.
pub mod bench;
pub mod bench_live;
pub mod demo;
pub mod plugin;
pub mod profile;
pub mod robot;
pub mod serve;
