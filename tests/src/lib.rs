//! Cross-crate test support: a server started in-process with simulated robots
//! ([`harness`]), a UDP impairment proxy for lossy links ([`proxy`]), and a small flow model
//! ([`model`]) so the tests measure the server rather than a network's forward pass.

pub mod harness;
pub mod model;
pub mod proxy;
