//! Cross-crate test support: a server started in-process with simulated robots
//! ([`harness`]), a UDP impairment proxy for lossy links and added delay ([`proxy`]), a network
//! namespace joined by a veth pair for traffic that must cross a real interface ([`netns`]),
//! a small flow model ([`model`]) so the tests measure the server rather than a network's
//! forward pass, and remote workers, well-behaved or hand-driven ([`workers`]).

pub mod harness;
pub mod model;
pub mod netns;
pub mod plugins;
pub mod proxy;
pub mod workers;
