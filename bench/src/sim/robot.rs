//! The robot's execution timeline in virtual time: which action starts when, and what a new
//! chunk does to it.
//!
//! This is the execution rule of the SDK's `ChunkExecutor` / `RobotRunner`
//! (`kairos_sdk::robot`, documented in `docs/TRACES.md`, "The execution rule"), restated over
//! continuous time so the simulator can jump from event to event:
//!
//! - Actions start one per control period (a *tick*) while the robot has one; a robot that was
//!   idle starts the first action of a newly arrived chunk at once. A *step* is one started action,
//!   counted from the start of the task; `started_at(t)` counts the ticks at or before `t`.
//! - A chunk answers an observation captured when `c` actions had started; its action `j` is
//!   meant for step `c + j`, and only its first `H` actions may run, so it covers `[c, c + H)`.
//! - When it arrives, its actions for the steps already started are discarded and the robot
//!   continues with it from its next tick; the old chunk's remaining actions are dropped. A chunk
//!   with nothing left (`started ≥ c + H`) is ignored and the old one keeps running.
//! - With nothing left to start the robot idles from the tick that found no action.

use kairos_core::time::Timestamp;

/// What happened to a chunk handed to [`Execution::accept`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accepted {
    /// The robot switched to the chunk.
    Used {
        /// Actions of the new chunk discarded because their step had already started.
        discarded: u32,
        /// Step from which the new chunk runs.
        from_step: u32,
    },
    /// Every action of the chunk was for a step already started; the old chunk continues.
    Stale,
}

/// A robot's execution state in virtual time.
#[derive(Clone, Debug)]
pub struct Execution {
    micros_per_step: f64,
    /// Tick time (µs, fractional) of action `anchor_step`.
    anchor_us: f64,
    anchor_step: u32,
    /// Exclusive end of the steps the current chunk covers.
    until: u32,
    /// Tick time of the current chunk's first executed action.
    chunk_started_at: Option<Timestamp>,
}

impl Execution {
    /// A robot with nothing to execute yet, no action started.
    pub fn new(control_hz: f32) -> Self {
        Execution {
            micros_per_step: 1e6 / f64::from(control_hz),
            anchor_us: 0.0,
            anchor_step: 0,
            until: 0,
            chunk_started_at: None,
        }
    }

    /// Exclusive end of the steps the current chunk covers: the robot idles once it has
    /// started this many actions.
    pub fn until(&self) -> u32 {
        self.until
    }

    /// Tick time of the current chunk's first executed action (`E.start` of Last Exec Info).
    pub fn chunk_started_at(&self) -> Option<Timestamp> {
        self.chunk_started_at
    }

    fn tick_us(&self, step: u32) -> f64 {
        self.anchor_us + f64::from(step.saturating_sub(self.anchor_step)) * self.micros_per_step
    }

    /// Actions started by `now` (ticks at or before `now`).
    pub fn started_at(&self, now: Timestamp) -> u32 {
        if self.until <= self.anchor_step {
            return self.anchor_step;
        }
        let elapsed = now.as_micros() as f64 - self.anchor_us;
        if elapsed < 0.0 {
            return self.anchor_step;
        }
        // The epsilon keeps `started_at(tick_of(k)) == k + 1` despite rounding to whole µs.
        let ticks = (elapsed / self.micros_per_step + 1e-9).floor() + 1.0;
        let ticks = if ticks >= f64::from(u32::MAX) {
            u32::MAX
        } else {
            ticks as u32
        };
        self.anchor_step.saturating_add(ticks).min(self.until)
    }

    /// When action `step` starts, if the current chunk covers it (`step < until`).
    pub fn tick_of(&self, step: u32) -> Option<Timestamp> {
        if step >= self.until || step < self.anchor_step {
            return None;
        }
        Some(Timestamp::from_micros(self.tick_us(step).ceil() as u64))
    }

    /// When the robot has started `count` actions (the tick of action `count − 1`), or `now`-
    /// independent `None` if the current chunk runs out first. `count = 0` is the anchor.
    pub fn reaches(&self, count: u32) -> Option<Timestamp> {
        if count <= self.anchor_step {
            return Some(Timestamp::from_micros(self.anchor_us.max(0.0).ceil() as u64));
        }
        self.tick_of(count - 1)
    }

    /// Whether the robot has nothing left to start at `now` (the tick after its last action).
    pub fn is_idle(&self, now: Timestamp) -> bool {
        self.started_at(now) >= self.until && now.as_micros() as f64 >= self.tick_us(self.until)
    }

    /// A chunk answering an observation captured after `obs_step` started actions, with
    /// horizon `horizon`, arrives at `now`.
    pub fn accept(&mut self, now: Timestamp, obs_step: u32, horizon: u32) -> Accepted {
        let started = self.started_at(now);
        let end = obs_step.saturating_add(horizon);
        if started >= end {
            return Accepted::Stale;
        }
        if self.is_idle(now) {
            // An idle robot starts the new chunk's first action at once.
            self.anchor_us = now.as_micros() as f64;
            self.anchor_step = started;
        }
        self.until = end;
        self.chunk_started_at = Some(Timestamp::from_micros(self.tick_us(started).ceil() as u64));
        Accepted::Used {
            discarded: started.saturating_sub(obs_step),
            from_step: started,
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
    fn an_idle_robot_starts_a_new_chunk_at_once() {
        let mut e = Execution::new(10.0); // one action per 100 ms
        assert!(e.is_idle(ms(0)));
        assert_eq!(e.started_at(ms(0)), 0);
        assert_eq!(
            e.accept(ms(50), 0, 8),
            Accepted::Used {
                discarded: 0,
                from_step: 0
            }
        );
        assert_eq!(e.chunk_started_at(), Some(ms(50)));
        assert_eq!(e.started_at(ms(50)), 1, "action 0 starts on arrival");
        assert_eq!(e.started_at(ms(149)), 1);
        assert_eq!(e.started_at(ms(150)), 2);
        assert_eq!(e.tick_of(4), Some(ms(450)));
        assert_eq!(e.reaches(5), Some(ms(450)));
        assert_eq!(e.tick_of(7), Some(ms(750)), "the last covered action");
        assert_eq!(e.tick_of(8), None);
        assert!(!e.is_idle(ms(849)));
        assert!(
            e.is_idle(ms(850)),
            "idle from the tick that finds no action"
        );
        assert_eq!(e.started_at(ms(5000)), 8);
    }

    #[test]
    fn a_chunk_arriving_mid_chunk_discards_the_steps_already_started() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 8);
        // Observation captured after 5 starts (the request went out at the tick of action 4,
        // t = 400 ms); reply at 630 ms: actions 5 and 6 have started since (ticks at 500, 600).
        assert_eq!(
            e.accept(ms(630), 5, 8),
            Accepted::Used {
                discarded: 2,
                from_step: 7
            }
        );
        assert_eq!(e.until(), 13);
        assert_eq!(
            e.chunk_started_at(),
            Some(ms(700)),
            "its first action runs at the next tick"
        );
        assert_eq!(e.tick_of(12), Some(ms(1200)), "the tick phase is kept");
    }

    #[test]
    fn a_late_chunk_after_idling_discards_what_the_old_chunk_covered() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 8);
        // Observation after 5 starts; the robot idles from 800 ms; the reply arrives at 1000 ms.
        assert!(e.is_idle(ms(1000)));
        assert_eq!(
            e.accept(ms(1000), 5, 8),
            Accepted::Used {
                discarded: 3,
                from_step: 8
            }
        );
        assert_eq!(e.chunk_started_at(), Some(ms(1000)));
        assert_eq!(e.tick_of(12), Some(ms(1400)));
    }

    #[test]
    fn a_chunk_with_nothing_left_is_ignored() {
        let mut e = Execution::new(10.0);
        e.accept(ms(0), 0, 20);
        // Observation after 2 starts, horizon 3: covers steps 2..5; at 700 ms 8 have started.
        assert_eq!(e.accept(ms(700), 2, 3), Accepted::Stale);
        assert_eq!(e.until(), 20);
    }
}
