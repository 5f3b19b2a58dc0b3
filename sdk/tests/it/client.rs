//! The client against a real QUIC/TLS protocol responder on 127.0.0.1.

#![allow(clippy::unwrap_used)] // helpers outside #[test] fns

use std::sync::Arc;
use std::time::Duration;

use crate::support::{Behavior, Hold, Kill, Responder, observation};
use kairos_sdk::client::{
    Client, ClientConfig, ClientError, NoRefetch, ROUND_CANCELLED, RoundRequest,
};
use kairos_sdk::protocol::{ErrorCode, FetchObservation, Observation, TaskOutcome};
use kairos_sdk::tls::Fingerprint;

fn config(responder: &Responder) -> ClientConfig {
    let mut config = ClientConfig::pinned(responder.addr, responder.fingerprint, "secret");
    config.connect_timeout = Duration::from_secs(5);
    config.reconnect.initial_backoff = Duration::from_millis(10);
    config
}

#[tokio::test]
async fn rounds_get_increasing_ids_and_replies() {
    let responder = Responder::start(Behavior::default());
    let client = Client::connect(config(&responder)).await.unwrap();
    let welcome = client.welcome().await.unwrap();
    assert_eq!(welcome.model.chunk_len, 8);
    let mut task = client.task(7);
    for round in 0..3u64 {
        let reply = task
            .submit(
                RoundRequest::new(observation(client.now_us())),
                &mut NoRefetch,
            )
            .await
            .unwrap();
        assert_eq!(reply.reply.round, round);
        assert_eq!(reply.reply.horizon, 4);
        assert_eq!(reply.attempts, 1);
        let actions = reply.reply.actions.to_f32().unwrap();
        assert_eq!(actions.len(), 8);
        assert_eq!(actions[0], round as f32);
        assert!(reply.received_at_us >= reply.sent_at_us);
    }
    let ended = task.end(TaskOutcome::Done, None).await.unwrap();
    assert_eq!(ended.rounds, 3);
    let seen = responder.seen();
    assert_eq!(seen.submits, [(7, 0, 0), (7, 1, 0), (7, 2, 0)]);
    assert_eq!(seen.ended, [(7, TaskOutcome::Done)]);
    assert_eq!(seen.connections, 1);
}

#[tokio::test]
async fn wrong_pin_is_refused_with_a_typed_error() {
    let responder = Responder::start(Behavior::default());
    let mut config = config(&responder);
    let wrong = Fingerprint([0xab; 32]);
    config.trust = kairos_sdk::tls::ServerTrust::Pinned(wrong);
    let error = Client::connect(config).await.unwrap_err();
    match error {
        ClientError::PinMismatch { expected, actual } => {
            assert_eq!(expected, wrong);
            assert_eq!(actual, responder.fingerprint);
        }
        other => panic!("expected a pin mismatch, got {other:?}"),
    }
    assert!(
        !ClientError::PinMismatch {
            expected: wrong,
            actual: wrong
        }
        .is_retryable()
    );
}

#[tokio::test]
async fn wrong_token_is_unauthorized() {
    let responder = Responder::start(Behavior::default());
    let mut config = config(&responder);
    config.token = "guess".to_owned();
    let error = Client::connect(config).await.unwrap_err();
    assert!(
        matches!(error, ClientError::Unauthorized(_)),
        "got {error:?}"
    );
    assert!(!error.is_retryable());
}

#[tokio::test]
async fn a_server_speaking_another_version_is_refused() {
    let responder = Responder::start(Behavior {
        welcome_protocol: 2,
        ..Behavior::default()
    });
    let error = Client::connect(config(&responder)).await.unwrap_err();
    assert!(
        matches!(&error, ClientError::VersionMismatch { client: 1, server } if server.contains('2')),
        "got {error:?}"
    );
    assert!(!error.is_retryable());
}

#[tokio::test]
async fn connect_to_nothing_times_out() {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let addr = socket.local_addr().unwrap();
    let mut config = ClientConfig::pinned(addr, Fingerprint([0; 32]), "secret");
    config.connect_timeout = Duration::from_millis(300);
    let error = Client::connect(config).await.unwrap_err();
    assert!(
        matches!(error, ClientError::Timeout { .. }),
        "got {error:?}"
    );
    assert!(error.is_retryable());
}

async fn resume_after_kill(kill: Kill) {
    let responder = Responder::start(Behavior {
        kill: Some((1, kill)),
        ..Behavior::default()
    });
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(3);
    let mut replies = Vec::new();
    for _ in 0..3 {
        let reply = task
            .submit(
                RoundRequest::new(observation(client.now_us())),
                &mut NoRefetch,
            )
            .await
            .unwrap();
        replies.push((reply.reply.round, reply.attempts));
    }
    // Round 1 needed a second attempt; each round was answered exactly once, in order.
    assert_eq!(replies, [(0, 1), (1, 2), (2, 1)]);
    let seen = responder.seen();
    assert!(seen.killed);
    assert_eq!(
        seen.submits,
        [(3, 0, 0), (3, 1, 0), (3, 1, 1), (3, 2, 0)],
        "the lost round is resent with the same id, then the next id follows"
    );
    assert_eq!(
        seen.generated,
        [(3, 0), (3, 1), (3, 2)],
        "no round generated twice"
    );
    assert_eq!(seen.connections, 2);
    let stats = client.stats();
    assert_eq!(stats.connects, 2);
    assert_eq!(stats.resent_rounds, 1);
}

#[tokio::test]
async fn connection_killed_before_generation_resumes_with_the_same_round() {
    resume_after_kill(Kill::BeforeGeneration).await;
}

#[tokio::test]
async fn connection_killed_after_generation_replays_the_cached_reply() {
    resume_after_kill(Kill::AfterGeneration).await;
}

#[tokio::test]
async fn reconnect_uses_zero_rtt() {
    let responder = Responder::start(Behavior::default());
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(1);
    task.submit(
        RoundRequest::new(observation(client.now_us())),
        &mut NoRefetch,
    )
    .await
    .unwrap();
    client.drop_connection().await;
    task.submit(
        RoundRequest::new(observation(client.now_us())),
        &mut NoRefetch,
    )
    .await
    .unwrap();
    let stats = client.stats();
    assert_eq!(stats.connects, 2);
    assert_eq!(
        stats.zero_rtt_accepted, 1,
        "the second connection resumed the TLS session with early data"
    );
}

#[tokio::test]
async fn fetch_observation_is_answered_on_the_round_stream() {
    let responder = Responder::start(Behavior {
        fetch_observation: true,
        ..Behavior::default()
    });
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(5);
    let mut asked = Vec::new();
    let mut source = |fetch: &FetchObservation| -> Option<Observation> {
        asked.push((fetch.round, fetch.age_us));
        Some(observation(999_999))
    };
    let reply = task
        .submit(RoundRequest::new(observation(1)), &mut source)
        .await
        .unwrap();
    assert_eq!(reply.refetches, 1);
    assert_eq!(reply.observation_captured_at_us, 999_999);
    assert_eq!(asked, [(0, 1234)]);
    // Without a source, the round's own observation goes back.
    task.submit(RoundRequest::new(observation(42)), &mut NoRefetch)
        .await
        .unwrap();
    assert_eq!(responder.seen().fresh, [999_999, 42]);
    assert_eq!(client.stats().refetches, 2);
}

#[tokio::test]
async fn a_failed_round_consumes_its_id() {
    let responder = Responder::start(Behavior {
        fail_round: Some((1, ErrorCode::InvalidRequest)),
        ..Behavior::default()
    });
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(9);
    task.submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap();
    let error = task
        .submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap_err();
    assert!(
        matches!(&error, ClientError::Server(reply) if reply.code == ErrorCode::InvalidRequest),
        "{error:?}"
    );
    assert!(!error.is_retryable());
    let reply = task
        .submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap();
    assert_eq!(reply.reply.round, 2);
}

#[tokio::test]
async fn oversized_requests_are_refused_locally() {
    let responder = Responder::start(Behavior::default());
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(2);
    let mut big = observation(0);
    big.instruction = "x".repeat(5000);
    let error = task
        .submit(RoundRequest::new(big), &mut NoRefetch)
        .await
        .unwrap_err();
    assert!(matches!(error, ClientError::Invalid(_)), "{error:?}");
    assert!(responder.seen().submits.is_empty(), "nothing was sent");
}

#[tokio::test]
async fn rebind_mid_round_keeps_the_connection() {
    // The responder holds the round after reading its Submit; the client rebinds while it is
    // held, and only then is the round generated and answered (to the new address).
    let hold = Arc::new(Hold::default());
    let responder = Responder::start(Behavior {
        hold: Some(hold.clone()),
        ..Behavior::default()
    });
    let client = Client::connect(config(&responder)).await.unwrap();
    let before = client.local_addr().unwrap();
    let mut task = client.task(4);
    let roaming = client.clone();
    let roam = tokio::spawn(async move {
        hold.entered.notified().await;
        let socket = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        roaming.rebind(socket).unwrap();
        hold.release.notify_one();
    });
    let reply = task
        .submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap();
    roam.await.unwrap();
    assert_ne!(client.local_addr().unwrap(), before);
    assert_eq!(reply.attempts, 1);
    assert_eq!(client.stats().connects, 1, "migrated, not reconnected");
}

#[tokio::test]
async fn closed_client_refuses_rounds() {
    let responder = Responder::start(Behavior::default());
    let client = Client::connect(config(&responder)).await.unwrap();
    let mut task = client.task(1);
    client.close().await;
    let error = task
        .submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap_err();
    assert!(matches!(error, ClientError::Closed), "{error:?}");
}

#[tokio::test]
async fn an_abandoned_round_is_cancelled_on_the_server() {
    let responder = Responder::start(Behavior {
        generation: Duration::from_secs(5),
        ..Behavior::default()
    });
    let mut config = config(&responder);
    config.round_timeout = Some(Duration::from_millis(200));
    let client = Client::connect(config).await.unwrap();
    let mut task = client.task(6);
    let error = task
        .submit(RoundRequest::new(observation(0)), &mut NoRefetch)
        .await
        .unwrap_err();
    assert!(
        matches!(error, ClientError::Timeout { what: "round", .. }),
        "{error:?}"
    );
    assert!(error.is_retryable());
    // The stream's STOP_SENDING reaches the responder: wait for it to say so.
    let cancellation = responder.seen().cancellation.clone();
    while responder.seen().cancelled.is_empty() {
        cancellation.notified().await;
    }
    assert_eq!(
        responder.seen().cancelled,
        [(0, u64::from(ROUND_CANCELLED))]
    );
    assert_eq!(task.next_round(), 1, "the abandoned round's id is used up");
}

#[test]
fn blocking_client_runs_rounds_from_a_plain_thread() {
    let server = tokio::runtime::Runtime::new().unwrap();
    let responder = server.block_on(async { Responder::start(Behavior::default()) });
    let client = kairos_sdk::BlockingClient::connect(config(&responder)).unwrap();
    assert_eq!(client.welcome().unwrap().robot, "robot-0");
    let mut task = client.task(12);
    for round in 0..2 {
        let reply = task
            .submit(
                RoundRequest::new(observation(client.now_us())),
                &mut NoRefetch,
            )
            .unwrap();
        assert_eq!(reply.reply.round, round);
        // The connection keeps being driven while the caller is away.
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(task.end(TaskOutcome::Done, None).unwrap().rounds, 2);
    client.close();
    assert_eq!(server.block_on(async { responder.seen().submits.len() }), 2);
}
