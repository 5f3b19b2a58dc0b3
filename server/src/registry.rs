//! Policies by name: where native policies and plugins meet.
//!
//! The server builds every horizon policy (per request, from the name and parameters the robot
//! sent) and its priority policy (once, from `kairos.toml`) through a [`Registry`]. The native
//! policies are registered at start; the plugin host registers each loaded plugin under its name
//! with the same kind of factory, so a plugin slots in wherever a native policy does.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::horizon::{self, HorizonError, HorizonPolicy, PolicyParams};
use crate::scheduler::registry::{PolicySpec, PolicySpecError};
use crate::scheduler::{self, PriorityPolicy};

/// Builds a policy from its parameters `A`, validating them.
pub type Factory<P, A, E> = Arc<dyn Fn(&A) -> Result<Box<P>, E> + Send + Sync>;

/// Factories keyed by policy name.
pub struct Registry<P: ?Sized, A, E> {
    factories: BTreeMap<String, Factory<P, A, E>>,
}

impl<P: ?Sized, A, E> Clone for Registry<P, A, E> {
    fn clone(&self) -> Self {
        Registry {
            factories: self.factories.clone(),
        }
    }
}

impl<P: ?Sized, A, E> Default for Registry<P, A, E> {
    fn default() -> Self {
        Registry {
            factories: BTreeMap::new(),
        }
    }
}

impl<P: ?Sized, A, E> std::fmt::Debug for Registry<P, A, E> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_set().entries(self.factories.keys()).finish()
    }
}

impl<P: ?Sized, A, E> Registry<P, A, E> {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Registers `factory` under `name`, replacing any earlier one (a plugin may shadow a native
    /// policy on purpose; the server logs it).
    pub fn register(
        &mut self,
        name: impl Into<String>,
        factory: impl Fn(&A) -> Result<Box<P>, E> + Send + Sync + 'static,
    ) -> &mut Self {
        self.factories.insert(name.into(), Arc::new(factory));
        self
    }

    /// Whether `name` is registered.
    pub fn contains(&self, name: &str) -> bool {
        self.factories.contains_key(name)
    }

    /// Registered names, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.factories.keys().map(String::as_str)
    }

    /// The factory registered under `name`.
    pub fn factory(&self, name: &str) -> Option<&Factory<P, A, E>> {
        self.factories.get(name)
    }

    /// Adds every entry of `other`, replacing entries of the same name.
    pub fn extend(&mut self, other: Registry<P, A, E>) -> &mut Self {
        self.factories.extend(other.factories);
        self
    }

    /// Builds `name` with `params`: `None` if the name is unknown, else the factory's answer.
    pub fn build(&self, name: &str, params: &A) -> Option<Result<Box<P>, E>> {
        self.factories.get(name).map(|f| f(params))
    }
}

/// Horizon policies by name, built per request from the request's parameters.
pub type HorizonRegistry = Registry<dyn HorizonPolicy, PolicyParams, HorizonError>;

/// Priority policies by name, built once from `[scheduler] policy = "name:key=value,..."`.
pub type PriorityRegistry = Registry<dyn PriorityPolicy, PolicySpec, PolicySpecError>;

/// The native priority policies (`fifo`, `plas`, `kairos`).
pub fn native_priority_policies() -> PriorityRegistry {
    let mut registry = PriorityRegistry::new();
    for factory in scheduler::registry::BUILTIN {
        let build = factory.build;
        registry.register(factory.name, move |spec: &PolicySpec| build(spec.clone()));
    }
    registry
}

/// Builds the priority policy `spec` names from `registry`.
pub fn build_priority(
    registry: &PriorityRegistry,
    spec: &PolicySpec,
) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    registry.build(&spec.name, spec).unwrap_or_else(|| {
        Err(PolicySpecError::UnknownPolicy {
            name: spec.name.clone(),
            known: registry.names().collect::<Vec<_>>().join(", "),
        })
    })
}

/// The native horizon policies (`threshold`, `static`, `spread`).
pub fn native_horizon_policies() -> HorizonRegistry {
    let mut registry = HorizonRegistry::new();
    for (name, _) in horizon::BUILTIN_POLICIES {
        let owned = name.to_string();
        registry.register(*name, move |params| horizon::builtin(&owned, params));
    }
    registry
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn native_horizon_policies_build_by_name_and_validate_params() {
        let registry = native_horizon_policies();
        assert!(registry.contains("threshold"));
        assert!(registry.contains("static"));
        let names: Vec<&str> = registry.names().collect();
        assert!(names.windows(2).all(|w| w[0] < w[1]));
        let policy = registry
            .build("threshold", &PolicyParams::new())
            .unwrap()
            .unwrap();
        assert_eq!(policy.name(), "threshold");
        let bad = PolicyParams::from([("t".to_string(), -1.0)]);
        assert!(registry.build("threshold", &bad).unwrap().is_err());
        assert!(registry.build("nope", &PolicyParams::new()).is_none());
    }

    #[test]
    fn a_registered_factory_shadows_a_native_one() {
        struct Always(usize);
        impl HorizonPolicy for Always {
            fn name(&self) -> &str {
                "mine"
            }
            fn choose(
                &mut self,
                _input: &horizon::HorizonInput<'_>,
            ) -> Result<usize, HorizonError> {
                Ok(self.0)
            }
        }
        let mut registry = native_horizon_policies();
        registry.register("threshold", |_| {
            Ok(Box::new(Always(3)) as Box<dyn HorizonPolicy>)
        });
        let policy = registry
            .build("threshold", &PolicyParams::new())
            .unwrap()
            .unwrap();
        assert_eq!(policy.name(), "mine");
    }

    #[test]
    fn native_priority_policies_build_from_specs() {
        let registry = native_priority_policies();
        for name in ["fifo", "plas", "kairos"] {
            let policy = build_priority(&registry, &name.parse().unwrap()).unwrap();
            assert_eq!(policy.name(), name);
        }
        assert!(build_priority(&registry, &"kairos:buckets=10".parse().unwrap()).is_ok());
        assert!(matches!(
            build_priority(&registry, &"kairos:nope=1".parse().unwrap()),
            Err(PolicySpecError::UnknownParam { .. })
        ));
        assert!(matches!(
            build_priority(&registry, &"lottery".parse().unwrap()),
            Err(PolicySpecError::UnknownPolicy { .. })
        ));
    }
}
