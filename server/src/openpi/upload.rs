//! The openpi endpoint's reads under the server's upload bounds ([`ReadBounds`], the same type
//! and rules the QUIC transport reads frames with), on a byte stream instead of framed streams.
//!
//! [`BoundedStream`] sits between the TCP socket and the websocket layer, which buffers a message
//! until it is complete. It cannot see message boundaries itself; the session marks them
//! ([`BoundedStream::message_done`]) each time the websocket layer yields a message. Between two
//! marks it enforces, on the bytes it lets through:
//! - **the minimum rate** ([`MinRate`]): from the first byte of a message, the bytes received
//!   must never fall behind `rate × (elapsed − grace)`; a read that falls behind fails with
//!   [`TooSlow`] (inside an `io::Error` of kind `TimedOut`), also while the peer sends nothing;
//! - **the budget**: every byte read takes a permit of the budget semaphore before it is read,
//!   and the permits come back at the next mark. While the budget is spent the socket is not
//!   read, so TCP flow control holds the sender back, and the time waiting counts against the
//!   minimum rate. The endpoint gives all connections of one robot the same budget, so a robot
//!   can make the server hold at most its budget of partly received requests.
//!
//! Bytes the websocket layer read past the end of a message (a pipelined next request) are
//! counted from the next mark on: at most one read step goes unbudgeted, per message.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, ready};

use kairos_sdk::protocol::{MinRate, ReadBounds, TooSlow};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::sync::{AcquireError, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};

/// Most bytes one read takes from the budget while a message is arriving.
pub const READ_STEP: usize = 64 << 10;

/// Most bytes one read takes from the budget on an idle connection (between messages): an idle
/// connection waits for the peer holding this much, so it is small.
pub const IDLE_STEP: usize = 4 << 10;

type Acquire = Pin<Box<dyn Future<Output = Result<OwnedSemaphorePermit, AcquireError>> + Send>>;

/// The message being received.
#[derive(Clone, Copy, Debug)]
struct Arriving {
    /// When its first byte was read.
    start: Instant,
    /// Bytes read since.
    received: u64,
}

/// A stream whose reads keep to [`ReadBounds`] (see the module docs). Writes pass through.
pub struct BoundedStream<S> {
    inner: S,
    bounds: ReadBounds,
    /// The budget's size: no read asks for more permits than there are.
    budget_bytes: usize,
    arriving: Option<Arriving>,
    /// Budget permits held for bytes read since the last mark.
    held: usize,
    /// Budget permits taken for the next read and not used yet.
    granted: usize,
    /// A budget acquisition in flight, and how many permits it asks for.
    acquiring: Option<(Acquire, usize)>,
    /// Wakes a read waiting for the peer or the budget when the rate's deadline passes.
    timer: Option<Pin<Box<Sleep>>>,
}

impl<S> BoundedStream<S> {
    /// `inner`, unbounded until [`BoundedStream::arm`].
    pub fn new(inner: S) -> BoundedStream<S> {
        BoundedStream {
            inner,
            bounds: ReadBounds::UNBOUNDED,
            budget_bytes: 0,
            arriving: None,
            held: 0,
            granted: 0,
            acquiring: None,
            timer: None,
        }
    }

    /// Reads from now on keep to `bounds`, whose budget (if any) holds `budget_bytes` permits
    /// in all.
    pub fn arm(&mut self, bounds: ReadBounds, budget_bytes: usize) {
        self.release();
        self.bounds = bounds;
        self.budget_bytes = budget_bytes.max(1);
    }

    /// Back to unbounded reads, the budget's permits given back.
    pub fn disarm(&mut self) {
        self.arm(ReadBounds::UNBOUNDED, 0);
    }

    /// The websocket layer yielded a message: its bytes leave the budget, and the next byte
    /// starts the next message's clock.
    pub fn message_done(&mut self) {
        if let Some(budget) = &self.bounds.budget {
            budget.add_permits(self.held);
        }
        self.held = 0;
        self.arriving = None;
    }

    /// Bytes of the message being received, as far as this stream has read them.
    pub fn received(&self) -> u64 {
        self.arriving.map_or(0, |a| a.received)
    }

    fn release(&mut self) {
        if let Some(budget) = &self.bounds.budget {
            budget.add_permits(self.held + self.granted);
        }
        self.held = 0;
        self.granted = 0;
        self.acquiring = None;
        self.arriving = None;
        self.timer = None;
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

    /// Permits for up to `want` bytes: `Ready(n)` once `n` are held for the next read.
    fn poll_budget(
        &mut self,
        cx: &mut Context<'_>,
        budget: &Arc<Semaphore>,
        want: usize,
    ) -> Poll<io::Result<usize>> {
        if self.granted > 0 {
            return Poll::Ready(Ok(self.granted));
        }
        let (acquire, asked) = self.acquiring.get_or_insert_with(|| {
            let asked = u32::try_from(want).unwrap_or(u32::MAX);
            (Box::pin(budget.clone().acquire_many_owned(asked)), want)
        });
        let asked = *asked;
        match ready!(acquire.as_mut().poll(cx)) {
            Ok(permit) => {
                // Counted by hand from here on: given back at the next mark (or when dropped).
                permit.forget();
                self.acquiring = None;
                self.granted = asked;
                Poll::Ready(Ok(asked))
            }
            Err(_) => {
                self.acquiring = None;
                Poll::Ready(Err(io::Error::other("the upload budget was closed")))
            }
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
        let step = if this.arriving.is_some() {
            READ_STEP
        } else {
            IDLE_STEP
        };
        let mut want = buf.remaining().min(step);
        if want == 0 {
            return Poll::Ready(Ok(()));
        }
        if let Some(budget) = this.bounds.budget.clone() {
            // Never more than the budget could ever grant besides what this stream holds; a
            // stream that holds all of it waits until its rate cuts it.
            want = want.min(this.budget_bytes.saturating_sub(this.held));
            if want == 0 {
                return this.wait(cx);
            }
            // An acquisition begun for an earlier, larger read may grant more than this one
            // takes; the rest goes back after the read.
            want = match this.poll_budget(cx, &budget, want) {
                Poll::Ready(Ok(granted)) => granted.min(want),
                Poll::Ready(Err(error)) => return Poll::Ready(Err(error)),
                Poll::Pending => return this.wait(cx),
            };
        }
        let read = {
            let unfilled = buf.initialize_unfilled_to(want);
            let mut limited = ReadBuf::new(unfilled);
            match Pin::new(&mut this.inner).poll_read(cx, &mut limited) {
                Poll::Ready(Ok(())) => limited.filled().len(),
                Poll::Ready(Err(error)) => return Poll::Ready(Err(error)),
                Poll::Pending => return this.wait(cx),
            }
        };
        buf.advance(read);
        if let Some(budget) = &this.bounds.budget {
            // The bytes read keep their permits until the next mark; the rest go back.
            budget.add_permits(this.granted - read);
            this.held += read;
            this.granted = 0;
        }
        if read > 0 {
            let arriving = this.arriving.get_or_insert(Arriving {
                start: Instant::now(),
                received: 0,
            });
            arriving.received += read as u64;
        }
        Poll::Ready(Ok(()))
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

    /// Virtual time: the runtime advances the clock only when every task waits, so the
    /// deadlines below are exact, not margins.
    #[tokio::test(start_paused = true)]
    async fn a_message_that_stalls_is_cut_when_it_falls_behind_the_rate() {
        let (mut peer, server) = duplex(1 << 16);
        let mut stream = BoundedStream::new(server);
        stream.arm(
            ReadBounds {
                min_rate: Some(rate()),
                budget: None,
            },
            0,
        );
        // An idle connection is never cut: no message has begun.
        let mut buf = [0u8; 64];
        let idle = tokio::time::timeout(Duration::from_secs(3600), stream.read(&mut buf)).await;
        assert!(idle.is_err(), "an idle connection waits");

        let start = Instant::now();
        peer.write_all(&[7u8; 500]).await.unwrap();
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
        stream.arm(
            ReadBounds {
                min_rate: Some(rate()),
                budget: None,
            },
            0,
        );
        let mut buf = [0u8; 2048];
        // 1100 B/s for 20 s, above the rate.
        for _ in 0..20 {
            peer.write_all(&[1u8; 1100]).await.unwrap();
            let mut got = 0;
            while got < 1100 {
                got += stream.read(&mut buf).await.unwrap();
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        assert_eq!(stream.received(), 22_000);
        stream.message_done();
        assert_eq!(stream.received(), 0);
        // After a mark, a long pause is idleness, not a stall.
        tokio::time::sleep(Duration::from_secs(600)).await;
        peer.write_all(&[2u8; 10]).await.unwrap();
        assert_eq!(stream.read(&mut buf).await.unwrap(), 10);
    }

    #[tokio::test(start_paused = true)]
    async fn reads_stop_at_the_budget_until_a_mark_gives_it_back() {
        let budget = Arc::new(Semaphore::new(10_000));
        let (mut peer_a, a) = duplex(1 << 16);
        let (mut peer_b, b) = duplex(1 << 16);
        let bounds = ReadBounds {
            min_rate: Some(rate()),
            budget: Some(budget.clone()),
        };
        let (mut a, mut b) = (BoundedStream::new(a), BoundedStream::new(b));
        a.arm(bounds.clone(), 10_000);
        b.arm(bounds, 10_000);
        peer_a.write_all(&[1u8; 30_000]).await.unwrap();
        peer_b.write_all(&[2u8; 30_000]).await.unwrap();
        let mut buf = vec![0u8; 1 << 16];
        let mut read_a = 0;
        while read_a < 10_000 {
            read_a += a.read(&mut buf).await.unwrap();
        }
        assert_eq!(read_a, 10_000, "a read the whole budget and no more");
        assert_eq!(budget.available_permits(), 0);
        // b shares the budget. Its message has not begun (it read nothing), so it just waits;
        // a's message, stuck at the budget, falls behind its rate meanwhile.
        let waiting = tokio::time::timeout(Duration::from_secs(60), b.read(&mut buf)).await;
        assert!(waiting.is_err(), "b waits for the budget");
        let error = a.read(&mut buf).await.unwrap_err();
        assert_eq!(too_slow(&error).map(|slow| slow.received), Some(10_000));
        // The stalled connection goes away: its bytes return to the budget and b reads.
        drop(a);
        let n = b.read(&mut buf).await.unwrap();
        assert!(n > 0 && n <= IDLE_STEP, "{n}");
        assert_eq!(budget.available_permits(), 10_000 - n);
        b.message_done();
        assert_eq!(budget.available_permits(), 10_000);
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
