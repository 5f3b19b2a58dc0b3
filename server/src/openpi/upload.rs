//! The openpi endpoint's reads under the server's upload bounds ([`ReadBounds`], the same type
//! and rules the QUIC transport reads frames with), on a byte stream instead of framed streams.
//!
//! [`BoundedStream`] sits between the TCP socket and the websocket layer, which buffers a message
//! until it is complete. It follows the websocket framing itself ([`FrameCursor`]: the HTTP
//! upgrade's head, then frame headers and payloads), so it can do what the QUIC reader does:
//! - **the budget**: a data frame takes its announced payload length from the budget semaphore
//!   before a byte of its payload is read, all of it at once (so connections that share a budget
//!   never hold parts of it while waiting for the rest), and gives it back when the session has
//!   the whole message ([`BoundedStream::message_done`]). While the budget is spent the socket is
//!   not read, so TCP flow control holds the sender back. The endpoint gives all connections of
//!   one robot the same budget;
//! - **the minimum rate** ([`MinRate`]): from the first byte of a data message, the bytes
//!   received must never fall behind `rate × (elapsed − grace)`; a read that falls behind fails
//!   with [`TooSlow`] (inside an `io::Error` of kind `TimedOut`), also while the peer sends
//!   nothing and while the frame waits for the budget.
//!
//! Control frames (ping, pong, close) take no budget and do not start the clock, so keep-alive
//! pings between requests are not an upload. A control frame may carry at most 125 bytes, but
//! the websocket layer refuses a longer one only once it has buffered all of it, so a control
//! frame that announces more is counted as an upload like a data frame. Under a budget, reads never cross a frame header, and a data frame's
//! header is held back until its payload is reserved: the websocket layer allocates a frame's
//! buffer from its header, so it only ever does so for frames the budget admitted.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, ready};

use kairos_sdk::protocol::{MinRate, ReadBounds, TooSlow};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::{AcquireError, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

/// The longest websocket frame header: 2 bytes, a 64-bit length, a 4-byte mask.
const MAX_HEADER: usize = 14;

/// The most payload a control frame may carry (RFC 6455, 5.5).
const MAX_CONTROL_PAYLOAD: u64 = 125;

/// Where a byte stream is in an HTTP upgrade followed by websocket frames: what the next byte
/// is. Sans-IO: [`FrameCursor::advance`] takes bytes as they are read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameCursor {
    /// In the upgrade request's head; `matched` bytes of its closing `\r\n\r\n` seen.
    HttpHead {
        /// Bytes of `\r\n\r\n` matched so far.
        matched: u8,
    },
    /// In a frame header: `have` of its bytes read.
    Header {
        /// The header so far.
        bytes: [u8; MAX_HEADER],
        /// How many of `bytes` are read.
        have: u8,
    },
    /// In a frame's payload.
    Payload {
        /// Bytes still to come.
        left: u64,
        /// Counted as an upload: a data frame (text, binary, continuation), or a control frame
        /// that announces more than [`MAX_CONTROL_PAYLOAD`] bytes.
        data: bool,
        /// Whether its bytes were taken from the budget.
        reserved: bool,
    },
}

/// What a header's first bytes say: its whole length, and (once that is read) the payload's
/// length and whether it is a data frame.
fn header_len(bytes: &[u8]) -> Option<usize> {
    let second = *bytes.get(1)?;
    let extended = match second & 0x7f {
        126 => 2,
        127 => 8,
        _ => 0,
    };
    let mask = if second & 0x80 != 0 { 4 } else { 0 };
    Some(2 + extended + mask)
}

fn is_data(first: u8) -> bool {
    first & 0x0f < 0x8
}

fn payload_len(bytes: &[u8]) -> u64 {
    match bytes[1] & 0x7f {
        126 => u64::from(u16::from_be_bytes([bytes[2], bytes[3]])),
        127 => u64::from_be_bytes([
            bytes[2], bytes[3], bytes[4], bytes[5], bytes[6], bytes[7], bytes[8], bytes[9],
        ]),
        n => u64::from(n),
    }
}

impl FrameCursor {
    /// At the start of an HTTP upgrade request.
    pub fn http() -> FrameCursor {
        FrameCursor::HttpHead { matched: 0 }
    }

    fn next_header() -> FrameCursor {
        FrameCursor::Header {
            bytes: [0; MAX_HEADER],
            have: 0,
        }
    }

    /// The most bytes a read may take without crossing into a frame header it has not parsed
    /// (`None`: any number, in the HTTP head). A payload's bytes come in one part.
    pub fn readable(&self) -> Option<u64> {
        match *self {
            FrameCursor::HttpHead { .. } => None,
            FrameCursor::Header { bytes, have } => {
                let have = usize::from(have);
                let whole = header_len(&bytes[..have]).unwrap_or(2);
                Some((whole - have) as u64)
            }
            FrameCursor::Payload { left, .. } => Some(left),
        }
    }

    /// Whether the next byte belongs to a data frame (the first header byte is the frame's
    /// opcode, so a header of no bytes yet is undecided: `false`).
    pub fn in_data_frame(&self) -> bool {
        match *self {
            FrameCursor::HttpHead { .. } => false,
            FrameCursor::Header { bytes, have } => have > 0 && is_data(bytes[0]),
            FrameCursor::Payload { data, .. } => data,
        }
    }

    /// Takes `bytes` as read, in order; returns how many of them belonged to data frames.
    pub fn advance(&mut self, mut bytes: &[u8]) -> u64 {
        let mut data_bytes = 0u64;
        while !bytes.is_empty() {
            match self {
                FrameCursor::HttpHead { matched } => {
                    const END: &[u8; 4] = b"\r\n\r\n";
                    let byte = bytes[0];
                    bytes = &bytes[1..];
                    *matched = if byte == END[usize::from(*matched)] {
                        *matched + 1
                    } else if byte == b'\r' {
                        1
                    } else {
                        0
                    };
                    if *matched == 4 {
                        *self = FrameCursor::next_header();
                    }
                }
                FrameCursor::Header {
                    bytes: header,
                    have,
                } => {
                    let at = usize::from(*have);
                    let whole = header_len(&header[..at]).unwrap_or(2);
                    let take = (whole - at).min(bytes.len());
                    header[at..at + take].copy_from_slice(&bytes[..take]);
                    bytes = &bytes[take..];
                    *have += take as u8;
                    let have = usize::from(*have);
                    let data = is_data(header[0]);
                    if data {
                        data_bytes += take as u64;
                    }
                    // Complete once its length is known and read (a short header's length is
                    // known at 2 bytes, an extended one's after its extension).
                    if have >= 2 && header_len(&header[..have]) == Some(have) {
                        let left = payload_len(&header[..have]);
                        // An oversized control frame is an upload from its first byte on.
                        let oversized = !data && left > MAX_CONTROL_PAYLOAD;
                        if oversized {
                            data_bytes += have as u64;
                        }
                        let data = data || oversized;
                        *self = if left == 0 {
                            FrameCursor::next_header()
                        } else {
                            FrameCursor::Payload {
                                left,
                                data,
                                reserved: false,
                            }
                        };
                    }
                }
                FrameCursor::Payload { left, data, .. } => {
                    let take = (*left).min(bytes.len() as u64);
                    bytes = &bytes[take as usize..];
                    *left -= take;
                    if *data {
                        data_bytes += take;
                    }
                    if *left == 0 {
                        *self = FrameCursor::next_header();
                    }
                }
            }
        }
        data_bytes
    }
}

type Acquire = Pin<Box<dyn Future<Output = Result<OwnedSemaphorePermit, AcquireError>> + Send>>;

/// Header bytes read from the socket and not handed on yet. A data frame's header waits here
/// until its payload is reserved: the websocket layer sizes its buffer from the header, so it
/// never sees a frame the budget has not admitted.
#[derive(Clone, Copy, Debug, Default)]
struct HeldHeader {
    bytes: [u8; MAX_HEADER],
    len: usize,
    delivered: usize,
    /// Whether it may be handed on.
    ready: bool,
}

/// The data message being received.
#[derive(Clone, Copy, Debug)]
struct Arriving {
    /// When its first byte was read.
    start: Instant,
    /// Bytes of it read since.
    received: u64,
}

/// A stream whose reads keep to [`ReadBounds`] (see the module docs). Writes pass through.
pub struct BoundedStream<S> {
    inner: S,
    bounds: ReadBounds,
    /// The budget's size: no frame takes more than this from it.
    budget_bytes: usize,
    cursor: FrameCursor,
    held: Option<HeldHeader>,
    arriving: Option<Arriving>,
    /// Budget permits held for the message being received.
    reserved: usize,
    /// A reservation in flight, and how many permits it asks for.
    acquiring: Option<(Acquire, usize)>,
    /// Wakes a read waiting for the peer or the budget when the rate's deadline passes.
    timer: Option<Pin<Box<Sleep>>>,
}

impl<S> BoundedStream<S> {
    /// `inner`, at the start of an HTTP upgrade, unbounded until [`BoundedStream::arm`].
    pub fn new(inner: S) -> BoundedStream<S> {
        BoundedStream {
            inner,
            bounds: ReadBounds::UNBOUNDED,
            budget_bytes: 0,
            cursor: FrameCursor::http(),
            held: None,
            arriving: None,
            reserved: 0,
            acquiring: None,
            timer: None,
        }
    }

    /// Reads from now on keep to `bounds`, whose budget (if any) holds `budget_bytes` permits
    /// in all.
    pub fn arm(&mut self, bounds: ReadBounds, budget_bytes: usize) {
        self.release();
        // A header held for a reservation that will not come now goes on as it is.
        if let Some(held) = &mut self.held {
            held.ready = true;
        }
        self.bounds = bounds;
        self.budget_bytes = budget_bytes.max(1);
    }

    /// Back to unbounded reads, the budget's permits given back.
    pub fn disarm(&mut self) {
        self.arm(ReadBounds::UNBOUNDED, 0);
    }

    /// The session has a whole data message: its bytes leave the budget, and the next data
    /// byte starts the next message's clock.
    pub fn message_done(&mut self) {
        if let Some(budget) = &self.bounds.budget {
            budget.add_permits(self.reserved);
        }
        self.reserved = 0;
        self.arriving = None;
        self.timer = None;
    }

    /// Bytes of the data message being received, as far as this stream has read them.
    pub fn received(&self) -> u64 {
        self.arriving.map_or(0, |a| a.received)
    }

    fn release(&mut self) {
        self.message_done();
        self.acquiring = None;
    }

    /// When the message being received falls behind the rate, if there is one.
    fn deadline(&self) -> Option<(MinRate, Arriving, Instant)> {
        let rate = self.bounds.min_rate?;
        let arriving = self.arriving?;
        let deadline = rate.deadline(arriving.start, arriving.received)?;
        Some((rate, arriving, deadline))
    }

    fn too_slow(rate: MinRate, arriving: Arriving) -> io::Error {
        io::Error::new(
            io::ErrorKind::TimedOut,
            rate.too_slow(arriving.start, arriving.received),
        )
    }

    /// A read that cannot go on now: pending, with a wake-up at the rate's deadline (or the
    /// rate's error if that has passed).
    fn wait(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let Some((rate, arriving, deadline)) = self.deadline() else {
            return Poll::Pending;
        };
        let timer = self
            .timer
            .get_or_insert_with(|| Box::pin(tokio::time::sleep_until(deadline)));
        if timer.deadline() != deadline {
            timer.as_mut().reset(deadline);
        }
        match timer.as_mut().poll(cx) {
            Poll::Ready(()) => Poll::Ready(Err(Self::too_slow(rate, arriving))),
            Poll::Pending => Poll::Pending,
        }
    }

    /// Takes a data payload of `left` bytes from `budget`, all at once.
    fn poll_reserve(
        &mut self,
        cx: &mut Context<'_>,
        budget: &Arc<Semaphore>,
        left: u64,
    ) -> Poll<io::Result<()>> {
        let want = usize::try_from(left)
            .unwrap_or(usize::MAX)
            .min(self.budget_bytes);
        let (acquire, asked) = self.acquiring.get_or_insert_with(|| {
            let asked = u32::try_from(want).unwrap_or(u32::MAX);
            (Box::pin(budget.clone().acquire_many_owned(asked)), want)
        });
        let asked = *asked;
        let acquired = ready!(acquire.as_mut().poll(cx));
        self.acquiring = None;
        match acquired {
            Ok(permit) => {
                // Counted by hand from here on: given back at the next mark (or when dropped).
                permit.forget();
                self.reserved += asked;
                Poll::Ready(Ok(()))
            }
            Err(_) => Poll::Ready(Err(io::Error::other("the upload budget was closed"))),
        }
    }
}

/// Whether `error` is a [`BoundedStream`] read that fell behind the minimum rate; its
/// [`TooSlow`] if so.
pub fn too_slow(error: &io::Error) -> Option<&TooSlow> {
    error.get_ref()?.downcast_ref::<TooSlow>()
}

impl<S> Drop for BoundedStream<S> {
    fn drop(&mut self) {
        self.release();
    }
}

impl<S: AsyncRead + Unpin> BoundedStream<S> {
    /// Reads into `buf` at most `limit` bytes (`None`: as many as fit), advancing the cursor
    /// and the message's clock over them.
    fn read_through(
        &mut self,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
        limit: Option<u64>,
    ) -> Poll<io::Result<()>> {
        let want = match limit {
            Some(limit) => buf
                .remaining()
                .min(usize::try_from(limit).unwrap_or(usize::MAX)),
            None => buf.remaining(),
        };
        let read = {
            let unfilled = buf.initialize_unfilled_to(want);
            let mut limited = ReadBuf::new(unfilled);
            match Pin::new(&mut self.inner).poll_read(cx, &mut limited) {
                Poll::Ready(Ok(())) => limited.filled().len(),
                Poll::Ready(Err(error)) => return Poll::Ready(Err(error)),
                Poll::Pending => return self.wait(cx),
            }
        };
        let start = buf.filled().len();
        let data = self.cursor.advance(&buf.initialized()[start..start + read]);
        buf.advance(read);
        self.count(data);
        Poll::Ready(Ok(()))
    }

    /// Hands on held header bytes that may go; whether it did.
    fn hand_on_held(&mut self, buf: &mut ReadBuf<'_>) -> bool {
        let Some(held) = &mut self.held else {
            return false;
        };
        if !held.ready {
            return false;
        }
        let n = buf.remaining().min(held.len - held.delivered);
        buf.put_slice(&held.bytes[held.delivered..held.delivered + n]);
        held.delivered += n;
        if held.delivered == held.len {
            self.held = None;
        }
        true
    }

    /// `data` more bytes of a data message arrived.
    fn count(&mut self, data: u64) {
        if data > 0 {
            let arriving = self.arriving.get_or_insert(Arriving {
                start: Instant::now(),
                received: 0,
            });
            arriving.received += data;
        }
    }

    /// A read under a budget: headers are read here and held; a data frame's header is handed
    /// on only once its payload is reserved.
    fn poll_budgeted(
        &mut self,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
        budget: &Arc<Semaphore>,
    ) -> Poll<io::Result<()>> {
        loop {
            if self.hand_on_held(buf) {
                return Poll::Ready(Ok(()));
            }
            match self.cursor {
                FrameCursor::Payload {
                    left,
                    data: true,
                    reserved: false,
                } => {
                    match self.poll_reserve(cx, budget, left) {
                        Poll::Ready(Ok(())) => {}
                        Poll::Ready(Err(error)) => return Poll::Ready(Err(error)),
                        Poll::Pending => return self.wait(cx),
                    }
                    if let FrameCursor::Payload { reserved, .. } = &mut self.cursor {
                        *reserved = true;
                    }
                    if let Some(held) = &mut self.held {
                        held.ready = true;
                    }
                }
                FrameCursor::Header { .. } => {
                    let need = self.cursor.readable().unwrap_or(2).min(MAX_HEADER as u64);
                    let mut bytes = [0u8; MAX_HEADER];
                    let mut read = ReadBuf::new(&mut bytes[..need as usize]);
                    match Pin::new(&mut self.inner).poll_read(cx, &mut read) {
                        Poll::Ready(Ok(())) => {}
                        Poll::Ready(Err(error)) => return Poll::Ready(Err(error)),
                        Poll::Pending => return self.wait(cx),
                    }
                    let got = read.filled();
                    if got.is_empty() {
                        // The end of the stream: what was held goes on first, then the end.
                        match &mut self.held {
                            Some(held) => held.ready = true,
                            None => return Poll::Ready(Ok(())),
                        }
                        continue;
                    }
                    let data = self.cursor.advance(got);
                    self.count(data);
                    let held = self.held.get_or_insert_with(HeldHeader::default);
                    held.bytes[held.len..held.len + got.len()].copy_from_slice(got);
                    held.len += got.len();
                    // A complete header goes on unless its payload must be reserved first.
                    held.ready = !matches!(
                        self.cursor,
                        FrameCursor::Header { .. }
                            | FrameCursor::Payload {
                                data: true,
                                reserved: false,
                                ..
                            }
                    );
                }
                FrameCursor::Payload { left, .. } => return self.read_through(cx, buf, Some(left)),
                FrameCursor::HttpHead { .. } => return self.read_through(cx, buf, None),
            }
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for BoundedStream<S> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        // A message already behind is cut before it may read what happens to be buffered.
        if let Some((rate, arriving, deadline)) = this.deadline()
            && Instant::now() >= deadline
        {
            return Poll::Ready(Err(Self::too_slow(rate, arriving)));
        }
        if buf.remaining() == 0 {
            return Poll::Ready(Ok(()));
        }
        match this.bounds.budget.clone() {
            Some(budget) => this.poll_budgeted(cx, buf, &budget),
            None if this.hand_on_held(buf) => Poll::Ready(Ok(())),
            None => this.read_through(cx, buf, None),
        }
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for BoundedStream<S> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().inner).poll_write(cx, data)
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use tokio::io::{AsyncReadExt, AsyncWriteExt, duplex};

    use super::*;

    fn rate() -> MinRate {
        MinRate {
            bytes_per_s: 1000,
            grace: Duration::from_secs(1),
        }
    }

    /// A masked client frame header of `opcode` announcing `len` bytes.
    fn header(opcode: u8, len: u64) -> Vec<u8> {
        let mut out = vec![0x80 | opcode];
        if len < 126 {
            out.push(0x80 | len as u8);
        } else if let Ok(len) = u16::try_from(len) {
            out.push(0x80 | 126);
            out.extend_from_slice(&len.to_be_bytes());
        } else {
            out.push(0x80 | 127);
            out.extend_from_slice(&len.to_be_bytes());
        }
        out.extend_from_slice(&[1, 2, 3, 4]);
        out
    }

    #[test]
    fn the_cursor_follows_the_head_and_frames_of_every_length() {
        let mut cursor = FrameCursor::http();
        assert_eq!(cursor.readable(), None);
        // The head may end in the same read as a pipelined frame begins.
        let mut bytes = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n".to_vec();
        bytes.extend(header(0x2, 3));
        bytes.extend([9, 9]);
        assert_eq!(cursor.advance(&bytes), 6 + 2);
        assert_eq!(
            cursor,
            FrameCursor::Payload {
                left: 1,
                data: true,
                reserved: false
            }
        );
        assert_eq!(cursor.advance(&[9]), 1);
        assert_eq!(cursor.readable(), Some(2), "a header is read 2 bytes first");
        // 16- and 64-bit lengths, fed one byte at a time.
        for len in [300u64, 70_000, 0] {
            for byte in header(0x2, len) {
                assert!(cursor.readable().is_some_and(|n| n >= 1));
                cursor.advance(&[byte]);
            }
            if len == 0 {
                assert_eq!(cursor.readable(), Some(2));
            } else {
                assert_eq!(cursor.readable(), Some(len));
                cursor.advance(&vec![0; len as usize]);
            }
        }
        // A ping is not data.
        assert_eq!(cursor.advance(&header(0x9, 4)), 0);
        assert!(!cursor.in_data_frame());
        assert_eq!(cursor.advance(&[1, 2, 3, 4]), 0);
        assert_eq!(cursor.readable(), Some(2));
    }

    /// A frame header with `fin`, `opcode`, `len` and an optional mask, as a client or a
    /// server writes it.
    fn header_with(fin: bool, opcode: u8, len: u64, mask: Option<[u8; 4]>) -> Vec<u8> {
        let mut out = vec![if fin { 0x80 } else { 0 } | opcode];
        let masked = if mask.is_some() { 0x80 } else { 0 };
        if len < 126 {
            out.push(masked | len as u8);
        } else if let Ok(len) = u16::try_from(len) {
            out.push(masked | 126);
            out.extend_from_slice(&len.to_be_bytes());
        } else {
            out.push(masked | 127);
            out.extend_from_slice(&len.to_be_bytes());
        }
        out.extend(mask.into_iter().flatten());
        out
    }

    #[test]
    fn a_header_split_anywhere_is_read_to_its_end_and_never_past_it() {
        // Short, 16-bit and 64-bit lengths, each masked and not: headers of 2 to 14 bytes.
        for len in [0u64, 1, 125, 126, 65_535, 65_536, u64::MAX >> 1] {
            for mask in [None, Some([0xa, 0xb, 0xc, 0xd])] {
                let bytes = header_with(true, 0x2, len, mask);
                for cut in 0..=bytes.len() {
                    let mut cursor = FrameCursor::next_header();
                    let mut data = cursor.advance(&bytes[..cut]);
                    // What a read may take now ends exactly where the header ends.
                    if cut < bytes.len() {
                        let readable = cursor.readable().expect("in a header");
                        assert!(readable >= 1, "len {len} mask {mask:?} cut {cut}");
                        assert!(cut as u64 + readable <= bytes.len() as u64);
                    }
                    // The rest, as a reader that honours `readable` would take it.
                    let mut at = cut;
                    while at < bytes.len() {
                        let step = cursor.readable().expect("in a header") as usize;
                        let step = step.min(bytes.len() - at);
                        data += cursor.advance(&bytes[at..at + step]);
                        at += step;
                    }
                    assert_eq!(data, bytes.len() as u64, "a data frame's header is data");
                    if len == 0 {
                        assert_eq!(cursor, FrameCursor::next_header());
                    } else {
                        assert_eq!(
                            cursor,
                            FrameCursor::Payload {
                                left: len,
                                data: true,
                                reserved: false
                            },
                            "len {len} mask {mask:?} cut {cut}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn control_frames_between_fragments_are_not_counted_and_oversized_ones_are() {
        let mut cursor = FrameCursor::next_header();
        let mask = Some([1, 2, 3, 4]);
        // A binary message in two fragments with a ping and a pong between them.
        let first = header_with(false, 0x2, 300, mask);
        let mut data = cursor.advance(&first) + cursor.advance(&[0; 300]);
        let ping = header_with(true, 0x9, 125, mask);
        assert_eq!(cursor.advance(&ping[..1]), 0);
        assert!(!cursor.in_data_frame(), "a ping's header is not data");
        assert_eq!(cursor.advance(&ping[1..]), 0);
        assert_eq!(
            cursor,
            FrameCursor::Payload {
                left: 125,
                data: false,
                reserved: false
            }
        );
        assert_eq!(cursor.advance(&[0; 125]), 0);
        assert_eq!(cursor.advance(&header_with(true, 0xA, 0, mask)), 0);
        let last = header_with(true, 0x0, 70_000, mask);
        data += cursor.advance(&last);
        assert!(cursor.in_data_frame(), "a continuation is data");
        data += cursor.advance(&vec![0; 70_000]);
        assert_eq!(data, (first.len() + 300 + last.len() + 70_000) as u64);
        assert_eq!(cursor, FrameCursor::next_header());

        // A ping that announces a megabyte is an upload, header included, although the
        // websocket layer will refuse it (only once it has all of it).
        let big_ping = header_with(true, 0x9, 1 << 20, mask);
        assert_eq!(cursor.advance(&big_ping), big_ping.len() as u64);
        assert_eq!(
            cursor,
            FrameCursor::Payload {
                left: 1 << 20,
                data: true,
                reserved: false
            }
        );
        assert!(cursor.in_data_frame());
        assert_eq!(cursor.advance(&[0; 1000]), 1000);
    }

    #[test]
    fn the_http_head_ends_at_the_first_blank_line_however_it_is_split() {
        // Near-misses of the blank line before the real one: a lone `\r`, `\r\r\n`, `\r\n\r` and
        // then a letter. The frame after the head is a masked text frame of 2 bytes.
        let head: &[u8] = b"GET / HTTP/1.1\rX\r\r\nHost: x\r\n\rY: 1\r\nZ: 2\r\r\n\r\n";
        let frame = [
            header_with(true, 0x1, 2, Some([9, 9, 9, 9])),
            b"hi".to_vec(),
        ]
        .concat();
        let bytes = [head, &frame].concat();
        for cut in 0..=bytes.len() {
            let mut cursor = FrameCursor::http();
            let mut data = cursor.advance(&bytes[..cut]);
            if cut < head.len() {
                assert_eq!(data, 0, "the head is not data");
                assert_eq!(cursor.readable(), None, "a read of the head is not limited");
            }
            data += cursor.advance(&bytes[cut..]);
            assert_eq!(data, frame.len() as u64, "cut {cut}");
            assert_eq!(cursor, FrameCursor::next_header(), "cut {cut}");
        }
        // A head that never ends keeps the cursor in it.
        let mut cursor = FrameCursor::http();
        assert_eq!(cursor.advance(&[b'\r', b'\n', b'\r', b'x'].repeat(1000)), 0);
        assert_eq!(cursor, FrameCursor::HttpHead { matched: 0 });
    }

    proptest::proptest! {
        /// Whatever bytes a client sends and however the reads split them, the cursor ends in
        /// the same place and counts the same data bytes, and never panics.
        #[test]
        fn the_cursor_does_not_depend_on_how_reads_split_the_bytes(
            bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..400),
            cuts in proptest::collection::vec(0usize..400, 0..20),
        ) {
            let mut whole = FrameCursor::http();
            let data_whole = whole.advance(&bytes);
            let mut split = FrameCursor::http();
            let mut cuts: Vec<usize> = cuts.into_iter().filter(|&c| c <= bytes.len()).collect();
            cuts.sort_unstable();
            let mut at = 0;
            let mut data_split = 0;
            for cut in cuts.into_iter().chain([bytes.len()]) {
                data_split += split.advance(&bytes[at..cut]);
                at = cut;
            }
            proptest::prop_assert_eq!(whole, split);
            proptest::prop_assert_eq!(data_whole, data_split);
        }
    }

    /// Virtual time: the runtime advances the clock only when every task waits, so the
    /// deadlines below are exact, not margins.
    #[tokio::test(start_paused = true)]
    async fn a_message_that_stalls_is_cut_when_it_falls_behind_the_rate() {
        let (mut peer, server) = duplex(1 << 16);
        let mut stream = BoundedStream::new(server);
        stream.cursor = FrameCursor::next_header();
        stream.arm(
            ReadBounds {
                min_rate: Some(rate()),
                budget: None,
            },
            0,
        );
        // An idle connection is never cut, nor one that only pings: no message has begun.
        peer.write_all(&header(0x9, 0)).await.unwrap();
        let mut buf = [0u8; 64];
        let mut got = 0;
        while got < 6 {
            got += stream.read(&mut buf).await.unwrap();
        }
        assert_eq!(stream.received(), 0, "a ping is not a message");
        let idle = tokio::time::timeout(Duration::from_secs(3600), stream.read(&mut buf)).await;
        assert!(idle.is_err(), "an idle connection waits");

        let start = Instant::now();
        peer.write_all(&header(0x2, 10_000)).await.unwrap();
        peer.write_all(&[7u8; 492]).await.unwrap();
        let mut got = 0;
        while got < 500 {
            got += stream.read(&mut buf).await.unwrap();
        }
        // 500 bytes at 1000 B/s buy half a second after the one-second grace.
        let error = stream.read(&mut buf).await.unwrap_err();
        assert_eq!(start.elapsed(), Duration::from_millis(1500));
        let slow = too_slow(&error).expect("a TooSlow error");
        assert_eq!(slow.received, 500);
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
    }

    #[tokio::test(start_paused = true)]
    async fn a_message_at_the_rate_is_never_cut_and_a_mark_restarts_the_clock() {
        let (mut peer, server) = duplex(1 << 16);
        let mut stream = BoundedStream::new(server);
        stream.cursor = FrameCursor::next_header();
        stream.arm(
            ReadBounds {
                min_rate: Some(rate()),
                budget: None,
            },
            0,
        );
        let mut buf = [0u8; 2048];
        peer.write_all(&header(0x2, 22_000)).await.unwrap();
        // 1100 B/s for 20 s, above the rate.
        for _ in 0..20 {
            peer.write_all(&[1u8; 1100]).await.unwrap();
            let mut got = 0;
            while got < 1100 {
                got += stream.read(&mut buf).await.unwrap();
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        assert_eq!(stream.received(), 8 + 22_000);
        stream.message_done();
        assert_eq!(stream.received(), 0);
        // After a mark, a long pause is idleness, not a stall.
        tokio::time::sleep(Duration::from_secs(600)).await;
        peer.write_all(&header(0x2, 10)).await.unwrap();
        assert_eq!(stream.read(&mut buf).await.unwrap(), 6);
    }

    #[tokio::test(start_paused = true)]
    async fn a_payload_is_read_only_once_it_is_wholly_reserved() {
        let budget = Arc::new(Semaphore::new(10_000));
        let (mut peer_a, a) = duplex(1 << 16);
        let (mut peer_b, b) = duplex(1 << 16);
        let bounds = ReadBounds {
            min_rate: Some(rate()),
            budget: Some(budget.clone()),
        };
        let (mut a, mut b) = (BoundedStream::new(a), BoundedStream::new(b));
        for stream in [&mut a, &mut b] {
            stream.cursor = FrameCursor::next_header();
            stream.arm(bounds.clone(), 10_000);
        }
        peer_a.write_all(&header(0x2, 6_000)).await.unwrap();
        peer_a.write_all(&[1u8; 3_000]).await.unwrap();
        let mut buf = vec![0u8; 1 << 16];
        // The header goes on once the payload is reserved, then the payload.
        assert_eq!(a.read(&mut buf).await.unwrap(), 8);
        assert_eq!(a.read(&mut buf).await.unwrap(), 3_000);
        // a holds its whole payload's reservation although only half of it came.
        assert_eq!(budget.available_permits(), 4_000);

        tokio::time::sleep(Duration::from_millis(3_500)).await;
        peer_b.write_all(&header(0x2, 6_000)).await.unwrap();
        peer_b.write_all(&[2u8; 6_000]).await.unwrap();
        // b's payload does not fit beside a's reservation: its header is read but held back,
        // so the websocket layer sees nothing of b's frame yet. (The semaphore sets aside what
        // is free for b, the first in line; nobody else gets ahead of it.)
        let waiting = tokio::time::timeout(Duration::from_millis(400), b.read(&mut buf)).await;
        assert!(waiting.is_err(), "b waits for the budget");
        assert_eq!(b.received(), 8);
        // a's stall is cut at its deadline: one second of grace, plus 3,008 bytes at 1000 B/s.
        let error = a.read(&mut buf).await.unwrap_err();
        assert_eq!(too_slow(&error).map(|slow| slow.received), Some(3_008));
        // The stalled connection goes away: its reservation returns, and b, still within its
        // own allowance, reads its payload.
        drop(a);
        let mut read_b = 0;
        while read_b < 8 + 6_000 {
            read_b += b.read(&mut buf).await.unwrap();
        }
        assert_eq!(budget.available_permits(), 4_000);
        b.message_done();
        assert_eq!(budget.available_permits(), 10_000);
    }

    #[tokio::test(start_paused = true)]
    async fn a_ping_is_read_while_the_budget_is_spent() {
        let budget = Arc::new(Semaphore::new(0));
        let (mut peer, server) = duplex(1 << 16);
        let mut stream = BoundedStream::new(server);
        stream.cursor = FrameCursor::next_header();
        stream.arm(
            ReadBounds {
                min_rate: Some(rate()),
                budget: Some(budget.clone()),
            },
            1000,
        );
        peer.write_all(&header(0x9, 4)).await.unwrap();
        peer.write_all(&[5u8; 4]).await.unwrap();
        let mut buf = [0u8; 64];
        let mut got = Vec::new();
        while got.len() < 10 {
            let n = stream.read(&mut buf).await.unwrap();
            got.extend_from_slice(&buf[..n]);
        }
        assert_eq!(got, [header(0x9, 4), vec![5u8; 4]].concat());
        assert_eq!(stream.received(), 0, "a ping is not an upload");
        // A data frame, though, waits for the budget with its header held back, until it
        // falls behind the rate: one second of grace plus its 6 header bytes.
        peer.write_all(&header(0x2, 10)).await.unwrap();
        let start = Instant::now();
        let error = stream.read(&mut buf).await.unwrap_err();
        assert_eq!(start.elapsed(), Duration::from_millis(1006));
        assert_eq!(too_slow(&error).map(|slow| slow.received), Some(6));
        assert_eq!(budget.available_permits(), 0);
    }

    #[tokio::test]
    async fn unarmed_reads_and_writes_pass_through() {
        let (mut peer, server) = duplex(1024);
        let mut stream = BoundedStream::new(server);
        peer.write_all(b"hello").await.unwrap();
        let mut buf = [0u8; 5];
        stream.read_exact(&mut buf).await.unwrap();
        assert_eq!(&buf, b"hello");
        stream.write_all(b"back").await.unwrap();
        let mut back = [0u8; 4];
        peer.read_exact(&mut back).await.unwrap();
        assert_eq!(&back, b"back");
    }
}
