//! The Kairos wire protocol, version 1 (normative text: `docs/PROTOCOL.md`): the sans-IO
//! messages, framing, codec and limits of the `kairos-protocol` crate, re-exported, plus [`io`],
//! reading and writing frames on quinn streams.

pub mod io;

pub use io::{
    MinRate, ReadBounds, ReadFrameError, TooSlow, WriteFrameError, read_frame, read_frame_bounded,
    read_message, read_message_bounded, write_body, write_frame, write_message,
};
pub use kairos_protocol::*;
