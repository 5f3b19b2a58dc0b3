//! Kairos SDK: the robot client, the wire protocol, and helpers for policy-plugin authors.

pub mod client;
pub mod protocol;
pub mod robot;
pub mod tls;
pub mod transport;
