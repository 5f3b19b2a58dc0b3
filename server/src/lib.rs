//! Kairos server: the execution-aware scheduler, horizon policies, plugin host, engine pool,
//! QUIC transport and the `kairos` command line.

pub mod cli;
pub mod horizon;
pub mod lifecycle;
pub mod plugin;
pub mod scheduler;
pub mod time;
