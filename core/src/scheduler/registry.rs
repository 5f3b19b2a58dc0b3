//! Priority policies by name, for the command line and config files.
//!
//! A policy is written `name` or `name:key=value,key=value`, e.g. `fifo`, `plas:beta=16`,
//! `kairos:buckets=inf,intra=fifo`. [`PolicySpec`] parses and prints that form (and is a string
//! in serde), [`build`] turns it into a policy, validating every parameter.
//!
//! Adding a native policy: write `scheduler/<name>.rs` implementing
//! [`PriorityPolicy`], declare it in `scheduler/mod.rs`, and add one [`Native`] line to
//! [`NATIVE_POLICIES`] whose `build` reads its parameters through [`PolicySpec::take`] helpers
//! and ends with [`PolicySpec::finish`]. The priority registry
//! ([`crate::registry::PriorityRegistry`]) registers that table; plugins register beside it.

use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;

use super::PriorityPolicy;
use super::fifo::Fifo;
use super::kairos::{IntraBucket, Kairos, KairosConfig};
use super::plas::{Plas, PlasConfig};
use super::srw::{DueOrder, Srw, SrwConfig};
use crate::registry::{Native, PriorityKind, build_native};

/// Why a policy spec was refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PolicySpecError {
    /// The text is not `name` or `name:key=value,...`.
    #[error("invalid policy spec `{spec}`: {reason}")]
    Syntax {
        /// The text.
        spec: String,
        /// What is wrong.
        reason: String,
    },
    /// No policy has this name.
    #[error("unknown priority policy `{name}` (known: {known})")]
    UnknownPolicy {
        /// The name given.
        name: String,
        /// The names that exist.
        known: String,
    },
    /// A parameter the policy does not have.
    #[error("policy `{policy}` has no parameter `{param}`")]
    UnknownParam {
        /// The policy.
        policy: String,
        /// The parameter.
        param: String,
    },
    /// A parameter value out of range or unparsable.
    #[error("policy `{policy}`: invalid `{param}={value}`: {reason}")]
    InvalidParam {
        /// The policy.
        policy: String,
        /// The parameter.
        param: String,
        /// The value given.
        value: String,
        /// What is wrong.
        reason: String,
    },
}

/// A policy name with its parameters, as written on the command line.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct PolicySpec {
    /// The policy name (`fifo`, `plas`, `kairos`, ...).
    pub name: String,
    /// Its parameters, sorted by key.
    pub params: BTreeMap<String, String>,
}

impl PolicySpec {
    /// A spec with no parameters.
    pub fn named(name: &str) -> Self {
        PolicySpec {
            name: name.to_string(),
            params: BTreeMap::new(),
        }
    }

    /// Removes and parses parameter `key` with `parse`, or returns `default` when absent.
    pub fn take<T>(
        &mut self,
        key: &str,
        default: T,
        parse: impl FnOnce(&str) -> Result<T, String>,
    ) -> Result<T, PolicySpecError> {
        match self.params.remove(key) {
            None => Ok(default),
            Some(value) => parse(&value).map_err(|reason| PolicySpecError::InvalidParam {
                policy: self.name.clone(),
                param: key.to_string(),
                value,
                reason,
            }),
        }
    }

    /// Fails if any parameter was not consumed by [`PolicySpec::take`].
    pub fn finish(&self) -> Result<(), PolicySpecError> {
        match self.params.keys().next() {
            Some(param) => Err(PolicySpecError::UnknownParam {
                policy: self.name.clone(),
                param: param.clone(),
            }),
            None => Ok(()),
        }
    }
}

impl FromStr for PolicySpec {
    type Err = PolicySpecError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let syntax = |reason: &str| PolicySpecError::Syntax {
            spec: s.to_string(),
            reason: reason.to_string(),
        };
        let (name, rest) = match s.split_once(':') {
            Some((name, rest)) => (name.trim(), Some(rest)),
            None => (s.trim(), None),
        };
        if name.is_empty()
            || !name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(syntax(
                "the name must be non-empty ASCII letters, digits, '-' or '_'",
            ));
        }
        let mut params = BTreeMap::new();
        for pair in rest.into_iter().flat_map(|r| r.split(',')) {
            let pair = pair.trim();
            if pair.is_empty() {
                continue;
            }
            let (key, value) = pair
                .split_once('=')
                .ok_or_else(|| syntax("parameters are key=value, separated by commas"))?;
            let (key, value) = (key.trim(), value.trim());
            if key.is_empty() || value.is_empty() {
                return Err(syntax("empty parameter name or value"));
            }
            if params.insert(key.to_string(), value.to_string()).is_some() {
                return Err(syntax(&format!("parameter `{key}` given twice")));
            }
        }
        Ok(PolicySpec {
            name: name.to_string(),
            params,
        })
    }
}

impl fmt::Display for PolicySpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name)?;
        for (i, (k, v)) in self.params.iter().enumerate() {
            write!(f, "{}{k}={v}", if i == 0 { ':' } else { ',' })?;
        }
        Ok(())
    }
}

impl TryFrom<String> for PolicySpec {
    type Error = PolicySpecError;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<PolicySpec> for String {
    fn from(spec: PolicySpec) -> String {
        spec.to_string()
    }
}

/// The native priority policies: the one table [`crate::registry::PriorityRegistry`] registers.
pub const NATIVE_POLICIES: &[Native<PriorityKind>] = &[
    Native {
        name: "fifo",
        summary: "first come, first served by request arrival (vLLM default); no parameters",
        build: build_fifo,
    },
    Native {
        name: "plas",
        summary: "Autellix PLAS: least attained generation service in exponential queues; queues=8, quantum_ms=1000, growth=2, beta=8",
        build: build_plas,
    },
    Native {
        name: "kairos",
        summary: "paper Algorithm 1: wait-ratio buckets, aging, longest execution first; buckets=10 (or inf), aging=4, intra=longest-exec|fifo",
        build: build_kairos,
    },
    Native {
        name: "srw",
        summary: "slack-aware shortest remaining work: robots already out of actions first (by remaining rounds from the hint or a learned Gittins index, aged by wait ratio), the rest by deadline; hints=1, warmup=20, slack=1, due_order=work|deadline",
        build: build_srw,
    },
];

/// Builds the native policy `spec` names, from [`NATIVE_POLICIES`].
pub fn build(spec: &PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    build_native::<PriorityKind>(&spec.name, spec)
}

/// Whether a scheduler ordering by the policy named `name` re-fetches stale observations when the
/// configuration does not say (`SchedulerConfig::refetch`). Algorithm 1 re-fetches (line 16), and so
/// does SRW, which replaces only its ordering; the FIFO and Autellix baselines do not
/// ([`BASELINES_WITHOUT_REFETCH`]). A name that is no native policy (a plugin's) runs inside Kairos
/// and gets Algorithm 1's re-fetch; a plugin that shadows a native name gets that policy's setting.
pub fn refetch_by_default(name: &str) -> bool {
    !BASELINES_WITHOUT_REFETCH.contains(&name)
}

/// The native policies that stand for systems without stale-observation re-fetch.
pub const BASELINES_WITHOUT_REFETCH: &[&str] = &["fifo", "plas"];

/// Parses `s` as a whole number in `[min, max]`.
pub fn parse_int<T: TryFrom<u64>>(s: &str, min: u64, max: u64) -> Result<T, String> {
    let v: u64 = s
        .parse()
        .map_err(|_| format!("not a whole number between {min} and {max}"))?;
    if v < min || v > max {
        return Err(format!("must be between {min} and {max}"));
    }
    T::try_from(v).map_err(|_| "out of range".to_string())
}

/// Parses `s` as a finite real number `> min_exclusive`.
pub fn parse_real(s: &str, min_exclusive: f64) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|_| "not a number".to_string())?;
    if !v.is_finite() || v <= min_exclusive {
        return Err(format!("must be a finite number > {min_exclusive}"));
    }
    Ok(v)
}

fn build_fifo(spec: &PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    spec.finish()?;
    Ok(Box::new(Fifo::default()))
}

fn build_plas(spec: &PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    // `take` consumes parameters so that `finish` can name any left over.
    let mut spec = spec.clone();
    let d = PlasConfig::default();
    let queues = spec.take("queues", d.queues, |s| parse_int(s, 1, 64))?;
    let quantum_us = spec.take("quantum_ms", d.quantum_us, |s| {
        let ms = parse_real(s, 0.0)?;
        let us = (ms * 1e3).round();
        if !(1.0..=1e15).contains(&us) {
            return Err("must be between 0.001 and 10^12 ms".into());
        }
        Ok(us as u64)
    })?;
    let growth = spec.take("growth", d.growth, |s| parse_int(s, 1, 1_000))?;
    let beta = spec.take("beta", d.beta, |s| parse_real(s, 0.0))?;
    spec.finish()?;
    Ok(Box::new(Plas::new(PlasConfig {
        queues,
        quantum_us,
        growth,
        beta,
    })))
}

fn build_kairos(spec: &PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    // `take` consumes parameters so that `finish` can name any left over.
    let mut spec = spec.clone();
    let d = KairosConfig::default();
    let buckets = spec.take("buckets", d.buckets, |s| {
        if s == "inf" || s == "∞" {
            Ok(None)
        } else {
            parse_int(s, 1, 1_000_000).map(Some)
        }
    })?;
    let aging = spec.take("aging", d.aging, |s| parse_int(s, 1, u64::from(u32::MAX)))?;
    let intra = spec.take("intra", d.intra, |s| match s {
        "longest-exec" => Ok(IntraBucket::LongestExecFirst),
        "fifo" => Ok(IntraBucket::Fifo),
        _ => Err("expected longest-exec or fifo".into()),
    })?;
    spec.finish()?;
    Ok(Box::new(Kairos::new(KairosConfig {
        buckets,
        aging,
        intra,
    })))
}

fn build_srw(spec: &PolicySpec) -> Result<Box<dyn PriorityPolicy>, PolicySpecError> {
    // `take` consumes parameters so that `finish` can name any left over.
    let mut spec = spec.clone();
    let d = SrwConfig::default();
    let flag = |s: &str| match s {
        "1" | "true" => Ok(true),
        "0" | "false" => Ok(false),
        _ => Err("expected 1 or 0".to_string()),
    };
    let hints = spec.take("hints", d.hints, flag)?;
    let warmup = spec.take("warmup", d.warmup, |s| parse_int(s, 0, 1_000_000))?;
    let slack = spec.take("slack", d.slack, flag)?;
    let due_order = spec.take("due_order", d.due_order, |s| match s {
        "work" => Ok(DueOrder::Work),
        "deadline" => Ok(DueOrder::Deadline),
        _ => Err("expected work or deadline".into()),
    })?;
    spec.finish()?;
    Ok(Box::new(Srw::new(SrwConfig {
        hints,
        warmup,
        slack,
        due_order,
    })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_print_and_build() {
        let spec: PolicySpec = "kairos:buckets=inf, intra=fifo".parse().unwrap();
        assert_eq!(spec.name, "kairos");
        assert_eq!(spec.to_string(), "kairos:buckets=inf,intra=fifo");
        assert_eq!(build(&spec).unwrap().name(), "kairos");
        for name in ["fifo", "plas", "kairos"] {
            assert_eq!(build(&PolicySpec::named(name)).unwrap().name(), name);
        }
        assert!(
            build(
                &"plas:beta=16,queues=4,quantum_ms=250,growth=3"
                    .parse()
                    .unwrap()
            )
            .is_ok()
        );
        let json = serde_json::to_string(&spec).unwrap();
        assert_eq!(json, "\"kairos:buckets=inf,intra=fifo\"");
        assert_eq!(serde_json::from_str::<PolicySpec>(&json).unwrap(), spec);
    }

    #[test]
    fn only_the_baselines_skip_the_refetch_by_default() {
        assert!(!refetch_by_default("fifo"));
        assert!(!refetch_by_default("plas"));
        assert!(refetch_by_default("kairos"));
        assert!(refetch_by_default("srw"));
        assert!(refetch_by_default("my-plugin"));
    }

    #[test]
    fn bad_specs_are_refused_with_the_reason() {
        let err = |s: &str| match s.parse::<PolicySpec>() {
            Ok(spec) => build(&spec).err().map(|e| e.to_string()),
            Err(e) => Some(e.to_string()),
        };
        assert!(err("sjf").unwrap().contains("unknown priority policy"));
        assert!(err("fifo:x=1").unwrap().contains("no parameter `x`"));
        assert!(err("kairos:buckets=0").unwrap().contains("between 1"));
        assert!(err("kairos:aging=-1").is_some());
        assert!(err("kairos:intra=random").unwrap().contains("longest-exec"));
        assert!(err("plas:beta=0").is_some());
        assert!(err("plas:beta=nan").is_some());
        assert!(err("kairos:buckets").unwrap().contains("key=value"));
        assert!(err("kairos:aging=2,aging=3").unwrap().contains("twice"));
        assert!(err(":x=1").is_some());
        assert!(err("kairos:buckets=5,aging=2").is_none());
    }
}
