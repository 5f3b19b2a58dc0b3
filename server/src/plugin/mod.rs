//! The plugin host: horizon and priority policies as sandboxed WebAssembly components.
//!
//! Users swap the horizon rule and the scheduling priority function without rebuilding the
//! server: a plugin is a component implementing world `horizon-policy` or `priority-policy`
//! of the WIT package `kairos:policy` (`wit/`, documented in `docs/PLUGINS.md`).
//!
//! - [`WasmHorizonPolicy`] and [`WasmPriorityPolicy`] wrap a component as a native
//!   [`HorizonPolicy`](kairos_core::horizon::HorizonPolicy) /
//!   [`PriorityPolicy`](kairos_core::scheduler::PriorityPolicy), so the action manager and the
//!   scheduler take them like any built-in policy. Each wraps a built-in fallback policy too.
//! - Loading ([`load`]) reads the component's world and version from its exports
//!   ([`inspect`]), refuses the wrong world, an unsupported version or an import the sandbox
//!   does not grant, and compiles through an authenticated code cache ([`cache`]).
//! - Every call runs under an epoch deadline and a memory cap ([`sandbox`]). A trap, a timeout,
//!   an exceeded limit or an invalid answer discards the instance, answers that decision with
//!   the fallback policy, is counted and logged once per kind with the plugin's name
//!   ([`health`]); a plugin that keeps failing is quarantined (skipped for a growing number of
//!   decisions, then probed again): for the one robot whose rounds it fails, and for everyone
//!   once several robots' are failing.
//! - The plugin file is watched; a changed file is compiled in the background and swapped in
//!   between two calls, so no decision in flight is dropped ([`reload`]).
//!
//! Calls run on the caller's thread, bounded by the deadline, exactly like a native policy's
//! computation; callers keep policies off async reactor threads as they do for native ones.
//! Components that import WASI run on a worker thread of their own instead, because
//! wasmtime-wasi's synchronous host functions drive their own Tokio runtime.

pub mod bindings;
pub mod cache;
pub mod componentize;
pub mod conformance;
pub mod engine;
pub mod factory;
pub mod health;
mod horizon;
pub mod inspect;
mod priority;
mod reload;
mod runtime;
pub mod sandbox;

use std::path::PathBuf;
use std::time::Duration;

pub use health::{FailureKind, PluginStats};
pub use horizon::{HorizonPlugin, OwnedHorizonInput, WasmHorizonPolicy};
pub use priority::WasmPriorityPolicy;
pub use runtime::{CallCost, CallFailure, LoadError, PluginMeta};

/// Which world a plugin implements.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PluginKind {
    /// World `horizon-policy`: how many actions of a chunk to execute.
    Horizon,
    /// World `priority-policy`: the dispatch order of pending requests.
    Priority,
}

impl std::fmt::Display for PluginKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PluginKind::Horizon => "horizon",
            PluginKind::Priority => "priority",
        })
    }
}

/// Whether an instance serves many calls or one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InstanceMode {
    /// One instance serves calls until it fails or the plugin is reloaded (fastest: see
    /// docs/BENCHMARKS.md; a plugin may keep state between calls).
    #[default]
    Reuse,
    /// A fresh instance for every call (no state survives a call; costs an instantiation).
    Fresh,
}

/// Limits and behaviour of one loaded plugin.
#[derive(Clone, Debug)]
pub struct PluginOptions {
    /// The name the plugin answers to (its policy `name()`, which replies report, and its log
    /// lines); `None`: its source's ([`PluginSource::name`], the file stem).
    pub name: Option<String>,
    /// Longest a call may run before it is interrupted.
    pub deadline: Duration,
    /// Longest making a new instance may take (the guest's start code; the Python runtime's
    /// set-up). Separate from `deadline`, so a call after a discarded instance is not charged
    /// for it.
    pub instantiate_deadline: Duration,
    /// Most bytes of linear memory an instance may have.
    pub memory_limit: usize,
    /// Fuel (roughly, wasm instructions) per call; `None` disables fuel metering (epoch
    /// deadlines still apply). Metering makes guest code slower.
    pub fuel: Option<u64>,
    /// Instance reuse.
    pub instance_mode: InstanceMode,
    /// Consecutive failures on one robot's decisions (or on decisions of no robot) after which
    /// the plugin is quarantined for that robot (or for everyone) ([`health`]).
    pub quarantine_after: u32,
    /// Robots in quarantine at the same time from which the plugin is quarantined for every
    /// robot ([`health`]).
    pub quarantine_robots: u32,
    /// Decisions a newly quarantined plugin sits out before it is tried again; doubles each
    /// time the retry fails (capped at [`MAX_PROBATION`]), resets on success or reload.
    pub probation: u32,
    /// Precompiled-code cache; `None` compiles at every load.
    pub cache: Option<cache::CodeCache>,
    /// How often to check the plugin file for changes; `None` disables hot reload.
    pub reload_poll: Option<Duration>,
    /// Where its fallbacks are exported too (`kairos_plugin_fallbacks_total`); `None`: not
    /// exported.
    pub fallback_counter: Option<prometheus_client::metrics::counter::Counter>,
    /// Where its quarantine is exported (`kairos_plugin_quarantined`, 1 while quarantined);
    /// `None`: not exported.
    pub quarantine_gauge: Option<prometheus_client::metrics::gauge::Gauge>,
}

/// The default per-call deadline of a component that imports WASI, either world.
///
/// Such a component carries a language runtime (componentize-py links CPython), whose cost per
/// call is set by the interpreter and by lifting the arguments into its objects, not by the
/// policy: measured with `kairos plugin check` on a loaded 2-core machine (load average 4), the
/// Python template `bound_py` takes 0.3 ms (median) to 12 ms (slowest of 200 random chunks) and
/// 100–110 ms for the 350 000 updates of the `huge K` case; the shipped `kairos_py` priority
/// plugin 0.9 ms per 200 pending requests and 135 ms for 10 000. A C component does the same
/// work in 0.5 ms and stays under the plain defaults. 500 ms is about 4× the slowest of those
/// measurements, so a component built from our templates passes the check at default settings
/// on a busy machine, while a looping one is still stopped within half a second (and
/// quarantined after three such calls). Set `deadline_ms` to tighten it for a fast plugin.
pub const WASI_DEADLINE: Duration = Duration::from_millis(500);

/// Longest quarantine, in decisions.
pub const MAX_PROBATION: u32 = 100_000;

impl PluginOptions {
    /// Defaults for a horizon plugin: 5 ms per call (a horizon decision is on every reply's
    /// critical path), 64 MiB of memory.
    pub fn horizon() -> Self {
        PluginOptions {
            deadline: Duration::from_millis(5),
            ..Self::common()
        }
    }

    /// Defaults for a priority plugin: 50 ms per call (one call orders the whole pending
    /// list), 64 MiB of memory.
    pub fn priority() -> Self {
        PluginOptions {
            deadline: Duration::from_millis(50),
            ..Self::common()
        }
    }

    /// The defaults for `kind`.
    pub fn for_kind(kind: PluginKind) -> Self {
        match kind {
            PluginKind::Horizon => Self::horizon(),
            PluginKind::Priority => Self::priority(),
        }
    }

    /// The defaults for a component of `kind` that does (`imports_wasi`) or does not import
    /// WASI: [`PluginOptions::for_kind`], with the deadline raised to [`WASI_DEADLINE`] for a
    /// component that imports WASI (see there for the rule and its measurements).
    pub fn for_component(kind: PluginKind, imports_wasi: bool) -> Self {
        let defaults = Self::for_kind(kind);
        PluginOptions {
            deadline: if imports_wasi {
                defaults.deadline.max(WASI_DEADLINE)
            } else {
                defaults.deadline
            },
            ..defaults
        }
    }

    fn common() -> Self {
        PluginOptions {
            name: None,
            deadline: Duration::from_millis(5),
            instantiate_deadline: Duration::from_secs(1),
            memory_limit: 64 << 20,
            fuel: None,
            instance_mode: InstanceMode::Reuse,
            quarantine_after: 3,
            quarantine_robots: 3,
            probation: 100,
            cache: None,
            reload_poll: Some(Duration::from_millis(500)),
            fallback_counter: None,
            quarantine_gauge: None,
        }
    }
}

/// Where a plugin comes from.
#[derive(Clone, Debug)]
pub enum PluginSource {
    /// A `.wasm` component file (watched for hot reload).
    File(PathBuf),
    /// Component bytes in memory (tests, `kairos plugin check` on stdin), with a name.
    Bytes {
        /// Name for logs.
        name: String,
        /// The component.
        wasm: Vec<u8>,
    },
}

impl PluginSource {
    /// The plugin's name for logs: the file stem, or the given name.
    pub fn name(&self) -> String {
        match self {
            PluginSource::File(path) => path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| path.display().to_string()),
            PluginSource::Bytes { name, .. } => name.clone(),
        }
    }
}
