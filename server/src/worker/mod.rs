//! Remote engine workers: the worker protocol (`kairos-worker/1`,
//! `kairos_sdk::protocol::worker`; docs/PROTOCOL.md §16) from both of its ends.
//!
//! - [`client`]: `kairos worker`'s side. It dials the scheduler, registers, runs the batches it
//!   is sent on a local engine instance and heartbeats ([`run`]).
//! - [`registration`]: the scheduler's side of a worker connection. `Register` is checked and
//!   the worker joins the pool; then its heartbeats are watched until it drains, goes silent or
//!   is removed.
//! - [`remote`]: the scheduler's side of a worker's batches: [`RemoteEngine`], one engine
//!   instance of the pool (`crate::pool::EngineInstance`) whose batches are QUIC streams.
//! - [`removal`]: how the scheduler removes a worker, once, counted by reason.
//! - [`readmission`]: how long a worker removed for unusable answers is refused registration.
//! - [`wire`]: the conversions between the engine's types and their wire forms, used by both
//!   ends, with the checks that make a worker's messages safe to use.
//!
//! A worker holds the worker token, but what it sends is untrusted input, like a robot's: every
//! message is checked (the protocol's rules, then the batch's counts, shapes and values) before
//! the scheduler computes with it or a robot sees any of it, and a worker that breaks a rule
//! is refused or removed, its batch run again elsewhere.

pub mod client;
pub mod readmission;
pub mod registration;
pub mod remote;
pub mod removal;
pub mod wire;

pub use client::{
    CONNECT_TIMEOUT, RECONNECT_FIRST, RECONNECT_MAX, WorkerError, WorkerOptions, WorkerReport,
    reconnect_delay, run,
};
pub use remote::RemoteEngine;
