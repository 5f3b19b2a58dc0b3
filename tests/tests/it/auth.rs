//! Authentication and task ownership over real QUIC: a wrong token is refused; a robot can
//! neither read nor advance nor end another robot's task. Admission limits are in `admission`.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use kairos_sdk::client::{ClientError, close_code};
use kairos_sdk::protocol::{ErrorCode, Message};
use kairos_tests::harness::{RawConnection, ServerOptions, TestServer, one_round};

fn two_robots() -> ServerOptions {
    ServerOptions {
        robots: vec![
            ("arm-1".to_string(), "token-one".to_string()),
            ("arm-2".to_string(), "token-two".to_string()),
        ],
        ..ServerOptions::default()
    }
}

fn server_code(error: ClientError) -> ErrorCode {
    match error {
        ClientError::Server(reply) => reply.code,
        other => panic!("expected a server error, got {other}"),
    }
}

/// The code and reason of an application close; panics on any other way of ending.
pub(crate) fn application_close_code(error: quinn::ConnectionError) -> (u64, String) {
    match error {
        quinn::ConnectionError::ApplicationClosed(close) => (
            close.error_code.into_inner(),
            String::from_utf8_lossy(&close.reason).into_owned(),
        ),
        other => panic!("expected an application close, got {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_is_refused_and_the_connection_closed() {
    let server = TestServer::start(two_robots()).await.unwrap();

    match server.connect("not-a-token").await {
        Err(error) => match error.downcast::<ClientError>().unwrap() {
            ClientError::Unauthorized(_) => {}
            other => panic!("expected Unauthorized, got {other}"),
        },
        Ok(_) => panic!("a wrong token was accepted"),
    }

    let (raw, answer) = RawConnection::hello(&server, "token-tw0").await.unwrap();
    match answer {
        Message::Error(error) => assert_eq!(error.code, ErrorCode::Unauthorized),
        other => panic!("expected an Unauthorized error frame, got {}", other.kind()),
    }
    let (code, _) = application_close_code(raw.connection.closed().await);
    assert_eq!(code, u64::from(close_code::UNAUTHORIZED));

    // The right token still works, and the refused connections took nothing with them.
    let robot = server.connect("token-two").await.unwrap();
    one_round(&robot, 1, 0).await.unwrap();
    robot.close().await;
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_cannot_read_advance_or_end_another_robots_task() {
    let server = TestServer::start(two_robots()).await.unwrap();
    let owner = server.connect("token-one").await.unwrap();
    let intruder = server.connect("token-two").await.unwrap();
    const TASK: u64 = 77;

    let first = one_round(&owner, TASK, 0).await.unwrap();
    one_round(&owner, TASK, 1).await.unwrap();

    // Advance: the next round id of someone else's task.
    let error = one_round(&intruder, TASK, 2).await.unwrap_err();
    assert_eq!(server_code(error), ErrorCode::UnknownTask);
    // Read: re-sending a finished round would return its cached chunk to its owner.
    let error = one_round(&intruder, TASK, 1).await.unwrap_err();
    assert_eq!(server_code(error), ErrorCode::UnknownTask);
    // End it.
    let error = intruder
        .task_from(TASK, 2)
        .end(kairos_sdk::protocol::TaskOutcome::Failed, None)
        .await
        .unwrap_err();
    assert_eq!(server_code(error), ErrorCode::UnknownTask);

    // The owner is unaffected: a re-sent finished round gets its cached chunk, the next round is
    // served, and the task's record has exactly its three rounds.
    let resent = one_round(&owner, TASK, 0).await.unwrap_err();
    assert_eq!(
        server_code(resent),
        ErrorCode::RoundOutOfOrder,
        "only the last round is cached"
    );
    let cached = one_round(&owner, TASK, 1).await.unwrap();
    assert_eq!(cached.reply.round, 1);
    assert_eq!(first.reply.round, 0);
    one_round(&owner, TASK, 2).await.unwrap();
    let ended = owner
        .task_from(TASK, 3)
        .end(kairos_sdk::protocol::TaskOutcome::Done, None)
        .await
        .unwrap();
    assert_eq!(ended.rounds, 3);
    // And the intruder can still run tasks of its own.
    one_round(&intruder, TASK + 1, 0).await.unwrap();

    owner.close().await;
    intruder.close().await;
    server.shutdown().await;
}
