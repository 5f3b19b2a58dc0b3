//! Contact-aware: execute the chunk through free-space transit, and hand control back just
//! before the chunk's own plan reaches a contact.
//!
//! Manipulation fails at contact (grasping an object that was knocked, releasing where noise
//! took the gripper), not on the way there: a plan that is still far from its target can run
//! open loop, a plan that is about to touch something should be re-made from a fresh
//! observation. The chunk itself says where its contact is: the plan **slows down** for a
//! target (precise contact needs it), or it **switches the gripper** (grasp, release). So this
//! rule cuts `margin` actions before the first such event, and executes only `h_min` once the
//! plan is already slow (inside the contact phase). It assumes velocity-like actions whose last
//! dimension is the gripper command (`> 0` closes), as in `kairos bench horizon`'s task.
//!
//! A planned **release** is the exception. Placing an object is a contact too, but there the
//! cut backfires: executing one action at a time, the robot re-plans at every step over the
//! goal, and each fresh plan puts the opening of the gripper a few actions later again, so the
//! release keeps being postponed while the object may slip (`docs/EVALUATION.md`, "A second
//! task"). With parameter `release` = `R`, when enough of the `S` samples drawn for the
//! observation (`quorum` of them) agree that the plan holds the object now and opens the
//! gripper at one of its actions 1..=`R` (0-based), the rule executes `R` actions: through the
//! release, or up to it when it is action `R` itself (then the next plan starts at the release).
//! A single sample is a noisy reading of the plan (the model's chunks at a grasp also open and
//! close again at times); several samples that agree are not.
//!
//! Exact semantics (a plugin twin must reproduce them bit for bit), over the final actions
//! `A[s][n][d]` of the `S` samples, `D` = action dimension, in `f64` widened from `f32`, no fused
//! multiply-add:
//!
//! 1. `speed_n = sqrt(Σ_{d < D−1} A[0][n][d]²)` (sample 0, dimension order; 0 when `D = 1`).
//! 2. `event` = the first `n ≥ 0` with `!(speed_n >= slow)` (a NaN counts as slow), or with
//!    `n ≥ 1` and `(A[0][n][D−1] > 0) != (A[0][n−1][D−1] > 0)` (the gripper switches), or `N`
//!    if there is none.
//! 3. `prefix = event − margin` if `event > margin`, else 0.
//! 4. Only with parameter `release` = `R`: sample `s` *plans a release* if `A[s][0][D−1] > 0`
//!    and `!(A[s][n][D−1] > 0)` for some `1 ≤ n ≤ min(R, N − 1)` (a NaN counts as open). If at
//!    least `quorum` samples plan a release, `prefix = max(prefix, R)`.
//! 5. `H = min(max(prefix, h_min), h_max)` with `h_min = max(input.h_min, param h_min)` and
//!    `h_max = min(input.h_max, N, param h_max)` (an `h_max` below `h_min` is raised to it), as
//!    in [`super::steady`].
//!
//! Parameters: `slow` (default 0.5, action units: the velocity command's norm below which the
//! plan counts as slowing for contact), `margin` (whole number ≥ 0, default 1), `h_min`
//! (optional), `h_max` (optional cap, whole number ≥ 1), `release` (optional whole number ≥ 1:
//! step 4's `R`; absent, step 4 is off) and `quorum` (whole number ≥ 1, default 1: the samples
//! that must agree; more than `S` never do). They are checked in that order, after unknown
//! names.

use super::params::{count, real, reject_unknown, whole};
use super::steady::clamp_with_cap;
use super::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};

/// Default speed below which the plan counts as slowing for a contact.
pub const DEFAULT_SLOW: f64 = 0.5;
/// Default number of actions cut before the first contact event.
pub const DEFAULT_MARGIN: usize = 1;
/// Default number of samples that must plan a release (step 4 of the module doc).
pub const DEFAULT_QUORUM: usize = 1;

/// The contact-aware policy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactAware {
    /// Speed (norm of the velocity dimensions) below which an action counts as slow.
    pub slow: f64,
    /// Actions cut before the first contact event.
    pub margin: usize,
    /// Lower bound on top of the robot's `h_min`.
    pub h_min: Option<usize>,
    /// Upper bound on top of the robot's `h_max`.
    pub h_max: Option<usize>,
    /// Step 4: execute this many actions through a planned release (`None`: off).
    pub release: Option<usize>,
    /// Step 4: samples that must plan the release.
    pub quorum: usize,
}

impl Default for ContactAware {
    fn default() -> Self {
        ContactAware {
            slow: DEFAULT_SLOW,
            margin: DEFAULT_MARGIN,
            h_min: None,
            h_max: None,
            release: None,
            quorum: DEFAULT_QUORUM,
        }
    }
}

impl ContactAware {
    /// Reads `slow`, `margin`, `h_min`, `h_max`, `release` and `quorum`; any other name is an
    /// error.
    pub fn from_params(params: &PolicyParams) -> Result<Self, HorizonError> {
        reject_unknown(
            params,
            &["slow", "margin", "h_min", "h_max", "release", "quorum"],
        )?;
        Ok(ContactAware {
            margin: whole(params, "margin", DEFAULT_MARGIN)?,
            slow: real(params, "slow", 0.0, Some(DEFAULT_SLOW))?.unwrap_or(DEFAULT_SLOW),
            h_min: count(params, "h_min")?,
            h_max: count(params, "h_max")?,
            release: count(params, "release")?,
            quorum: count(params, "quorum")?.unwrap_or(DEFAULT_QUORUM),
        })
    }
}

/// `speed_n` of step 1 of the module doc: the norm of action `n`'s velocity dimensions (all but
/// the last) in sample 0.
pub fn planned_speed(chunk: &ChunkView<'_>, n: usize) -> f64 {
    let a = chunk.action(0, n);
    let mut acc = 0.0f64;
    for &x in &a[..a.len().saturating_sub(1)] {
        let x = f64::from(x);
        acc += x * x;
    }
    acc.sqrt()
}

/// Whether the gripper command (the last dimension) of action `n ≥ 1` of sample 0 differs in
/// sign from action `n − 1`'s.
pub fn gripper_switches(chunk: &ChunkView<'_>, n: usize) -> bool {
    let d = chunk.action_dim;
    let closed = |n: usize| chunk.action(0, n)[d - 1] > 0.0;
    closed(n) != closed(n - 1)
}

/// `event` of step 2 of the module doc: the first action that is slow or switches the gripper,
/// or `N`.
pub fn first_contact(chunk: &ChunkView<'_>, slow: f64) -> usize {
    (0..chunk.chunk_len)
        .find(|&n| {
            // Written so that a NaN speed counts as slow.
            let fast = planned_speed(chunk, n) >= slow;
            !fast || (n >= 1 && gripper_switches(chunk, n))
        })
        .unwrap_or(chunk.chunk_len)
}

/// Step 4 of the module doc: how many samples hold the object at action 0 (gripper command
/// `> 0`) and open the gripper within actions `1..=min(within, N − 1)`.
pub fn planned_releases(chunk: &ChunkView<'_>, within: usize) -> usize {
    let d = chunk.action_dim;
    if d == 0 {
        // No gripper dimension: nothing can be released.
        return 0;
    }
    let last = within.min(chunk.chunk_len.saturating_sub(1));
    (0..chunk.samples)
        .filter(|&s| {
            // Written so that a NaN gripper command counts as open.
            let closed = |n: usize| chunk.action(s, n)[d - 1] > 0.0;
            closed(0) && (1..=last).any(|n| !closed(n))
        })
        .count()
}

impl HorizonPolicy for ContactAware {
    fn name(&self) -> &str {
        "contact"
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let config = if input.params.is_empty() {
            *self
        } else {
            ContactAware::from_params(input.params)?
        };
        if !input.chunk.is_consistent() {
            return Err(HorizonError::Unsupported(
                "chunk buffers do not match their dimensions".into(),
            ));
        }
        let mut prefix = first_contact(&input.chunk, config.slow).saturating_sub(config.margin);
        if let Some(release) = config.release
            && planned_releases(&input.chunk, release) >= config.quorum
        {
            prefix = prefix.max(release);
        }
        clamp_with_cap(prefix, config.h_min, config.h_max, input)
    }
}
