//! The cross-crate tests, one test binary (`cargo test -p kairos-tests --test it`; one module:
//! `cargo test -p kairos-tests --test it e2e::`).
//!
//! Each module was a test binary of its own; every binary links the whole server (wasmtime,
//! Candle, quinn), so one binary instead of eight saves a link and a compile of the shared code
//! per module (see "CI time" in docs/BENCHMARKS.md). A new cross-crate test is a new module
//! here, not a new file in `tests/`.

mod admission;
mod attackers;
mod auth;
mod binaries;
mod boundaries;
mod chunking;
mod dead_driver;
mod demo;
mod e2e;
mod fuzz_replay;
mod hostile_workers;
mod isolation;
mod lossy;
mod malformed;
mod metrics;
mod metrics_listener;
mod openpi;
mod openpi_guards;
mod plugins_served;
mod replay_horizon;
mod sim_runner_agreement;
mod sim_vs_live;
mod smolvla_served;
mod tenants;
mod uploads;
mod workers;
