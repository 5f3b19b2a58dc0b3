//! Replaying horizon decisions with the real horizon policies.
//!
//! A trace round carries, per action, the ratio of its final diffusion update's norm to the mean
//! norm of its earlier updates (`RoundTrace::confidence`). That ratio is everything the §3.1
//! threshold policy reads, so the simulator rebuilds a one-dimensional, two-step chunk whose
//! updates have exactly those norms — step 0 has norm 1, the final step has norm `ratio` — and
//! hands it to the same [`HorizonPolicy`] the action manager runs. Rounds recorded without
//! confidence replay their recorded horizon through the `static` policy.

use kairos_sdk::trace::{HorizonSetting, RoundTrace};

use kairos_core::horizon::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use kairos_core::registry::{HorizonRegistry, Origin};
use kairos_core::scheduler::ServerLoad;

/// Why a horizon setting cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayHorizonError {
    /// The policy refused the rebuilt chunk, or the setting names no native policy.
    #[error(transparent)]
    Policy(#[from] HorizonError),
}

/// One task's horizon policy, fed rebuilt chunks.
pub struct ReplayHorizon {
    policy: Box<dyn HorizonPolicy>,
    fallback: Box<dyn HorizonPolicy>,
    /// What `policy` is handed as the request's parameters: empty for a native policy (built
    /// with the setting's), the setting's for a plugin.
    call_params: PolicyParams,
    recent: Vec<u32>,
    updates: Vec<f32>,
    actions: Vec<f32>,
    fallback_params: PolicyParams,
}

/// Horizons remembered per task for `HorizonInput::recent_horizons`.
const RECENT: usize = 8;

impl ReplayHorizon {
    /// The policy of `setting`, built from the native registry.
    pub fn new(setting: &HorizonSetting) -> Result<Self, ReplayHorizonError> {
        let policy = kairos_core::horizon::builtin(&setting.policy, &setting.params)?;
        Self::with_policy(policy, PolicyParams::new())
    }

    /// The policy of `setting`, built from `registry` (natives and loaded plugins: what
    /// `kairos bench sim --horizon-plugin` replays). A native policy is built with the
    /// setting's parameters; anything else (a plugin checks its parameters on every call, as
    /// in a served request) is handed them with every chunk.
    pub fn with_registry(
        setting: &HorizonSetting,
        registry: &HorizonRegistry,
    ) -> Result<Self, ReplayHorizonError> {
        let policy = registry.resolve(&setting.policy, &setting.params)?;
        let per_call = match registry.origin(&setting.policy) {
            Some(Origin::Native) => PolicyParams::new(),
            _ => setting.params.clone(),
        };
        Self::with_policy(policy, per_call)
    }

    fn with_policy(
        policy: Box<dyn HorizonPolicy>,
        per_call: PolicyParams,
    ) -> Result<Self, ReplayHorizonError> {
        let fallback =
            kairos_core::horizon::builtin("static", &PolicyParams::from([("h".to_string(), 1.0)]))?;
        Ok(ReplayHorizon {
            policy,
            fallback,
            call_params: per_call,
            recent: Vec::with_capacity(RECENT),
            updates: Vec::new(),
            actions: Vec::new(),
            fallback_params: PolicyParams::new(),
        })
    }

    /// The horizon for `round` of a task with chunks of `chunk_len` actions, with no server
    /// load known (trace generation).
    pub fn choose(
        &mut self,
        round: &RoundTrace,
        round_index: u64,
        chunk_len: u32,
        control_hz: f32,
    ) -> Result<u32, ReplayHorizonError> {
        self.choose_under(round, round_index, chunk_len, control_hz, None)
    }

    /// [`ReplayHorizon::choose`] with the server's load at the decision, as the simulated
    /// scheduler reports it ([`kairos_core::scheduler::Scheduler::load`]).
    pub fn choose_under(
        &mut self,
        round: &RoundTrace,
        round_index: u64,
        chunk_len: u32,
        control_hz: f32,
        load: Option<ServerLoad>,
    ) -> Result<u32, ReplayHorizonError> {
        let n = chunk_len as usize;
        self.updates.clear();
        self.updates.resize(n, 1.0);
        match &round.confidence {
            Some(c) => self.updates.extend_from_slice(c),
            None => self.updates.resize(2 * n, 1.0),
        }
        self.actions.clear();
        self.actions.resize(n, 0.0);
        let chunk = ChunkView {
            samples: 1,
            steps: 2,
            chunk_len: n,
            action_dim: 1,
            updates: &self.updates,
            actions: &self.actions,
        };
        let (policy, params) = if round.confidence.is_some() {
            // A native policy was built with the setting's parameters (empty means "use them");
            // a plugin gets them here.
            (&mut self.policy, &self.call_params)
        } else {
            // Without the updates the only faithful replay is the recorded decision.
            self.fallback_params
                .insert("h".to_string(), f64::from(round.horizon));
            (&mut self.fallback, &self.fallback_params)
        };
        let input = HorizonInput {
            chunk,
            h_min: 1,
            h_max: n,
            control_hz,
            round_index,
            recent_horizons: &self.recent,
            params,
            load,
        };
        let h = policy.choose(&input)?;
        let h = kairos_core::horizon::validate_horizon(h, &input)?;
        let h = u32::try_from(h).unwrap_or(chunk_len);
        if self.recent.len() == RECENT {
            self.recent.remove(0);
        }
        self.recent.push(h);
        Ok(h)
    }
}

/// Per-action confidence ratios for a chunk whose threshold-`t` horizon is `target`: action `n`
/// gets `1 + t·(n + ½)/target`, so the first action above `1 + t` is action `target` and the
/// threshold policy answers exactly `target` (higher thresholds answer proportionally more).
pub fn confidence_for_target(target: u32, threshold: f64, chunk_len: u32) -> Vec<f32> {
    let target = f64::from(target.max(1));
    (0..chunk_len)
        .map(|n| (1.0 + threshold * (f64::from(n) + 0.5) / target) as f32)
        .collect()
}
