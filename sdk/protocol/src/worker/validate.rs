//! The rules a worker's messages are checked against ([`Validate`]) before the scheduler uses
//! them: a worker holds the worker token, but its messages are untrusted input like a robot's.
//!
//! Strings use the robot protocol's [`Limits`] (names `max_name_bytes`, the token
//! `max_token_bytes`, free text `max_message_bytes`); tensors its rank and dimension limits.
//! Numbers a scheduler computes with must be finite and in range: a profile's latencies and
//! batch sizes are bounded by [`MAX_PROFILE_LATENCY_MS`], [`MAX_WORKER_BATCH`] and
//! [`MAX_PROFILE_POINTS`], so no arithmetic on them can overflow. What depends on the served
//! model (a `Chunks`' shapes, counts and values against the batch) is the scheduler's check.

use super::{Chunks, Drain, Heartbeat, ProfileWire, Register, WorkResult};
use crate::limits::{check_name, check_size, check_tensor, invalid_request};
use crate::{Limits, ModelInfo, Validate, ValidationError};

/// Longest a worker may declare one batch takes, ms: ten minutes. A profile beyond it describes
/// no engine a robot could wait for.
pub const MAX_PROFILE_LATENCY_MS: f64 = 600_000.0;

/// Largest batch a worker may declare (profile points and `max_batch`).
pub const MAX_WORKER_BATCH: u32 = 1024;

/// Most points a worker's profile may have.
pub const MAX_PROFILE_POINTS: usize = 64;

impl Validate for ModelInfo {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_name("model.name", &self.name, limits)?;
        check_size(
            || "model.cameras (count)".to_owned(),
            self.cameras.len(),
            limits.max_images,
        )?;
        for (index, camera) in self.cameras.iter().enumerate() {
            check_name(&format!("model.cameras[{index}]"), camera, limits)?;
        }
        Ok(())
    }
}

fn check_batch(field: impl Into<String>, batch: u32) -> Result<(), ValidationError> {
    if batch == 0 || batch > MAX_WORKER_BATCH {
        return Err(invalid_request(
            field,
            format!("must be in 1..={MAX_WORKER_BATCH}, got {batch}"),
        ));
    }
    Ok(())
}

impl Validate for ProfileWire {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_name("profile.model", &self.model, limits)?;
        check_size(
            || "profile.device".to_owned(),
            self.device.len(),
            limits.max_message_bytes,
        )?;
        if self.points.is_empty() || self.points.len() > MAX_PROFILE_POINTS {
            return Err(invalid_request(
                "profile.points",
                format!(
                    "needs 1..={MAX_PROFILE_POINTS} points, got {}",
                    self.points.len()
                ),
            ));
        }
        let mut batches = Vec::with_capacity(self.points.len());
        for (index, point) in self.points.iter().enumerate() {
            check_batch(format!("profile.points[{index}].batch"), point.batch)?;
            let latency = point.latency_ms;
            if !(latency.is_finite() && latency > 0.0 && latency <= MAX_PROFILE_LATENCY_MS) {
                return Err(invalid_request(
                    format!("profile.points[{index}].latency_ms"),
                    format!(
                        "a latency must be a finite number of ms in (0, {MAX_PROFILE_LATENCY_MS}], \
                         got {latency}"
                    ),
                ));
            }
            batches.push(point.batch);
        }
        batches.sort_unstable();
        if batches.windows(2).any(|pair| pair[0] == pair[1]) {
            return Err(invalid_request(
                "profile.points",
                "two points of the same batch size",
            ));
        }
        check_batch("profile.max_batch", self.max_batch)
    }
}

impl Validate for Register {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_size(
            || "token".to_owned(),
            self.token.len(),
            limits.max_token_bytes,
        )?;
        if self.worker_id.is_empty() {
            return Err(invalid_request("worker_id", "empty"));
        }
        check_name("worker_id", &self.worker_id, limits)?;
        self.model.validate(limits)?;
        self.profile.validate(limits)?;
        check_batch("max_batch", self.max_batch)
    }
}

impl Validate for Heartbeat {
    fn validate(&self, _limits: &Limits) -> Result<(), ValidationError> {
        Ok(())
    }
}

impl Validate for Drain {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_size(
            || "reason".to_owned(),
            self.reason.len(),
            limits.max_message_bytes,
        )
    }
}

impl Validate for WorkResult {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        match (&self.chunk, &self.error) {
            (Some(chunk), None) => {
                check_tensor("chunk.actions", &chunk.actions, limits, invalid_request)?;
                check_tensor("chunk.updates", &chunk.updates, limits, invalid_request)?;
                check_tensor("chunk.noise", &chunk.noise, limits, invalid_request)
            }
            (None, Some(error)) => {
                check_size(|| "error".to_owned(), error.len(), limits.max_message_bytes)
            }
            _ => Err(invalid_request(
                "result",
                "exactly one of `chunk` and `error` must be present",
            )),
        }
    }
}

impl Validate for Chunks {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        for (index, result) in self.results.iter().enumerate() {
            result.validate(limits).map_err(|error| match error {
                ValidationError::TooLarge { field, len, max } => ValidationError::TooLarge {
                    field: format!("results[{index}].{field}"),
                    len,
                    max,
                },
                ValidationError::InvalidRequest { field, reason } => {
                    invalid_request(format!("results[{index}].{field}"), reason)
                }
                other => other,
            })?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{ProfilePointWire, WorkChunk, WorkerTier};
    use super::*;
    use crate::Tensor;

    fn register() -> Register {
        Register {
            protocol: 1,
            token: "kairos_worker_x".into(),
            worker_id: "w0".into(),
            model: ModelInfo {
                name: "m".into(),
                chunk_len: 4,
                action_dim: 2,
                state_dim: 3,
                steps: 2,
                max_images: 1,
                cameras: vec!["front".into()],
            },
            profile: ProfileWire {
                model: "m".into(),
                device: "cpu".into(),
                points: vec![
                    ProfilePointWire {
                        batch: 1,
                        latency_ms: 2.5,
                    },
                    ProfilePointWire {
                        batch: 4,
                        latency_ms: 6.0,
                    },
                ],
                max_batch: 4,
            },
            max_batch: 4,
            tier: WorkerTier::Edge,
        }
    }

    #[test]
    fn a_registration_with_an_unusable_profile_or_oversized_strings_is_refused() {
        let limits = Limits::default();
        assert_eq!(register().validate(&limits), Ok(()));
        let latency = |ms: f64| {
            let mut r = register();
            r.profile.points[1].latency_ms = ms;
            r
        };
        for ms in [1e300, f64::INFINITY, f64::NAN, -1.0, 0.0, 600_001.0] {
            let error = latency(ms).validate(&limits).unwrap_err();
            assert!(error.to_string().contains("latency_ms"), "{ms}: {error}");
        }
        assert_eq!(latency(600_000.0).validate(&limits), Ok(()));
        type Break = fn(&mut Register);
        let broken: Vec<(&str, Break)> = vec![
            ("worker_id", |r| r.worker_id = "w".repeat(129)),
            ("worker_id", |r| r.worker_id.clear()),
            ("token", |r| r.token = "t".repeat(513)),
            ("model.name", |r| r.model.name = "m".repeat(129)),
            ("model.cameras", |r| r.model.cameras = vec!["c".into(); 9]),
            ("profile.device", |r| r.profile.device = "d".repeat(4097)),
            ("profile.points", |r| r.profile.points.clear()),
            ("profile.points", |r| {
                r.profile.points = vec![r.profile.points[0]; MAX_PROFILE_POINTS + 1]
            }),
            ("profile.points", |r| {
                r.profile.points[1].batch = r.profile.points[0].batch
            }),
            ("batch", |r| r.profile.points[0].batch = 0),
            ("batch", |r| {
                r.profile.points[1].batch = MAX_WORKER_BATCH + 1
            }),
            ("profile.max_batch", |r| r.profile.max_batch = 0),
            ("max_batch", |r| r.max_batch = u32::MAX),
        ];
        for (field, break_it) in broken {
            let mut r = register();
            break_it(&mut r);
            let error = r.validate(&limits).unwrap_err();
            assert!(error.to_string().contains(field), "{field}: {error}");
        }
    }

    #[test]
    fn a_results_error_text_and_tensors_are_held_to_the_limits() {
        let limits = Limits::default();
        let tensor = Tensor::from_f32(vec![1, 4, 2], &[0.0; 8]).unwrap();
        let chunk = WorkChunk {
            actions: tensor.clone(),
            updates: Tensor::from_f32(vec![1, 2, 4, 2], &[0.0; 16]).unwrap(),
            noise: tensor,
        };
        let chunks = |results: Vec<WorkResult>| Chunks {
            batch_id: 1,
            attempt: 0,
            compute_us: 10,
            results,
        };
        let ok = WorkResult {
            chunk: Some(chunk.clone()),
            error: None,
        };
        let failed = |text: String| WorkResult {
            chunk: None,
            error: Some(text),
        };
        assert_eq!(
            chunks(vec![ok.clone(), failed("x".repeat(4096))]).validate(&limits),
            Ok(())
        );
        let error = chunks(vec![ok.clone(), failed("x".repeat(100_036))])
            .validate(&limits)
            .unwrap_err();
        assert!(error.to_string().contains("results[1].error"), "{error}");
        for neither_or_both in [
            WorkResult {
                chunk: None,
                error: None,
            },
            WorkResult {
                chunk: Some(chunk.clone()),
                error: Some("and an error".into()),
            },
        ] {
            assert!(chunks(vec![neither_or_both]).validate(&limits).is_err());
        }
        let mut short = chunk;
        short.actions.data.pop();
        let error = chunks(vec![WorkResult {
            chunk: Some(short),
            error: None,
        }])
        .validate(&limits)
        .unwrap_err();
        assert!(error.to_string().contains("chunk.actions"), "{error}");
        let drain = Drain {
            reason: "r".repeat(4097),
        };
        assert!(drain.validate(&limits).is_err());
    }
}
