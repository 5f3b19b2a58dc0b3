//! The `kairos` binary as users run it: one test binary (`cargo test -p kairos-cli --test it`).
//! A new test of the command line is a new module here, not a new file in `tests/`.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

mod bench_horizon;
mod bench_live_plugins;
mod bench_plugins;
mod bench_scale;
mod browser;
mod deploy;
mod fleet_page;
mod live_fleet;
mod openpi_pi05;
mod predict;
mod prometheus;
mod worker_processes;

pub use kairos_tests::plugins::repo_root;
