//! Kairos server.

pub mod time;
