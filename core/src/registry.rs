//! Policies by name: one registry shape for both kinds of policy, where natives and plugins meet.
//!
//! A [`Registry<K>`] maps a policy name to a factory that builds the policy from its parameters.
//! There is one per kind ([`PolicyKind`]): [`HorizonRegistry`] (built per request from the
//! name and parameters the robot sent) and [`PriorityRegistry`] (built once from a
//! [`PolicySpec`] such as `kairos:buckets=10`). Each kind's native policies are one table
//! ([`PolicyKind::NATIVES`]: `horizon::NATIVE_POLICIES`, `scheduler::registry::NATIVE_POLICIES`);
//! nothing else matches on policy names. The plugin host registers each loaded plugin with the
//! same kind of factory ([`Registry::register_plugin`]), so a plugin slots in wherever a native
//! policy does. Everything that builds policies by name (`serve`, `sim`, `bench live`,
//! `bench horizon`) takes these registries.
//!
//! Names are resolved by these rules:
//! - [`Registry::natives`] holds the kind's native table;
//! - a plugin may **shadow** a native policy of the same name ([`Registry::register_plugin`]
//!   returns [`Origin::Native`] so the caller can say so); the native stays available to
//!   whoever kept it (the action manager's native fallback does);
//! - two plugins under one name **conflict**: [`RegistryError::Conflict`];
//! - [`Registry::register`] (policies registered in code: tests, embedders) and
//!   [`Registry::extend`] (layering one registry over another) replace whatever had the name;
//! - an unknown name is an error that lists every registered name ([`Registry::resolve`]).

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::horizon::{self, HorizonError, HorizonPolicy, PolicyParams};
use crate::scheduler::registry::{PolicySpec, PolicySpecError};
use crate::scheduler::{self, PriorityPolicy};

/// Builds a policy from its parameters `A`, validating them.
pub type Factory<P, A, E> = Arc<dyn Fn(&A) -> Result<Box<P>, E> + Send + Sync>;

/// A kind of policy: what its registry's factories build, from what, and how they fail.
pub trait PolicyKind: Sized + 'static {
    /// The policy trait object (`dyn HorizonPolicy`, `dyn PriorityPolicy`).
    type Policy: ?Sized + 'static;
    /// What a factory reads: the request's parameters, or a whole spec.
    type Params: 'static;
    /// Why a policy could not be built.
    type Error: 'static;
    /// `horizon` or `priority`, for messages.
    const NAME: &'static str;
    /// The native policies, registered by [`Registry::natives`].
    const NATIVES: &'static [Native<Self>];

    /// The error for `name`, which is not registered; `known` lists the registered names.
    fn unknown(name: &str, known: &str) -> Self::Error;
}

/// What a factory of kind `K` returns: the policy, or why it could not be built.
pub type Built<K> = Result<Box<<K as PolicyKind>::Policy>, <K as PolicyKind>::Error>;

/// One native policy: its name, what it does, and how to build it.
pub struct Native<K: PolicyKind> {
    /// Its name.
    pub name: &'static str,
    /// One line for `--help` and error messages: what it does and its parameters.
    pub summary: &'static str,
    /// Builds it, validating every parameter.
    pub build: fn(&K::Params) -> Built<K>,
}

impl<K: PolicyKind> std::fmt::Debug for Native<K> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Native").field("name", &self.name).finish()
    }
}

/// Horizon policies: built per request from the request's parameters.
#[derive(Clone, Copy, Debug)]
pub struct HorizonKind;

impl PolicyKind for HorizonKind {
    type Policy = dyn HorizonPolicy;
    type Params = PolicyParams;
    type Error = HorizonError;
    const NAME: &'static str = "horizon";
    const NATIVES: &'static [Native<Self>] = horizon::NATIVE_POLICIES;

    fn unknown(name: &str, known: &str) -> HorizonError {
        HorizonError::InvalidParam {
            name: "policy".into(),
            reason: format!("unknown horizon policy `{name}` (known: {known})"),
        }
    }
}

/// Priority policies: built once from `[scheduler] policy = "name:key=value,..."`.
#[derive(Clone, Copy, Debug)]
pub struct PriorityKind;

impl PolicyKind for PriorityKind {
    type Policy = dyn PriorityPolicy;
    type Params = PolicySpec;
    type Error = PolicySpecError;
    const NAME: &'static str = "priority";
    const NATIVES: &'static [Native<Self>] = scheduler::registry::NATIVE_POLICIES;

    fn unknown(name: &str, known: &str) -> PolicySpecError {
        PolicySpecError::UnknownPolicy {
            name: name.to_string(),
            known: known.to_string(),
        }
    }
}

/// Where a registered policy comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// The kind's native table.
    Native,
    /// A loaded WASM plugin.
    Plugin,
    /// Registered in code with [`Registry::register`].
    Registered,
}

/// A name the registry refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RegistryError {
    /// A second plugin under a name a plugin already has.
    #[error("two {kind} plugins are named `{name}`; give one another name")]
    Conflict {
        /// `horizon` or `priority`.
        kind: &'static str,
        /// The name.
        name: String,
    },
}

struct Entry<K: PolicyKind> {
    factory: Factory<K::Policy, K::Params, K::Error>,
    origin: Origin,
}

impl<K: PolicyKind> Clone for Entry<K> {
    fn clone(&self) -> Self {
        Entry {
            factory: self.factory.clone(),
            origin: self.origin,
        }
    }
}

/// Factories of one kind of policy, keyed by name. See the module documentation for the rules.
pub struct Registry<K: PolicyKind> {
    entries: BTreeMap<String, Entry<K>>,
}

impl<K: PolicyKind> Clone for Registry<K> {
    fn clone(&self) -> Self {
        Registry {
            entries: self.entries.clone(),
        }
    }
}

impl<K: PolicyKind> Default for Registry<K> {
    fn default() -> Self {
        Registry {
            entries: BTreeMap::new(),
        }
    }
}

impl<K: PolicyKind> std::fmt::Debug for Registry<K> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_map()
            .entries(self.entries.iter().map(|(name, e)| (name, e.origin)))
            .finish()
    }
}

impl<K: PolicyKind> Registry<K> {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// The kind's native policies.
    pub fn natives() -> Self {
        let mut registry = Self::new();
        for native in K::NATIVES {
            registry.insert(native.name, Arc::new(native.build), Origin::Native);
        }
        registry
    }

    /// Registers `factory` under `name` in code, replacing anything of that name.
    pub fn register(
        &mut self,
        name: impl Into<String>,
        factory: impl Fn(&K::Params) -> Built<K> + Send + Sync + 'static,
    ) -> &mut Self {
        self.insert(name.into(), Arc::new(factory), Origin::Registered);
        self
    }

    /// Registers a plugin's factory under `name`. A plugin may shadow a native or code-registered
    /// policy (the previous origin is returned, so the caller can say so) but not another plugin.
    pub fn register_plugin(
        &mut self,
        name: impl Into<String>,
        factory: impl Fn(&K::Params) -> Built<K> + Send + Sync + 'static,
    ) -> Result<Option<Origin>, RegistryError> {
        let name = name.into();
        let previous = self.origin(&name);
        if previous == Some(Origin::Plugin) {
            return Err(RegistryError::Conflict {
                kind: K::NAME,
                name,
            });
        }
        self.insert(name, Arc::new(factory), Origin::Plugin);
        Ok(previous)
    }

    fn insert(
        &mut self,
        name: impl Into<String>,
        factory: Factory<K::Policy, K::Params, K::Error>,
        origin: Origin,
    ) {
        self.entries.insert(name.into(), Entry { factory, origin });
    }

    /// Whether `name` is registered.
    pub fn contains(&self, name: &str) -> bool {
        self.entries.contains_key(name)
    }

    /// Where the policy registered under `name` comes from.
    pub fn origin(&self, name: &str) -> Option<Origin> {
        self.entries.get(name).map(|e| e.origin)
    }

    /// Registered names, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.entries.keys().map(String::as_str)
    }

    /// The factory registered under `name`.
    pub fn factory(&self, name: &str) -> Option<&Factory<K::Policy, K::Params, K::Error>> {
        self.entries.get(name).map(|e| &e.factory)
    }

    /// Adds every entry of `other`, replacing entries of the same name (layering: the
    /// caller's policies over configured plugins over natives).
    pub fn extend(&mut self, other: Registry<K>) -> &mut Self {
        self.entries.extend(other.entries);
        self
    }

    /// Builds `name` with `params`: `None` if the name is unknown, else the factory's answer.
    pub fn build(
        &self,
        name: &str,
        params: &K::Params,
    ) -> Option<Result<Box<K::Policy>, K::Error>> {
        self.entries.get(name).map(|e| (e.factory)(params))
    }

    /// Builds `name` with `params`; an unknown name is the kind's error listing every
    /// registered name.
    pub fn resolve(&self, name: &str, params: &K::Params) -> Built<K> {
        self.build(name, params).unwrap_or_else(|| {
            Err(K::unknown(
                name,
                &self.names().collect::<Vec<_>>().join(", "),
            ))
        })
    }
}

/// Builds the native policy `name` of kind `K` straight from its table, without making a
/// registry (what per-task callers such as the simulator's horizon replay use).
pub fn build_native<K: PolicyKind>(name: &str, params: &K::Params) -> Built<K> {
    match K::NATIVES.iter().find(|n| n.name == name) {
        Some(native) => (native.build)(params),
        None => {
            // Sorted, as a registry lists them.
            let mut known: Vec<&str> = K::NATIVES.iter().map(|n| n.name).collect();
            known.sort_unstable();
            Err(K::unknown(name, &known.join(", ")))
        }
    }
}

/// Policies available beyond the native ones (plugins and policies registered in code), one
/// registry per kind, layered over the natives by whoever builds policies: the server
/// (`transport::launch::start`), the simulator ([`kairos_bench::sim::SimConfig::policies`]).
#[derive(Clone, Debug, Default)]
pub struct Policies {
    /// Extra horizon policies; a name here shadows a native policy of the same name.
    pub horizon: HorizonRegistry,
    /// Extra priority policies.
    pub priority: PriorityRegistry,
}

impl Policies {
    /// The natives with these policies over them, one registry per kind.
    pub fn with_natives(&self) -> (HorizonRegistry, PriorityRegistry) {
        let mut horizon = HorizonRegistry::natives();
        horizon.extend(self.horizon.clone());
        let mut priority = PriorityRegistry::natives();
        priority.extend(self.priority.clone());
        (horizon, priority)
    }
}

/// Horizon policies by name, built per request from the request's parameters.
pub type HorizonRegistry = Registry<HorizonKind>;

/// Priority policies by name, built once from `[scheduler] policy = "name:key=value,..."`.
pub type PriorityRegistry = Registry<PriorityKind>;

/// The native priority policies (`fifo`, `plas`, `kairos`, `srw`): [`Registry::natives`].
pub fn native_priority_policies() -> PriorityRegistry {
    PriorityRegistry::natives()
}

/// Builds the priority policy `spec` names from `registry`:
/// `registry.resolve(&spec.name, spec)`.
pub fn build_priority(
    registry: &PriorityRegistry,
    spec: &PolicySpec,
) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    registry.resolve(&spec.name, spec)
}

/// The native horizon policies (`threshold`, `static`, `spread`): [`Registry::natives`].
pub fn native_horizon_policies() -> HorizonRegistry {
    HorizonRegistry::natives()
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Always(usize);

    impl HorizonPolicy for Always {
        fn name(&self) -> &str {
            "mine"
        }
        fn choose(&mut self, _input: &horizon::HorizonInput<'_>) -> Result<usize, HorizonError> {
            Ok(self.0)
        }
    }

    fn always(_: &PolicyParams) -> Result<Box<dyn HorizonPolicy>, HorizonError> {
        Ok(Box::new(Always(3)))
    }

    #[test]
    fn every_native_name_resolves_through_its_registry() {
        let horizons = HorizonRegistry::natives();
        let names: Vec<&str> = horizons.names().collect();
        assert_eq!(
            names,
            [
                "contact",
                "load-aware",
                "spread",
                "static",
                "steady",
                "threshold"
            ]
        );
        for native in HorizonKind::NATIVES {
            // `static` requires `h`; the others build with their defaults.
            let params = match native.name {
                "static" => PolicyParams::from([("h".to_string(), 4.0)]),
                _ => PolicyParams::new(),
            };
            let policy = horizons.resolve(native.name, &params).unwrap();
            assert_eq!(policy.name(), native.name);
            assert_eq!(horizons.origin(native.name), Some(Origin::Native));
            assert_eq!(
                build_native::<HorizonKind>(native.name, &params)
                    .unwrap()
                    .name(),
                native.name
            );
        }
        let priorities = PriorityRegistry::natives();
        let names: Vec<&str> = priorities.names().collect();
        assert_eq!(names, ["fifo", "kairos", "plas", "srw"]);
        for native in PriorityKind::NATIVES {
            let spec = PolicySpec::named(native.name);
            assert_eq!(
                priorities.resolve(native.name, &spec).unwrap().name(),
                native.name
            );
            assert_eq!(
                build_priority(&priorities, &spec).unwrap().name(),
                native.name
            );
            assert_eq!(
                build_native::<PriorityKind>(native.name, &spec)
                    .unwrap()
                    .name(),
                native.name
            );
        }
    }

    #[test]
    fn natives_validate_their_parameters() {
        let horizons = HorizonRegistry::natives();
        let bad = PolicyParams::from([("t".to_string(), -1.0)]);
        assert!(horizons.resolve("threshold", &bad).is_err());
        assert!(horizons.resolve("static", &PolicyParams::new()).is_err());
        let priorities = PriorityRegistry::natives();
        assert!(build_priority(&priorities, &"kairos:buckets=10".parse().unwrap()).is_ok());
        assert!(matches!(
            build_priority(&priorities, &"kairos:nope=1".parse().unwrap()),
            Err(PolicySpecError::UnknownParam { .. })
        ));
    }

    #[test]
    fn an_unknown_name_is_an_error_listing_every_registered_name() {
        let mut horizons = HorizonRegistry::natives();
        horizons.register_plugin("bound", always).unwrap();
        match horizons.resolve("nope", &PolicyParams::new()) {
            Err(HorizonError::InvalidParam { name, reason }) => {
                assert_eq!(name, "policy");
                assert!(
                    reason.contains("`nope`")
                        && reason.contains(
                            "bound, contact, load-aware, spread, static, steady, threshold"
                        ),
                    "{reason}"
                );
            }
            other => panic!(
                "expected an unknown-policy error, got {:?}",
                other.map(|p| p.name().to_string())
            ),
        }
        assert!(horizons.build("nope", &PolicyParams::new()).is_none());
        let error = build_native::<HorizonKind>("bound", &PolicyParams::new())
            .err()
            .unwrap();
        assert!(
            error
                .to_string()
                .contains("contact, load-aware, spread, static, steady, threshold"),
            "{error}"
        );
        match build_priority(&PriorityRegistry::natives(), &"lottery".parse().unwrap()) {
            Err(PolicySpecError::UnknownPolicy { name, known }) => {
                assert_eq!(name, "lottery");
                assert_eq!(known, "fifo, kairos, plas, srw");
            }
            other => panic!(
                "expected UnknownPolicy, got {:?}",
                other.map(|p| p.name().to_string())
            ),
        }
    }

    #[test]
    fn a_plugin_shadows_a_native_and_conflicts_with_another_plugin() {
        let mut registry = HorizonRegistry::natives();
        // A new name: nothing shadowed.
        assert_eq!(registry.register_plugin("mine", always), Ok(None));
        // A native name: shadowed, and said so.
        assert_eq!(
            registry.register_plugin("threshold", always),
            Ok(Some(Origin::Native))
        );
        assert_eq!(registry.origin("threshold"), Some(Origin::Plugin));
        let policy = registry.resolve("threshold", &PolicyParams::new()).unwrap();
        assert_eq!(policy.name(), "mine");
        // A second plugin under a plugin's name: refused, the first one stays.
        assert_eq!(
            registry.register_plugin("mine", always),
            Err(RegistryError::Conflict {
                kind: "horizon",
                name: "mine".into()
            })
        );
        // Code-registered policies replace, and a plugin may shadow them too.
        registry.register("spread", always);
        assert_eq!(registry.origin("spread"), Some(Origin::Registered));
        assert_eq!(
            registry.register_plugin("spread", always),
            Ok(Some(Origin::Registered))
        );
        // Layering: the later registry wins.
        let mut base = HorizonRegistry::natives();
        base.extend(registry);
        assert_eq!(base.origin("threshold"), Some(Origin::Plugin));
        assert_eq!(base.origin("static"), Some(Origin::Native));
    }
}
