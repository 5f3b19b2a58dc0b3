//! Kairos server: the execution-aware scheduler, horizon policies, plugin host, engine pool,
//! QUIC transport and the `kairos` command line.

pub mod action;
pub mod cli;
pub mod config;
pub mod driver;
pub mod horizon;
pub mod lifecycle;
pub mod plugin;
pub mod pool;
pub mod registry;
pub mod scheduler;
pub mod sim;
pub mod time;
pub mod transport;
pub mod validation;
pub mod workload;
