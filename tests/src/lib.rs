//! Cross-crate test support: a server started in-process with simulated robots
//! ([`harness`]), a UDP impairment proxy for lossy links and added delay ([`proxy`]), a network
//! namespace joined by a veth pair for traffic that must cross a real interface ([`netns`]),
//! a raw openpi client for probing the websocket endpoint byte by byte ([`openpi_wire`]), a
//! small flow model ([`model`]) so the tests measure the server rather than a network's forward
//! pass, and remote workers, well-behaved or hand-driven ([`workers`]); and the mixed soak's
//! hostile parties: attacks on the listeners ([`attacks`]) and a worker that answers unusably
//! ([`hostile_worker`]).

pub mod attacks;
pub mod harness;
pub mod hostile_worker;
pub mod model;
pub mod netns;
pub mod openpi_wire;
pub mod plugins;
pub mod proxy;
pub mod workers;
