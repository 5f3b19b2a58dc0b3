//! Kairos's evaluation tools, apart from the serving library (as TGI keeps its benchmark apart
//! from its router):
//! - [`sim`]: the virtual-time simulator, which drives the same scheduler, batching, placement
//!   and horizon code as the server (`kairos-core`), and its experiments; [`workload`]: the
//!   paper's workloads turned into traces;
//! - [`horizon_bench`]: the closed-loop control task that judges horizon policies by task
//!   success, with its small flow-matching policy (trained here, served through the model scheme
//!   it registers, `horizon-flow:DIR`); [`chunking_bench`]: the same tasks with a delay between
//!   an observation and its chunk, judging the server's chunking strategies;
//! - [`live_replay`]: traces replayed over real QUIC against a real server;
//! - [`fleet`]: fleets of simulated robots against a server;
//! - [`demo`]: the README's first command; [`plot`]: PNG and SVG plots of the results.
//!
//! Serving (`kairos-server`) never depends on this crate; the `kairos` binary (`kairos-cli`)
//! does, for `kairos bench`, `kairos demo` and `kairos robot`.

pub mod chunking_bench;
pub mod demo;
pub mod fleet;
pub mod horizon_bench;
pub mod live_replay;
pub mod plot;
pub mod sim;
pub mod workload;
