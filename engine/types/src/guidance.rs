//! Steering one request's sampling toward the actions its robot has already committed to.
//!
//! A robot keeps executing its previous chunk while the next one is generated; the first `d`
//! actions of the new chunk belong to instants whose actions are already fixed. A [`Guidance`]
//! carries those actions (the previous chunk from the observation's capture on) into the
//! sampler, which applies it to the request's rows only, so requests with different guidance
//! (or none) share a batch without changing each other's results.

/// How LeRobot 0.6.1 weighs the previous chunk's actions beyond the committed ones
/// (`RTCAttentionSchedule`, `RTCProcessor.get_prefix_weights`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PrefixSchedule {
    /// 1 on the committed actions, 0 after.
    Zeros,
    /// 1 up to the execution horizon, 0 after.
    Ones,
    /// 1 on the committed actions, then linearly down to 0 at the execution horizon.
    Linear,
    /// As `Linear`, each weight `w` shaped to `w · expm1(w) / (e − 1)`.
    Exp,
}

/// What the sampler does with the committed actions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum GuidanceMode {
    /// Real-time chunking exactly as LeRobot 0.6.1's `RTCProcessor.denoise_step`: the velocity
    /// is computed before the sample is marked as needing a gradient, so the vector–Jacobian
    /// product of its correction is the identity and the correction is the weighted error.
    Rtc,
    /// Real-time chunking as the paper (Black, Galliker, Levine 2025) defines it: the weighted
    /// error pulled back through the velocity network (a true vector–Jacobian product, one
    /// backward pass per step). Only model paths with autograd can run it.
    RtcVjp,
    /// A hard prefix (GR00T-style inpainting): after every step the committed actions are
    /// written into the sample at the current noise level (on the straight path from the
    /// request's own initial noise), so the chunk ends on exactly them.
    Inpaint,
}

impl GuidanceMode {
    /// The mode's name, as the chunking strategies call it.
    pub fn as_str(self) -> &'static str {
        match self {
            GuidanceMode::Rtc => "rtc",
            GuidanceMode::RtcVjp => "rtc_vjp",
            GuidanceMode::Inpaint => "inpaint",
        }
    }
}

/// One request's guidance.
#[derive(Clone, Debug, PartialEq)]
pub struct Guidance {
    /// How it is applied.
    pub mode: GuidanceMode,
    /// The previous chunk from the observation's capture on, in the robot's units (what the
    /// robot executes), `[L][action_dim]` row-major: row `i` is what the robot had planned for
    /// the instant of this chunk's action `i` (LeRobot's `prev_chunk_left_over`). `L` may be
    /// shorter than the chunk (LeRobot pads it with zeros) but not longer.
    pub prefix: Vec<f32>,
    /// How many of `prefix`'s rows the robot executes before the new chunk arrives (LeRobot's
    /// `inference_delay`, the predicted `d`): weight 1 for `rtc`, written in for `inpaint`.
    pub delay: usize,
    /// `rtc`, `rtc_vjp`: how many of `prefix`'s rows guide the chunk at all (LeRobot's
    /// `execution_horizon`, cut to `L`).
    pub execution_horizon: usize,
    /// `rtc`, `rtc_vjp`: the weights between `delay` and `execution_horizon`.
    pub schedule: PrefixSchedule,
    /// `rtc`, `rtc_vjp`: the cap on the guidance weight (LeRobot's `max_guidance_weight`).
    pub max_guidance_weight: f32,
}

impl Guidance {
    /// Rows of `prefix` for a model whose actions have `action_dim` values (0 if it does not
    /// divide).
    pub fn prefix_rows(&self, action_dim: usize) -> usize {
        if action_dim == 0 || !self.prefix.len().is_multiple_of(action_dim) {
            0
        } else {
            self.prefix.len() / action_dim
        }
    }
}

/// Which guidance modes a model (on its current backend) can apply.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct GuidanceSupport {
    /// [`GuidanceMode::Rtc`] and [`GuidanceMode::Inpaint`]: per-row work in the sampler, which
    /// every flow model that samples through it can do.
    pub prefix: bool,
    /// [`GuidanceMode::RtcVjp`]: needs a backward pass through the velocity network.
    pub vjp: bool,
}

impl GuidanceSupport {
    /// No guidance (a model that does not sample with the shared flow sampler).
    pub const NONE: GuidanceSupport = GuidanceSupport {
        prefix: false,
        vjp: false,
    };
    /// `rtc` and `inpaint`, not `rtc_vjp` (the fast CPU kernels have no backward pass).
    pub const PREFIX: GuidanceSupport = GuidanceSupport {
        prefix: true,
        vjp: false,
    };
    /// Every mode.
    pub const ALL: GuidanceSupport = GuidanceSupport {
        prefix: true,
        vjp: true,
    };

    /// Whether `mode` is supported.
    pub fn supports(self, mode: GuidanceMode) -> bool {
        match mode {
            GuidanceMode::Rtc | GuidanceMode::Inpaint => self.prefix,
            GuidanceMode::RtcVjp => self.vjp,
        }
    }
}

/// What the server's chunking strategies may do with a model.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct ModelChunking {
    /// The guidance its sampler applies on its backend.
    pub guidance: GuidanceSupport,
    /// What its actions are (whether a state can be rolled forward through them).
    pub action_space: ActionSpace,
}

/// What a model's actions are, as far as rolling a state forward goes.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub enum ActionSpace {
    /// Not known (velocity commands, deltas, or a model that does not say): the server cannot
    /// predict the state a robot will have after executing actions.
    #[default]
    Unspecified,
    /// Absolute position targets that the robot reaches within a control step: after executing
    /// action `a`, state element `state_index[j]` is `a[j]` (one entry per action value; a
    /// gripper or other value without a state counterpart is `None`).
    AbsolutePosition {
        /// For each action value, the state element it sets.
        state_index: Vec<Option<usize>>,
    },
}

impl ActionSpace {
    /// The state after the robot executed `actions` (`[n][action_dim]`, oldest first) from
    /// `state`: the last action's targets written into their state elements. `None` when the
    /// action space does not allow it, or an index is out of range.
    pub fn roll_forward(
        &self,
        state: &[f32],
        actions: &[f32],
        action_dim: usize,
    ) -> Option<Vec<f32>> {
        let ActionSpace::AbsolutePosition { state_index } = self else {
            return None;
        };
        if action_dim == 0 || state_index.len() != action_dim {
            return None;
        }
        let mut out = state.to_vec();
        let Some(last) = actions.chunks_exact(action_dim).last() else {
            return Some(out);
        };
        for (value, index) in last.iter().zip(state_index) {
            if let Some(i) = *index {
                *out.get_mut(i)? = *value;
            }
        }
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_absolute_position_state_ends_on_the_last_target() {
        let space = ActionSpace::AbsolutePosition {
            state_index: vec![Some(2), Some(0), None],
        };
        let state = [0.0, 1.0, 2.0, 3.0];
        let actions = [9.0, 8.0, 7.0, 5.0, 4.0, 3.0];
        assert_eq!(
            space.roll_forward(&state, &actions, 3),
            Some(vec![4.0, 1.0, 5.0, 3.0])
        );
        assert_eq!(space.roll_forward(&state, &[], 3), Some(state.to_vec()));
        assert_eq!(
            ActionSpace::Unspecified.roll_forward(&state, &actions, 3),
            None
        );
        let out_of_range = ActionSpace::AbsolutePosition {
            state_index: vec![Some(9), None, None],
        };
        assert_eq!(out_of_range.roll_forward(&state, &actions, 3), None);
    }

    #[test]
    fn support_names_what_each_path_can_do() {
        assert!(GuidanceSupport::PREFIX.supports(GuidanceMode::Rtc));
        assert!(GuidanceSupport::PREFIX.supports(GuidanceMode::Inpaint));
        assert!(!GuidanceSupport::PREFIX.supports(GuidanceMode::RtcVjp));
        assert!(GuidanceSupport::ALL.supports(GuidanceMode::RtcVjp));
        assert!(!GuidanceSupport::NONE.supports(GuidanceMode::Rtc));
    }
}
