//! The engine's integration tests, one test binary (`cargo test -p kairos-engine --test it`).
//!
//! Each module was a test binary of its own; every binary links Candle, so one binary instead of
//! several saves a link and a compile of the shared code per module (see "CI time" in
//! docs/BENCHMARKS.md). A new integration test is a new module here, not a new file in `tests/`.

mod examples_help;
mod loader_errors;
mod models;
mod pi_fast;
mod pi_parity;
mod pi_pipeline;
mod pi_rtc;
mod smolvla_bf16;
mod smolvla_fixture;
mod smolvla_goldens;
mod smolvla_loading;
mod smolvla_parity;
mod smolvla_processors;
mod smolvla_random_checkpoint;
mod smolvla_rtc;
mod smolvla_vlm;
mod vjp_check;
