//! Write Kairos policy plugins in Rust.
//!
//! A policy is a plain Rust type implementing [`HorizonPolicy`] or [`PriorityPolicy`] over
//! plain Rust types ([`Chunk`], [`HorizonContext`], [`Pending`], [`Params`]), so its logic is
//! unit-tested natively with `cargo test`. One line exports it as a component of the
//! `kairos:policy` world when built for `wasm32-wasip2`:
//!
//! ```
//! use kairos_guest::{Chunk, HorizonContext, HorizonError, HorizonPolicy, Params};
//!
//! /// Executes half the chunk, within the robot's bounds.
//! pub struct Half;
//!
//! impl HorizonPolicy for Half {
//!     fn choose(chunk: &Chunk<'_>, ctx: &HorizonContext<'_>, _: &Params<'_>) -> Result<u32, HorizonError> {
//!         Ok((chunk.chunk_len / 2).clamp(ctx.h_min, ctx.h_max))
//!     }
//! }
//!
//! kairos_guest::register_horizon_policy!(Half);
//! ```
//!
//! Build the component (on a machine with the target; see `docs/PLUGINS.md`):
//!
//! ```text
//! rustup target add wasm32-wasip2
//! cargo build --release --target wasm32-wasip2      # crate-type = ["cdylib"]
//! kairos plugin check target/wasm32-wasip2/release/my_policy.wasm
//! ```
//!
//! The export macros expand to nothing on other targets, so the same crate builds and
//! tests natively.

use std::fmt;

#[doc(hidden)]
pub mod __private {
    pub use wit_bindgen;

    /// Generated bindings of the `horizon-policy` world.
    pub mod horizon {
        wit_bindgen::generate!({
            path: "../../wit/since_v0.1.0",
            world: "horizon-policy",
            runtime_path: "crate::__private::wit_bindgen::rt",
            pub_export_macro: true,
            export_macro_name: "export_horizon_policy",
            default_bindings_module: "kairos_guest::__private::horizon",
        });
    }

    /// Generated bindings of the `priority-policy` world.
    pub mod priority {
        wit_bindgen::generate!({
            path: "../../wit/since_v0.1.0",
            world: "priority-policy",
            runtime_path: "crate::__private::wit_bindgen::rt",
            pub_export_macro: true,
            export_macro_name: "export_priority_policy",
            default_bindings_module: "kairos_guest::__private::priority",
        });
    }

    use horizon::exports::kairos::policy::horizon as wh;
    use priority::exports::kairos::policy::priority as wp;

    /// Adapts a [`crate::HorizonPolicy`] to the generated export trait.
    pub struct HorizonExport<P>(std::marker::PhantomData<P>);

    impl<P: crate::HorizonPolicy> wh::Guest for HorizonExport<P> {
        fn choose(
            chunk: wh::Chunk,
            context: wh::HorizonContext,
            params: Vec<horizon::kairos::policy::types::Param>,
        ) -> Result<u32, wh::HorizonError> {
            let params: Vec<(String, f64)> =
                params.into_iter().map(|p| (p.name, p.value)).collect();
            let chunk = crate::Chunk {
                samples: chunk.samples,
                steps: chunk.steps,
                chunk_len: chunk.chunk_len,
                action_dim: chunk.action_dim,
                updates: &chunk.updates,
                actions: &chunk.actions,
            };
            let context = crate::HorizonContext {
                h_min: context.h_min,
                h_max: context.h_max,
                control_hz: context.control_hz,
                round_index: context.round_index,
                recent_horizons: &context.recent_horizons,
            };
            P::choose(&chunk, &context, &crate::Params(&params)).map_err(|e| match e {
                crate::HorizonError::InvalidParam { name, reason } => {
                    wh::HorizonError::InvalidParam(wh::ParamProblem { name, reason })
                }
                crate::HorizonError::Unsupported(m) => wh::HorizonError::Unsupported(m),
                crate::HorizonError::Failed(m) => wh::HorizonError::Failed(m),
            })
        }
    }

    /// Adapts a [`crate::PriorityPolicy`] to the generated export trait.
    pub struct PriorityExport<P>(std::marker::PhantomData<P>);

    impl<P: crate::PriorityPolicy> wp::Guest for PriorityExport<P> {
        fn order(
            now_us: u64,
            pending: Vec<wp::Pending>,
            params: Vec<priority::kairos::policy::types::Param>,
        ) -> Result<Vec<u32>, String> {
            let params: Vec<(String, f64)> =
                params.into_iter().map(|p| (p.name, p.value)).collect();
            let pending: Vec<crate::Pending> = pending
                .into_iter()
                .map(|p| crate::Pending {
                    request: p.request,
                    task: p.task,
                    round_index: p.round_index,
                    arrived_at_us: p.arrived_at_us,
                    task_started_at_us: p.task_started_at_us,
                    skipped: p.skipped,
                    wait_ns: p.wait_ns,
                    attained_service_ns: p.attained_service_ns,
                    queued_ns: p.queued_ns,
                    last_exec_ns: p.last_exec_ns,
                    exec_ends_at_us: p.exec_ends_at_us,
                    last_gen_ns: p.last_gen_ns,
                    rounds_completed: p.rounds_completed,
                    remaining: p.remaining.map(|r| crate::RemainingWork {
                        rounds: r.rounds,
                        seconds: r.seconds,
                    }),
                })
                .collect();
            P::order(now_us, &pending, &crate::Params(&params))
        }

        fn task_finished(summary: wp::FinishedTask) {
            P::task_finished(&crate::FinishedTask {
                task: summary.task,
                rounds: summary.rounds,
                latency_ns: summary.latency_ns,
                attained_service_ns: summary.attained_service_ns,
                wait_ns: summary.wait_ns,
            });
        }
    }
}

/// Exports `$policy` (a [`HorizonPolicy`]) as the component's `horizon-policy` world.
/// Expands to nothing unless the target is `wasm32`.
#[macro_export]
macro_rules! register_horizon_policy {
    ($policy:ty) => {
        #[cfg(target_arch = "wasm32")]
        $crate::__private::horizon::export_horizon_policy!(
            $crate::__private::HorizonExport<$policy>
            with_types_in $crate::__private::horizon
        );
    };
}

/// Exports `$policy` (a [`PriorityPolicy`]) as the component's `priority-policy` world.
/// Expands to nothing unless the target is `wasm32`.
#[macro_export]
macro_rules! register_priority_policy {
    ($policy:ty) => {
        #[cfg(target_arch = "wasm32")]
        $crate::__private::priority::export_priority_policy!(
            $crate::__private::PriorityExport<$policy>
            with_types_in $crate::__private::priority
        );
    };
}

/// One generated chunk and its per-step updates (see the WIT `chunk` record).
#[derive(Clone, Copy, Debug)]
pub struct Chunk<'a> {
    /// `S`: samples drawn for the observation.
    pub samples: u32,
    /// `K`: refinement steps.
    pub steps: u32,
    /// `N`: actions per chunk.
    pub chunk_len: u32,
    /// `D`: values per action.
    pub action_dim: u32,
    /// `[S][K][N][D]` updates.
    pub updates: &'a [f32],
    /// `[S][N][D]` final actions.
    pub actions: &'a [f32],
}

impl<'a> Chunk<'a> {
    /// The update (length `D`) step `k` applied to action `n` of sample `s`.
    pub fn update(&self, s: u32, k: u32, n: u32) -> &'a [f32] {
        let d = self.action_dim as usize;
        let start = ((s as usize * self.steps as usize + k as usize) * self.chunk_len as usize
            + n as usize)
            * d;
        &self.updates[start..start + d]
    }

    /// Final action `n` of sample `s`.
    pub fn action(&self, s: u32, n: u32) -> &'a [f32] {
        let d = self.action_dim as usize;
        let start = (s as usize * self.chunk_len as usize + n as usize) * d;
        &self.actions[start..start + d]
    }
}

/// The round's context (see the WIT `horizon-context` record).
#[derive(Clone, Copy, Debug)]
pub struct HorizonContext<'a> {
    /// Smallest horizon the robot accepts (≥ 1).
    pub h_min: u32,
    /// Largest horizon the robot accepts (≤ `chunk_len`).
    pub h_max: u32,
    /// Actions per second.
    pub control_hz: f32,
    /// Round index within the task.
    pub round_index: u64,
    /// The task's recent horizons, oldest first.
    pub recent_horizons: &'a [u32],
}

/// The policy's parameters, sorted by name.
#[derive(Clone, Copy, Debug)]
pub struct Params<'a>(pub &'a [(String, f64)]);

impl Params<'_> {
    /// The value of `name`, if given.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.0.iter().find(|(n, _)| n == name).map(|(_, v)| *v)
    }

    /// The first parameter not in `known`, if any (to reject typos).
    pub fn unknown(&self, known: &[&str]) -> Option<&str> {
        self.0
            .iter()
            .map(|(n, _)| n.as_str())
            .find(|n| !known.contains(n))
    }

    /// Whether there are no parameters.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

/// Why a horizon policy could not decide.
#[derive(Clone, Debug, PartialEq)]
pub enum HorizonError {
    /// A parameter is missing or out of range.
    InvalidParam {
        /// Which.
        name: String,
        /// Why.
        reason: String,
    },
    /// The input lacks what the policy needs.
    Unsupported(String),
    /// Anything else.
    Failed(String),
}

impl fmt::Display for HorizonError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            HorizonError::InvalidParam { name, reason } => {
                write!(f, "invalid parameter `{name}`: {reason}")
            }
            HorizonError::Unsupported(m) => write!(f, "unsupported: {m}"),
            HorizonError::Failed(m) => write!(f, "failed: {m}"),
        }
    }
}

/// A horizon policy: how many actions of the chunk the robot executes.
pub trait HorizonPolicy {
    /// The horizon for this round, within `[ctx.h_min, ctx.h_max]`.
    fn choose(
        chunk: &Chunk<'_>,
        ctx: &HorizonContext<'_>,
        params: &Params<'_>,
    ) -> Result<u32, HorizonError>;
}

/// The client's remaining-work hint.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RemainingWork {
    /// Rounds left, this one included.
    pub rounds: Option<u32>,
    /// Seconds of execution left.
    pub seconds: Option<f32>,
}

/// One pending request with its task's lifecycle summary (see the WIT `pending` record).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pending {
    /// Request id.
    pub request: u64,
    /// Task id.
    pub task: u64,
    /// Round index within the task.
    pub round_index: u64,
    /// Arrival, µs.
    pub arrived_at_us: u64,
    /// The task's first arrival, µs.
    pub task_started_at_us: u64,
    /// Decisions that passed it over.
    pub skipped: u32,
    /// Σ W_j, ns.
    pub wait_ns: u64,
    /// Σ |G_j|, ns.
    pub attained_service_ns: u64,
    /// Σ queueing time of the task's requests (this one's included), ns.
    pub queued_ns: u64,
    /// |E_last|, ns.
    pub last_exec_ns: Option<u64>,
    /// When the robot runs out of actions (`E_last.end`), µs.
    pub exec_ends_at_us: Option<u64>,
    /// |G_last|, ns.
    pub last_gen_ns: Option<u64>,
    /// Rounds answered.
    pub rounds_completed: u32,
    /// The client's hint.
    pub remaining: Option<RemainingWork>,
}

/// A task that ended.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FinishedTask {
    /// Task id.
    pub task: u64,
    /// Rounds it took.
    pub rounds: u32,
    /// First request to end of last execution, ns.
    pub latency_ns: u64,
    /// Σ |G_j|, ns.
    pub attained_service_ns: u64,
    /// Σ W_j, ns.
    pub wait_ns: u64,
}

/// A priority policy: the dispatch order of the pending requests.
pub trait PriorityPolicy {
    /// Every index of `pending` exactly once, most urgent first.
    fn order(now_us: u64, pending: &[Pending], params: &Params<'_>) -> Result<Vec<u32>, String>;

    /// A task ended. Default: ignore.
    fn task_finished(_summary: &FinishedTask) {}
}

/// Seconds in `ns` nanoseconds, exactly as the server's `Duration::as_secs_f64` computes
/// them (so a plugin can reproduce a native policy bit for bit).
pub fn secs(ns: u64) -> f64 {
    std::time::Duration::from_nanos(ns).as_secs_f64()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Executes half the chunk, within bounds; refuses unknown parameters.
    struct Half;

    impl HorizonPolicy for Half {
        fn choose(
            chunk: &Chunk<'_>,
            ctx: &HorizonContext<'_>,
            params: &Params<'_>,
        ) -> Result<u32, HorizonError> {
            if let Some(name) = params.unknown(&[]) {
                return Err(HorizonError::InvalidParam {
                    name: name.into(),
                    reason: "unknown".into(),
                });
            }
            Ok((chunk.chunk_len / 2).clamp(ctx.h_min, ctx.h_max))
        }
    }
    register_horizon_policy!(Half);

    /// Longest remaining work first.
    struct MostRemaining;

    impl PriorityPolicy for MostRemaining {
        fn order(_now: u64, pending: &[Pending], _: &Params<'_>) -> Result<Vec<u32>, String> {
            let mut order: Vec<u32> = (0..pending.len() as u32).collect();
            order.sort_by_key(|&i| {
                std::cmp::Reverse(pending[i as usize].remaining.and_then(|r| r.rounds))
            });
            Ok(order)
        }
    }
    register_priority_policy!(MostRemaining);

    #[test]
    fn policy_logic_runs_natively() {
        let updates = vec![0.0; 2 * 10 * 3];
        let actions = vec![0.0; 10 * 3];
        let chunk = Chunk {
            samples: 1,
            steps: 2,
            chunk_len: 10,
            action_dim: 3,
            updates: &updates,
            actions: &actions,
        };
        let ctx = HorizonContext {
            h_min: 2,
            h_max: 4,
            control_hz: 30.0,
            round_index: 0,
            recent_horizons: &[],
        };
        assert_eq!(Half::choose(&chunk, &ctx, &Params(&[])), Ok(4));
        let bad = [("x".to_string(), 1.0)];
        assert!(matches!(
            Half::choose(&chunk, &ctx, &Params(&bad)),
            Err(HorizonError::InvalidParam { .. })
        ));
        assert_eq!(chunk.update(0, 1, 9).len(), 3);

        let pending = [
            Pending {
                remaining: Some(RemainingWork {
                    rounds: Some(2),
                    seconds: None,
                }),
                ..Pending::default()
            },
            Pending {
                remaining: Some(RemainingWork {
                    rounds: Some(9),
                    seconds: None,
                }),
                ..Pending::default()
            },
            Pending::default(),
        ];
        assert_eq!(
            MostRemaining::order(0, &pending, &Params(&[])),
            Ok(vec![1, 0, 2])
        );
    }
}
