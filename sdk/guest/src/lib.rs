//! Write Kairos policy plugins in Rust.
//!
//! A policy is a plain Rust type implementing [`HorizonPolicy`] or [`PriorityPolicy`] over
//! plain Rust types ([`Chunk`], [`HorizonContext`], [`PendingColumns`], [`Params`]), so its
//! logic is unit-tested natively with `cargo test`. One line exports it as a component of the
//! `kairos:policy@0.3.0` world (`wit/since_v0.3.0/`) when built for `wasm32-wasip2`:
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
//! A priority policy gets the pending requests as columns ([`PendingColumns`], one slice per
//! field, optional fields flagged by the `PRESENT_*` bits) and answers with sort keys, which
//! the server sorts natively, or with a full order ([`Ranking`]). Keys are the fast path: no
//! sort runs in the sandbox. [`PendingColumns::row`] rebuilds one request as a [`Pending`] for
//! policies that prefer rows.
//!
//! ```
//! use kairos_guest::{Params, PendingColumns, PriorityPolicy, Ranking};
//!
//! /// Least attained service first (Autellix's PLAS without its anti-starvation rule).
//! pub struct LeastService;
//!
//! impl PriorityPolicy for LeastService {
//!     fn rank(_now_us: u64, pending: &PendingColumns<'_>, _: &Params<'_>) -> Result<Ranking, String> {
//!         // Ascending keys: the least served first; ties by arrival, then request id.
//!         Ok(Ranking::Keys { major: pending.attained_service_ns.to_vec(), minor: Vec::new() })
//!     }
//! }
//!
//! kairos_guest::register_priority_policy!(LeastService);
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
            path: "../../wit/since_v0.3.0",
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
            path: "../../wit/since_v0.3.0",
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
                load: context.load.map(|l| crate::ServerLoad {
                    queued: l.queued,
                    running: l.running,
                    open_tasks: l.open_tasks,
                    backlog_ns: l.backlog_ns,
                }),
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
        fn rank(
            now_us: u64,
            pending: wp::PendingColumns,
            params: Vec<priority::kairos::policy::types::Param>,
        ) -> Result<wp::Ranking, String> {
            let params: Vec<(String, f64)> =
                params.into_iter().map(|p| (p.name, p.value)).collect();
            // Borrowed, not copied: the columns arrived as one block each and stay in place.
            let columns = crate::PendingColumns {
                request: &pending.request,
                task: &pending.task,
                round_index: &pending.round_index,
                arrived_at_us: &pending.arrived_at_us,
                task_started_at_us: &pending.task_started_at_us,
                skipped: &pending.skipped,
                wait_ns: &pending.wait_ns,
                attained_service_ns: &pending.attained_service_ns,
                queued_ns: &pending.queued_ns,
                last_exec_ns: &pending.last_exec_ns,
                exec_ends_at_us: &pending.exec_ends_at_us,
                last_gen_ns: &pending.last_gen_ns,
                rounds_completed: &pending.rounds_completed,
                remaining_rounds: &pending.remaining_rounds,
                remaining_seconds: &pending.remaining_seconds,
                present: &pending.present,
            };
            // The server sends columns of equal length; checking once here is what lets
            // policies index every column by `0..len()` (and `row`) without a panic path on
            // plugin input.
            columns.check()?;
            Ok(match P::rank(now_us, &columns, &crate::Params(&params))? {
                crate::Ranking::Keys { major, minor } => {
                    wp::Ranking::Keys(wp::SortKeys { major, minor })
                }
                crate::Ranking::Order(order) => wp::Ranking::Order(order),
            })
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
        // The generated export macro takes a type *name* (`$ty:ident`), not a generic path,
        // hence the alias; the anonymous const keeps it out of the caller's namespace.
        #[cfg(target_arch = "wasm32")]
        const _: () = {
            type KairosGuestExport = $crate::__private::HorizonExport<$policy>;
            $crate::__private::horizon::export_horizon_policy!(
                KairosGuestExport with_types_in $crate::__private::horizon
            );
        };
    };
}

/// Exports `$policy` (a [`PriorityPolicy`]) as the component's `priority-policy` world.
/// Expands to nothing unless the target is `wasm32`.
#[macro_export]
macro_rules! register_priority_policy {
    ($policy:ty) => {
        // The generated export macro takes a type *name* (`$ty:ident`), not a generic path,
        // hence the alias; the anonymous const keeps it out of the caller's namespace.
        #[cfg(target_arch = "wasm32")]
        const _: () = {
            type KairosGuestExport = $crate::__private::PriorityExport<$policy>;
            $crate::__private::priority::export_priority_policy!(
                KairosGuestExport with_types_in $crate::__private::priority
            );
        };
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
    /// The server's load at the decision (0.3.0); `None` where there is no server (trace
    /// generation, some `kairos plugin check` cases).
    pub load: Option<ServerLoad>,
}

/// The server's load when the chunk's forward pass ended (see the WIT `server-load` record).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ServerLoad {
    /// Requests waiting for dispatch.
    pub queued: u32,
    /// Requests in batches still running.
    pub running: u32,
    /// Tasks open on the server.
    pub open_tasks: u32,
    /// How long until an engine is free again if no new request came (the work in hand): a
    /// request sent now waits about this long.
    pub backlog_ns: u64,
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

/// One pending request with its task's lifecycle summary: row `i` of a [`PendingColumns`]
/// (see [`PendingColumns::row`]), for policies that prefer to work row by row.
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
    /// The client's hint: `Some` when it sent at least one of the two estimates. (The columns
    /// carry each estimate's presence separately, so a hint with neither reads as `None`.)
    pub remaining: Option<RemainingWork>,
}

/// [`PendingColumns::present`] bit: the row's `last_exec_ns` is known.
pub const PRESENT_LAST_EXEC_NS: u8 = 1 << 0;
/// [`PendingColumns::present`] bit: the row's `exec_ends_at_us` is known.
pub const PRESENT_EXEC_ENDS_AT_US: u8 = 1 << 1;
/// [`PendingColumns::present`] bit: the row's `last_gen_ns` is known.
pub const PRESENT_LAST_GEN_NS: u8 = 1 << 2;
/// [`PendingColumns::present`] bit: the row's `remaining_rounds` is known.
pub const PRESENT_REMAINING_ROUNDS: u8 = 1 << 3;
/// [`PendingColumns::present`] bit: the row's `remaining_seconds` is known.
pub const PRESENT_REMAINING_SECONDS: u8 = 1 << 4;

/// The pending requests, one borrowed column per field (see the WIT `pending-columns`
/// record): row `i` of every column describes pending request `i`.
///
/// Optional fields are plain columns plus a bit in [`present`](Self::present) (the
/// `PRESENT_*` constants); a field whose bit is clear holds 0 and means "unknown". Columns
/// handed to [`PriorityPolicy::rank`] all have [`len`](Self::len) rows (the export checks
/// this before calling the policy), so indexing any column by `0..len()` cannot panic.
#[derive(Clone, Copy, Debug, Default)]
pub struct PendingColumns<'a> {
    /// Request ids.
    pub request: &'a [u64],
    /// Task ids.
    pub task: &'a [u64],
    /// Round indices within the tasks.
    pub round_index: &'a [u64],
    /// Arrivals, µs.
    pub arrived_at_us: &'a [u64],
    /// The tasks' first arrivals, µs.
    pub task_started_at_us: &'a [u64],
    /// Decisions that passed each request over.
    pub skipped: &'a [u32],
    /// Σ W_j, ns.
    pub wait_ns: &'a [u64],
    /// Σ |G_j|, ns.
    pub attained_service_ns: &'a [u64],
    /// Σ queueing time of each task's requests (this one's included), ns.
    pub queued_ns: &'a [u64],
    /// |E_last|, ns ([`PRESENT_LAST_EXEC_NS`]).
    pub last_exec_ns: &'a [u64],
    /// When the robot runs out of actions (`E_last.end`), µs ([`PRESENT_EXEC_ENDS_AT_US`]).
    pub exec_ends_at_us: &'a [u64],
    /// |G_last|, ns ([`PRESENT_LAST_GEN_NS`]).
    pub last_gen_ns: &'a [u64],
    /// Rounds answered.
    pub rounds_completed: &'a [u32],
    /// The client's estimate of rounds left, this one included
    /// ([`PRESENT_REMAINING_ROUNDS`]).
    pub remaining_rounds: &'a [u32],
    /// The client's estimate of seconds of execution left ([`PRESENT_REMAINING_SECONDS`]).
    pub remaining_seconds: &'a [f32],
    /// Which optional fields each row has: an or of `PRESENT_*` bits.
    pub present: &'a [u8],
}

impl<'a> PendingColumns<'a> {
    /// Rows (pending requests): the length of `request`.
    pub fn len(&self) -> usize {
        self.request.len()
    }

    /// Whether there are no pending requests (the server's parameter check at load).
    pub fn is_empty(&self) -> bool {
        self.request.is_empty()
    }

    /// `Ok` if every column has [`len`](Self::len) rows, else which one does not. The export
    /// runs this before [`PriorityPolicy::rank`]; call it yourself on columns you build.
    pub fn check(&self) -> Result<(), String> {
        let n = self.len();
        let lengths = [
            ("task", self.task.len()),
            ("round_index", self.round_index.len()),
            ("arrived_at_us", self.arrived_at_us.len()),
            ("task_started_at_us", self.task_started_at_us.len()),
            ("skipped", self.skipped.len()),
            ("wait_ns", self.wait_ns.len()),
            ("attained_service_ns", self.attained_service_ns.len()),
            ("queued_ns", self.queued_ns.len()),
            ("last_exec_ns", self.last_exec_ns.len()),
            ("exec_ends_at_us", self.exec_ends_at_us.len()),
            ("last_gen_ns", self.last_gen_ns.len()),
            ("rounds_completed", self.rounds_completed.len()),
            ("remaining_rounds", self.remaining_rounds.len()),
            ("remaining_seconds", self.remaining_seconds.len()),
            ("present", self.present.len()),
        ];
        match lengths.iter().find(|&&(_, len)| len != n) {
            None => Ok(()),
            Some((name, len)) => Err(format!(
                "pending column `{name}` has {len} rows, `request` has {n}"
            )),
        }
    }

    /// Row `i` as a [`Pending`], its `Option`s rebuilt from the `present` bits.
    ///
    /// # Panics
    ///
    /// If `i >= len()` or a column is shorter than `request` (never for `i < len()` in
    /// columns given to [`PriorityPolicy::rank`]).
    pub fn row(&self, i: usize) -> Pending {
        let bits = self.present[i];
        let has = |bit: u8| bits & bit != 0;
        let remaining =
            (has(PRESENT_REMAINING_ROUNDS) || has(PRESENT_REMAINING_SECONDS)).then(|| {
                RemainingWork {
                    rounds: has(PRESENT_REMAINING_ROUNDS).then(|| self.remaining_rounds[i]),
                    seconds: has(PRESENT_REMAINING_SECONDS).then(|| self.remaining_seconds[i]),
                }
            });
        Pending {
            request: self.request[i],
            task: self.task[i],
            round_index: self.round_index[i],
            arrived_at_us: self.arrived_at_us[i],
            task_started_at_us: self.task_started_at_us[i],
            skipped: self.skipped[i],
            wait_ns: self.wait_ns[i],
            attained_service_ns: self.attained_service_ns[i],
            queued_ns: self.queued_ns[i],
            last_exec_ns: has(PRESENT_LAST_EXEC_NS).then(|| self.last_exec_ns[i]),
            exec_ends_at_us: has(PRESENT_EXEC_ENDS_AT_US).then(|| self.exec_ends_at_us[i]),
            last_gen_ns: has(PRESENT_LAST_GEN_NS).then(|| self.last_gen_ns[i]),
            rounds_completed: self.rounds_completed[i],
            remaining,
        }
    }

    /// Every row in order, as [`row`](Self::row) builds them (same panics).
    pub fn rows(&self) -> impl Iterator<Item = Pending> + 'a {
        let columns = *self;
        (0..columns.len()).map(move |i| columns.row(i))
    }
}

/// Owned columns built from rows, to hand [`PendingColumns`] to a policy in unit tests.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PendingColumnsBuf {
    request: Vec<u64>,
    task: Vec<u64>,
    round_index: Vec<u64>,
    arrived_at_us: Vec<u64>,
    task_started_at_us: Vec<u64>,
    skipped: Vec<u32>,
    wait_ns: Vec<u64>,
    attained_service_ns: Vec<u64>,
    queued_ns: Vec<u64>,
    last_exec_ns: Vec<u64>,
    exec_ends_at_us: Vec<u64>,
    last_gen_ns: Vec<u64>,
    rounds_completed: Vec<u32>,
    remaining_rounds: Vec<u32>,
    remaining_seconds: Vec<f32>,
    present: Vec<u8>,
}

impl PendingColumnsBuf {
    /// The columns of `rows`, laid out as the server sends them: an absent optional field
    /// holds 0 with its `present` bit clear.
    pub fn from_rows(rows: &[Pending]) -> Self {
        let mut buf = PendingColumnsBuf::default();
        for row in rows {
            let rounds = row.remaining.and_then(|r| r.rounds);
            let seconds = row.remaining.and_then(|r| r.seconds);
            let bit = |known: bool, bit: u8| if known { bit } else { 0 };
            buf.request.push(row.request);
            buf.task.push(row.task);
            buf.round_index.push(row.round_index);
            buf.arrived_at_us.push(row.arrived_at_us);
            buf.task_started_at_us.push(row.task_started_at_us);
            buf.skipped.push(row.skipped);
            buf.wait_ns.push(row.wait_ns);
            buf.attained_service_ns.push(row.attained_service_ns);
            buf.queued_ns.push(row.queued_ns);
            buf.last_exec_ns.push(row.last_exec_ns.unwrap_or(0));
            buf.exec_ends_at_us.push(row.exec_ends_at_us.unwrap_or(0));
            buf.last_gen_ns.push(row.last_gen_ns.unwrap_or(0));
            buf.rounds_completed.push(row.rounds_completed);
            buf.remaining_rounds.push(rounds.unwrap_or(0));
            buf.remaining_seconds.push(seconds.unwrap_or(0.0));
            buf.present.push(
                bit(row.last_exec_ns.is_some(), PRESENT_LAST_EXEC_NS)
                    | bit(row.exec_ends_at_us.is_some(), PRESENT_EXEC_ENDS_AT_US)
                    | bit(row.last_gen_ns.is_some(), PRESENT_LAST_GEN_NS)
                    | bit(rounds.is_some(), PRESENT_REMAINING_ROUNDS)
                    | bit(seconds.is_some(), PRESENT_REMAINING_SECONDS),
            );
        }
        buf
    }

    /// Borrowed columns over this buffer.
    pub fn columns(&self) -> PendingColumns<'_> {
        PendingColumns {
            request: &self.request,
            task: &self.task,
            round_index: &self.round_index,
            arrived_at_us: &self.arrived_at_us,
            task_started_at_us: &self.task_started_at_us,
            skipped: &self.skipped,
            wait_ns: &self.wait_ns,
            attained_service_ns: &self.attained_service_ns,
            queued_ns: &self.queued_ns,
            last_exec_ns: &self.last_exec_ns,
            exec_ends_at_us: &self.exec_ends_at_us,
            last_gen_ns: &self.last_gen_ns,
            rounds_completed: &self.rounds_completed,
            remaining_rounds: &self.remaining_rounds,
            remaining_seconds: &self.remaining_seconds,
            present: &self.present,
        }
    }
}

/// A priority policy's answer (see the WIT `ranking` variant).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Ranking {
    /// Sort keys, one pair per pending row; the server sorts (no sort in the sandbox, the
    /// fast path). It dispatches by `(major[i], minor[i], arrived_at_us[i], request[i])`
    /// ascending, so the smallest key is the most urgent. Either list may be empty, meaning
    /// all zeros (FIFO: both empty; a single-key policy: `minor` empty); otherwise it must
    /// have exactly one entry per row. Because `request` ends the key, the order is total.
    Keys {
        /// The first key, ascending.
        major: Vec<u64>,
        /// The second key, ascending among equal `major`.
        minor: Vec<u64>,
    },
    /// Indices into the pending rows, most urgent first: every index from 0 to `len() - 1`
    /// exactly once.
    Order(Vec<u32>),
}

impl Ranking {
    /// The order in which the server dispatches `pending` under this ranking, most urgent
    /// first, or why it would reject the ranking (and fall back to its built-in policy).
    /// For unit tests: the export never calls it.
    pub fn dispatch_order(&self, pending: &PendingColumns<'_>) -> Result<Vec<u32>, String> {
        pending.check()?;
        let n = pending.len();
        let rows =
            u32::try_from(n).map_err(|_| format!("{n} pending rows do not fit a u32 index"))?;
        match self {
            Ranking::Keys { major, minor } => {
                for (name, keys) in [("major", major), ("minor", minor)] {
                    if !keys.is_empty() && keys.len() != n {
                        return Err(format!("{name} has {} keys for {n} rows", keys.len()));
                    }
                }
                let key = |keys: &[u64], i: usize| keys.get(i).copied().unwrap_or(0);
                let mut order: Vec<u32> = (0..rows).collect();
                order.sort_by_key(|&i| {
                    let i = i as usize; // lossless: i < n, a usize
                    (
                        key(major, i),
                        key(minor, i),
                        pending.arrived_at_us[i],
                        pending.request[i],
                    )
                });
                Ok(order)
            }
            Ranking::Order(order) => {
                let mut seen = vec![false; n];
                if order.len() != n {
                    return Err(format!("order has {} indices for {n} rows", order.len()));
                }
                for &i in order {
                    match seen.get_mut(i as usize) {
                        Some(s) if !*s => *s = true,
                        Some(_) => return Err(format!("index {i} appears twice")),
                        None => return Err(format!("index {i} is out of range")),
                    }
                }
                Ok(order.clone())
            }
        }
    }
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

/// A priority policy: ranks the pending requests for dispatch.
pub trait PriorityPolicy {
    /// Rank `pending`: [`Ranking::Keys`] (the server sorts by `(major, minor,
    /// arrived_at_us, request)` ascending; no sort in the sandbox) or a full
    /// [`Ranking::Order`], most urgent first.
    ///
    /// Every column of `pending` has `pending.len()` rows. An empty `pending` is a valid call
    /// (the server makes one at load to check `params`). `now_us` is the decision time on the
    /// timestamps' clock. An `Err` (or a ranking of the wrong length) makes the server use its
    /// built-in policy for this decision; a plugin that keeps failing is quarantined.
    fn rank(
        now_us: u64,
        pending: &PendingColumns<'_>,
        params: &Params<'_>,
    ) -> Result<Ranking, String>;

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

    /// Most remaining rounds first (unknown last), by sort keys over the columns.
    struct MostRemaining;

    impl PriorityPolicy for MostRemaining {
        fn rank(
            _now: u64,
            pending: &PendingColumns<'_>,
            params: &Params<'_>,
        ) -> Result<Ranking, String> {
            if let Some(name) = params.unknown(&[]) {
                return Err(format!("unknown parameter {name}"));
            }
            let major = pending
                .remaining_rounds
                .iter()
                .zip(pending.present)
                .map(|(&rounds, &bits)| {
                    if bits & PRESENT_REMAINING_ROUNDS != 0 {
                        u64::from(u32::MAX - rounds)
                    } else {
                        u64::MAX
                    }
                })
                .collect();
            Ok(Ranking::Keys {
                major,
                minor: Vec::new(),
            })
        }
    }
    register_priority_policy!(MostRemaining);

    /// Least attained service first, row by row, answering with a full order.
    struct LeastService;

    impl PriorityPolicy for LeastService {
        fn rank(
            _now: u64,
            pending: &PendingColumns<'_>,
            _: &Params<'_>,
        ) -> Result<Ranking, String> {
            let mut rows: Vec<(u32, Pending)> = (0..).zip(pending.rows()).collect();
            rows.sort_by_key(|(i, p)| (p.attained_service_ns, *i));
            Ok(Ranking::Order(rows.into_iter().map(|(i, _)| i).collect()))
        }
    }

    fn remaining(rounds: Option<u32>, seconds: Option<f32>) -> Pending {
        Pending {
            remaining: Some(RemainingWork { rounds, seconds }),
            ..Pending::default()
        }
    }

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
            load: None,
        };
        assert_eq!(Half::choose(&chunk, &ctx, &Params(&[])), Ok(4));
        let bad = [("x".to_string(), 1.0)];
        assert!(matches!(
            Half::choose(&chunk, &ctx, &Params(&bad)),
            Err(HorizonError::InvalidParam { .. })
        ));
        assert_eq!(chunk.update(0, 1, 9).len(), 3);

        // Row 3 has a seconds hint but no rounds: it ranks with the unknowns.
        let buf = PendingColumnsBuf::from_rows(&[
            Pending {
                request: 10,
                ..remaining(Some(2), None)
            },
            Pending {
                request: 11,
                ..remaining(Some(9), None)
            },
            Pending {
                request: 12,
                ..Pending::default()
            },
            Pending {
                request: 13,
                arrived_at_us: 5,
                ..remaining(None, Some(60.0))
            },
            Pending {
                request: 14,
                arrived_at_us: 1,
                ..remaining(Some(9), None)
            },
        ]);
        let pending = buf.columns();
        let ranking = MostRemaining::rank(0, &pending, &Params(&[])).unwrap();
        assert_eq!(
            ranking,
            Ranking::Keys {
                major: vec![
                    u64::from(u32::MAX - 2),
                    u64::from(u32::MAX - 9),
                    u64::MAX,
                    u64::MAX,
                    u64::from(u32::MAX - 9),
                ],
                minor: vec![],
            }
        );
        // Ties on `major` fall to arrival, then request id.
        assert_eq!(ranking.dispatch_order(&pending), Ok(vec![1, 4, 0, 2, 3]));
        assert!(MostRemaining::rank(0, &pending, &Params(&bad)).is_err());
        assert_eq!(
            MostRemaining::rank(0, &PendingColumns::default(), &Params(&[])),
            Ok(Ranking::Keys {
                major: vec![],
                minor: vec![]
            })
        );
    }

    #[test]
    fn a_row_policy_answers_with_an_order() {
        let rows: Vec<Pending> = [30, 10, 20, 10]
            .into_iter()
            .map(|attained_service_ns| Pending {
                attained_service_ns,
                ..Pending::default()
            })
            .collect();
        let buf = PendingColumnsBuf::from_rows(&rows);
        let ranking = LeastService::rank(0, &buf.columns(), &Params(&[])).unwrap();
        assert_eq!(ranking, Ranking::Order(vec![1, 3, 2, 0]));
        assert_eq!(ranking.dispatch_order(&buf.columns()), Ok(vec![1, 3, 2, 0]));
    }

    #[test]
    fn row_rebuilds_options_from_present_bits() {
        // Absent fields hold a nonzero value here on purpose: the bits alone decide. No two
        // bits are set in the same rows, so reading one field by another's bit fails.
        let n = 5;
        let present = [
            0,
            PRESENT_LAST_EXEC_NS | PRESENT_REMAINING_ROUNDS | PRESENT_REMAINING_SECONDS,
            PRESENT_EXEC_ENDS_AT_US | PRESENT_REMAINING_ROUNDS,
            PRESENT_LAST_GEN_NS | PRESENT_REMAINING_SECONDS,
            0x1f,
        ];
        let ids: Vec<u64> = (100..100 + n).collect();
        let skipped: Vec<u32> = (0..n as u32).collect();
        let rounds_completed: Vec<u32> = (20..20 + n as u32).collect();
        let pending = PendingColumns {
            request: &ids,
            task: &[1, 2, 3, 4, 5],
            round_index: &[6, 7, 8, 9, 10],
            arrived_at_us: &[11, 12, 13, 14, 15],
            task_started_at_us: &[1, 1, 1, 1, 1],
            skipped: &skipped,
            wait_ns: &[7; 5],
            attained_service_ns: &[8; 5],
            queued_ns: &[9; 5],
            last_exec_ns: &[1000, 1001, 1002, 1003, 1004],
            exec_ends_at_us: &[2000, 2001, 2002, 2003, 2004],
            last_gen_ns: &[3000, 3001, 3002, 3003, 3004],
            rounds_completed: &rounds_completed,
            remaining_rounds: &[40, 41, 42, 43, 44],
            remaining_seconds: &[0.5, 1.5, 2.5, 3.5, 4.5],
            present: &present,
        };
        assert_eq!(pending.check(), Ok(()));
        assert_eq!(pending.len(), 5);
        assert!(!pending.is_empty());

        let r0 = pending.row(0);
        assert_eq!(
            r0,
            Pending {
                request: 100,
                task: 1,
                round_index: 6,
                arrived_at_us: 11,
                task_started_at_us: 1,
                skipped: 0,
                wait_ns: 7,
                attained_service_ns: 8,
                queued_ns: 9,
                last_exec_ns: None,
                exec_ends_at_us: None,
                last_gen_ns: None,
                rounds_completed: 20,
                remaining: None,
            }
        );
        // Each row's optional fields, flattened: (last exec, exec end, last gen, rounds, seconds).
        let optionals = |p: Pending| {
            (
                p.last_exec_ns,
                p.exec_ends_at_us,
                p.last_gen_ns,
                p.remaining.and_then(|r| r.rounds),
                p.remaining.and_then(|r| r.seconds),
            )
        };
        assert_eq!(
            optionals(pending.row(1)),
            (Some(1001), None, None, Some(41), Some(1.5))
        );
        assert_eq!(
            optionals(pending.row(2)),
            (None, Some(2002), None, Some(42), None)
        );
        assert_eq!(
            optionals(pending.row(3)),
            (None, None, Some(3003), None, Some(3.5))
        );
        assert!(pending.row(2).remaining.is_some() && pending.row(3).remaining.is_some());
        let r4 = pending.row(4);
        assert_eq!(
            (
                r4.request,
                r4.skipped,
                r4.rounds_completed,
                r4.last_exec_ns,
                r4.exec_ends_at_us,
                r4.last_gen_ns,
                r4.remaining
            ),
            (
                104,
                4,
                24,
                Some(1004),
                Some(2004),
                Some(3004),
                Some(RemainingWork {
                    rounds: Some(44),
                    seconds: Some(4.5)
                })
            )
        );

        // Rows survive the round trip through the server's layout, except a hint with
        // neither estimate, which the columns cannot express.
        let rows: Vec<Pending> = pending.rows().collect();
        assert_eq!(rows.len(), 5);
        let buf = PendingColumnsBuf::from_rows(&rows);
        assert_eq!(buf.columns().rows().collect::<Vec<_>>(), rows);
        let empty_hint = PendingColumnsBuf::from_rows(&[remaining(None, None)]);
        assert_eq!(empty_hint.columns().row(0).remaining, None);
        assert_eq!(empty_hint.columns().present, &[0]);
    }

    #[test]
    fn inconsistent_columns_and_bad_rankings_are_caught() {
        let buf = PendingColumnsBuf::from_rows(&[Pending::default(), Pending::default()]);
        let mut pending = buf.columns();
        let keys = |major: Vec<u64>, minor: Vec<u64>| Ranking::Keys { major, minor };
        assert_eq!(
            keys(vec![], vec![]).dispatch_order(&pending),
            Ok(vec![0, 1])
        );
        assert_eq!(
            keys(vec![], vec![5, 4]).dispatch_order(&pending),
            Ok(vec![1, 0])
        );
        assert!(keys(vec![1], vec![]).dispatch_order(&pending).is_err());
        assert!(
            keys(vec![], vec![1, 2, 3])
                .dispatch_order(&pending)
                .is_err()
        );
        assert!(Ranking::Order(vec![0]).dispatch_order(&pending).is_err());
        assert!(Ranking::Order(vec![1, 1]).dispatch_order(&pending).is_err());
        assert!(Ranking::Order(vec![0, 2]).dispatch_order(&pending).is_err());

        pending.present = &[0];
        let err = pending.check().unwrap_err();
        assert!(err.contains("present"), "{err}");
        assert!(keys(vec![], vec![]).dispatch_order(&pending).is_err());
    }

    /// The adapter the export macro wires up (compiled on every target, called natively here):
    /// columns in, ranking out, inconsistent columns refused before the policy runs.
    #[test]
    fn the_export_adapter_converts_both_ways() {
        use __private::priority::exports::kairos::policy::priority as wp;
        use wp::Guest as _;

        type Export = __private::PriorityExport<MostRemaining>;
        let columns = |n: usize, present: Vec<u8>| wp::PendingColumns {
            request: (0..n as u64).collect(),
            task: vec![0; n],
            round_index: vec![0; n],
            arrived_at_us: vec![0; n],
            task_started_at_us: vec![0; n],
            skipped: vec![0; n],
            wait_ns: vec![0; n],
            attained_service_ns: vec![0; n],
            queued_ns: vec![0; n],
            last_exec_ns: vec![0; n],
            exec_ends_at_us: vec![0; n],
            last_gen_ns: vec![0; n],
            rounds_completed: vec![0; n],
            remaining_rounds: vec![3; n],
            remaining_seconds: vec![0.0; n],
            present,
        };
        match Export::rank(0, columns(2, vec![PRESENT_REMAINING_ROUNDS, 0]), Vec::new()) {
            Ok(wp::Ranking::Keys(keys)) => {
                assert_eq!(keys.major, vec![u64::from(u32::MAX - 3), u64::MAX]);
                assert!(keys.minor.is_empty());
            }
            other => panic!("unexpected {other:?}"),
        }
        assert!(Export::rank(0, columns(2, vec![0]), Vec::new()).is_err());
        let param = __private::priority::kairos::policy::types::Param {
            name: "x".into(),
            value: 1.0,
        };
        assert!(Export::rank(0, columns(0, vec![]), vec![param]).is_err());
    }
}
