//! Codec properties: every message round-trips, no byte string panics the decoder, every
//! truncation of a valid frame is `Truncated`, and bodies written the way a Python client writes
//! them decode.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::collections::BTreeMap;
use std::io::Cursor;

use kairos_sdk::protocol::frame::encode_header;
use kairos_sdk::protocol::*;
use proptest::collection::{btree_map, vec};
use proptest::prelude::*;

const MAX: u32 = 1 << 20;

fn name() -> impl Strategy<Value = String> {
    "[a-z_]{0,12}"
}

fn dtype() -> impl Strategy<Value = DType> {
    prop_oneof![
        Just(DType::F32),
        Just(DType::F16),
        Just(DType::Bf16),
        Just(DType::U8)
    ]
}

fn tensor() -> impl Strategy<Value = Tensor> {
    (dtype(), vec(0u32..5, 0..4)).prop_flat_map(|(dtype, shape)| {
        let len = shape.iter().product::<u32>() as usize * dtype.size();
        vec(any::<u8>(), len).prop_map(move |data| Tensor {
            dtype,
            shape: shape.clone(),
            data,
        })
    })
}

fn image() -> impl Strategy<Value = Image> {
    let payload = prop_oneof![
        vec(any::<u8>(), 0..64).prop_map(|data| ImagePayload::Jpeg { data }),
        vec(any::<u8>(), 0..64).prop_map(|data| ImagePayload::Png { data }),
        tensor().prop_map(|tensor| ImagePayload::Raw { tensor }),
    ];
    (name(), payload).prop_map(|(camera, payload)| Image { camera, payload })
}

fn observation() -> impl Strategy<Value = Observation> {
    (any::<u64>(), tensor(), vec(image(), 0..3), ".{0,20}").prop_map(
        |(captured_at_us, state, images, instruction)| Observation {
            captured_at_us,
            state,
            images,
            instruction,
        },
    )
}

fn finite_f32() -> impl Strategy<Value = f32> {
    -1e6f32..1e6
}

fn last_exec() -> impl Strategy<Value = LastExecInfo> {
    (
        any::<u64>(),
        any::<u32>(),
        finite_f32(),
        proptest::option::of(any::<u64>()),
        proptest::option::of(any::<u32>()),
    )
        .prop_map(
            |(exec_started_at_us, actions_remaining, control_hz, round, delay)| LastExecInfo {
                exec_started_at_us,
                actions_remaining,
                control_hz,
                round,
                delay,
            },
        )
}

fn horizon() -> impl Strategy<Value = HorizonSelection> {
    (name(), btree_map(name(), -1e9f64..1e9, 0..4), any::<u32>()).prop_map(
        |(policy, params, samples)| HorizonSelection {
            policy,
            params,
            samples,
        },
    )
}

fn remaining() -> impl Strategy<Value = RemainingHint> {
    (
        proptest::option::of(any::<u32>()),
        proptest::option::of(finite_f32()),
    )
        .prop_map(|(rounds, seconds)| RemainingHint { rounds, seconds })
}

fn limits() -> impl Strategy<Value = Limits> {
    (vec(any::<u32>(), 14)).prop_map(|v| Limits {
        max_frame: v[0],
        max_image_bytes: v[1],
        max_images: v[2],
        max_instruction_bytes: v[3],
        max_state_len: v[4],
        max_params: v[5],
        max_samples: v[6],
        max_tensor_rank: v[7],
        max_tensor_dim: v[8],
        max_name_bytes: v[9],
        max_token_bytes: v[10],
        max_message_bytes: v[11],
        max_history: v[12],
        max_image_pixels: v[13],
    })
}

fn interval() -> impl Strategy<Value = IntervalUs> {
    (any::<u64>(), any::<u64>()).prop_map(|(start_us, end_us)| IntervalUs { start_us, end_us })
}

fn error_code() -> impl Strategy<Value = ErrorCode> {
    prop_oneof![
        Just(ErrorCode::BadFrame),
        Just(ErrorCode::TooLarge),
        Just(ErrorCode::InvalidObservation),
        Just(ErrorCode::InvalidRequest),
        Just(ErrorCode::UnsupportedVersion),
        Just(ErrorCode::Unauthorized),
        Just(ErrorCode::Forbidden),
        Just(ErrorCode::UnknownTask),
        Just(ErrorCode::RoundOutOfOrder),
        Just(ErrorCode::UnknownPolicy),
        Just(ErrorCode::Overloaded),
        Just(ErrorCode::Internal),
        Just(ErrorCode::ShuttingDown),
    ]
}

fn message() -> impl Strategy<Value = Message> {
    let hello = (any::<u32>(), name(), name()).prop_map(|(protocol, token, client)| {
        Message::Hello(Hello {
            protocol,
            token,
            client,
        })
    });
    let model = (name(), vec(any::<u32>(), 5)).prop_map(|(name, v)| ModelInfo {
        name,
        chunk_len: v[0],
        action_dim: v[1],
        state_dim: v[2],
        steps: v[3],
        max_images: v[4],
        cameras: Vec::new(),
    });
    let welcome = (any::<u32>(), name(), name(), model, limits()).prop_map(
        |(protocol, server, robot, model, limits)| {
            Message::Welcome(Welcome {
                protocol,
                server,
                robot,
                model,
                limits,
            })
        },
    );
    let submit = (
        vec(any::<u64>(), 3),
        observation(),
        proptest::option::of(last_exec()),
        proptest::option::of(horizon()),
        proptest::option::of(remaining()),
        any::<u32>(),
    )
        .prop_map(
            |(ids, observation, last_exec, horizon, remaining, attempt)| {
                Message::Submit(Submit {
                    task: ids[0],
                    round: ids[1],
                    sent_at_us: ids[2],
                    observation,
                    last_exec,
                    horizon,
                    remaining,
                    attempt,
                    control_hz: None,
                    // The optional sampler seed round-trips when present and stays absent when
                    // not.
                    seed: (ids[0] % 3 == 0).then_some(ids[1] ^ ids[2]),
                    chunking: (ids[1] % 4 == 0).then(|| ChunkingSelection {
                        schedule: Some(PrefixSchedule::Exp),
                        max_guidance_weight: Some(5.0),
                        execution_horizon: Some(8),
                        ..ChunkingSelection::new(ChunkingStrategy::ALL[(ids[2] % 7) as usize])
                    }),
                })
            },
        );
    let fetch = vec(any::<u64>(), 3).prop_map(|v| {
        Message::FetchObservation(FetchObservation {
            task: v[0],
            round: v[1],
            age_us: v[2],
        })
    });
    let fresh = (any::<u64>(), observation()).prop_map(|(sent_at_us, observation)| {
        Message::FreshObservation(FreshObservation {
            sent_at_us,
            observation,
        })
    });
    let timing = (vec(any::<u64>(), 4), any::<u32>()).prop_map(|(v, batch_size)| Timing {
        queue_us: v[0],
        refetch_us: v[1],
        inference_us: v[2],
        total_us: v[3],
        batch_size,
    });
    let reply = (
        vec(any::<u64>(), 2),
        vec(any::<u32>(), 2),
        tensor(),
        name(),
        timing,
    )
        .prop_map(|(ids, sizes, actions, policy, timing)| {
            Message::Reply(Reply {
                task: ids[0],
                round: ids[1],
                horizon: sizes[0],
                chunk_len: sizes[1],
                actions,
                policy,
                timing,
                // The chunking fields round-trip when present and stay absent when not.
                start: (ids[0] % 2 == 0).then_some(sizes[0] / 2),
                delay: (ids[0] % 2 == 0).then_some(sizes[1]),
                chunking: (ids[1] % 2 == 0).then(|| "rtc".to_owned()),
            })
        });
    let outcome = prop_oneof![Just(TaskOutcome::Done), Just(TaskOutcome::Failed)];
    let end = (
        any::<u64>(),
        outcome,
        any::<u64>(),
        proptest::option::of(last_exec()),
    )
        .prop_map(|(task, outcome, sent_at_us, last_exec)| {
            Message::EndTask(EndTask {
                task,
                outcome,
                sent_at_us,
                last_exec,
            })
        });
    let record = (
        any::<u64>(),
        proptest::option::of(interval()),
        proptest::option::of(interval()),
        proptest::option::of(any::<u32>()),
    )
        .prop_map(|(round, generation, execution, horizon)| RoundRecordWire {
            round,
            generation,
            execution,
            horizon,
        });
    let ended =
        (vec(any::<u64>(), 3), any::<u32>(), vec(record, 0..4)).prop_map(|(v, rounds, history)| {
            Message::TaskEnded(TaskEnded {
                task: v[0],
                rounds,
                wait_us: v[1],
                attained_service_us: v[2],
                history,
            })
        });
    let error = (
        error_code(),
        ".{0,30}",
        any::<bool>(),
        proptest::option::of(any::<u32>()),
    )
        .prop_map(|(code, message, retryable, retry_after_ms)| {
            Message::Error(ErrorReply {
                code,
                message,
                retryable,
                retry_after_ms,
            })
        });
    prop_oneof![
        hello, welcome, submit, fetch, fresh, reply, end, ended, error
    ]
}

proptest! {
    #[test]
    fn every_message_round_trips(message in message()) {
        let bytes = message.encode(MAX).unwrap();
        prop_assert_eq!(bytes[0], message.kind() as u8);
        let (decoded, used) = Message::decode_from(&bytes, MAX).unwrap();
        prop_assert_eq!(used, bytes.len());
        prop_assert_eq!(decoded, message);
    }

    #[test]
    fn every_truncation_of_a_valid_frame_is_truncated(message in message(), cut in any::<prop::sample::Index>()) {
        let bytes = message.encode(MAX).unwrap();
        let cut = cut.index(bytes.len());
        let result = Message::decode_from(&bytes[..cut], MAX);
        prop_assert!(matches!(result, Err(FrameError::Truncated { .. })), "cut at {}: {:?}", cut, result);
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in vec(any::<u8>(), 0..512)) {
        let _ = Message::decode_from(&bytes, MAX);
        let _ = Message::decode_from(&bytes, 16);
    }

    #[test]
    fn arbitrary_bodies_behind_a_valid_header_never_panic(kind in 0usize..9, body in vec(any::<u8>(), 0..512)) {
        let kind = MessageKind::ALL[kind];
        let mut bytes = encode_header(kind, body.len() as u32).to_vec();
        bytes.extend_from_slice(&body);
        if let Ok((message, _)) = Message::decode_from(&bytes, MAX) {
            let _ = message.validate(&Limits::default());
        }
    }

    #[test]
    fn corrupted_valid_frames_never_panic(message in message(), flips in vec((any::<prop::sample::Index>(), any::<u8>()), 1..8)) {
        let mut bytes = message.encode(MAX).unwrap();
        for (at, value) in flips {
            let at = at.index(bytes.len());
            bytes[at] = value;
        }
        if let Ok((message, _)) = Message::decode_from(&bytes, MAX) {
            let _ = message.validate(&Limits::default());
        }
    }

    #[test]
    fn validation_never_panics(message in message(), limits in limits()) {
        let _ = message.validate(&limits);
    }
}

fn small_submit() -> Submit {
    Submit {
        task: 7,
        round: 0,
        sent_at_us: 1_000,
        observation: Observation {
            captured_at_us: 990,
            state: Tensor::from_f32(vec![2], &[0.5, -1.0]).unwrap(),
            images: vec![],
            instruction: "go".to_owned(),
        },
        last_exec: None,
        horizon: None,
        remaining: None,
        attempt: 0,
        control_hz: None,
        seed: None,
        chunking: None,
    }
}

/// The worked example in docs/PROTOCOL.md is exactly what this crate sends.
#[test]
fn worked_example_bytes() {
    let bytes = Message::Submit(small_submit()).encode(MAX).unwrap();
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(
        hex,
        concat!(
            "10",
            "0000007a",
            "84",
            "a4",
            "7461736b",
            "07",
            "a5",
            "726f756e64",
            "00",
            "aa",
            "73656e745f61745f7573",
            "cd03e8",
            "ab",
            "6f62736572766174696f6e",
            "84",
            "ae",
            "63617074757265645f61745f7573",
            "cd03de",
            "a5",
            "7374617465",
            "83",
            "a5",
            "6474797065",
            "a3",
            "663332",
            "a5",
            "7368617065",
            "91",
            "02",
            "a4",
            "64617461",
            "c408",
            "0000003f",
            "000080bf",
            "a6",
            "696d61676573",
            "90",
            "ab",
            "696e737472756374696f6e",
            "a2",
            "676f",
        )
    );
}

/// A body built the way Python's `msgpack.packb` builds it: floats as float64, integers where
/// floats are expected, `bin` for bytes, unknown keys, `nil` for absent options.
#[test]
fn python_style_body_decodes() {
    use rmpv::Value;
    let s = |text: &str| Value::from(text);
    let state = Value::Map(vec![
        (s("dtype"), s("f32")),
        (s("shape"), Value::Array(vec![Value::from(1)])),
        (s("data"), Value::Binary(1.0f32.to_le_bytes().to_vec())),
    ]);
    let body = Value::Map(vec![
        (s("task"), Value::from(1)),
        (s("round"), Value::from(2)),
        (s("sent_at_us"), Value::from(3)),
        (
            s("observation"),
            Value::Map(vec![
                (s("captured_at_us"), Value::from(3)),
                (s("state"), state),
                (
                    s("images"),
                    Value::Array(vec![Value::Map(vec![
                        (s("camera"), s("front")),
                        (
                            s("payload"),
                            Value::Map(vec![
                                (s("encoding"), s("jpeg")),
                                (s("data"), Value::Binary(vec![0xff, 0xd8])),
                            ]),
                        ),
                    ])]),
                ),
                (s("instruction"), s("pick")),
            ]),
        ),
        (
            s("last_exec"),
            Value::Map(vec![
                (s("exec_started_at_us"), Value::from(0)),
                (s("actions_remaining"), Value::from(5)),
                (s("control_hz"), Value::F64(30.0)),
            ]),
        ),
        (
            s("horizon"),
            Value::Map(vec![
                (s("policy"), s("threshold")),
                (
                    s("params"),
                    Value::Map(vec![
                        (s("t"), Value::F64(0.4)),
                        (s("h_min"), Value::from(8)),
                    ]),
                ),
            ]),
        ),
        (s("remaining"), Value::Nil),
        (s("future_field"), Value::Array(vec![Value::from(1)])),
    ]);
    let mut encoded = Vec::new();
    rmpv::encode::write_value(&mut encoded, &body).unwrap();
    let mut bytes = encode_header(MessageKind::Submit, encoded.len() as u32).to_vec();
    bytes.extend_from_slice(&encoded);
    let (message, _) = Message::decode_from(&bytes, MAX).unwrap();
    let Message::Submit(submit) = message else {
        panic!("not a submit: {message:?}")
    };
    assert_eq!(submit.round, 2);
    assert_eq!(submit.observation.state.to_f32().unwrap(), [1.0]);
    assert_eq!(submit.last_exec.unwrap().control_hz, 30.0);
    submit.validate(&Limits::default()).unwrap();
    let horizon = submit.horizon.unwrap();
    assert_eq!(horizon.samples, 1, "samples defaults to 1");
    assert_eq!(
        horizon.params,
        BTreeMap::from([("h_min".to_owned(), 8.0), ("t".to_owned(), 0.4)])
    );
    assert_eq!(submit.remaining, None);
    assert_eq!(submit.attempt, 0);
}

#[test]
fn envelope_is_strict() {
    let mut bytes = Message::Submit(small_submit()).encode(MAX).unwrap();
    // A trailing byte inside the announced body.
    bytes.push(0xc0);
    let len = (bytes.len() - HEADER_LEN) as u32;
    bytes[1..5].copy_from_slice(&len.to_be_bytes());
    assert!(matches!(
        Message::decode_from(&bytes, MAX),
        Err(FrameError::Malformed { kind: MessageKind::Submit, reason }) if reason.contains("after")
    ));
    // An array where a map is required.
    let mut array = encode_header(MessageKind::FetchObservation, 4).to_vec();
    array.extend_from_slice(&[0x93, 1, 2, 3]);
    assert!(matches!(
        Message::decode_from(&array, MAX),
        Err(FrameError::Malformed { .. })
    ));
    // Deep nesting under an unknown key is refused without recursing 100k levels.
    let mut deep = vec![0x81, 0xa1, b'x'];
    deep.extend(std::iter::repeat_n(0x91, 100_000));
    deep.push(0xc0);
    let mut frame = encode_header(MessageKind::FetchObservation, deep.len() as u32).to_vec();
    frame.extend_from_slice(&deep);
    assert!(matches!(
        Message::decode_from(&frame, MAX),
        Err(FrameError::Malformed { .. })
    ));
    // A container announcing 4 billion elements in a 6-byte body.
    let mut lie = encode_header(MessageKind::FetchObservation, 5).to_vec();
    lie.extend_from_slice(&[0xdf, 0xff, 0xff, 0xff, 0xff]);
    assert!(matches!(
        Message::decode_from(&lie, MAX),
        Err(FrameError::Malformed { .. })
    ));
}

#[test]
fn header_errors_are_typed() {
    let bytes = Message::Submit(small_submit()).encode(MAX).unwrap();
    assert_eq!(
        Message::decode_from(&bytes, 10).unwrap_err(),
        FrameError::FrameTooLarge {
            len: (bytes.len() - HEADER_LEN) as u32,
            max: 10
        }
    );
    let mut unknown = bytes.clone();
    unknown[0] = 0x42;
    assert_eq!(
        Message::decode_from(&unknown, MAX).unwrap_err(),
        FrameError::UnknownKind(0x42)
    );
    assert_eq!(
        FrameError::UnknownKind(0x42).code(),
        ErrorCode::BadFrame,
        "an unknown kind is a bad frame"
    );
    assert!(Message::Submit(small_submit()).encode(10).is_err());
    // `check` walks frames without decoding them.
    let mut two = bytes.clone();
    two.extend_from_slice(&bytes);
    let mut cursor = Cursor::new(&two[..]);
    Frame::check(&mut cursor, MAX).unwrap();
    Frame::check(&mut cursor, MAX).unwrap();
    assert_eq!(cursor.position() as usize, two.len());
}

#[test]
fn validation_enforces_every_limit() {
    let limits = Limits::default();
    let ok = small_submit();
    ok.validate(&limits).unwrap();

    let check = |edit: &dyn Fn(&mut Submit), code: ErrorCode, field: &str| {
        let mut submit = small_submit();
        edit(&mut submit);
        let error = submit.validate(&limits).unwrap_err();
        assert_eq!(error.code(), code, "{error}");
        let text = error.to_string();
        assert!(text.contains(field), "{text:?} should name {field:?}");
    };
    check(
        &|s| s.observation.instruction = "x".repeat(4097),
        ErrorCode::TooLarge,
        "observation.instruction",
    );
    check(
        &|s| s.observation.state = Tensor::from_f32(vec![1025], &[0.0; 1025]).unwrap(),
        ErrorCode::TooLarge,
        "observation.state.shape[0]",
    );
    check(
        &|s| s.observation.state.data.pop().map(drop).unwrap_or(()),
        ErrorCode::InvalidObservation,
        "observation.state.data",
    );
    check(
        &|s| s.observation.state = Tensor::from_u8(vec![2], vec![1, 2]).unwrap(),
        ErrorCode::InvalidObservation,
        "observation.state",
    );
    let jpeg = |camera: &str, len: usize| Image {
        camera: camera.to_owned(),
        payload: ImagePayload::Jpeg {
            data: vec![0xff; len],
        },
    };
    check(
        &|s| s.observation.images = (0..9).map(|i| jpeg(&format!("c{i}"), 1)).collect(),
        ErrorCode::TooLarge,
        "observation.images (count)",
    );
    check(
        &|s| s.observation.images = vec![jpeg("front", (4 << 20) + 1)],
        ErrorCode::TooLarge,
        "observation.images[0].payload.data",
    );
    check(
        &|s| s.observation.images = vec![jpeg("front", 1), jpeg("front", 1)],
        ErrorCode::InvalidObservation,
        "observation.images[1].camera",
    );
    check(
        &|s| s.observation.images = vec![jpeg(&"c".repeat(129), 1)],
        ErrorCode::TooLarge,
        "observation.images[0].camera",
    );
    check(
        &|s| {
            s.observation.images = vec![Image {
                camera: "wrist".to_owned(),
                payload: ImagePayload::Raw {
                    tensor: Tensor::from_u8(vec![2, 2], vec![0; 4]).unwrap(),
                },
            }]
        },
        ErrorCode::InvalidObservation,
        "observation.images[0].payload.tensor.shape",
    );
    check(
        &|s| {
            s.observation.images = vec![Image {
                camera: "wrist".to_owned(),
                payload: ImagePayload::Raw {
                    tensor: Tensor {
                        dtype: DType::U8,
                        shape: vec![1, 1, 1, 1, 1],
                        data: vec![0],
                    },
                },
            }]
        },
        ErrorCode::TooLarge,
        "shape (rank)",
    );
    check(
        &|s| {
            s.observation.images = vec![Image {
                camera: "wrist".to_owned(),
                payload: ImagePayload::Raw {
                    tensor: Tensor {
                        dtype: DType::U8,
                        shape: vec![8193, 1, 1],
                        data: vec![0; 8193],
                    },
                },
            }]
        },
        ErrorCode::TooLarge,
        "shape[0]",
    );
    let selection = |params: BTreeMap<String, f64>, samples: u32| HorizonSelection {
        policy: "threshold".to_owned(),
        params,
        samples,
    };
    check(
        &|s| {
            s.horizon = Some(selection(
                (0..33).map(|i| (format!("p{i}"), 1.0)).collect(),
                1,
            ))
        },
        ErrorCode::TooLarge,
        "horizon.params (count)",
    );
    check(
        &|s| s.horizon = Some(selection(BTreeMap::from([("t".to_owned(), f64::NAN)]), 1)),
        ErrorCode::InvalidRequest,
        "horizon.params",
    );
    check(
        &|s| s.horizon = Some(selection(BTreeMap::new(), 17)),
        ErrorCode::TooLarge,
        "horizon.samples",
    );
    check(
        &|s| s.horizon = Some(selection(BTreeMap::new(), 0)),
        ErrorCode::InvalidRequest,
        "horizon.samples",
    );
    check(
        &|s| {
            s.last_exec = Some(LastExecInfo {
                exec_started_at_us: 0,
                actions_remaining: 3,
                control_hz: 0.0,
                round: None,
                delay: None,
            })
        },
        ErrorCode::InvalidRequest,
        "last_exec.control_hz",
    );
    check(
        &|s| {
            s.remaining = Some(RemainingHint {
                rounds: None,
                seconds: Some(-1.0),
            })
        },
        ErrorCode::InvalidRequest,
        "remaining.seconds",
    );

    let hello = Hello {
        protocol: 1,
        token: "t".repeat(513),
        client: "c".to_owned(),
    };
    assert_eq!(
        hello.validate(&limits).unwrap_err().code(),
        ErrorCode::TooLarge
    );

    let reply = |horizon: u32, rows: u32| Reply {
        task: 1,
        round: 1,
        horizon,
        chunk_len: 4,
        actions: Tensor::from_f32(vec![rows, 2], &vec![0.0; rows as usize * 2]).unwrap(),
        policy: "static".to_owned(),
        timing: Timing::default(),
        start: None,
        delay: None,
        chunking: None,
    };
    reply(3, 3).validate(&limits).unwrap();
    assert!(reply(3, 2).validate(&limits).is_err());
    assert!(reply(5, 5).validate(&limits).is_err());
}

#[test]
fn error_replies_carry_codes_and_retryability() {
    let overloaded = ErrorReply::new(ErrorCode::Overloaded, "busy");
    assert!(overloaded.retryable);
    let too_large = ErrorReply::from(&FrameError::FrameTooLarge { len: 9, max: 1 });
    assert_eq!(too_large.code, ErrorCode::TooLarge);
    assert!(!too_large.retryable);
    let bytes = Message::Error(overloaded.clone()).encode(MAX).unwrap();
    let (decoded, _) = Message::decode_from(&bytes, MAX).unwrap();
    assert_eq!(decoded, Message::Error(overloaded));
    // The code's wire spelling is its Display.
    let body = rmp_serde::to_vec_named(&ErrorCode::RoundOutOfOrder).unwrap();
    let spelled: String = rmp_serde::from_slice(&body).unwrap();
    assert_eq!(spelled, ErrorCode::RoundOutOfOrder.to_string());
}
