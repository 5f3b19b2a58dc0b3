//! Malformed input over a real QUIC stream: each class gets its typed error on its own stream,
//! and the server keeps serving — the same connection and another robot alike.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use kairos_sdk::protocol::{
    EndTask, ErrorCode, Image, ImagePayload, Message, MessageKind, Observation, Submit,
    TaskOutcome, Tensor, Welcome, frame::encode_header,
};
use kairos_tests::harness::{RawConnection, ServerOptions, TestServer, one_round};

const MAX_IMAGE_BYTES: u32 = 64 * 1024;

fn submit(task: u64, round: u64, state: Tensor, images: Vec<Image>) -> Submit {
    Submit {
        task,
        round,
        sent_at_us: 1_000,
        observation: Observation {
            captured_at_us: 1_000,
            state,
            images,
            instruction: String::new(),
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

fn good_state() -> Tensor {
    Tensor::from_f32(vec![6], &[0.0; 6]).unwrap()
}

fn frame(message: Message) -> Vec<u8> {
    message.encode(u32::MAX).unwrap()
}

fn raw_image(shape: Vec<u32>) -> Image {
    let len = shape.iter().product::<u32>() as usize;
    Image {
        camera: "front".into(),
        payload: ImagePayload::Raw {
            tensor: Tensor::from_u8(shape, vec![0; len]).unwrap(),
        },
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_malformed_input_class_gets_its_error_and_the_server_keeps_serving() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| config.limits.max_image_bytes = MAX_IMAGE_BYTES,
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let (raw, welcome) = RawConnection::hello(&server, &server.token).await.unwrap();
    let limits = match welcome {
        Message::Welcome(welcome) => welcome.limits,
        other => panic!("expected Welcome, got {}", other.kind()),
    };
    let bystander = server.connect(&server.token).await.unwrap();
    let mut bystander_round = 0;

    // A valid round first, so "round id going backwards" has something to go back from.
    match raw
        .exchange(
            &frame(Message::Submit(submit(5, 5, good_state(), Vec::new()))),
            false,
        )
        .await
        .unwrap()
    {
        Message::Reply(reply) => assert_eq!((reply.task, reply.round), (5, 5)),
        other => panic!("expected a Reply, got {}", other.kind()),
    }

    let truncated = {
        let body = frame(Message::Submit(submit(6, 0, good_state(), Vec::new())));
        body[..body.len() / 2].to_vec()
    };
    let oversize_frame = encode_header(MessageKind::Submit, limits.max_frame + 1).to_vec();
    let oversize_image = frame(Message::Submit(submit(
        6,
        0,
        good_state(),
        vec![Image {
            camera: "front".into(),
            payload: ImagePayload::Jpeg {
                data: vec![0xff; MAX_IMAGE_BYTES as usize + 1],
            },
        }],
    )));
    let wrong_dtype = frame(Message::Submit(submit(
        6,
        0,
        Tensor::from_u8(vec![6], vec![0; 6]).unwrap(),
        Vec::new(),
    )));
    let wrong_state_len = frame(Message::Submit(submit(
        6,
        0,
        Tensor::from_f32(vec![5], &[0.0; 5]).unwrap(),
        Vec::new(),
    )));
    let wrong_image_shape = frame(Message::Submit(submit(
        6,
        0,
        good_state(),
        vec![raw_image(vec![4, 4, 2])],
    )));
    let too_many_images = frame(Message::Submit(submit(
        6,
        0,
        good_state(),
        vec![
            raw_image(vec![2, 2, 3]),
            Image {
                camera: "wrist".into(),
                ..raw_image(vec![2, 2, 3])
            },
            Image {
                camera: "top".into(),
                ..raw_image(vec![2, 2, 3])
            },
        ],
    )));
    let backwards = frame(Message::Submit(submit(5, 3, good_state(), Vec::new())));
    let unknown_task = frame(Message::EndTask(EndTask {
        task: 4242,
        outcome: TaskOutcome::Done,
        sent_at_us: 1_000,
        last_exec: None,
    }));
    let unknown_kind = {
        let mut bytes = frame(Message::Submit(submit(6, 0, good_state(), Vec::new())));
        bytes[0] = 0x55;
        bytes
    };
    let not_msgpack = {
        let mut bytes = encode_header(MessageKind::Submit, 4).to_vec();
        bytes.extend_from_slice(&[0xc1, 0xc1, 0xc1, 0xc1]);
        bytes
    };
    let wrong_direction = frame(Message::Welcome(Welcome {
        protocol: 1,
        server: "me".into(),
        robot: "me".into(),
        model: kairos_sdk::protocol::ModelInfo {
            name: "m".into(),
            chunk_len: 1,
            action_dim: 1,
            state_dim: 1,
            steps: 1,
            max_images: 0,
            cameras: Vec::new(),
        },
        limits: limits.clone(),
    }));

    let cases: Vec<(&str, Vec<u8>, bool, ErrorCode)> = vec![
        ("truncated frame", truncated, true, ErrorCode::BadFrame),
        ("oversize frame", oversize_frame, false, ErrorCode::TooLarge),
        ("oversize image", oversize_image, false, ErrorCode::TooLarge),
        (
            "wrong state dtype",
            wrong_dtype,
            false,
            ErrorCode::InvalidObservation,
        ),
        (
            "wrong state length",
            wrong_state_len,
            false,
            ErrorCode::InvalidObservation,
        ),
        (
            "wrong image shape",
            wrong_image_shape,
            false,
            ErrorCode::InvalidObservation,
        ),
        (
            "too many images",
            too_many_images,
            false,
            ErrorCode::TooLarge,
        ),
        (
            "round id going backwards",
            backwards,
            false,
            ErrorCode::RoundOutOfOrder,
        ),
        (
            "EndTask for an unknown task",
            unknown_task,
            false,
            ErrorCode::UnknownTask,
        ),
        (
            "unknown frame kind",
            unknown_kind,
            true,
            ErrorCode::BadFrame,
        ),
        (
            "body is not MessagePack",
            not_msgpack,
            true,
            ErrorCode::BadFrame,
        ),
        (
            "server message sent by a client",
            wrong_direction,
            true,
            ErrorCode::BadFrame,
        ),
    ];
    for (name, bytes, finish, expected) in cases {
        match raw.exchange(&bytes, finish).await {
            Ok(Message::Error(error)) => {
                assert_eq!(error.code, expected, "{name}: {}", error.message);
                assert!(!error.message.is_empty(), "{name}: the error says why");
                assert!(
                    !error.retryable,
                    "{name}: a malformed request is not retryable"
                );
            }
            Ok(other) => panic!("{name}: expected an Error, got {}", other.kind()),
            Err(error) => panic!("{name}: no answer: {error}"),
        }
        // Another robot is still served...
        let reply = one_round(&bystander, 900, bystander_round).await;
        assert!(
            reply.is_ok(),
            "{name}: the bystander was not served: {reply:?}"
        );
        bystander_round += 1;
    }
    // ...and so is the connection that sent all of the above.
    match raw
        .exchange(
            &frame(Message::Submit(submit(5, 6, good_state(), Vec::new()))),
            false,
        )
        .await
        .unwrap()
    {
        Message::Reply(reply) => assert_eq!(reply.round, 6),
        other => panic!("expected a Reply, got {}", other.kind()),
    }

    raw.close().await;
    bystander.close().await;
    let report = server.shutdown().await;
    assert_eq!(report.driver.replies, 2 + bystander_round);
}
