//! Kairos SDK: the wire protocol, the robot client, and the robot-side runner.
//!
//! - [`protocol`]: protocol v1 messages, framing, codec and size limits (`docs/PROTOCOL.md`);
//! - [`client`]: the async client (pinned TLS, rounds with re-fetch, resume after connection
//!   loss), [`blocking`] for synchronous robot loops;
//! - [`robot`]: the paper's `get_obs`/`send_act` shim, the pure [`robot::ChunkExecutor`] and the
//!   runner that executes chunks in real time with asynchronous inference;
//! - [`tls`], [`transport`]: TLS and QUIC settings shared with the server;
//! - [`data_dir`]: the files a local server writes for robots (pin, tokens).
//!
//! The common entry points are re-exported here. The crate has no `unsafe` code, and keeps it so.

#![forbid(unsafe_code)]

pub mod blocking;
pub mod client;
pub mod data_dir;
pub mod protocol;
pub mod robot;
pub mod tls;
pub mod trace;
pub mod transport;

pub use blocking::{BlockingClient, BlockingTask};
pub use client::{
    Client, ClientConfig, ClientError, NoRefetch, ObservationSource, RoundReply, RoundRequest, Task,
};
pub use robot::{
    Alignment, Robot, RobotRunner, RunnerConfig, RunnerEvent, SimulatedRobot, TaskSummary,
};
pub use tls::{Fingerprint, ServerTrust};
