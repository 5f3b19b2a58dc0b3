//! Reading and writing frames on QUIC streams.

use std::sync::Arc;
use std::time::Duration;

use bytes::BytesMut;
use quinn::{ReadError, RecvStream, SendStream, WriteError};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;

use kairos_protocol::codec::{EncodeError, Message, WireBody, encode_body};
use kairos_protocol::frame::{Frame, FrameError, HEADER_LEN, parse_header};
use kairos_protocol::limits::Limits;

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
    /// The peer sent slower than the reader's [`MinRate`].
    #[error(
        "upload too slow: {received} bytes in {elapsed_ms} ms, under the minimum of \
         {bytes_per_s} bytes/s after a grace of {grace_ms} ms"
    )]
    TooSlow {
        /// Bytes of the frame (header included) received when the reader gave up.
        received: u64,
        /// Time since the read began, ms.
        elapsed_ms: u64,
        /// The minimum rate.
        bytes_per_s: u64,
        /// The grace period.
        grace_ms: u64,
    },
}

/// The slowest a peer may send: after `grace`, a frame must have arrived at `bytes_per_s` or
/// faster, measured from the start of the read. The reader gives up at the first moment the
/// bytes received fall behind `bytes_per_s × (elapsed − grace)`, so a stalled upload is dropped
/// after `grace + received / bytes_per_s`, while slow Wi-Fi above the rate is never cut.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MinRate {
    /// Minimum rate, bytes per second (0: no minimum).
    pub bytes_per_s: u64,
    /// Time before the rate applies.
    pub grace: Duration,
}

impl MinRate {
    /// The moment by which more than `received` bytes must have arrived, for a read that began
    /// at `start`; `None` if there is no minimum.
    pub fn deadline(&self, start: Instant, received: u64) -> Option<Instant> {
        if self.bytes_per_s == 0 {
            return None;
        }
        let allowed = Duration::try_from_secs_f64(received as f64 / self.bytes_per_s as f64)
            .unwrap_or(Duration::MAX);
        // Past the end of time: no deadline at all.
        start.checked_add(self.grace.saturating_add(allowed))
    }
}

/// How a server reads frames from an untrusted peer: a minimum upload rate, and a budget of
/// bytes of partly received frames shared by all streams of one connection. A frame takes its
/// announced length from the budget before its body is read, and gives it back when it is
/// complete (or fails); while the budget is empty the stream is not read, so QUIC flow control
/// stops the peer, and the time waiting counts against the minimum rate.
#[derive(Clone, Debug)]
pub struct ReadBounds {
    /// The minimum rate (`None`: wait forever, as the client does for its server).
    pub min_rate: Option<MinRate>,
    /// The connection's budget, in bytes (`None`: unbounded).
    pub budget: Option<Arc<Semaphore>>,
}

impl ReadBounds {
    /// No rate and no budget: [`read_frame`]'s behaviour.
    pub const UNBOUNDED: ReadBounds = ReadBounds {
        min_rate: None,
        budget: None,
    };
}

/// Runs `read` until `deadline`, or fails with [`ReadFrameError::TooSlow`].
async fn before<T>(
    deadline: Option<Instant>,
    rate: Option<MinRate>,
    start: Instant,
    received: u64,
    read: impl std::future::Future<Output = Result<T, ReadFrameError>>,
) -> Result<T, ReadFrameError> {
    let (Some(deadline), Some(rate)) = (deadline, rate) else {
        return read.await;
    };
    let too_slow = || ReadFrameError::TooSlow {
        received,
        elapsed_ms: u64::try_from(start.elapsed().as_millis()).unwrap_or(u64::MAX),
        bytes_per_s: rate.bytes_per_s,
        grace_ms: u64::try_from(rate.grace.as_millis()).unwrap_or(u64::MAX),
    };
    // Checked first: a stream that is already behind does not get to read what happens to be
    // buffered (the timeout below polls `read` once before it looks at the clock).
    if Instant::now() >= deadline {
        return Err(too_slow());
    }
    match tokio::time::timeout_at(deadline, read).await {
        Ok(result) => result,
        Err(_) => Err(too_slow()),
    }
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
    read_frame_bounded(recv, limits, &ReadBounds::UNBOUNDED).await
}

/// [`read_frame`] within `bounds` (see [`ReadBounds`]).
pub async fn read_frame_bounded(
    recv: &mut RecvStream,
    limits: &Limits,
    bounds: &ReadBounds,
) -> Result<Option<Frame>, ReadFrameError> {
    let start = Instant::now();
    let rate = bounds.min_rate;
    let deadline = |received: u64| rate.and_then(|rate| rate.deadline(start, received));
    let mut header = [0u8; HEADER_LEN];
    let mut got = 0;
    while got < HEADER_LEN {
        let read = async { Ok(recv.read(&mut header[got..]).await?) };
        match before(deadline(got as u64), rate, start, got as u64, read).await? {
            Some(n) => got += n,
            None if got == 0 => return Ok(None),
            None => {
                return Err(FrameError::Truncated {
                    needed: HEADER_LEN,
                    available: got,
                }
                .into());
            }
        }
    }
    let (kind, len) = parse_header(header, limits.max_frame)?;
    let len = len as usize;
    // Held until the body is complete: bytes of partly received frames.
    let _permit: Option<OwnedSemaphorePermit> = match &bounds.budget {
        Some(budget) => {
            let take = async {
                // A closed budget means the connection is going away.
                budget
                    .clone()
                    .acquire_many_owned(u32::try_from(len).unwrap_or(u32::MAX))
                    .await
                    .map_err(|_| ReadFrameError::Read(ReadError::ClosedStream))
            };
            let received = HEADER_LEN as u64;
            Some(before(deadline(received), rate, start, received, take).await?)
        }
        None => None,
    };
    let mut body = BytesMut::with_capacity(len.min(READ_STEP));
    while body.len() < len {
        let wanted = (len - body.len()).min(READ_STEP);
        let received = (HEADER_LEN + body.len()) as u64;
        let read = async { Ok(recv.read_chunk(wanted, true).await?) };
        match before(deadline(received), rate, start, received, read).await? {
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
    read_message_bounded(recv, limits, &ReadBounds::UNBOUNDED).await
}

/// [`read_message`] within `bounds` (see [`ReadBounds`]).
pub async fn read_message_bounded(
    recv: &mut RecvStream,
    limits: &Limits,
    bounds: &ReadBounds,
) -> Result<Option<Message>, ReadFrameError> {
    match read_frame_bounded(recv, limits, bounds).await? {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_min_rate_deadline_grows_with_the_bytes_received() {
        let start = Instant::now();
        let rate = MinRate {
            bytes_per_s: 8192,
            grace: Duration::from_secs(5),
        };
        // Nothing yet: the grace period.
        assert_eq!(
            rate.deadline(start, 0),
            Some(start + Duration::from_secs(5))
        );
        // Each 8 KiB buys one more second: a stall after 80 KiB is cut 15 s after the start.
        assert_eq!(
            rate.deadline(start, 80 * 1024),
            Some(start + Duration::from_secs(15))
        );
        // A 2 MB observation over slow Wi-Fi at 10 KB/s (above the rate) is never cut: at every
        // moment its bytes are ahead of the deadline they buy.
        for second in 1..=200u64 {
            let received = 10_000 * second;
            let deadline = rate.deadline(start, received).unwrap();
            assert!(deadline > start + Duration::from_secs(second));
        }
        let none = MinRate {
            bytes_per_s: 0,
            grace: Duration::ZERO,
        };
        assert_eq!(none.deadline(start, 0), None);
    }
}
