//! Users' plugins in the simulator (`kairos bench sim --priority-plugin F.wasm
//! --horizon-plugin G.wasm --param k=v`): loaded by the server's own
//! [`load_configured`](kairos_server::plugin::factory::load_configured), registered in the same
//! per-kind registries as the natives ([`Policies`]), and compared against the built-in
//! systems as rows of their own in the same tables, CSV and plots.
//!
//! - A **priority** plugin is a scheduler: it gets the rows a baseline scheduler gets, one per
//!   horizon setting (`F.wasm` replays the static-horizon traces, `F.wasm + dyn. horizon` the
//!   dynamic ones), so a twin of a native policy reproduces that policy's rows exactly.
//! - A **horizon** plugin decides how much of each chunk runs, which decides the work: the
//!   trace generator records every task a third time with the plugin choosing `H` (a trace
//!   setting named after the plugin, [`UserPlugin::horizon_setting`]), and Algorithm 1's
//!   scheduler replays it (`Kairos + G.wasm`, beside `Kairos` with the native threshold rule).
//!
//! The simulation is synchronous and runs on the bench's worker threads, never on a tokio
//! worker. A plugin call that fails is answered by the native fallback, as in `serve`, and
//! logged; the per-call deadline is generous ([`BENCH_DEADLINE`]) because the bench measures
//! decisions in virtual time, not call latency (`kairos plugin check` measures that).

use std::path::{Path, PathBuf};
use std::time::Duration;

use kairos_sdk::trace::HorizonSetting;

use super::experiment::Variant;
use crate::workload::generate::{DYNAMIC, STATIC};
use kairos_core::horizon::PolicyParams;
use kairos_core::registry::Policies;
use kairos_core::scheduler::PolicySpec;
use kairos_server::config::PluginConfig;
use kairos_server::plugin::factory::{PluginSetupError, load_configured};

/// Per-call deadline of a plugin in the bench: a looping plugin is still stopped, but a busy
/// machine never turns a slow call into a fallback decision that would change the numbers.
pub const BENCH_DEADLINE: Duration = Duration::from_secs(2);

/// Which kind of policy a plugin file was given as.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PluginRole {
    /// `--priority-plugin`.
    Priority,
    /// `--horizon-plugin`.
    Horizon,
}

/// One loaded plugin as the bench shows it.
#[derive(Clone, Debug, PartialEq)]
pub struct UserPlugin {
    /// Its file.
    pub file: PathBuf,
    /// Priority or horizon.
    pub role: PluginRole,
    /// The name it is registered under: the file stem plus `-wasm`, so that a twin of a native
    /// policy (`fifo.wasm`) never shadows the native it is compared against.
    pub name: String,
    /// Its file name, for labels (`fifo.wasm`).
    pub label: String,
    /// Parameters handed to it (`--param`).
    pub params: PolicyParams,
}

/// Why the users' plugins cannot be set up.
#[derive(Debug, thiserror::Error)]
pub enum UserPluginError {
    /// Loading through the server's plugin factory failed.
    #[error(transparent)]
    Setup(#[from] PluginSetupError),
    /// The file implements the other world than the flag it was given with says.
    #[error("{file} was given as a {given} plugin but implements the other policy world")]
    WrongWorld {
        /// The file.
        file: String,
        /// `priority` or `horizon`.
        given: &'static str,
    },
    /// The file name gives no usable policy name.
    #[error("{0}: a plugin file needs a name of ASCII letters, digits, '-' or '_' (plus .wasm)")]
    Name(String),
    /// A priority plugin refused its parameters (checked once, before any run).
    #[error("{file}: {source}")]
    Params {
        /// The file.
        file: String,
        /// Why.
        source: kairos_core::scheduler::PolicySpecError,
    },
}

impl UserPlugin {
    /// The priority spec that selects it with its parameters.
    pub fn spec(&self) -> PolicySpec {
        let mut spec = PolicySpec::named(&self.name);
        for (k, v) in &self.params {
            spec.params.insert(k.clone(), v.to_string());
        }
        spec
    }

    /// The trace setting a horizon plugin's tasks are recorded under: named after the plugin,
    /// its policy the plugin with its parameters.
    pub fn horizon_setting(&self) -> (String, HorizonSetting) {
        (
            self.name.clone(),
            HorizonSetting {
                policy: self.name.clone(),
                params: self.params.clone(),
            },
        )
    }

    /// The systems that show this plugin in the online experiment (see the module docs).
    /// `refetch`: whether a priority plugin's runs re-fetch stale observations (a horizon
    /// plugin runs under Algorithm 1, which does).
    pub fn variants(&self, refetch: bool) -> Vec<Variant> {
        let mut out = match self.role {
            PluginRole::Priority => {
                let mut s = Variant::new(&self.name, &self.label, self.spec(), STATIC);
                let mut d = Variant::new(
                    &format!("{}-dynamic", self.name),
                    &format!("{} + dyn. horizon", self.label),
                    self.spec(),
                    DYNAMIC,
                );
                s.refetch = refetch;
                d.refetch = refetch;
                vec![s, d]
            }
            PluginRole::Horizon => vec![Variant::new(
                &self.name,
                &format!("Kairos + {}", self.label),
                PolicySpec::named("kairos"),
                &self.name,
            )],
        };
        for v in &mut out {
            v.user = true;
        }
        out
    }
}

/// The users' plugins, loaded.
#[derive(Clone, Debug, Default)]
pub struct UserPlugins {
    /// Every plugin, in the order given (priority plugins first).
    pub plugins: Vec<UserPlugin>,
    /// Their registries, to layer over the natives ([`crate::sim::SimConfig::policies`]).
    pub policies: Policies,
}

impl UserPlugins {
    /// The extra trace settings the horizon plugins need.
    pub fn horizon_settings(&self) -> Vec<(String, HorizonSetting)> {
        self.plugins
            .iter()
            .filter(|p| p.role == PluginRole::Horizon)
            .map(UserPlugin::horizon_setting)
            .collect()
    }

    /// Every plugin's systems for the online experiment.
    pub fn variants(&self, refetch: bool) -> Vec<Variant> {
        self.plugins
            .iter()
            .flat_map(|p| p.variants(refetch))
            .collect()
    }
}

fn plugin_name(file: &Path) -> Result<(String, String), UserPluginError> {
    let bad = || UserPluginError::Name(file.display().to_string());
    let label = file
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .ok_or_else(bad)?;
    let stem = file
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .ok_or_else(bad)?;
    if stem.is_empty()
        || !stem
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        return Err(bad());
    }
    Ok((format!("{stem}-wasm"), label))
}

/// Where the benches cache compiled plugin code: `explicit` (`--plugin-cache`), else the user's
/// cache directory ([`CodeCache::default_dir`](kairos_server::plugin::cache::CodeCache::default_dir)),
/// else a directory under the system's temporary directory.
pub fn plugin_cache_dir(explicit: Option<PathBuf>) -> PathBuf {
    explicit
        .or_else(kairos_server::plugin::cache::CodeCache::default_dir)
        .unwrap_or_else(|| std::env::temp_dir().join("kairos-plugin-cache"))
}

/// Loads `priority` and `horizon` plugin files through the server's plugin factory, each with
/// `params`, compiled code cached under `cache_dir`. Each file must implement the world of the
/// flag it was given with.
pub fn load_user_plugins(
    priority: &[PathBuf],
    horizon: &[PathBuf],
    params: &PolicyParams,
    cache_dir: &Path,
) -> Result<UserPlugins, UserPluginError> {
    let mut plugins = Vec::new();
    let mut configs = Vec::new();
    for (files, role) in [
        (priority, PluginRole::Priority),
        (horizon, PluginRole::Horizon),
    ] {
        for file in files {
            let (name, label) = plugin_name(file)?;
            configs.push(PluginConfig {
                name: Some(name.clone()),
                deadline_ms: Some(BENCH_DEADLINE.as_millis() as u64),
                hot_reload: false,
                ..PluginConfig::file(file)
            });
            plugins.push(UserPlugin {
                file: file.clone(),
                role,
                name,
                label,
                params: params.clone(),
            });
        }
    }
    if plugins.is_empty() {
        return Ok(UserPlugins::default());
    }
    let (horizons, priorities) = load_configured(&configs, cache_dir, None)?;
    for p in &plugins {
        let (registered, given) = match p.role {
            PluginRole::Priority => (priorities.contains(&p.name), "priority"),
            PluginRole::Horizon => (horizons.contains(&p.name), "horizon"),
        };
        if !registered {
            return Err(UserPluginError::WrongWorld {
                file: p.file.display().to_string(),
                given,
            });
        }
        if p.role == PluginRole::Priority {
            kairos_core::registry::build_priority(&priorities, &p.spec()).map_err(|source| {
                UserPluginError::Params {
                    file: p.file.display().to_string(),
                    source,
                }
            })?;
        }
    }
    Ok(UserPlugins {
        plugins,
        policies: Policies {
            horizon: horizons,
            priority: priorities,
        },
    })
}
