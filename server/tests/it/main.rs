//! The server's integration tests, one test binary (`cargo test -p kairos-server --test it`).
//!
//! Each module was a test binary of its own; every binary links wasmtime and Candle, so one
//! binary instead of several saves a link and a compile of the shared code per module (see "CI
//! time" in docs/BENCHMARKS.md). A new integration test is a new module here, not a new file in
//! `tests/`.

mod load_horizon;
mod plugin_common;
mod plugin_containment;
mod plugin_reload;
mod plugin_twins;
