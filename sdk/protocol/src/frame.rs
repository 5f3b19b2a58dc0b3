//! Framing, sans-IO: `kind: u8 | length: u32 big-endian | body`.
//!
//! [`Frame::check`] and [`Frame::parse`] work on a `Cursor<&[u8]>` the way mini-redis's frame
//! parser does: a caller that buffers a byte stream calls `parse` and, on
//! [`FrameError::Truncated`], reads more bytes and tries again. The header is checked before the
//! body is touched, so a peer announcing a 4 GiB frame costs nothing but the 5-byte header.

use std::io::Cursor;

use bytes::Bytes;

use super::messages::MessageKind;

/// Bytes of the frame header: the kind byte and the 4-byte body length.
pub const HEADER_LEN: usize = 5;

/// One frame: its kind and its undecoded body.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frame {
    /// What the body holds.
    pub kind: MessageKind,
    /// The MessagePack body.
    pub body: Bytes,
}

/// Why bytes are not a frame (or a frame is not a message).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The bytes end before the frame does. `needed` is the whole frame's length, header
    /// included, as far as it is known (5 while the header itself is incomplete).
    #[error("truncated frame: {needed} bytes needed, {available} available")]
    Truncated {
        /// Bytes the frame needs.
        needed: usize,
        /// Bytes there were.
        available: usize,
    },
    /// The kind byte names no message of protocol v1.
    #[error("unknown frame kind 0x{0:02x}")]
    UnknownKind(u8),
    /// The header announces a body longer than the receiver accepts.
    #[error("frame body of {len} bytes exceeds the limit of {max}")]
    FrameTooLarge {
        /// Announced body length.
        len: u32,
        /// The receiver's limit.
        max: u32,
    },
    /// The body is not a valid encoding of the message its kind names.
    #[error("malformed {kind} body: {reason}")]
    Malformed {
        /// The frame's kind.
        kind: MessageKind,
        /// What the decoder found.
        reason: String,
    },
}

impl FrameError {
    /// The wire error code to answer with: `too_large` for an oversized frame, `bad_frame`
    /// otherwise.
    pub fn code(&self) -> super::ErrorCode {
        match self {
            FrameError::FrameTooLarge { .. } => super::ErrorCode::TooLarge,
            _ => super::ErrorCode::BadFrame,
        }
    }
}

impl From<&FrameError> for super::ErrorReply {
    fn from(error: &FrameError) -> super::ErrorReply {
        super::ErrorReply::new(error.code(), error.to_string())
    }
}

/// Decodes a frame header: the kind must be known and the body length at most `max_body`.
pub fn parse_header(
    header: [u8; HEADER_LEN],
    max_body: u32,
) -> Result<(MessageKind, u32), FrameError> {
    let kind = MessageKind::from_byte(header[0]).ok_or(FrameError::UnknownKind(header[0]))?;
    let len = u32::from_be_bytes([header[1], header[2], header[3], header[4]]);
    if len > max_body {
        return Err(FrameError::FrameTooLarge { len, max: max_body });
    }
    Ok((kind, len))
}

/// The 5-byte header of a frame of `kind` with a body of `body_len` bytes.
pub fn encode_header(kind: MessageKind, body_len: u32) -> [u8; HEADER_LEN] {
    let len = body_len.to_be_bytes();
    [kind as u8, len[0], len[1], len[2], len[3]]
}

impl Frame {
    /// Checks that a whole frame starts at the cursor's position and advances past it, without
    /// copying the body. On error the cursor position is unspecified; reset it before retrying.
    pub fn check(src: &mut Cursor<&[u8]>, max_body: u32) -> Result<MessageKind, FrameError> {
        let (kind, len) = Self::header_at(src, max_body)?;
        let start = src.position() as usize;
        let available = src.get_ref().len().saturating_sub(start);
        if available < len as usize {
            return Err(FrameError::Truncated {
                needed: HEADER_LEN + len as usize,
                available: HEADER_LEN + available,
            });
        }
        src.set_position((start + len as usize) as u64);
        Ok(kind)
    }

    /// Parses the frame at the cursor's position and advances past it.
    pub fn parse(src: &mut Cursor<&[u8]>, max_body: u32) -> Result<Frame, FrameError> {
        let start = src.position() as usize;
        let kind = Self::check(src, max_body)?;
        let end = src.position() as usize;
        let body = Bytes::copy_from_slice(&src.get_ref()[start + HEADER_LEN..end]);
        Ok(Frame { kind, body })
    }

    fn header_at(src: &mut Cursor<&[u8]>, max_body: u32) -> Result<(MessageKind, u32), FrameError> {
        let start = src.position() as usize;
        let rest = src.get_ref().get(start..).unwrap_or_default();
        let Some(header) = rest.first_chunk::<HEADER_LEN>() else {
            return Err(FrameError::Truncated {
                needed: HEADER_LEN,
                available: rest.len(),
            });
        };
        let parsed = parse_header(*header, max_body)?;
        src.set_position((start + HEADER_LEN) as u64);
        Ok(parsed)
    }

    /// Header and body as one buffer, ready to write.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_LEN + self.body.len());
        // A `Frame` is built by `parse` or `Message::encode`, both of which bound the body by a
        // u32 length.
        let len = u32::try_from(self.body.len()).unwrap_or(u32::MAX);
        out.extend_from_slice(&encode_header(self.kind, len));
        out.extend_from_slice(&self.body);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_checks_kind_before_length() {
        assert_eq!(
            parse_header([0x55, 0xff, 0xff, 0xff, 0xff], 10),
            Err(FrameError::UnknownKind(0x55))
        );
        assert_eq!(
            parse_header([0x10, 0, 0, 1, 0], 255),
            Err(FrameError::FrameTooLarge { len: 256, max: 255 })
        );
        assert_eq!(
            parse_header([0x10, 0, 0, 0, 255], 255),
            Ok((MessageKind::Submit, 255))
        );
    }

    #[test]
    fn parse_consumes_exactly_one_frame() {
        let mut bytes = encode_header(MessageKind::Welcome, 2).to_vec();
        bytes.extend_from_slice(&[0x80, 0x80]);
        bytes.extend_from_slice(&encode_header(MessageKind::Reply, 0));
        let mut cursor = Cursor::new(&bytes[..]);
        let first = Frame::parse(&mut cursor, 100).unwrap();
        assert_eq!(first.kind, MessageKind::Welcome);
        assert_eq!(&first.body[..], &[0x80, 0x80]);
        assert_eq!(cursor.position(), 7);
        let second = Frame::parse(&mut cursor, 100).unwrap();
        assert_eq!(second.kind, MessageKind::Reply);
        assert!(second.body.is_empty());
        assert_eq!(
            Frame::parse(&mut cursor, 100),
            Err(FrameError::Truncated {
                needed: 5,
                available: 0
            })
        );
    }

    #[test]
    fn announced_length_beyond_the_data_is_truncated() {
        let mut bytes = encode_header(MessageKind::Submit, 10).to_vec();
        bytes.extend_from_slice(&[0; 4]);
        assert_eq!(
            Frame::check(&mut Cursor::new(&bytes[..]), 100),
            Err(FrameError::Truncated {
                needed: 15,
                available: 9
            })
        );
    }
}
