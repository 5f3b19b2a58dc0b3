//! Wire messages → `Valid*` types (`kairos_core::round`), checked against the served model.
//!
//! Two layers of checks run on every request before it reaches the driver:
//! 1. the protocol's own ([`Validate`], in `kairos-protocol`): sizes against [`Limits`], tensor
//!    byte lengths, a 1-D `f32` state, finite numbers, `control_hz > 0`;
//! 2. the served model's (here): state length, image count, raw image channels, the horizon
//!    policy (registered, parameters valid, samples within the limit), and client timestamps that
//!    are consistent with each other (mapped onto the server clock by
//!    [`kairos_core::clock_map`]).
//!
//! Then [`decode`] decodes images on a bounded pool, before the queue. [`error`] holds
//! [`RequestError`], the one error type a connection task answers with.

pub mod chunking;
pub mod decode;
pub mod error;

use kairos_core::action::ActionManager;
use kairos_core::clock_map::ClockMap;
use kairos_core::round::{ValidEndTask, ValidObservation, ValidSubmit, round_seed};
use kairos_core::scheduler::{ExecReport, RemainingWork, RobotId, RoundSubmit, TaskEnd, TaskId};
use kairos_engine::image_features::ImageLimits;
use kairos_engine::{ActionRequest, ImageFormat, ImageInput, InputError, MAX_SAMPLES, ModelSpec};
use kairos_sdk::protocol::{
    DType, EndTask, FreshObservation, Hello, ImagePayload, LastExecInfo, Limits, Observation,
    PROTOCOL_VERSION, Submit, TaskOutcome, Validate,
};

pub use self::chunking::ChunkingRules;
pub use self::decode::{DecodePool, decode_images};
pub use self::error::RequestError;

/// What a request is checked against.
pub struct Validator {
    /// The served model's shapes.
    pub spec: ModelSpec,
    /// The limits announced in `Welcome`.
    pub limits: Limits,
    /// What the chunking strategies may do for the model.
    pub chunking: ChunkingRules,
}

pub(crate) fn observation_error(
    field: impl Into<String>,
    reason: impl Into<String>,
) -> RequestError {
    RequestError::Observation {
        field: field.into(),
        reason: reason.into(),
    }
}

fn invalid(field: impl Into<String>, reason: impl Into<String>) -> RequestError {
    RequestError::Invalid {
        field: field.into(),
        reason: reason.into(),
    }
}

impl Validator {
    /// Checks `Hello`'s fields and version (the token is checked by the caller).
    pub fn hello(&self, hello: &Hello) -> Result<u32, RequestError> {
        hello.validate(&self.limits)?;
        if hello.protocol < PROTOCOL_VERSION {
            return Err(RequestError::UnsupportedVersion(hello.protocol));
        }
        Ok(PROTOCOL_VERSION)
    }

    /// Checks a round request and builds its horizon policy.
    pub fn submit(
        &self,
        submit: Submit,
        robot: RobotId,
        actions: &ActionManager,
        clock: ClockMap,
    ) -> Result<ValidSubmit, RequestError> {
        submit.validate(&self.limits)?;
        let observation = self.observation(submit.observation, submit.sent_at_us, &clock)?;
        let last_exec = submit
            .last_exec
            .map(|e| exec_report(&e, submit.sent_at_us, &clock))
            .transpose()?;
        let (policy, samples) = match &submit.horizon {
            Some(h) => (
                actions.build_for(robot, Some(&h.policy), Some(&h.params))?,
                h.samples as usize,
            ),
            None => (actions.build_for(robot, None, None)?, 1),
        };
        if samples > MAX_SAMPLES {
            return Err(invalid(
                "horizon.samples",
                format!("{samples}, the engine draws at most {MAX_SAMPLES}"),
            ));
        }
        let committed = submit.last_exec.is_some_and(|e| e.actions_remaining > 0);
        let chunking = self.chunking.resolve(
            submit.chunking,
            &self.spec.name,
            self.spec.state_dim,
            committed,
        )?;
        let mut observation = observation;
        observation.request.samples = samples;
        // The client's own sampler seed when it sent one (reproducible evaluation), else the
        // fixed mix of task and round.
        observation.request.seed = submit
            .seed
            .unwrap_or_else(|| round_seed(submit.task, submit.round));
        Ok(ValidSubmit {
            round: RoundSubmit {
                task: TaskId(submit.task),
                robot,
                round: submit.round,
                sent_at: clock.to_server(submit.sent_at_us),
                obs_captured_at: observation.captured_at,
                last_exec,
                remaining: submit.remaining.map(|r| RemainingWork {
                    rounds: r.rounds,
                    seconds: r.seconds,
                }),
                control_hz: submit.control_hz,
            },
            observation,
            policy,
            samples,
            control_hz: submit.last_exec.map(|e| e.control_hz).or(submit.control_hz),
            clock,
            chunking,
            exec_round: submit.last_exec.and_then(|e| e.round),
            exec_delay: submit.last_exec.and_then(|e| e.delay),
        })
    }

    /// Checks a re-fetched observation. `samples` and `seed` are left for the caller to copy from
    /// the queued one.
    pub fn fresh(
        &self,
        fresh: FreshObservation,
        clock: ClockMap,
    ) -> Result<ValidObservation, RequestError> {
        fresh.validate(&self.limits)?;
        self.observation(fresh.observation, fresh.sent_at_us, &clock)
    }

    /// Checks an `EndTask`.
    pub fn end_task(&self, end: EndTask, clock: ClockMap) -> Result<ValidEndTask, RequestError> {
        end.validate(&self.limits)?;
        let exec = end
            .last_exec
            .map(|e| exec_report(&e, end.sent_at_us, &clock))
            .transpose()?;
        Ok(ValidEndTask {
            task: TaskId(end.task),
            end: match end.outcome {
                TaskOutcome::Done => TaskEnd::Done,
                TaskOutcome::Failed => TaskEnd::Failed,
            },
            exec,
            sent_at: clock.to_server(end.sent_at_us),
            clock,
        })
    }

    fn observation(
        &self,
        observation: Observation,
        sent_at_us: u64,
        clock: &ClockMap,
    ) -> Result<ValidObservation, RequestError> {
        let spec = &self.spec;
        if observation.captured_at_us > sent_at_us {
            return Err(invalid(
                "observation.captured_at_us",
                format!(
                    "captured at {} µs, after the message was sent at {sent_at_us} µs",
                    observation.captured_at_us
                ),
            ));
        }
        let state = observation
            .state
            .to_f32()
            .map_err(|e| observation_error("observation.state", e.to_string()))?;
        let mut images = Vec::with_capacity(observation.images.len());
        let mut cameras = Vec::with_capacity(observation.images.len());
        for (i, image) in observation.images.into_iter().enumerate() {
            images.push(image_input(i, image.payload)?);
            cameras.push(image.camera);
        }
        let request = ActionRequest {
            cameras,
            state,
            images,
            instruction: observation.instruction,
            samples: 1,
            seed: 0,
            guidance: None,
        };
        // Everything the engine would refuse, refused here with the field named, so that a bad
        // observation fails only its own round and never reaches a batch.
        spec.check_request(&request, &self.image_limits()).map_err(
            |InputError { field, reason }| {
                observation_error(format!("observation.{field}"), reason)
            },
        )?;
        Ok(ValidObservation {
            captured_at: clock.to_server(observation.captured_at_us),
            request,
        })
    }

    /// The image bounds of [`Limits`]: raw and encoded images alike, the latter checked from
    /// their headers.
    pub fn image_limits(&self) -> ImageLimits {
        ImageLimits {
            max_side: self.limits.max_tensor_dim as usize,
            max_pixels: self.limits.max_image_pixels as usize,
        }
    }
}

fn image_input(index: usize, payload: ImagePayload) -> Result<ImageInput, RequestError> {
    let field = format!("observation.images[{index}]");
    Ok(match payload {
        ImagePayload::Jpeg { data } => ImageInput::Encoded {
            format: ImageFormat::Jpeg,
            bytes: data,
        },
        ImagePayload::Png { data } => ImageInput::Encoded {
            format: ImageFormat::Png,
            bytes: data,
        },
        ImagePayload::Raw { tensor } => {
            // The protocol check guarantees rank 3 and a matching byte length.
            let [height, width, channels] = match tensor.shape.as_slice() {
                [h, w, c] => [*h as usize, *w as usize, *c as usize],
                other => {
                    return Err(observation_error(
                        format!("{field}.payload.tensor.shape"),
                        format!("expected [height, width, channels], got {other:?}"),
                    ));
                }
            };
            match tensor.dtype {
                DType::U8 => ImageInput::RawU8 {
                    height,
                    width,
                    channels,
                    data: tensor.data,
                },
                DType::F32 => ImageInput::RawF32 {
                    height,
                    width,
                    channels,
                    data: tensor.to_f32().map_err(|e| {
                        observation_error(format!("{field}.payload.tensor"), e.to_string())
                    })?,
                },
                other => {
                    return Err(observation_error(
                        format!("{field}.payload.tensor.dtype"),
                        format!("a raw image is u8 or f32, got {other:?}"),
                    ));
                }
            }
        }
    })
}

fn exec_report(
    info: &LastExecInfo,
    sent_at_us: u64,
    clock: &ClockMap,
) -> Result<ExecReport, RequestError> {
    if info.exec_started_at_us > sent_at_us {
        return Err(invalid(
            "last_exec.exec_started_at_us",
            format!(
                "execution started at {} µs, after the message was sent at {sent_at_us} µs",
                info.exec_started_at_us
            ),
        ));
    }
    Ok(ExecReport {
        started_at: clock.to_server(info.exec_started_at_us),
        actions_remaining: info.actions_remaining,
        control_hz: info.control_hz,
    })
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use std::time::Duration;

    use kairos_core::registry::native_horizon_policies;
    use kairos_core::time::Timestamp;
    use kairos_sdk::protocol::{ErrorCode, ErrorReply, HorizonSelection, Image, MAX_ROUND, Tensor};

    use super::*;

    fn validator() -> Validator {
        Validator {
            spec: ModelSpec {
                cameras: Vec::new(),
                camera_aliases: Default::default(),
                name: "m".into(),
                chunk_len: 8,
                action_dim: 2,
                state_dim: 3,
                steps: 4,
                max_images: 1,
            },
            limits: Limits::default(),
            chunking: ChunkingRules::default(),
        }
    }

    fn actions() -> ActionManager {
        let natives = native_horizon_policies();
        ActionManager::new(natives.clone(), &natives, "threshold", BTreeMap::new()).unwrap()
    }

    fn submit() -> Submit {
        Submit {
            task: 5,
            round: 2,
            sent_at_us: 1_000_000,
            observation: Observation {
                captured_at_us: 990_000,
                state: Tensor::from_f32(vec![3], &[1.0, 2.0, 3.0]).unwrap(),
                images: Vec::new(),
                instruction: "pick".into(),
            },
            last_exec: Some(LastExecInfo {
                exec_started_at_us: 900_000,
                actions_remaining: 4,
                control_hz: 50.0,
                round: None,
                delay: None,
            }),
            horizon: None,
            remaining: None,
            attempt: 0,
            control_hz: None,
            seed: None,
            chunking: None,
        }
    }

    fn check(s: Submit) -> Result<ValidSubmit, RequestError> {
        validator().submit(
            s,
            RobotId(1),
            &actions(),
            ClockMap::new(
                Timestamp::from_micros(5_000_000),
                1_000_000,
                Duration::from_micros(200),
            ),
        )
    }

    #[test]
    fn a_good_submit_maps_onto_the_server_clock() {
        let v = check(submit()).unwrap();
        assert_eq!(v.round.task, TaskId(5));
        assert_eq!(v.round.robot, RobotId(1));
        assert_eq!(v.round.sent_at.as_micros(), 4_999_900);
        assert_eq!(v.round.obs_captured_at.as_micros(), 4_989_900);
        let exec = v.round.last_exec.unwrap();
        assert_eq!(exec.started_at.as_micros(), 4_899_900);
        assert_eq!(exec.actions_remaining, 4);
        assert_eq!(v.observation.request.state, vec![1.0, 2.0, 3.0]);
        assert_eq!(v.observation.request.seed, round_seed(5, 2));
        assert_ne!(round_seed(5, 2), round_seed(5, 3));
        // A client's own sampler seed wins over the derived one.
        let seeded = check(Submit {
            seed: Some(77),
            ..submit()
        })
        .unwrap();
        assert_eq!(seeded.observation.request.seed, 77);
        assert_eq!(v.samples, 1);
        assert_eq!(v.policy.policy.name(), "threshold");
        assert_eq!(v.control_hz, Some(50.0));
    }

    #[test]
    fn a_first_round_carries_its_control_rate_to_the_scheduler() {
        let mut s = submit();
        s.last_exec = None;
        s.control_hz = Some(0.4);
        let v = check(s).unwrap();
        assert_eq!(v.round.control_hz, Some(0.4));
        assert_eq!(v.control_hz, Some(0.4));
        // The execution report's rate wins when both are present.
        let mut s = submit();
        s.control_hz = Some(7.0);
        assert_eq!(check(s).unwrap().control_hz, Some(50.0));
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let mut s = submit();
            s.control_hz = Some(bad);
            assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz {bad}");
        }
    }

    fn code(s: Submit) -> ErrorCode {
        let err = check(s).unwrap_err();
        ErrorReply::from(&err).code
    }

    #[test]
    fn each_bad_field_gets_its_code() {
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![2], &[1.0, 2.0]).unwrap();
        assert_eq!(code(s), ErrorCode::InvalidObservation, "state too short");

        let mut s = submit();
        s.observation.state = Tensor::from_u8(vec![3], vec![1, 2, 3]).unwrap();
        assert_eq!(code(s), ErrorCode::InvalidObservation, "state dtype");

        let raw = |shape: Vec<u32>| Image {
            camera: "front".into(),
            payload: ImagePayload::Raw {
                tensor: Tensor::from_u8(
                    shape.clone(),
                    vec![0; shape.iter().product::<u32>() as usize],
                )
                .unwrap(),
            },
        };
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 3])];
        assert!(check(s).is_ok());
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 5])];
        assert_eq!(code(s), ErrorCode::InvalidObservation, "channels");
        let mut s = submit();
        s.observation.images = vec![raw(vec![2, 2, 3]), {
            let mut i = raw(vec![2, 2, 3]);
            i.camera = "wrist".into();
            i
        }];
        assert_eq!(code(s), ErrorCode::InvalidObservation, "too many images");

        let mut s = submit();
        s.observation.images = vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Jpeg {
                data: vec![0; Limits::default().max_image_bytes as usize + 1],
            },
        }];
        assert_eq!(code(s), ErrorCode::TooLarge, "oversize image");

        let mut s = submit();
        s.last_exec.as_mut().unwrap().control_hz = 0.0;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz");
        let mut s = submit();
        s.last_exec.as_mut().unwrap().control_hz = f32::NAN;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "control_hz NaN");
        let mut s = submit();
        s.last_exec.as_mut().unwrap().exec_started_at_us = 2_000_000;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "exec in the future");
        let mut s = submit();
        s.observation.captured_at_us = 2_000_000;
        assert_eq!(code(s), ErrorCode::InvalidRequest, "captured after sent");

        let selection = |policy: &str, params: &[(&str, f64)], samples: u32| HorizonSelection {
            policy: policy.into(),
            params: params.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            samples,
        };
        let mut s = submit();
        s.horizon = Some(selection("nope", &[], 1));
        assert_eq!(code(s), ErrorCode::UnknownPolicy);
        let mut s = submit();
        s.horizon = Some(selection("threshold", &[("t", -2.0)], 1));
        assert_eq!(code(s), ErrorCode::InvalidRequest, "bad param");
        let mut s = submit();
        s.horizon = Some(selection("threshold", &[], 1000));
        assert_eq!(code(s), ErrorCode::TooLarge, "samples over the limit");
        let mut s = submit();
        s.horizon = Some(selection("static", &[("h", 4.0)], 2));
        let v = check(s).unwrap();
        assert_eq!((v.samples, v.observation.request.samples), (2, 2));
        assert_eq!(v.policy.policy.name(), "static");
    }

    /// A 2x2 RGB PNG.
    const PNG_2X2: [u8; 73] = [
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44,
        0x52, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x02, 0x08, 0x02, 0x00, 0x00, 0x00, 0xfd,
        0xd4, 0x9a, 0x73, 0x00, 0x00, 0x00, 0x10, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x10,
        0x50, 0x30, 0x00, 0x22, 0x06, 0x08, 0x05, 0x00, 0x0a, 0x0e, 0x01, 0x81, 0x56, 0x33, 0xee,
        0xf3, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
    ];

    /// The head of a decompression bomb: a PNG header declaring 8192x8192 RGB (192 MiB of
    /// pixels) and the first 26 bytes of its data.
    const PNG_BOMB_HEAD: [u8; 83] = [
        0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44,
        0x52, 0x00, 0x00, 0x20, 0x00, 0x00, 0x00, 0x20, 0x00, 0x08, 0x02, 0x00, 0x00, 0x00, 0xfd,
        0xc8, 0x5d, 0x0e, 0x00, 0x00, 0x00, 0x1a, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0xed, 0xc1,
        0x01, 0x0d, 0x00, 0x00, 0x00, 0xc2, 0xa0, 0xf7, 0x4f, 0x6d, 0x0f, 0x07, 0x14, 0x00, 0x00,
        0x00, 0xf0, 0x6e, 0x10, 0x00, 0x00, 0x01, 0x4b, 0x9e, 0xa3, 0x3c, 0x00, 0x00, 0x00, 0x00,
        0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82,
    ];

    fn with_image(payload: ImagePayload) -> Submit {
        let mut s = submit();
        s.observation.images = vec![Image {
            camera: "front".into(),
            payload,
        }];
        s
    }

    /// The refusal's wire form: it must be `invalid_observation`, not retryable, and name
    /// `field`.
    fn refused(s: Submit, field: &str) -> String {
        let reply = ErrorReply::from(&check(s).unwrap_err());
        assert_eq!(
            reply.code,
            ErrorCode::InvalidObservation,
            "{}",
            reply.message
        );
        assert!(!reply.retryable);
        assert!(
            reply.message.contains(field),
            "{} names {field}",
            reply.message
        );
        reply.message
    }

    #[test]
    fn everything_the_engine_would_refuse_is_refused_before_the_queue() {
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![3], &[1.0, f32::NAN, 3.0]).unwrap();
        refused(s, "observation.state[1]");
        let mut s = submit();
        s.observation.state = Tensor::from_f32(vec![3], &[f32::INFINITY, 0.0, 3.0]).unwrap();
        refused(s, "observation.state[0]");

        // Bytes that claim to be an image but are not one.
        refused(
            with_image(ImagePayload::Png {
                data: b"GIF89a, not a PNG".to_vec(),
            }),
            "observation.images[0]",
        );
        refused(
            with_image(ImagePayload::Jpeg {
                data: PNG_2X2.to_vec(),
            }),
            "observation.images[0]",
        );
        assert!(
            check(with_image(ImagePayload::Png {
                data: PNG_2X2.to_vec()
            }))
            .is_ok()
        );

        let raw_f32 = |shape: Vec<u32>, values: &[f32]| ImagePayload::Raw {
            tensor: Tensor::from_f32(shape, values).unwrap(),
        };
        refused(
            with_image(raw_f32(vec![1, 2, 1], &[0.5, f32::NAN])),
            "observation.images[0]",
        );
        assert!(check(with_image(raw_f32(vec![1, 2, 1], &[0.5, 1.0]))).is_ok());
        // No pixels: a 0-wide image.
        let message = refused(
            with_image(raw_f32(vec![4, 0, 3], &[])),
            "observation.images[0]",
        );
        assert!(message.contains("4x0"), "{message}");
    }

    #[test]
    fn a_decompression_bomb_is_refused_from_its_header() {
        let message = refused(
            with_image(ImagePayload::Png {
                data: PNG_BOMB_HEAD.to_vec(),
            }),
            "observation.images[0]",
        );
        assert!(message.contains("8192x8192"), "{message}");
        assert!(message.contains("over the limit"), "{message}");
        // The cap is the configured one: the 2x2 image passes at 4 pixels, not at 3.
        let mut v = validator();
        v.limits.max_image_pixels = 3;
        let small = with_image(ImagePayload::Png {
            data: PNG_2X2.to_vec(),
        });
        let clock = ClockMap::new(Timestamp::from_micros(5_000_000), 1_000_000, Duration::ZERO);
        let error = v.submit(small, RobotId(1), &actions(), clock).unwrap_err();
        assert_eq!(error.code(), ErrorCode::InvalidObservation);
        assert!(error.to_string().contains("4 pixels"), "{error}");
    }

    #[tokio::test]
    async fn decoding_turns_files_into_pixels_before_the_queue() {
        let pool = DecodePool::new(1, validator().image_limits());
        let valid = check(with_image(ImagePayload::Png {
            data: PNG_2X2.to_vec(),
        }))
        .unwrap();
        let decoded = pool.decode_submit(valid).await.unwrap();
        assert_eq!(
            decoded.observation.request.images,
            vec![ImageInput::RawU8 {
                height: 2,
                width: 2,
                channels: 3,
                data: [0x10, 0x20, 0x30].repeat(4),
            }]
        );
        // A file whose header is fine but whose pixel data is cut off fails its own round here.
        let mut truncated = PNG_2X2.to_vec();
        truncated.truncate(50);
        let valid = check(with_image(ImagePayload::Png { data: truncated })).unwrap();
        let error = pool.decode_submit(valid).await.unwrap_err();
        assert_eq!(error.code(), ErrorCode::InvalidObservation);
        assert!(
            error.to_string().contains("observation.images[0]"),
            "{error}"
        );
    }

    #[test]
    fn round_ids_are_bounded() {
        let mut s = submit();
        s.round = MAX_ROUND;
        assert!(check(s).is_ok());
        for round in [MAX_ROUND + 1, u64::MAX] {
            let mut s = submit();
            s.round = round;
            let reply = ErrorReply::from(&check(s).unwrap_err());
            assert_eq!(reply.code, ErrorCode::InvalidRequest);
            assert!(reply.message.contains("round"), "{}", reply.message);
        }
    }

    #[test]
    fn hello_requires_a_supported_version() {
        let v = validator();
        let hello = |protocol| Hello {
            protocol,
            token: "t".into(),
            client: "c".into(),
        };
        assert_eq!(v.hello(&hello(1)).unwrap(), 1);
        assert_eq!(
            v.hello(&hello(7)).unwrap(),
            1,
            "newer clients speak v1 to us"
        );
        assert!(matches!(
            v.hello(&hello(0)),
            Err(RequestError::UnsupportedVersion(0))
        ));
    }
}
