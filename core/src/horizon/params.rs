//! Parameter parsing shared by the native horizon policies.

use super::{HorizonError, PolicyParams};

/// Fails on any parameter not in `known`, so a typo (`h-min`) is an error rather than a silently
/// ignored setting.
pub(crate) fn reject_unknown(params: &PolicyParams, known: &[&str]) -> Result<(), HorizonError> {
    match params.keys().find(|k| !known.contains(&k.as_str())) {
        Some(name) => Err(HorizonError::InvalidParam {
            name: name.clone(),
            reason: format!("unknown parameter (expected one of: {})", known.join(", ")),
        }),
        None => Ok(()),
    }
}

/// A finite real parameter `>= min`, or `default` when absent.
pub(crate) fn real(
    params: &PolicyParams,
    name: &str,
    min: f64,
    default: Option<f64>,
) -> Result<Option<f64>, HorizonError> {
    match params.get(name) {
        None => Ok(default),
        Some(&v) if v.is_finite() && v >= min => Ok(Some(v)),
        Some(&v) => Err(HorizonError::InvalidParam {
            name: name.to_string(),
            reason: format!("{v} is not a finite number >= {min}"),
        }),
    }
}

/// A whole-number parameter `>= 1` (a count of actions), or `None` when absent.
pub(crate) fn count(params: &PolicyParams, name: &str) -> Result<Option<usize>, HorizonError> {
    match params.get(name) {
        None => Ok(None),
        Some(&v) if v.is_finite() && v >= 1.0 && v.fract() == 0.0 && v <= 1e9 => {
            Ok(Some(v as usize))
        }
        Some(&v) => Err(HorizonError::InvalidParam {
            name: name.to_string(),
            reason: format!("{v} is not a whole number of actions >= 1"),
        }),
    }
}

/// A whole-number parameter `>= 0` (e.g. a margin of actions), or `default` when absent.
pub(crate) fn whole(
    params: &PolicyParams,
    name: &str,
    default: usize,
) -> Result<usize, HorizonError> {
    match params.get(name) {
        None => Ok(default),
        Some(&v) if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v <= 1e9 => Ok(v as usize),
        Some(&v) => Err(HorizonError::InvalidParam {
            name: name.to_string(),
            reason: format!("{v} is not a whole number of actions >= 0"),
        }),
    }
}
