//! Kairos server: the I/O shell around the pure core (`kairos-core`). The QUIC endpoint for
//! robots and workers (`transport`), the openpi-compatible websocket endpoint (`openpi`), request
//! validation (`validation`), the driver's shell that runs the core on a thread of its own
//! (`driver`), the engine pool (`pool`), remote engine workers from both ends (`worker`), the
//! WASM plugin host (`plugin`), configuration and the data directory (`config`, `data_dir`),
//! metrics and readiness (`metrics`), and the parsers strangers feed, as fuzz targets
//! (`fuzz_targets`).
//!
//! Tools that drive servers (the simulator, fleets, the demo, benchmarks) live in `kairos-bench`;
//! the `kairos` command line lives in `kairos-cli`. Neither is a dependency of this crate.

pub mod clock;
pub mod config;
pub mod credentials;
pub mod data_dir;
pub mod driver;
pub mod fuzz_targets;
pub mod metrics;
pub mod openpi;
pub mod plugin;
pub mod pool;
pub mod transport;
pub mod validation;
pub mod worker;
