//! Plugins as policy factories, the shape the server's policy registries take: a horizon
//! policy is built per request from the request's parameters, the priority policy once from a
//! spec such as `myplugin:buckets=10`.

use std::path::Path;
use std::time::Duration;

use super::cache::CodeCache;
use super::inspect::inspect;
use super::{
    HorizonPlugin, LoadError, PluginKind, PluginOptions, PluginSource, WasmPriorityPolicy,
};
use crate::config::PluginConfig;
use kairos_core::horizon::{self, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use kairos_core::registry::{
    HorizonKind, HorizonRegistry, Origin, PolicyKind, PriorityKind, PriorityRegistry, RegistryError,
};
use kairos_core::scheduler::{PolicySpec, PolicySpecError, PriorityPolicy, build_policy};

/// Calls a native policy with its own default parameters, whatever the request carried (those
/// were meant for the plugin).
struct WithDefaults(Box<dyn HorizonPolicy>);

impl HorizonPolicy for WithDefaults {
    fn name(&self) -> &str {
        self.0.name()
    }

    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        let defaults = PolicyParams::new();
        self.0.choose(&HorizonInput {
            params: &defaults,
            ..*input
        })
    }
}

/// A horizon-policy factory for `plugin`: each call returns a cheap handle (shared compiled
/// code, shared health, pooled instances) that answers with the native policy `fallback`
/// (e.g. `threshold`, with its default parameters) whenever the plugin fails. The request's
/// parameters are checked by the plugin itself on every call.
pub fn horizon_factory(
    plugin: HorizonPlugin,
    fallback: &str,
) -> Result<
    impl Fn(&PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> + Send + Sync + 'static,
    HorizonError,
> {
    // Fail now, at start-up, if the fallback does not exist.
    horizon::builtin(fallback, &PolicyParams::new())?;
    let fallback = fallback.to_string();
    Ok(move |_params: &PolicyParams| {
        let native = horizon::builtin(&fallback, &PolicyParams::new())?;
        Ok(Box::new(plugin.policy(Box::new(WithDefaults(native)))) as Box<dyn HorizonPolicy>)
    })
}

/// The parameters of a priority spec as plugin parameters: every value must be a number
/// (`inf` is one).
pub fn spec_params(spec: &PolicySpec) -> Result<PolicyParams, PolicySpecError> {
    spec.params
        .iter()
        .map(|(name, value)| match value.parse::<f64>() {
            Ok(v) if !v.is_nan() => Ok((name.clone(), v)),
            _ => Err(PolicySpecError::InvalidParam {
                policy: spec.name.clone(),
                param: name.clone(),
                value: value.clone(),
                reason: "plugin parameters are numbers".into(),
            }),
        })
        .collect()
}

/// A priority-policy factory for the plugin in `source`: building it loads the plugin (the
/// code cache makes that cheap after the first time), checks the spec's parameters with a
/// trial call, and uses the native policy `fallback` for decisions the plugin fails.
pub fn priority_factory(
    source: PluginSource,
    options: PluginOptions,
    fallback: PolicySpec,
) -> Result<
    impl Fn(&PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> + Send + Sync + 'static,
    PolicySpecError,
> {
    build_policy(&fallback)?;
    Ok(move |spec: &PolicySpec| {
        let params = spec_params(spec)?;
        let native = build_policy(&fallback)?;
        WasmPriorityPolicy::load(&source, &params, options.clone(), native)
            .map(|policy| Box::new(policy) as Box<dyn PriorityPolicy>)
            .map_err(|e: LoadError| PolicySpecError::InvalidParam {
                policy: spec.name.clone(),
                param: "(plugin)".into(),
                value: spec.to_string(),
                reason: e.to_string(),
            })
    })
}

/// Why a configured plugin could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum PluginSetupError {
    /// Loading, inspecting or compiling the component failed.
    #[error(transparent)]
    Load(#[from] LoadError),
    /// The component exports no policy world, or both.
    #[error("plugin `{name}` ({path}): {reason}")]
    World {
        /// The plugin.
        name: String,
        /// Its file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// The fallback horizon policy does not exist.
    #[error("plugin `{name}`: fallback {source}")]
    HorizonFallback {
        /// The plugin.
        name: String,
        /// Why.
        source: HorizonError,
    },
    /// The fallback priority policy does not exist or its spec is invalid.
    #[error("plugin `{name}`: fallback {source}")]
    PriorityFallback {
        /// The plugin.
        name: String,
        /// Why.
        source: PolicySpecError,
    },
    /// Two plugins of one kind under one name.
    #[error(transparent)]
    Registry(#[from] RegistryError),
    /// The code cache directory cannot be used.
    #[error("plugin code cache: {0}")]
    Cache(#[from] super::cache::CacheError),
}

/// How `/metrics` labels a plugin's kind.
fn policy_kind(kind: PluginKind) -> crate::metrics::PolicyKind {
    match kind {
        PluginKind::Horizon => crate::metrics::PolicyKind::Horizon,
        PluginKind::Priority => crate::metrics::PolicyKind::Priority,
    }
}

/// The configured plugins as policy registries: each horizon plugin is compiled once (its
/// instances are pooled and shared by every request that selects it); each priority plugin is
/// loaded when the scheduler builds its policy. Compiled code is cached under `cache_dir`.
pub fn load_configured(
    plugins: &[PluginConfig],
    cache_dir: &Path,
    metrics: Option<&crate::metrics::Metrics>,
) -> Result<(HorizonRegistry, PriorityRegistry), PluginSetupError> {
    let mut horizons = HorizonRegistry::new();
    let mut priorities = PriorityRegistry::new();
    if plugins.is_empty() {
        return Ok((horizons, priorities));
    }
    let cache = CodeCache::open(cache_dir)?;
    for plugin in plugins {
        let name = plugin.name();
        let (kind, imports_wasi) = world_of(plugin, &name)?;
        let defaults = PluginOptions::for_component(kind, imports_wasi);
        // Registered under `name`, the plugin also answers to it: replies and logs say what the
        // configuration and the robots call it, not the file stem.
        let options = PluginOptions {
            name: Some(name.clone()),
            deadline: plugin
                .deadline_ms
                .map_or(defaults.deadline, Duration::from_millis),
            memory_limit: plugin.memory_mib.map_or(defaults.memory_limit, |mib| {
                usize::try_from(mib.saturating_mul(1 << 20)).unwrap_or(usize::MAX)
            }),
            cache: Some(cache.clone()),
            fallback_counter: metrics.map(|m| m.fallback_counter(policy_kind(kind), &name)),
            quarantine_gauge: metrics.map(|m| m.quarantine_gauge(policy_kind(kind), &name)),
            reload_poll: if plugin.hot_reload {
                defaults.reload_poll
            } else {
                None
            },
            ..defaults
        };
        let source = PluginSource::File(plugin.file.clone());
        match kind {
            PluginKind::Horizon => {
                let fallback = plugin.fallback.as_deref().unwrap_or("threshold");
                let loaded = HorizonPlugin::load(&source, options)?;
                let factory = horizon_factory(loaded, fallback).map_err(|source| {
                    PluginSetupError::HorizonFallback {
                        name: name.clone(),
                        source,
                    }
                })?;
                tracing::info!(plugin = %name, file = %plugin.file.display(), fallback, "horizon plugin loaded");
                let shadowed = horizons.register_plugin(name.clone(), factory)?;
                note_shadowing::<HorizonKind>(&name, shadowed);
            }
            PluginKind::Priority => {
                let fallback: PolicySpec =
                    plugin
                        .fallback
                        .as_deref()
                        .unwrap_or("kairos")
                        .parse()
                        .map_err(|source| PluginSetupError::PriorityFallback {
                            name: name.clone(),
                            source,
                        })?;
                let factory = priority_factory(source, options, fallback).map_err(|source| {
                    PluginSetupError::PriorityFallback {
                        name: name.clone(),
                        source,
                    }
                })?;
                tracing::info!(plugin = %name, file = %plugin.file.display(), "priority plugin loaded");
                let shadowed = priorities.register_plugin(name.clone(), factory)?;
                note_shadowing::<PriorityKind>(&name, shadowed);
            }
        }
    }
    Ok((horizons, priorities))
}

/// Says when a plugin takes a native policy's name: requests for that name get the plugin.
/// `shadowed` is what the plugin registry had under the name; it holds plugins only, so the
/// natives are consulted too.
fn note_shadowing<K: PolicyKind>(name: &str, shadowed: Option<Origin>) {
    if shadowed.is_some() || K::NATIVES.iter().any(|n| n.name == name) {
        tracing::warn!(plugin = %name, kind = K::NAME,
            "plugin shadows the native policy of the same name: requests for it get the plugin");
    }
}

/// The world `plugin` implements, read from the component (which must export exactly one, in a
/// version this host supports), and whether it imports WASI.
fn world_of(plugin: &PluginConfig, name: &str) -> Result<(PluginKind, bool), PluginSetupError> {
    let wasm = std::fs::read(&plugin.file).map_err(|source| LoadError::Read {
        path: plugin.file.clone(),
        source,
    })?;
    let world_error = |reason: String| PluginSetupError::World {
        name: name.to_string(),
        path: plugin.file.display().to_string(),
        reason,
    };
    let info = inspect(&wasm).map_err(|e| world_error(e.to_string()))?;
    let kind = match info.exports.as_slice() {
        [(kind, _)] => *kind,
        [] => return Err(world_error("exports no policy interface".into())),
        _ => {
            return Err(world_error(
                "exports both policy interfaces; a plugin implements one world".into(),
            ));
        }
    };
    info.check(kind).map_err(|e| world_error(e.to_string()))?;
    Ok((kind, info.imports_wasi))
}
