//! Kairos SDK.
