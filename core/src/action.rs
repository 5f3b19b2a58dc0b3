//! The action manager: the return path of every round (paper §4, "Action Manager").
//!
//! For each generated chunk it runs the round's horizon policy on the per-step updates `U`,
//! checks the answer with [`validate_horizon`], falls back to the server's default *native*
//! policy when the requested one fails or answers out of range (counted, and named in the
//! reply's `policy` field), trims the chunk to `H` actions of sample 0, and builds the `Reply`.
//! The policy object comes from the [`HorizonRegistry`], so native policies and WASM plugins are
//! called the same way.
//!
//! Every call here may block (a plugin waits for its sandbox up to its deadline), so the driver
//! calls [`ActionManager::answer_batch`] on tokio's blocking pool, never on a runtime worker.

use std::collections::BTreeMap;
use std::sync::Mutex;

use kairos_engine_types::ActionChunk;
use kairos_protocol::{ErrorReply, Reply, Tensor, Timing};

use crate::error::RoundError;
use crate::horizon::{
    ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams, validate_horizon,
};
use crate::registry::{Factory, HorizonRegistry};
use crate::scheduler::{RequestId, RobotId, ServerLoad};
use crate::sync::lock;

/// The horizon policy a round asked for, already built (its parameters validated).
pub struct RoundPolicy {
    /// The policy object.
    pub policy: Box<dyn HorizonPolicy>,
    /// Its parameters, passed again on every call (policies may be shared by plugins' workers).
    pub params: PolicyParams,
}

impl std::fmt::Debug for RoundPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RoundPolicy")
            .field("policy", &self.policy.name())
            .field("params", &self.params)
            .finish()
    }
}

/// What the robot's execution context adds to the policy's input.
#[derive(Clone, Copy, Debug)]
pub struct RoundContext<'a> {
    /// Actions per second the robot executes at (1.0 when the robot has not said).
    pub control_hz: f32,
    /// Answered rounds of the task before this one.
    pub round_index: u64,
    /// Horizons of the task's most recent rounds, oldest first.
    pub recent_horizons: &'a [u32],
    /// The server's load when the batch's forward pass ended (`None`: not known).
    pub load: Option<ServerLoad>,
}

/// The horizon chosen for one chunk.
#[derive(Clone, Debug, PartialEq)]
pub struct HorizonChoice {
    /// Actions the robot may execute.
    pub horizon: usize,
    /// The policy that chose it.
    pub policy: String,
    /// Why the requested policy was not used, when the fallback answered.
    pub fallback_reason: Option<HorizonError>,
}

/// Neither the requested policy nor the native fallback produced a horizon (only possible for a
/// chunk whose buffers do not match its dimensions, which the engine pool already refuses).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "no horizon: the requested policy failed ({requested}) and so did the fallback ({fallback})"
)]
pub struct NoHorizon {
    /// The requested policy's error.
    pub requested: HorizonError,
    /// The fallback's error.
    pub fallback: HorizonError,
}

/// Applies horizon policies to finished chunks. Shared by every batch task.
pub struct ActionManager {
    registry: HorizonRegistry,
    default_policy: String,
    default_params: PolicyParams,
    fallback_policy: String,
    fallback_params: PolicyParams,
    /// Always the native factory, even if a plugin shadows its name for requests.
    fallback_factory: Factory<dyn HorizonPolicy, PolicyParams, HorizonError>,
    /// Decisions the fallback answered, by the policy that failed: every registered policy from
    /// the start, at zero (names are bounded by the registry), so that a rate over them sees the
    /// first fallback. The server exports these counts; nothing else counts them.
    fallbacks: Mutex<BTreeMap<String, u64>>,
}

impl std::fmt::Debug for ActionManager {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ActionManager")
            .field("policies", &self.registry.names().collect::<Vec<_>>())
            .field("default_policy", &self.default_policy)
            .field("fallback_policy", &self.fallback_policy)
            .finish_non_exhaustive()
    }
}

/// The default horizon policy cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ActionConfigError {
    /// No policy of that name is registered.
    #[error("default horizon policy `{0}` is not registered")]
    Unknown(String),
    /// Its parameters are invalid.
    #[error("default horizon policy `{policy}`: {error}")]
    Params {
        /// The policy.
        policy: String,
        /// What is wrong.
        error: HorizonError,
    },
}

/// The native policy used as the fallback when the default is not native.
pub const NATIVE_FALLBACK: &str = "threshold";

impl ActionManager {
    /// An action manager whose default policy (used when a request names none) is
    /// `default_policy` with `default_params`. Requests may name anything in `registry` or
    /// `natives` (`registry` wins on a name clash, so a plugin may shadow a native policy). The
    /// fallback is always a native policy: the default if it is native, else `threshold` with its
    /// default parameters.
    pub fn new(
        registry: HorizonRegistry,
        natives: &HorizonRegistry,
        default_policy: &str,
        default_params: PolicyParams,
    ) -> Result<ActionManager, ActionConfigError> {
        let mut merged = natives.clone();
        merged.extend(registry);
        match merged.build(default_policy, &default_params) {
            None => return Err(ActionConfigError::Unknown(default_policy.to_string())),
            Some(Err(error)) => {
                return Err(ActionConfigError::Params {
                    policy: default_policy.to_string(),
                    error,
                });
            }
            Some(Ok(_)) => {}
        }
        let (fallback_policy, fallback_params) = if natives.contains(default_policy) {
            (default_policy.to_string(), default_params.clone())
        } else {
            (NATIVE_FALLBACK.to_string(), PolicyParams::new())
        };
        let fallback_factory = natives
            .factory(&fallback_policy)
            .cloned()
            .ok_or_else(|| ActionConfigError::Unknown(fallback_policy.clone()))?;
        if let Err(error) = fallback_factory(&fallback_params) {
            return Err(ActionConfigError::Params {
                policy: fallback_policy,
                error,
            });
        }
        let fallbacks = merged.names().map(|name| (name.to_string(), 0)).collect();
        Ok(ActionManager {
            registry: merged,
            default_policy: default_policy.to_string(),
            default_params,
            fallback_policy,
            fallback_params,
            fallback_factory,
            fallbacks: Mutex::new(fallbacks),
        })
    }

    /// The registry requests' policies are built from.
    pub fn registry(&self) -> &HorizonRegistry {
        &self.registry
    }

    /// The default policy's name and parameters.
    pub fn default_selection(&self) -> (&str, &PolicyParams) {
        (&self.default_policy, &self.default_params)
    }

    /// Builds the policy a request named; `None` means "the default".
    pub fn build(
        &self,
        name: Option<&str>,
        params: Option<&PolicyParams>,
    ) -> Result<RoundPolicy, PolicyLookupError> {
        let (name, params) = match name {
            Some(name) => (name, params.cloned().unwrap_or_default()),
            None => (self.default_policy.as_str(), self.default_params.clone()),
        };
        match self.registry.build(name, &params) {
            None => Err(PolicyLookupError::Unknown {
                name: name.to_string(),
                known: self.registry.names().collect::<Vec<_>>().join(", "),
            }),
            Some(Err(error)) => Err(PolicyLookupError::Params {
                name: name.to_string(),
                error,
            }),
            Some(Ok(policy)) => Ok(RoundPolicy { policy, params }),
        }
    }

    /// [`ActionManager::build`] for a round of `robot`: the policy is told whose rounds it
    /// decides ([`HorizonPolicy::serve_robot`]).
    pub fn build_for(
        &self,
        robot: RobotId,
        name: Option<&str>,
        params: Option<&PolicyParams>,
    ) -> Result<RoundPolicy, PolicyLookupError> {
        let mut round = self.build(name, params)?;
        round.policy.serve_robot(robot);
        Ok(round)
    }

    /// How many times the fallback answered since start.
    pub fn fallback_count(&self) -> u64 {
        self.fallbacks_by_policy().values().sum()
    }

    /// How many times the fallback answered since start, by the policy that failed.
    pub fn fallbacks_by_policy(&self) -> BTreeMap<String, u64> {
        lock(&self.fallbacks).clone()
    }

    /// Chooses `H` for `chunk` with the round's policy, falling back to the native default.
    pub fn choose(
        &self,
        round: &mut RoundPolicy,
        chunk: &ActionChunk,
        context: RoundContext<'_>,
    ) -> Result<HorizonChoice, NoHorizon> {
        let view = ChunkView {
            samples: chunk.samples,
            steps: chunk.steps,
            chunk_len: chunk.chunk_len,
            action_dim: chunk.action_dim,
            updates: &chunk.updates,
            actions: &chunk.actions,
        };
        let input = |params| HorizonInput {
            chunk: view,
            h_min: 1,
            h_max: chunk.chunk_len,
            control_hz: context.control_hz,
            round_index: context.round_index,
            recent_horizons: context.recent_horizons,
            params,
            load: context.load,
        };
        let requested_input = input(&round.params);
        let requested = round
            .policy
            .choose(&requested_input)
            .and_then(|h| validate_horizon(h, &requested_input));
        let requested_error = match requested {
            Ok(horizon) => {
                // A plugin that failed internally answered through its own native fallback: the
                // reply names that policy, not the plugin (PROTOCOL.md §6).
                let answered_by = round.policy.answered_by();
                return Ok(HorizonChoice {
                    horizon,
                    policy: answered_by.unwrap_or(round.policy.name()).to_string(),
                    fallback_reason: None,
                });
            }
            Err(error) => error,
        };
        *lock(&self.fallbacks)
            .entry(round.policy.name().to_string())
            .or_insert(0) += 1;
        tracing::warn!(policy = round.policy.name(), error = %requested_error,
            fallback = %self.fallback_policy, "horizon policy failed; using the native fallback");
        let fallback_input = input(&self.fallback_params);
        let fallback = (self.fallback_factory)(&self.fallback_params).and_then(|mut policy| {
            policy
                .choose(&fallback_input)
                .and_then(|h| validate_horizon(h, &fallback_input))
        });
        match fallback {
            Ok(horizon) => Ok(HorizonChoice {
                horizon,
                policy: self.fallback_policy.clone(),
                fallback_reason: Some(requested_error),
            }),
            Err(fallback) => Err(NoHorizon {
                requested: requested_error,
                fallback,
            }),
        }
    }
}

/// One round of a batch whose chunk is being generated: what choosing its horizon needs.
#[derive(Debug)]
pub struct HorizonJob {
    /// The request.
    pub request: RequestId,
    /// The client's task id.
    pub task: u64,
    /// The client's round id.
    pub round: u64,
    /// The round's horizon policy.
    pub policy: RoundPolicy,
    /// Actions per second the robot executes at.
    pub control_hz: f32,
    /// Answered rounds of the task before this one.
    pub round_index: u64,
    /// Horizons of the task's most recent rounds, oldest first.
    pub recent_horizons: Vec<u32>,
}

impl ActionManager {
    /// The answer to each round of a generated batch: its horizon policy (or the fallback) on its
    /// chunk, with the server's `load` when the batch's generation ended, then the trimmed reply. `jobs`
    /// and `chunks` pair up in order (a chunk the engine could not make is its wire error
    /// already); a round without a chunk fails, and so does a round the engine failed alone (the batch's others go on).
    /// Blocking: runs every round's policy in turn on the calling thread.
    pub fn answer_batch(
        &self,
        jobs: Vec<HorizonJob>,
        chunks: Vec<Result<ActionChunk, ErrorReply>>,
        load: Option<ServerLoad>,
    ) -> Vec<(RequestId, Result<Reply, ErrorReply>)> {
        let mut chunks = chunks.into_iter();
        jobs.into_iter()
            .map(|mut job| {
                let chunk = match chunks.next() {
                    Some(Ok(chunk)) => chunk,
                    Some(Err(error)) => return (job.request, Err(error)),
                    None => {
                        let error = RoundError::Internal("the engine returned no chunk".into());
                        return (job.request, Err(ErrorReply::from(&error)));
                    }
                };
                let context = RoundContext {
                    control_hz: job.control_hz,
                    round_index: job.round_index,
                    recent_horizons: &job.recent_horizons,
                    load,
                };
                let answer = self
                    .choose(&mut job.policy, &chunk, context)
                    .map(|choice| build_reply(job.task, job.round, &chunk, &choice))
                    .map_err(|e| ErrorReply::from(&RoundError::Internal(e.to_string())));
                (job.request, answer)
            })
            .collect()
    }
}

/// A request's horizon policy cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolicyLookupError {
    /// No such policy.
    #[error("unknown horizon policy `{name}` (available: {known})")]
    Unknown {
        /// The name asked for.
        name: String,
        /// Registered names.
        known: String,
    },
    /// Its parameters are invalid.
    #[error("horizon policy `{name}`: {error}")]
    Params {
        /// The policy.
        name: String,
        /// What is wrong.
        error: HorizonError,
    },
}

/// The reply for one round: the first `horizon` actions of sample 0 as an `f32` `[H, D]` tensor.
/// `timing` is filled in by the driver when the reply is sent.
pub fn build_reply(task: u64, round: u64, chunk: &ActionChunk, choice: &HorizonChoice) -> Reply {
    let horizon = choice.horizon.min(chunk.chunk_len);
    let actions = &chunk.sample_actions(0)[..horizon * chunk.action_dim];
    let mut data = Vec::with_capacity(actions.len() * 4);
    for a in actions {
        data.extend_from_slice(&a.to_le_bytes());
    }
    Reply {
        task,
        round,
        horizon: u32::try_from(horizon).unwrap_or(u32::MAX),
        chunk_len: u32::try_from(chunk.chunk_len).unwrap_or(u32::MAX),
        actions: Tensor {
            dtype: kairos_protocol::DType::F32,
            shape: vec![
                u32::try_from(horizon).unwrap_or(u32::MAX),
                u32::try_from(chunk.action_dim).unwrap_or(u32::MAX),
            ],
            data,
        },
        policy: choice.policy.clone(),
        timing: Timing::default(),
        start: None,
        delay: None,
        chunking: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::horizon::HorizonInput;
    use crate::registry::native_horizon_policies;

    /// A chunk of N=4 actions, D=1, K=3 steps where action `cut` still moves a lot at the last
    /// step and every other action converges (updates 1.0, 0.5, 0.1).
    fn chunk(cut: usize) -> ActionChunk {
        let (n, k) = (4, 3);
        let mut updates = Vec::new();
        for step in 0..k {
            for action in 0..n {
                updates.push(match (step, action == cut) {
                    (0, _) => 1.0,
                    (1, _) => 0.5,
                    (_, false) => 0.1,
                    (_, true) => 5.0,
                });
            }
        }
        ActionChunk {
            samples: 1,
            steps: k,
            chunk_len: n,
            action_dim: 1,
            actions: vec![10.0, 11.0, 12.0, 13.0],
            updates,
            noise: vec![0.0; n],
        }
    }

    fn context() -> RoundContext<'static> {
        RoundContext {
            control_hz: 30.0,
            round_index: 0,
            recent_horizons: &[],
            load: None,
        }
    }

    fn manager() -> ActionManager {
        let natives = native_horizon_policies();
        ActionManager::new(natives.clone(), &natives, "threshold", PolicyParams::new()).unwrap()
    }

    #[test]
    fn threshold_policy_trims_at_the_first_unconverged_action() {
        let manager = manager();
        let mut policy = manager.build(None, None).unwrap();
        let choice = manager.choose(&mut policy, &chunk(2), context()).unwrap();
        assert_eq!(choice.horizon, 2);
        assert_eq!(choice.policy, "threshold");
        assert!(choice.fallback_reason.is_none());
        let reply = build_reply(7, 3, &chunk(2), &choice);
        assert_eq!(reply.horizon, 2);
        assert_eq!(reply.chunk_len, 4);
        assert_eq!(reply.actions.shape, vec![2, 1]);
        assert_eq!(reply.actions.to_f32().unwrap(), vec![10.0, 11.0]);
    }

    #[test]
    fn static_policy_is_selectable_by_name() {
        let manager = manager();
        let params = PolicyParams::from([("h".to_string(), 3.0)]);
        let mut policy = manager.build(Some("static"), Some(&params)).unwrap();
        let choice = manager.choose(&mut policy, &chunk(0), context()).unwrap();
        assert_eq!((choice.horizon, choice.policy.as_str()), (3, "static"));
    }

    #[test]
    fn unknown_policies_and_bad_params_are_refused_up_front() {
        let manager = manager();
        assert!(matches!(
            manager.build(Some("nope"), None),
            Err(PolicyLookupError::Unknown { .. })
        ));
        let params = PolicyParams::from([("h".to_string(), 0.5)]);
        assert!(matches!(
            manager.build(Some("static"), Some(&params)),
            Err(PolicyLookupError::Params { .. })
        ));
    }

    #[test]
    fn a_failing_or_out_of_range_policy_falls_back_and_is_counted() {
        struct Broken(Result<usize, HorizonError>);
        impl HorizonPolicy for Broken {
            fn name(&self) -> &str {
                "broken"
            }
            fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
                self.0.clone()
            }
        }
        let manager = manager();
        for answer in [Ok(99), Ok(0), Err(HorizonError::Failed("trap".into()))] {
            let mut round = RoundPolicy {
                policy: Box::new(Broken(answer)),
                params: PolicyParams::new(),
            };
            let choice = manager.choose(&mut round, &chunk(1), context()).unwrap();
            assert_eq!(choice.policy, "threshold");
            assert_eq!(choice.horizon, 1);
            assert!(choice.fallback_reason.is_some());
        }
        assert_eq!(manager.fallback_count(), 3);
    }

    #[test]
    fn the_reply_names_the_policy_that_answered_inside_a_plugin() {
        // A plugin that timed out answers through its own native fallback (`answered_by`): the
        // reply names the fallback, as PROTOCOL.md §6 says, not the plugin.
        struct FellBack;
        impl HorizonPolicy for FellBack {
            fn name(&self) -> &str {
                "hloop"
            }
            fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
                Ok(2)
            }
            fn answered_by(&self) -> Option<&str> {
                Some("threshold")
            }
        }
        let manager = manager();
        let mut round = RoundPolicy {
            policy: Box::new(FellBack),
            params: PolicyParams::new(),
        };
        let choice = manager.choose(&mut round, &chunk(1), context()).unwrap();
        assert_eq!((choice.horizon, choice.policy.as_str()), (2, "threshold"));
    }

    #[test]
    fn default_policy_must_exist_and_a_plugin_default_falls_back_to_threshold() {
        let natives = native_horizon_policies();
        assert!(matches!(
            ActionManager::new(natives.clone(), &natives, "nope", PolicyParams::new()),
            Err(ActionConfigError::Unknown(_))
        ));
        let mut with_plugin = natives.clone();
        with_plugin.register("plugin", |_| {
            Ok(Box::new(crate::horizon::threshold::Threshold::default()) as Box<dyn HorizonPolicy>)
        });
        let manager =
            ActionManager::new(with_plugin, &natives, "plugin", PolicyParams::new()).unwrap();
        assert_eq!(manager.fallback_policy, NATIVE_FALLBACK);
        assert_eq!(manager.default_selection().0, "plugin");
    }
}
