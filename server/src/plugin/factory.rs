//! Plugins as policy factories, the shape the server's policy registries take: a horizon
//! policy is built per request from the request's parameters, the priority policy once from a
//! spec such as `myplugin:buckets=10`.

use super::{HorizonPlugin, LoadError, PluginOptions, PluginSource, WasmPriorityPolicy};
use crate::horizon::{self, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use crate::scheduler::{PolicySpec, PolicySpecError, PriorityPolicy, build_policy};

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
