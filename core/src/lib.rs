//! The pure logic of Kairos: what the server decides, without the server.
//!
//! - [`scheduler`]: the pending queue, the priority policies (FIFO, PLAS, Algorithm 1, SRW),
//!   placement on edge and cloud engines, batching from engine profiles;
//! - [`lifecycle`]: per-task generation and execution history and the paper's wait rule;
//! - [`horizon`]: horizon policies, which decide how many actions of a chunk a robot executes;
//! - [`action`]: the action manager, the return path that applies a round's horizon policy
//!   with its native fallback and builds the reply;
//! - [`chunking`]: each round's predicted delay `d` and its chunking strategy (what the server
//!   does about the actions a robot executes while its round is in flight);
//! - [`registry`]: name → factory registries of horizon and priority policies (native and
//!   plugin alike);
//! - [`driver`]: the driver's sans-IO state machine around the scheduler, events with `now` in,
//!   effects out, and the statistics it reports as data;
//! - [`round`], [`clock_map`], [`error`]: validated rounds, robot clocks on the server clock,
//!   and the failures the core decides itself with their wire codes;
//! - [`time`], [`stats`], [`sync`]: timestamps, the one percentile definition, and the one way
//!   to take a shared lock.
//!
//! Nothing here reads a clock, touches a socket or needs an async runtime: the live server
//! (`kairos-server`) drives this code from its shell, and the simulator (`kairos-bench`) drives
//! the same code in virtual time. Cargo enforces it: this crate's dependencies are the wire
//! protocol's types, the engine's data types, serde, thiserror and tracing.

pub mod action;
pub mod chunking;
pub mod clock_map;
pub mod driver;
pub mod error;
pub mod horizon;
pub mod lifecycle;
pub mod registry;
pub mod round;
pub mod scheduler;
pub mod stats;
pub mod sync;
pub mod time;
