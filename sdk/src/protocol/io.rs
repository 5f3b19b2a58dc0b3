//! Reading and writing frames on QUIC streams.

use bytes::BytesMut;
use quinn::{ReadError, ReadExactError, RecvStream, SendStream, WriteError};

use super::codec::{EncodeError, Message, WireBody, encode_body};
use super::frame::{Frame, FrameError, HEADER_LEN, parse_header};
use super::limits::Limits;

/// Bodies grow in steps of at most this much as their bytes arrive, so a peer that announces a
/// large frame and sends nothing costs no more than the bytes it actually sent.
const READ_STEP: usize = 64 * 1024;

/// A frame could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadFrameError {
    /// The bytes are not a valid frame (or message).
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// The stream or its connection failed.
    #[error("stream read failed: {0}")]
    Read(#[from] ReadError),
}

/// A frame could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteFrameError {
    /// The message could not be encoded within the limit.
    #[error(transparent)]
    Encode(#[from] EncodeError),
    /// The stream or its connection failed.
    #[error("stream write failed: {0}")]
    Write(#[from] WriteError),
}

/// Reads one frame. `Ok(None)` if the peer finished the stream cleanly before a new frame began.
/// A frame that the stream's end cuts short is [`FrameError::Truncated`].
pub async fn read_frame(
    recv: &mut RecvStream,
    limits: &Limits,
) -> Result<Option<Frame>, ReadFrameError> {
    let mut header = [0u8; HEADER_LEN];
    match recv.read_exact(&mut header).await {
        Ok(()) => {}
        Err(ReadExactError::FinishedEarly(0)) => return Ok(None),
        Err(ReadExactError::FinishedEarly(available)) => {
            return Err(FrameError::Truncated {
                needed: HEADER_LEN,
                available,
            }
            .into());
        }
        Err(ReadExactError::ReadError(error)) => return Err(error.into()),
    }
    let (kind, len) = parse_header(header, limits.max_frame)?;
    let len = len as usize;
    let mut body = BytesMut::with_capacity(len.min(READ_STEP));
    while body.len() < len {
        let wanted = (len - body.len()).min(READ_STEP);
        match recv.read_chunk(wanted, true).await? {
            Some(chunk) => body.extend_from_slice(&chunk.bytes),
            None => {
                return Err(FrameError::Truncated {
                    needed: HEADER_LEN + len,
                    available: HEADER_LEN + body.len(),
                }
                .into());
            }
        }
    }
    Ok(Some(Frame {
        kind,
        body: body.freeze(),
    }))
}

/// Reads and decodes one message (see [`read_frame`]). Does not [`validate`] it.
///
/// [`validate`]: super::Validate::validate
pub async fn read_message(
    recv: &mut RecvStream,
    limits: &Limits,
) -> Result<Option<Message>, ReadFrameError> {
    match read_frame(recv, limits).await? {
        Some(frame) => Ok(Some(Message::decode(&frame)?)),
        None => Ok(None),
    }
}

/// Writes a frame as is.
pub async fn write_frame(send: &mut SendStream, frame: &Frame) -> Result<(), WriteFrameError> {
    send.write_all(&frame.to_bytes()).await?;
    Ok(())
}

/// Encodes and writes one message; `max_body` is the receiver's frame limit.
pub async fn write_message(
    send: &mut SendStream,
    message: &Message,
    max_body: u32,
) -> Result<(), WriteFrameError> {
    let bytes = message.encode(max_body)?;
    send.write_all(&bytes).await?;
    Ok(())
}

/// Encodes and writes one message body (see [`encode_body`]).
pub async fn write_body<T: WireBody>(
    send: &mut SendStream,
    body: &T,
    max_body: u32,
) -> Result<(), WriteFrameError> {
    let bytes = encode_body(body, max_body)?;
    send.write_all(&bytes).await?;
    Ok(())
}
