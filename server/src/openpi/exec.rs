//! Last Exec Info for openpi clients, inferred from call timing (they send none).
//!
//! An openpi client (`WebsocketClientPolicy.infer`) is synchronous: it sends a request, blocks
//! until the reply, executes some of the chunk, and only then sends the next request. So for
//! consecutive requests `i` and `i+1` of one connection:
//!
//! - the robot started executing chunk `i` when reply `i` was written (`E_i.start`; the one-way
//!   network delay is not known and not added);
//! - it had nothing left that it would still execute when it sent request `i+1`: it asks when it
//!   needs actions, and a chunk's unexecuted tail is discarded (openpi's `ActionChunkBroker` and
//!   its replanning examples), so `actions_remaining = 0` and `E_i.end` = the arrival of
//!   request `i+1`;
//! - the control rate is the configured `[openpi] control_hz`, or else estimated as the actions
//!   of reply `i` over the interval `E_i` (the rate at which the whole chunk would have run in
//!   that time), averaged over the connection. The scheduler uses it to predict when the next
//!   request comes (`H / control_hz` after a reply): with the estimate, one interval after the
//!   last, which is right for a client that executes the same share of every chunk.
//!
//! The first request has no Last Exec Info. When the connection closes, the last chunk is
//! reported executed until the close.
//!
//! What this cannot know, and what the chunking strategies make of it: a blocking client
//! executes nothing while its call is in flight, so every round is planned as for an idle
//! robot (nothing committed: the reply's `start` is 0, `rtc` and `inpaint` have no previous
//! actions to guide toward, `arrival_state` no state to roll forward, `ensemble` no overlap to
//! blend). A client that does keep executing (its own thread running the previous chunk) is
//! invisible here; the server cannot tell it from a blocking one. The robot's actual `d` is not
//! reported either (there is no control clock on the wire), so the server scores its
//! prediction from the timestamps alone.

use kairos_sdk::protocol::LastExecInfo;

use kairos_core::time::Timestamp;

/// Estimated control rates are kept in this range (Hz): a client that calls again at once (a
/// benchmark loop) would otherwise report an infinite rate.
pub const HZ_RANGE: (f64, f64) = (0.1, 1000.0);

/// One connection's execution estimate.
#[derive(Clone, Debug, Default)]
pub struct ExecEstimate {
    configured_hz: Option<f32>,
    /// When the last reply was written, how many actions it held, and its round.
    last_reply: Option<(Timestamp, u32, u64)>,
    /// Running estimate of the control rate.
    estimated_hz: Option<f64>,
}

impl ExecEstimate {
    /// An estimate that reports `configured_hz` when it is set, else its own estimate.
    pub fn new(configured_hz: Option<f32>) -> ExecEstimate {
        ExecEstimate {
            configured_hz,
            ..ExecEstimate::default()
        }
    }

    /// A request arrived at `now`: the Last Exec Info it stands for (times in µs on the server
    /// clock), `None` before the first reply.
    pub fn on_request(&mut self, now: Timestamp) -> Option<LastExecInfo> {
        let (replied_at, actions, _) = self.last_reply?;
        let interval = now.saturating_since(replied_at).as_secs_f64();
        let sample = (f64::from(actions) / interval.max(1e-6)).clamp(HZ_RANGE.0, HZ_RANGE.1);
        self.estimated_hz = Some(match self.estimated_hz {
            Some(old) => 0.5 * old + 0.5 * sample,
            None => sample,
        });
        self.report(replied_at)
    }

    /// The connection closed: the execution of the last chunk, if any, ends at the close (the
    /// task end's `sent_at`).
    pub fn on_close(&self) -> Option<LastExecInfo> {
        let (replied_at, _, _) = self.last_reply?;
        self.report(replied_at)
    }

    /// The reply of round `round` with `actions` actions was written at `at`.
    pub fn on_reply(&mut self, at: Timestamp, actions: u32, round: u64) {
        self.last_reply = Some((at, actions, round));
    }

    /// The control rate reported: configured, else estimated (`None` before any interval).
    pub fn control_hz(&self) -> Option<f32> {
        self.configured_hz
            .or_else(|| self.estimated_hz.map(|hz| hz as f32))
    }

    fn report(&self, replied_at: Timestamp) -> Option<LastExecInfo> {
        Some(LastExecInfo {
            exec_started_at_us: replied_at.as_micros(),
            actions_remaining: 0,
            control_hz: self.control_hz()?,
            round: self.last_reply.map(|(_, _, round)| round),
            delay: None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at_ms(ms: u64) -> Timestamp {
        Timestamp::from_micros(ms * 1000)
    }

    #[test]
    fn the_interval_between_reply_and_request_is_the_execution() {
        let mut exec = ExecEstimate::new(None);
        assert_eq!(
            exec.on_request(at_ms(0)),
            None,
            "nothing before the first reply"
        );
        assert_eq!(exec.on_close(), None);
        exec.on_reply(at_ms(100), 10, 0);
        // Ten actions, the next call 200 ms after the reply: 50 Hz.
        let info = exec.on_request(at_ms(300)).unwrap();
        assert_eq!(info.exec_started_at_us, 100_000);
        assert_eq!(info.actions_remaining, 0);
        assert!((info.control_hz - 50.0).abs() < 1e-3, "{info:?}");
        // The next interval says 25 Hz: the estimate moves halfway.
        exec.on_reply(at_ms(400), 10, 0);
        let info = exec.on_request(at_ms(800)).unwrap();
        assert!((info.control_hz - 37.5).abs() < 1e-3, "{info:?}");
        exec.on_reply(at_ms(900), 10, 0);
        let closed = exec.on_close().unwrap();
        assert_eq!(closed.exec_started_at_us, 900_000);
    }

    #[test]
    fn a_configured_rate_wins_and_an_immediate_call_is_clamped() {
        let mut exec = ExecEstimate::new(Some(15.0));
        exec.on_reply(at_ms(10), 50, 0);
        assert_eq!(exec.on_request(at_ms(10)).unwrap().control_hz, 15.0);
        let mut exec = ExecEstimate::new(None);
        exec.on_reply(at_ms(10), 50, 0);
        let info = exec.on_request(at_ms(10)).unwrap();
        assert_eq!(f64::from(info.control_hz), HZ_RANGE.1);
    }
}
