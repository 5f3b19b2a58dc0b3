//! Kairos server: the execution-aware scheduler, horizon policies, plugin host, engine pool,
//! QUIC transport, the harnesses that drive fleets of robots against it (`fleet`, `demo`,
//! `live_replay`), and the `kairos` command line (`cli`, which only parses and prints).

pub mod action;
pub mod cli;
pub mod config;
pub mod data_dir;
pub mod demo;
pub mod driver;
pub mod fleet;
pub mod fuzz_targets;
pub mod horizon;
pub mod horizon_bench;
pub mod lifecycle;
pub mod live_replay;
pub mod metrics;
pub mod openpi;
pub mod plot;
pub mod plugin;
pub mod pool;
pub mod registry;
pub mod scheduler;
pub mod sim;
pub mod stats;
pub mod time;
pub mod transport;
pub mod validation;
pub mod worker;
pub mod workload;
