//! The SDK's integration tests, one test binary (`cargo test -p kairos-sdk --test it`).
//!
//! Each module was a test binary of its own; one binary instead of several saves a link and a
//! compile of the shared code per module (see "CI time" in docs/BENCHMARKS.md). A new
//! integration test is a new module here, not a new file in `tests/`.

mod client;
mod codec;
mod python_client;
mod runner;
mod support;
