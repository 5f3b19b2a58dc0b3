//! Messages to frames and back.
//!
//! Encoding is `rmp_serde::to_vec_named`: every struct is a MessagePack map keyed by field name.
//! Decoding is strict about the envelope and lenient about content: the body must be exactly one
//! MessagePack map (no trailing bytes, nesting at most [`MAX_DEPTH`], every map key a `str`),
//! unknown keys are ignored so a newer peer can add optional fields, enumerations are names only
//! (`strict::name`), and numbers decode into the field's type when they fit (an
//! integer where a float is expected, a float64 where a float32 is expected), so clients in
//! languages without a float32 type work unchanged.

use bytes::Bytes;
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::frame::{Frame, FrameError, HEADER_LEN, encode_header};
use super::messages::{
    EndTask, ErrorReply, FetchObservation, FreshObservation, Hello, MessageKind, Reply, Submit,
    TaskEnded, Welcome,
};

/// Deepest MessagePack nesting a body may have. Protocol v1 messages nest at most 6 deep; the
/// bound keeps a hostile body from recursing the decoder off its stack.
pub const MAX_DEPTH: usize = 32;

/// Any protocol v1 message.
#[derive(Clone, Debug, PartialEq)]
#[allow(clippy::large_enum_variant)] // messages are built, sent, and dropped; never stored in bulk
pub enum Message {
    /// C→S, first message of a connection.
    Hello(Hello),
    /// S→C, answer to `Hello`.
    Welcome(Welcome),
    /// C→S, opens a round.
    Submit(Submit),
    /// S→C, asks for a fresher observation.
    FetchObservation(FetchObservation),
    /// C→S, the fresher observation.
    FreshObservation(FreshObservation),
    /// S→C, the round's actions.
    Reply(Reply),
    /// C→S, ends a task.
    EndTask(EndTask),
    /// S→C, the ended task's record.
    TaskEnded(TaskEnded),
    /// S→C, the request on this stream failed.
    Error(ErrorReply),
}

/// A message that cannot be encoded.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// MessagePack serialisation failed.
    #[error("cannot encode {kind}: {source}")]
    Serialize {
        /// The message's kind.
        kind: MessageKind,
        /// The serialiser's error.
        source: rmp_serde::encode::Error,
    },
    /// The body is longer than the limit (the sender's copy of the receiver's `max_frame`).
    #[error("{kind} body of {len} bytes exceeds the frame limit of {max}")]
    TooLarge {
        /// The message's kind.
        kind: MessageKind,
        /// Body length.
        len: usize,
        /// The limit.
        max: u32,
    },
}

impl Message {
    /// The frame kind this message travels as.
    pub fn kind(&self) -> MessageKind {
        match self {
            Message::Hello(_) => MessageKind::Hello,
            Message::Welcome(_) => MessageKind::Welcome,
            Message::Submit(_) => MessageKind::Submit,
            Message::FetchObservation(_) => MessageKind::FetchObservation,
            Message::FreshObservation(_) => MessageKind::FreshObservation,
            Message::Reply(_) => MessageKind::Reply,
            Message::EndTask(_) => MessageKind::EndTask,
            Message::TaskEnded(_) => MessageKind::TaskEnded,
            Message::Error(_) => MessageKind::Error,
        }
    }

    /// The whole frame, header included, if the body is at most `max_body` bytes.
    pub fn encode(&self, max_body: u32) -> Result<Vec<u8>, EncodeError> {
        match self {
            Message::Hello(m) => encode_body(m, max_body),
            Message::Welcome(m) => encode_body(m, max_body),
            Message::Submit(m) => encode_body(m, max_body),
            Message::FetchObservation(m) => encode_body(m, max_body),
            Message::FreshObservation(m) => encode_body(m, max_body),
            Message::Reply(m) => encode_body(m, max_body),
            Message::EndTask(m) => encode_body(m, max_body),
            Message::TaskEnded(m) => encode_body(m, max_body),
            Message::Error(m) => encode_body(m, max_body),
        }
    }

    /// The message as a [`Frame`] (header not materialised).
    pub fn to_frame(&self, max_body: u32) -> Result<Frame, EncodeError> {
        let mut bytes = self.encode(max_body)?;
        let body = bytes.split_off(HEADER_LEN);
        Ok(Frame {
            kind: self.kind(),
            body: Bytes::from(body),
        })
    }

    /// Decodes a frame's body as the message its kind names.
    pub fn decode(frame: &Frame) -> Result<Message, FrameError> {
        let kind = frame.kind;
        let body = &frame.body[..];
        Ok(match kind {
            MessageKind::Hello => Message::Hello(decode_body(kind, body)?),
            MessageKind::Welcome => Message::Welcome(decode_body(kind, body)?),
            MessageKind::Submit => Message::Submit(decode_body(kind, body)?),
            MessageKind::FetchObservation => Message::FetchObservation(decode_body(kind, body)?),
            MessageKind::FreshObservation => Message::FreshObservation(decode_body(kind, body)?),
            MessageKind::Reply => Message::Reply(decode_body(kind, body)?),
            MessageKind::EndTask => Message::EndTask(decode_body(kind, body)?),
            MessageKind::TaskEnded => Message::TaskEnded(decode_body(kind, body)?),
            MessageKind::Error => Message::Error(decode_body(kind, body)?),
            MessageKind::Register
            | MessageKind::Registered
            | MessageKind::Refused
            | MessageKind::Heartbeat
            | MessageKind::Drain
            | MessageKind::RunBatch
            | MessageKind::Chunks => {
                return Err(FrameError::Malformed {
                    kind,
                    reason: "a worker-protocol message on a robot stream".into(),
                });
            }
        })
    }

    /// Parses and decodes the first frame of `bytes`; returns the message and the bytes it used.
    pub fn decode_from(bytes: &[u8], max_body: u32) -> Result<(Message, usize), FrameError> {
        let mut cursor = std::io::Cursor::new(bytes);
        let frame = Frame::parse(&mut cursor, max_body)?;
        Ok((Message::decode(&frame)?, cursor.position() as usize))
    }
}

/// A message body type and the frame kind it travels as.
pub trait WireBody: Serialize + DeserializeOwned {
    /// The frame kind.
    const KIND: MessageKind;
}

macro_rules! wire_body {
    ($($variant:ident => $body:ident),*) => {$(
        impl WireBody for $body {
            const KIND: MessageKind = MessageKind::$variant;
        }

        impl From<$body> for Message {
            fn from(message: $body) -> Message {
                Message::$variant(message)
            }
        }
    )*};
}
wire_body!(
    Hello => Hello,
    Welcome => Welcome,
    Submit => Submit,
    FetchObservation => FetchObservation,
    FreshObservation => FreshObservation,
    Reply => Reply,
    EndTask => EndTask,
    TaskEnded => TaskEnded,
    Error => ErrorReply
);

/// One body as a whole frame, header included, without building a [`Message`] (so no copy of
/// the body's images).
pub fn encode_body<T: WireBody>(body: &T, max_body: u32) -> Result<Vec<u8>, EncodeError> {
    let kind = T::KIND;
    let mut out = vec![0u8; HEADER_LEN];
    rmp_serde::encode::write_named(&mut out, body)
        .map_err(|source| EncodeError::Serialize { kind, source })?;
    let len = out.len() - HEADER_LEN;
    let too_large = || EncodeError::TooLarge {
        kind,
        len,
        max: max_body,
    };
    let body_len = u32::try_from(len)
        .ok()
        .filter(|&body_len| body_len <= max_body)
        .ok_or_else(too_large)?;
    out[..HEADER_LEN].copy_from_slice(&encode_header(kind, body_len));
    Ok(out)
}

/// Decodes one message body: exactly one MessagePack map, at most [`MAX_DEPTH`] deep.
pub fn decode_body<T: DeserializeOwned>(kind: MessageKind, body: &[u8]) -> Result<T, FrameError> {
    let malformed = |reason: String| FrameError::Malformed { kind, reason };
    match body.first() {
        Some(0x80..=0x8f | 0xde | 0xdf) => {}
        Some(marker) => {
            return Err(malformed(format!(
                "the body must be a MessagePack map, it starts with 0x{marker:02x}"
            )));
        }
        None => return Err(malformed("empty body".to_owned())),
    }
    let len = msgpack_value_len(body).map_err(|reason| malformed(reason.to_owned()))?;
    if len != body.len() {
        return Err(malformed(format!(
            "{} bytes after the body's map",
            body.len() - len
        )));
    }
    let mut deserializer = rmp_serde::Deserializer::from_read_ref(body);
    deserializer.set_max_depth(MAX_DEPTH);
    T::deserialize(&mut deserializer).map_err(|error| malformed(error.to_string()))
}

/// Length in bytes of the MessagePack value at the start of `buf`, checking on the way that every
/// map key is a MessagePack `str` (docs/PROTOCOL.md §4: bodies are maps with string keys; serde
/// would otherwise read an integer key as a field's index and a `bin` key as its name) and that
/// containers nest at most [`MAX_DEPTH`] deep.
///
/// Iterative (no recursion, whatever the nesting) and linear in the bytes it walks; string, binary
/// and extension payloads are skipped by their announced length, never copied.
pub fn msgpack_value_len(buf: &[u8]) -> Result<usize, &'static str> {
    const ENDS_INSIDE: &str = "the body ends inside a MessagePack value";
    /// A container being walked: values left in it, and whether it is a map (whose values at
    /// even counts left are keys).
    struct Open {
        left: u64,
        map: bool,
    }
    let mut pos = 0usize;
    let mut stack: Vec<Open> = Vec::new();
    // Values still to walk. Every value takes at least one byte, so more pending values than
    // bytes left can only be a lie about a container's size.
    let mut pending: u64 = 1;
    loop {
        let is_key = match stack.last_mut() {
            Some(open) => {
                let key = open.map && open.left % 2 == 0;
                open.left -= 1;
                key
            }
            None => false,
        };
        pending -= 1;
        let marker = *buf.get(pos).ok_or(ENDS_INSIDE)?;
        if is_key && !matches!(marker, 0xa0..=0xbf | 0xd9 | 0xda | 0xdb) {
            return Err("a map key is not a str: expected a MessagePack str");
        }
        pos += 1;
        let read_len = |at: usize, width: usize| -> Result<u64, &'static str> {
            let bytes = buf.get(at..at + width).ok_or(ENDS_INSIDE)?;
            Ok(bytes.iter().fold(0u64, |acc, &b| (acc << 8) | u64::from(b)))
        };
        // (payload bytes to skip after the length field, values contained)
        let (skip, items): (u64, u64) = match marker {
            0x00..=0x7f | 0xe0..=0xff | 0xc0 | 0xc2 | 0xc3 => (0, 0),
            0x80..=0x8f => (0, 2 * u64::from(marker & 0x0f)),
            0x90..=0x9f => (0, u64::from(marker & 0x0f)),
            0xa0..=0xbf => (u64::from(marker & 0x1f), 0),
            0xc1 => return Err("the reserved MessagePack marker 0xc1"),
            // bin 8/16/32, str 8/16/32
            0xc4 | 0xd9 => (read_len(pos, 1)? + 1, 0),
            0xc5 | 0xda => (read_len(pos, 2)? + 2, 0),
            0xc6 | 0xdb => (read_len(pos, 4)? + 4, 0),
            // ext 8/16/32: length, then a type byte, then the payload
            0xc7 => (read_len(pos, 1)? + 2, 0),
            0xc8 => (read_len(pos, 2)? + 3, 0),
            0xc9 => (read_len(pos, 4)? + 5, 0),
            0xca => (4, 0),
            0xcb => (8, 0),
            0xcc | 0xd0 => (1, 0),
            0xcd | 0xd1 => (2, 0),
            0xce | 0xd2 => (4, 0),
            0xcf | 0xd3 => (8, 0),
            // fixext 1/2/4/8/16: a type byte, then the payload
            0xd4 => (2, 0),
            0xd5 => (3, 0),
            0xd6 => (5, 0),
            0xd7 => (9, 0),
            0xd8 => (17, 0),
            0xdc => (2, read_len(pos, 2)?),
            0xdd => (4, read_len(pos, 4)?),
            0xde => (2, 2 * read_len(pos, 2)?),
            0xdf => (4, 2 * read_len(pos, 4)?),
        };
        let end = (pos as u64)
            .checked_add(skip)
            .filter(|&end| end <= buf.len() as u64)
            .ok_or(ENDS_INSIDE)?;
        pos = end as usize;
        pending += items;
        if pending > (buf.len() - pos) as u64 {
            return Err(ENDS_INSIDE);
        }
        if items > 0 {
            if stack.len() == MAX_DEPTH {
                return Err("MessagePack nesting deeper than 32 levels");
            }
            stack.push(Open {
                left: items,
                map: matches!(marker, 0x80..=0x8f | 0xde | 0xdf),
            });
        }
        while stack.last().is_some_and(|open| open.left == 0) {
            stack.pop();
        }
        if stack.is_empty() {
            return Ok(pos);
        }
    }
}
