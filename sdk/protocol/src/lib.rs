//! The Kairos wire protocol, version 1 (normative text: `docs/PROTOCOL.md`).
//!
//! Shared by the robot client and the server. Transport: QUIC (TLS 1.3, ALPN `kairos/1`).
//! A connection starts with a `Hello`/`Welcome` exchange on the first bidirectional stream; then
//! every round is its own bidirectional stream opened by the client: `Submit`, zero or more
//! `FetchObservation`/`FreshObservation` exchanges, then exactly one `Reply` or `Error`.
//! Every message is one frame: `kind: u8 | length: u32 big-endian | body`, where body is a
//! MessagePack map with string keys (see `messages`).
//!
//! The layers, each usable alone:
//! - [`frame`]: bytes ↔ [`Frame`] (sans-IO, `Cursor`-based, never panics);
//! - [`codec`]: [`Frame`] ↔ [`Message`] (MessagePack, strict envelope);
//! - [`limits`]: [`Limits`] and [`Validate`], the size checks on every field;
//!
//! Reading and writing frames on quinn streams is `kairos_sdk::protocol::io`: this crate does no
//! I/O, so the pure core (`kairos-core`) and fuzz targets use it without a runtime.

pub mod codec;
pub mod frame;
pub mod limits;
pub mod messages;
mod strict;
mod tensor;
pub mod worker;

pub use codec::{EncodeError, MAX_DEPTH, Message, WireBody, encode_body};
pub use frame::{Frame, FrameError, HEADER_LEN};
pub use limits::{Limits, MAX_ROUND, Validate, ValidationError, check_raw_image};
pub use messages::*;
pub use tensor::TensorError;

/// Protocol version spoken by this crate.
pub const PROTOCOL_VERSION: u32 = 1;

/// ALPN identifier of protocol version 1.
pub const ALPN: &[u8] = b"kairos/1";
