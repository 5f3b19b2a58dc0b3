//! Execution-horizon policies: how many actions of a generated chunk the robot may execute.
//!
//! The action manager calls a [`HorizonPolicy`] on the return path of every round (paper §3.1,
//! "Action Manager" in §4). Policies are pure: everything they may look at is in
//! [`HorizonInput`], so a native policy, a WASM plugin and the simulator's replay all see the
//! same thing. The answer is validated by [`validate_horizon`] before anyone uses it.
//!
//! Native policies (each module documents its exact arithmetic, for plugin twins):
//! - [`threshold`]: the paper's §3.1 confidence threshold (default);
//! - [`fixed`]: a static horizon `h`;
//! - [`spread`]: agreement across `S ≥ 2` samples of the chunk;
//! - [`steady`]: execute while the chunk's actions stay steady, cut before the chunk changes
//!   course (the closed-loop bench's best trade-off, `docs/eval/horizon/`).
//! - [`contact`]: execute through transit, cut before the chunk's planned contact (slows down
//!   or switches the gripper), but run through a release that several samples agree on (the
//!   contact task's policy, `docs/eval/horizon-contact/`);
//! - [`load_aware`]: the threshold rule, lengthened by the server's backlog (reads
//!   [`HorizonInput::load`]).
//!
//! [`NATIVE_POLICIES`] is their table (what the horizon registry registers); [`builtin`] builds
//! one by name with validated parameters. The parameters given there are the
//! policy's defaults; a non-empty [`HorizonInput::params`] overrides them for that call (validated
//! the same way), so one instance can serve requests with different parameters.

pub mod contact;
pub mod fixed;
pub mod load_aware;
mod params;
pub mod spread;
pub mod steady;
pub mod threshold;

use std::collections::BTreeMap;

use crate::registry::{HorizonKind, Native, build_native};
use crate::scheduler::{RobotId, ServerLoad};

/// User parameters of a policy, e.g. `{"t": 0.4, "h_min": 8}`. Sorted, so hashing and
/// wire encoding are deterministic.
pub type PolicyParams = BTreeMap<String, f64>;

/// A read-only view of one generated chunk and the diffusion updates that produced it.
///
/// Flat row-major layouts, identical to `kairos_engine_types::ActionChunk`:
/// `updates` is `[samples][steps][chunk_len][action_dim]`, `actions` is
/// `[samples][chunk_len][action_dim]`.
#[derive(Clone, Copy, Debug)]
pub struct ChunkView<'a> {
    /// Samples `S` drawn for this observation (1 unless the request asked for more).
    pub samples: usize,
    /// Refinement steps `K`.
    pub steps: usize,
    /// Actions per chunk `N`.
    pub chunk_len: usize,
    /// Action dimension `D`.
    pub action_dim: usize,
    /// `[S][K][N][D]` per-step updates.
    pub updates: &'a [f32],
    /// `[S][N][D]` final actions.
    pub actions: &'a [f32],
}

impl<'a> ChunkView<'a> {
    /// The update vector (length `D`) that step `k` applied to action `n` of sample `s`.
    pub fn update(&self, s: usize, k: usize, n: usize) -> &'a [f32] {
        let d = self.action_dim;
        let start = ((s * self.steps + k) * self.chunk_len + n) * d;
        &self.updates[start..start + d]
    }

    /// Final action `n` of sample `s` (length `D`).
    pub fn action(&self, s: usize, n: usize) -> &'a [f32] {
        let d = self.action_dim;
        let start = (s * self.chunk_len + n) * d;
        &self.actions[start..start + d]
    }

    /// Whether the flat buffers have the lengths the dimensions promise.
    pub fn is_consistent(&self) -> bool {
        let per_sample = self.chunk_len * self.action_dim;
        self.samples >= 1
            && self.steps >= 1
            && self.chunk_len >= 1
            && self.action_dim >= 1
            && self.updates.len() == self.samples * self.steps * per_sample
            && self.actions.len() == self.samples * per_sample
    }
}

/// Everything a horizon policy may base its decision on.
#[derive(Clone, Copy, Debug)]
pub struct HorizonInput<'a> {
    /// The chunk and its updates.
    pub chunk: ChunkView<'a>,
    /// Smallest horizon the robot accepts (`H_min` in §3.1); at least 1.
    pub h_min: usize,
    /// Largest horizon the robot accepts; at most `chunk.chunk_len`.
    pub h_max: usize,
    /// The robot's control frequency, actions per second.
    pub control_hz: f32,
    /// Index of this round within its task (0 for the first chunk).
    pub round_index: u64,
    /// Horizons chosen for this task's most recent rounds, oldest first (bounded).
    pub recent_horizons: &'a [u32],
    /// The request's policy parameters.
    pub params: &'a PolicyParams,
    /// The server's load when the chunk's forward pass ended ([`Scheduler::load`]); `None`
    /// where there is no server (trace generation, conformance cases without it). Plugins see it
    /// from `kairos:policy@0.3.0` on.
    ///
    /// [`Scheduler::load`]: crate::scheduler::Scheduler::load
    pub load: Option<ServerLoad>,
}

/// Why a policy could not decide.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HorizonError {
    /// A parameter is missing or out of range.
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParam {
        /// Parameter name.
        name: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The input lacks what the policy needs (e.g. a spread policy given one sample).
    #[error("unsupported input: {0}")]
    Unsupported(String),
    /// The policy answered something outside `[h_min, h_max]`.
    #[error("horizon {horizon} is outside [{h_min}, {h_max}]")]
    OutOfRange {
        /// The answer.
        horizon: usize,
        /// Lower bound.
        h_min: usize,
        /// Upper bound.
        h_max: usize,
    },
    /// The policy failed (a trap, a timeout or a refusal inside a plugin).
    #[error("policy failed: {0}")]
    Failed(String),
}

/// A rule that maps a generated chunk to the number of actions to execute.
pub trait HorizonPolicy: Send {
    /// A short stable name (`threshold`, `static`, a plugin's name).
    fn name(&self) -> &str;

    /// Choose the horizon `H` for this round, `h_min <= H <= h_max`.
    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError>;

    /// The policy that produced the last successful [`choose`](Self::choose), when it was not this
    /// policy's own logic: a plugin whose call failed (timeout, trap, quarantine) answers through
    /// its native fallback, and the reply must name the policy that really chose `H`
    /// (`docs/PROTOCOL.md` §6). `None`: this policy answered itself.
    fn answered_by(&self) -> Option<&str> {
        None
    }

    /// Tells the policy which robot's rounds it decides, once, when the server builds it for a
    /// round ([`ActionManager::build_for`](crate::action::ActionManager::build_for)). A policy
    /// that keeps state across rounds of many robots scopes it by robot: a plugin's quarantine
    /// is the robot's first, so one robot's inputs cannot take the plugin from the others.
    /// Default: ignored.
    fn serve_robot(&mut self, _robot: RobotId) {}
}

/// Checks that a policy's answer can be executed: `h_min <= horizon <= h_max`.
pub fn validate_horizon(horizon: usize, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
    if horizon < input.h_min || horizon > input.h_max || horizon == 0 {
        return Err(HorizonError::OutOfRange {
            horizon,
            h_min: input.h_min,
            h_max: input.h_max,
        });
    }
    Ok(horizon)
}

/// The native horizon policies: the one table [`crate::registry::HorizonRegistry`] registers.
pub const NATIVE_POLICIES: &[Native<HorizonKind>] = &[
    Native {
        name: "threshold",
        summary: "paper §3.1: cut at the first action whose final diffusion update exceeds (1+t)x its earlier mean; params t (0.4), h_min, step (the step read, default the last)",
        build: build_threshold,
    },
    Native {
        name: "static",
        summary: "always h actions; param h (required)",
        build: build_static,
    },
    Native {
        name: "spread",
        summary: "cut where S>=2 samples disagree by more than threshold (RMS std over dims); params threshold (0.1), h_min",
        build: build_spread,
    },
    Native {
        name: "steady",
        summary: "execute while consecutive actions differ by <= delta, cut margin actions before the first change; params delta (0.25), margin (1), h_min, h_max",
        build: build_steady,
    },
    Native {
        name: "contact",
        summary: "execute until the chunk plans a contact (speed of the velocity dims < slow, or the last dim, the gripper, switches sign), cut margin actions before, but execute release actions when quorum samples plan to open the held gripper within them; params slow (0.5), margin (1), h_min, h_max, release, quorum (1)",
        build: build_contact,
    },
    Native {
        name: "load-aware",
        summary: "threshold rule plus the actions the server's backlog lasts (longer H when busy); params t (0.4), h_min, gain (1)",
        build: build_load_aware,
    },
];

fn build_load_aware(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(load_aware::LoadAware::from_params(params)?))
}

fn build_threshold(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(threshold::Threshold::from_params(params)?))
}

fn build_static(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(fixed::StaticHorizon::from_params(params)?))
}

fn build_spread(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(spread::Spread::from_params(params)?))
}

fn build_contact(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(contact::ContactAware::from_params(params)?))
}

fn build_steady(params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    Ok(Box::new(steady::Steady::from_params(params)?))
}

/// Builds the native policy `name` with `params` (validated: unknown names, out-of-range or
/// non-integral values are errors), from [`NATIVE_POLICIES`].
pub fn builtin(name: &str, params: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
    build_native::<HorizonKind>(name, params)
}

#[cfg(test)]
mod tests;
