//! Predicting each round's `d`: how many control steps pass between the capture of its
//! observation and the arrival of its chunk, and how many of those the robot spends executing
//! the actions it committed to. Pure: every time is an argument.
//!
//! The arrival is the instant the batch starts, plus what is still ahead of the round: the
//! scheduler's expected queue wait (zero once the batch starts), the engine profile's time for
//! the batch (and a remote instance's round trip), the server's own time between the end of
//! generation and the reply (horizon policies, hand-off), and the task's one-way network time.
//! The robot executes one action per control tick; its ticks run at `control_hz` from the start
//! of the chunk it is executing (Last Exec Info), so the steps between capture and arrival are
//! the ticks between them, and the actions it executes are those ticks, up to the actions it
//! had left.

use std::collections::VecDeque;
use std::time::Duration;

use crate::scheduler::ExecReport;
use crate::time::Timestamp;

/// What a prediction is made from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DelayInputs {
    /// When the round's observation was captured (server clock).
    pub captured_at: Timestamp,
    /// When the prediction is made.
    pub now: Timestamp,
    /// How much longer the round is expected to wait before its batch starts.
    pub queue_wait: Duration,
    /// The batch's expected generation time (the engine profile's latency at its size, plus a
    /// remote instance's round trip).
    pub generation: Duration,
    /// The server's own time from the end of generation to the reply being sent.
    pub reply_overhead: Duration,
    /// The task's one-way network time, server to robot.
    pub network: Duration,
    /// The robot's execution phase when it sent the round (server clock), if it had one.
    pub exec: Option<ExecReport>,
    /// When the round was sent (the instant `exec` describes).
    pub sent_at: Timestamp,
}

/// A round's predicted `d`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DelayPrediction {
    /// When the chunk is expected at the robot.
    pub arrival: Timestamp,
    /// Control steps from the capture to the arrival.
    pub delay: u32,
    /// Actions the robot executes in that time: `delay`, less any it would run out of. The
    /// reply's start index.
    pub start: u32,
    /// Actions of its current chunk the robot had left at the capture.
    pub remaining_at_capture: u32,
}

/// A thousandth of a tick: a tick period rounded to the robot's clock (33 333 µs at 30 Hz) must
/// still count as a whole tick after many periods.
const TICK_SLACK: f64 = 1e-3;

/// Control ticks of a robot whose ticks fall at `origin + m / hz` (m = 0, 1, ...) in
/// `(from, to]`; before `origin` no tick counts.
fn ticks_between(origin: Timestamp, hz: f64, from: Timestamp, to: Timestamp) -> u32 {
    if to <= from || !(hz.is_finite() && hz > 0.0) {
        return 0;
    }
    // Ticks at or before `t`: floor((t - origin) * hz) + 1 for t >= origin.
    let upto = |t: Timestamp| -> i64 {
        if t < origin {
            0
        } else {
            let elapsed = t.saturating_since(origin).as_secs_f64();
            (elapsed * hz + TICK_SLACK).floor().min(4e9) as i64 + 1
        }
    };
    u32::try_from((upto(to) - upto(from)).max(0)).unwrap_or(u32::MAX)
}

/// The predicted `d` of a round (see the module docs).
pub fn predict_delay(inputs: &DelayInputs) -> DelayPrediction {
    let arrival = inputs.now.max(inputs.captured_at)
        + inputs.queue_wait
        + inputs.generation
        + inputs.reply_overhead
        + inputs.network;
    let Some(exec) = inputs
        .exec
        .filter(|e| e.control_hz.is_finite() && e.control_hz > 0.0)
    else {
        // No execution phase: the robot is idle and executes nothing until the chunk arrives.
        return DelayPrediction {
            arrival,
            delay: 0,
            start: 0,
            remaining_at_capture: 0,
        };
    };
    let hz = f64::from(exec.control_hz);
    let delay = ticks_between(exec.started_at, hz, inputs.captured_at, arrival);
    // Actions left at the capture: those left at the send, plus any executed in between.
    let remaining_at_capture = exec.actions_remaining.saturating_add(ticks_between(
        exec.started_at,
        hz,
        inputs.captured_at,
        inputs.sent_at,
    ));
    DelayPrediction {
        arrival,
        delay,
        start: delay.min(remaining_at_capture),
        remaining_at_capture,
    }
}

/// The actual `d` of a round from the robot's next Last Exec Info when it did not report it:
/// the ticks from the capture to when it started executing the chunk (`exec.started_at`).
pub fn actual_delay_from_times(captured_at: Timestamp, exec: &ExecReport) -> u32 {
    let hz = f64::from(exec.control_hz);
    if !(hz.is_finite() && hz > 0.0) || exec.started_at <= captured_at {
        return 0;
    }
    let steps = exec.started_at.saturating_since(captured_at).as_secs_f64() * hz;
    (steps + TICK_SLACK).floor().min(f64::from(u32::MAX)) as u32
}

/// A smoothed estimate of a task's one-way network time: the least of the recent uplink delays
/// (a message's read time less its mapped send time), which is the connection's RTT / 2 by the
/// way the clock mapping is made (`crate::clock_map`) and excludes upload time and jitter.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NetworkEstimate {
    recent: VecDeque<Duration>,
}

impl NetworkEstimate {
    /// Uplink samples the estimate is the minimum over.
    pub const WINDOW: usize = 8;

    /// Records a message sent at `sent_at` (mapped) and read at `received`.
    pub fn observe(&mut self, sent_at: Timestamp, received: Timestamp) {
        if self.recent.len() >= Self::WINDOW {
            self.recent.pop_front();
        }
        self.recent.push_back(received.saturating_since(sent_at));
    }

    /// The estimate (zero before any sample).
    pub fn get(&self) -> Duration {
        self.recent.iter().min().copied().unwrap_or_default()
    }
}

/// An exponentially weighted moving average of a duration (weight 1/8 on each new sample).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DurationAverage {
    micros: Option<f64>,
}

impl DurationAverage {
    /// Adds a sample.
    pub fn observe(&mut self, sample: Duration) {
        let x = sample.as_secs_f64() * 1e6;
        self.micros = Some(match self.micros {
            None => x,
            Some(m) => m + (x - m) / 8.0,
        });
    }

    /// The average (zero before any sample).
    pub fn get(&self) -> Duration {
        Duration::from_micros(self.micros.unwrap_or(0.0).max(0.0).round() as u64)
    }
}

/// How well a task's `d` was predicted: predicted against actual, per round that reported it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DelayErrorStats {
    /// Rounds compared.
    pub rounds: u32,
    /// Rounds predicted exactly.
    pub exact: u32,
    /// Σ (predicted − actual), steps.
    pub sum_error: i64,
    /// Σ |predicted − actual|, steps.
    pub sum_abs_error: u64,
    /// The largest |predicted − actual|, steps.
    pub max_abs_error: u32,
}

impl DelayErrorStats {
    /// Records one round.
    pub fn record(&mut self, predicted: u32, actual: u32) {
        let error = i64::from(predicted) - i64::from(actual);
        self.rounds = self.rounds.saturating_add(1);
        if error == 0 {
            self.exact = self.exact.saturating_add(1);
        }
        self.sum_error = self.sum_error.saturating_add(error);
        self.sum_abs_error = self.sum_abs_error.saturating_add(error.unsigned_abs());
        self.max_abs_error = self
            .max_abs_error
            .max(u32::try_from(error.unsigned_abs()).unwrap_or(u32::MAX));
    }

    /// Mean signed error (predicted − actual), steps; 0 before any round.
    pub fn mean_error(&self) -> f64 {
        if self.rounds == 0 {
            0.0
        } else {
            self.sum_error as f64 / f64::from(self.rounds)
        }
    }

    /// Mean absolute error, steps; 0 before any round.
    pub fn mean_abs_error(&self) -> f64 {
        if self.rounds == 0 {
            0.0
        } else {
            self.sum_abs_error as f64 / f64::from(self.rounds)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn us(micros: u64) -> Timestamp {
        Timestamp::from_micros(micros)
    }

    fn inputs(exec: Option<ExecReport>) -> DelayInputs {
        DelayInputs {
            captured_at: us(1_000_000),
            now: us(1_010_000),
            queue_wait: Duration::from_millis(20),
            generation: Duration::from_millis(40),
            reply_overhead: Duration::from_millis(2),
            network: Duration::from_millis(3),
            exec,
            sent_at: us(1_000_000),
        }
    }

    #[test]
    fn d_counts_the_robots_ticks_between_capture_and_arrival() {
        // 30 Hz: ticks every 33 333 µs from 900 000 µs (the robot's own rounding).
        let exec = ExecReport {
            started_at: us(900_000),
            actions_remaining: 10,
            control_hz: 30.0,
        };
        let p = predict_delay(&inputs(Some(exec)));
        // Arrival at 1.010 + 0.020 + 0.040 + 0.002 + 0.003 = 1.075 s; ticks after the 1.000 s
        // capture up to then: 1.0000 (no: at 999 999 µs, before), 1.0333, 1.0667.
        assert_eq!(p.arrival, us(1_075_000));
        assert_eq!((p.delay, p.start, p.remaining_at_capture), (2, 2, 10));
        // A robot that runs out executes only what it has.
        let short = ExecReport {
            actions_remaining: 1,
            ..exec
        };
        let p = predict_delay(&inputs(Some(short)));
        assert_eq!((p.delay, p.start), (2, 1));
        // An idle robot (no phase): nothing executes before the chunk.
        let p = predict_delay(&inputs(None));
        assert_eq!((p.delay, p.start, p.remaining_at_capture), (0, 0, 0));
    }

    #[test]
    fn a_tick_between_capture_and_send_was_still_ahead_at_the_capture() {
        // 10 Hz from 0; captured at 1.000 s, sent at 1.150 s with 3 left: one tick (1.1 s)
        // between capture and send, so 4 were left at the capture.
        let exec = ExecReport {
            started_at: us(0),
            actions_remaining: 3,
            control_hz: 10.0,
        };
        let p = predict_delay(&DelayInputs {
            sent_at: us(1_150_000),
            now: us(1_150_000),
            queue_wait: Duration::ZERO,
            generation: Duration::from_millis(100),
            reply_overhead: Duration::ZERO,
            network: Duration::ZERO,
            ..inputs(Some(exec))
        });
        // Arrival 1.25 s: ticks 1.1 and 1.2.
        assert_eq!((p.delay, p.start, p.remaining_at_capture), (2, 2, 4));
    }

    #[test]
    fn the_actual_d_from_times_and_the_estimators() {
        let exec = ExecReport {
            started_at: us(1_250_000),
            actions_remaining: 3,
            control_hz: 10.0,
        };
        assert_eq!(actual_delay_from_times(us(1_000_000), &exec), 2);
        assert_eq!(actual_delay_from_times(us(1_300_000), &exec), 0);
        let mut net = NetworkEstimate::default();
        assert_eq!(net.get(), Duration::ZERO);
        net.observe(us(100), us(900));
        net.observe(us(1_000), us(1_300));
        net.observe(us(2_000), us(2_500));
        assert_eq!(net.get(), Duration::from_micros(300));
        let mut avg = DurationAverage::default();
        avg.observe(Duration::from_millis(8));
        avg.observe(Duration::from_millis(16));
        assert_eq!(avg.get(), Duration::from_millis(9));
        let mut stats = DelayErrorStats::default();
        stats.record(3, 2);
        stats.record(2, 4);
        stats.record(1, 1);
        assert_eq!((stats.rounds, stats.exact, stats.max_abs_error), (3, 1, 2));
        assert!((stats.mean_error() - (-1.0 / 3.0)).abs() < 1e-12);
        assert!((stats.mean_abs_error() - 1.0).abs() < 1e-12);
    }
}
