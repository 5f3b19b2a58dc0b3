//! The robot's execution timeline: which action it executes when, and what a new chunk does to
//! it. This is the execution rule the SDK runner follows too (documented in `docs/TRACES.md`,
//! "The execution rule"), so that a simulated robot and a live one agree.
//!
//! - Actions are executed one per `1/control_hz` while the robot has one to execute; a *step*
//!   is one executed action, counted from the start of the task.
//! - A chunk answers an observation taken at step `o`; its action `j` is meant for step `o + j`,
//!   and only its first `H` actions may be executed, so it covers steps `[o, o + H)`.
//! - When a chunk arrives, the actions meant for steps the robot has already executed (or is
//!   executing) are discarded, and the robot continues with the new chunk from its next step.
//!   A chunk with nothing left to execute is dropped and the old one kept.
//! - With nothing to execute the robot stalls, and resumes the moment a usable chunk arrives.

use crate::time::Timestamp;

/// What happened to a chunk handed to [`Execution::accept`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accepted {
    /// The robot switched to the chunk, discarding this many of its first actions.
    Used {
        /// Actions of the new chunk whose step had already been executed.
        discarded: u32,
        /// Step from which the new chunk is executed.
        from_step: u32,
    },
    /// Every action of the chunk was for a step already executed; the old chunk continues.
    Stale,
}

/// A robot's execution state in virtual time.
#[derive(Clone, Debug)]
pub struct Execution {
    micros_per_step: f64,
    /// Virtual time (µs, fractional) at which action `anchor_step` starts, while executing.
    anchor_us: f64,
    anchor_step: u32,
    /// Exclusive end of the executable steps of the current chunk.
    until: u32,
    /// When the robot started executing the current chunk.
    chunk_started_at: Option<Timestamp>,
}

impl Execution {
    /// A robot at step 0 with nothing to execute yet.
    pub fn new(control_hz: f32) -> Self {
        Execution {
            micros_per_step: 1e6 / f64::from(control_hz),
            anchor_us: 0.0,
            anchor_step: 0,
            until: 0,
            chunk_started_at: None,
        }
    }

    /// Steps the robot may execute before it runs dry (exclusive end of the current chunk).
    pub fn until(&self) -> u32 {
        self.until
    }

    /// When the robot began executing its current chunk (`E.start` of Last Exec Info).
    pub fn chunk_started_at(&self) -> Option<Timestamp> {
        self.chunk_started_at
    }

    /// Actions completed by `now`.
    pub fn completed_at(&self, now: Timestamp) -> u32 {
        if self.until <= self.anchor_step {
            return self.anchor_step;
        }
        let elapsed = now.as_micros() as f64 - self.anchor_us;
        if elapsed <= 0.0 {
            return self.anchor_step;
        }
        // The small epsilon keeps `completed_at(time_of(k)) == k` despite rounding to µs.
        let steps = (elapsed / self.micros_per_step + 1e-9).floor();
        let steps = if steps >= f64::from(u32::MAX) { u32::MAX } else { steps as u32 };
        self.anchor_step.saturating_add(steps).min(self.until)
    }

    /// Whether the robot has nothing left to execute at `now`.
    pub fn is_dry(&self, now: Timestamp) -> bool {
        self.completed_at(now) >= self.until
    }

    /// The earliest time at which `step` actions will have been completed, assuming no new
    /// chunk arrives; `None` if the current chunk runs out before (the robot would stall).
    pub fn time_of(&self, step: u32) -> Option<Timestamp> {
        if step <= self.anchor_step {
            return Some(Timestamp::from_micros(self.anchor_us.max(0.0).ceil() as u64));
        }
        if step > self.until {
            return None;
        }
        let us = self.anchor_us + f64::from(step - self.anchor_step) * self.micros_per_step;
        Some(Timestamp::from_micros(us.ceil() as u64))
    }

    /// A chunk answering an observation taken at step `obs_step`, with horizon `horizon`,
    /// arrives at `now`.
    pub fn accept(&mut self, now: Timestamp, obs_step: u32, horizon: u32) -> Accepted {
        let done = self.completed_at(now);
        let dry = done >= self.until;
        // While executing, the action in progress belongs to the old chunk.
        let from_step = if dry { done } else { done + 1 };
        let end = obs_step.saturating_add(horizon);
        if from_step >= end {
            return Accepted::Stale;
        }
        if dry {
            self.anchor_us = now.as_micros() as f64;
            self.anchor_step = done;
        }
        self.until = end;
        self.chunk_started_at = Some(now);
        Accepted::Used {
            discarded: from_step.saturating_sub(obs_step),
            from_step,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: u64) -> Timestamp {
        Timestamp::from_micros(v * 1000)
    }

    #[test]
    fn a_stalled_robot_resumes_at_its_step_when_a_chunk_arrives() {
        let mut e = Execution::new(10.0); // 100 ms per action
        assert!(e.is_dry(ms(0)));
        assert_eq!(
            e.accept(ms(50), 0, 8),
            Accepted::Used {
                discarded: 0,
                from_step: 0
            }
        );
        assert_eq!(e.completed_at(ms(50)), 0);
        assert_eq!(e.completed_at(ms(349)), 2);
        assert_eq!(e.time_of(4), Some(ms(450)));
        assert_eq!(e.completed_at(ms(450)), 4);
        assert_eq!(e.time_of(8), Some(ms(850)));
        assert_eq!(e.time_of(9), None);
        assert!(e.is_dry(ms(850)));
        assert_eq!(e.completed_at(ms(5000)), 8);
    }

    #[test]
    fn an_early_chunk_discards_the_actions_already_executed() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 8);
        // Observation at step 4 (t=400 ms), reply at 630 ms: steps 4, 5 done, 6 in progress.
        assert_eq!(
            e.accept(ms(630), 4, 8),
            Accepted::Used {
                discarded: 3,
                from_step: 7
            }
        );
        assert_eq!(e.until(), 12);
        // Execution is continuous: step 12 completes at 1200 ms.
        assert_eq!(e.time_of(12), Some(ms(1200)));
    }

    #[test]
    fn a_late_chunk_after_a_stall_discards_what_the_old_chunk_covered() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 8);
        // Observation at step 4; the robot runs dry at 800 ms; the reply arrives at 1000 ms.
        assert!(e.is_dry(ms(1000)));
        assert_eq!(
            e.accept(ms(1000), 4, 8),
            Accepted::Used {
                discarded: 4,
                from_step: 8
            }
        );
        assert_eq!(e.time_of(12), Some(ms(1400)));
        assert_eq!(e.chunk_started_at(), Some(ms(1000)));
    }

    #[test]
    fn a_chunk_with_nothing_left_is_dropped() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 20);
        // Observation at step 2 with horizon 3 covers steps 2..5; at 700 ms step 7 is next.
        assert_eq!(e.accept(ms(700), 2, 3), Accepted::Stale);
        assert_eq!(e.until(), 20);
    }
}
