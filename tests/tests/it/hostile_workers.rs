//! Workers are untrusted input, like robots: a worker holding the worker token that lies in its
//! `Register` or answers its batches with nonsense is refused or removed (counted in
//! `kairos_worker_removed_total{reason}`), its batch runs again on a healthy worker, and nothing
//! it sent reaches a robot or can stop the scheduler. Each test plays the hostile worker by hand
//! over real QUIC ([`RawWorker`]) against a scheduler with no local engine; the healthy worker
//! is the real `kairos worker` library.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::time::Duration;

use kairos_engine::ActionModel;
use kairos_sdk::client::RoundReply;
use kairos_sdk::protocol::Tensor;
use kairos_sdk::protocol::worker::{
    Chunks, RunBatch, WorkChunk, WorkResult, WorkerMessage, close_code as worker_close,
};
use kairos_server::driver::EngineView;
use kairos_tests::harness::{RobotPlan, ServerOptions, TestServer, one_round, run_fleet};
use kairos_tests::model::TestFlow;
use kairos_tests::workers::{RawBatch, RawWorker, register_message, spawn_worker};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::task::JoinHandle;

/// Hang guard only: every wait below ends on an event well before it.
const GIVE_UP: Duration = Duration::from_secs(60);

fn no_engine_with_metrics() -> ServerOptions {
    ServerOptions {
        engines: 0,
        max_batch: 2,
        tweak: |config| config.metrics.listen = Some("127.0.0.1:0".parse().unwrap()),
        ..ServerOptions::default()
    }
}

async fn wait_engines(server: &TestServer, done: impl Fn(&[EngineView]) -> bool) {
    tokio::time::timeout(GIVE_UP, async {
        loop {
            let engines = server.server().driver.engines().await.unwrap();
            if done(&engines) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    })
    .await
    .expect("the engines reached the state waited for");
}

fn live(engines: &[EngineView]) -> usize {
    engines.iter().filter(|e| e.live).count()
}

/// GETs `/metrics` (real TCP, `Connection: close`); the response body.
async fn scrape(addr: SocketAddr) -> String {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nHost: kairos\r\n\r\n")
        .await
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    response
}

/// The value of the sample `series` in `text`.
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

/// A hostile worker registers first and alone, so the robot's round goes to it; once it holds
/// the batch a healthy worker joins. Returns the hostile worker, the batch it holds, the round
/// in flight (robot task 1, round 0) and the healthy worker's stop handle.
async fn hostile_holds_a_round(
    server: &TestServer,
    latency_ms: f64,
) -> (
    RawWorker,
    RawBatch,
    JoinHandle<RoundReply>,
    tokio::sync::oneshot::Sender<()>,
) {
    let register = register_message(server, "liar", latency_ms).unwrap();
    let (liar, answer) = RawWorker::register(server, &register).await.unwrap();
    assert!(matches!(answer, WorkerMessage::Registered(_)), "{answer:?}");
    wait_engines(server, |e| live(e) == 1).await;
    let client = server.connect(&server.token).await.unwrap();
    let round = tokio::spawn(async move {
        let reply = one_round(&client, 1, 0).await;
        client.close().await;
        reply.expect("the round is answered")
    });
    let batch = tokio::time::timeout(GIVE_UP, liar.next_batch())
        .await
        .unwrap()
        .unwrap();
    let (stop, _healthy) = spawn_worker(server, "honest").unwrap();
    wait_engines(server, |e| live(e) == 2).await;
    (liar, batch, round, stop)
}

/// A chunk of [`TestFlow`]'s shapes for each request of `run`, every value `value`.
fn chunks_of(run: &RunBatch, value: f32) -> Chunks {
    let spec = TestFlow::new().spec().clone();
    let (k, n, d) = (
        spec.steps as u32,
        spec.chunk_len as u32,
        spec.action_dim as u32,
    );
    let results = run
        .requests
        .iter()
        .map(|request| {
            let s = request.samples.max(1);
            let tensor = |shape: Vec<u32>| {
                let len = shape.iter().product::<u32>() as usize;
                Tensor::from_f32(shape, &vec![value; len]).unwrap()
            };
            WorkResult {
                chunk: Some(WorkChunk {
                    actions: tensor(vec![s, n, d]),
                    updates: tensor(vec![s, k, n, d]),
                    noise: tensor(vec![s, n, d]),
                }),
                error: None,
            }
        })
        .collect();
    Chunks {
        batch_id: run.batch_id,
        attempt: run.attempt,
        compute_us: 10,
        results,
    }
}

fn assert_finite(reply: &RoundReply) {
    let actions = reply.reply.actions.to_f32().unwrap();
    assert!(!actions.is_empty());
    assert!(
        actions.iter().all(|a| a.is_finite()),
        "the robot got {actions:?}"
    );
}

/// The hostile worker was closed as unusable, and counted once under `reason`.
async fn assert_removed(server: &TestServer, liar: &RawWorker, code: u32, reason: &str) {
    let (closed, why) = tokio::time::timeout(GIVE_UP, liar.closed()).await.unwrap();
    assert_eq!(closed, u64::from(code), "{why}");
    let text = scrape(server.server().metrics_addr.unwrap()).await;
    assert_eq!(
        sample(
            &text,
            &format!("kairos_worker_removed_total{{reason=\"{reason}\"}}")
        ),
        Some(1.0),
        "{text}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_profile_that_would_overflow_the_scheduler_is_refused_at_registration() {
    let server = TestServer::start(no_engine_with_metrics()).await.unwrap();
    // 1e300 ms made the first round panic the driver thread; the others are no profile either.
    for latency_ms in [1e300, f64::INFINITY, f64::NAN, -1.0, 0.0] {
        let register = register_message(&server, "liar", latency_ms).unwrap();
        let (liar, answer) = RawWorker::register(&server, &register).await.unwrap();
        match answer {
            WorkerMessage::Refused(refused) => {
                assert!(refused.reason.contains("latency"), "{refused:?}");
                assert!(!refused.retryable);
            }
            other => panic!("a profile of {latency_ms} ms was accepted: {other:?}"),
        }
        let (code, _) = liar.closed().await;
        assert_eq!(code, u64::from(worker_close::REFUSED));
    }
    // Names beyond the protocol's limit are refused too.
    let mut long = register_message(&server, "liar", 1.0).unwrap();
    long.worker_id = "w".repeat(10_000);
    let (_liar, answer) = RawWorker::register(&server, &long).await.unwrap();
    assert!(
        matches!(&answer, WorkerMessage::Refused(r) if r.reason.contains("worker_id")),
        "{answer:?}"
    );
    let text = scrape(server.server().metrics_addr.unwrap()).await;
    assert_eq!(
        sample(
            &text,
            r#"kairos_worker_removed_total{reason="invalid_registration"}"#
        ),
        Some(6.0),
        "{text}"
    );

    // The scheduler is untouched: a healthy worker serves a robot.
    let (stop, healthy) = spawn_worker(&server, "honest").unwrap();
    wait_engines(&server, |e| live(e) == 1).await;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(1, 3, 4)])
        .await
        .unwrap();
    assert_eq!(logs[0].rounds.len(), 3);
    let _ = stop.send(());
    healthy.await.unwrap().unwrap();
    let report = server.shutdown().await;
    assert_eq!(report.driver.replies, 3);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nan_actions_from_a_worker_never_reach_a_robot() {
    let server = TestServer::start(no_engine_with_metrics()).await.unwrap();
    let (liar, batch, round, stop) = hostile_holds_a_round(&server, 0.05).await;
    let nan = chunks_of(&batch.run, f32::NAN);
    batch.answer(&nan).await.unwrap();
    let reply = tokio::time::timeout(GIVE_UP, round).await.unwrap().unwrap();
    assert_finite(&reply);
    assert_removed(&server, &liar, worker_close::BATCH_LOST, "invalid_answer").await;
    let _ = stop.send(());
    let report = server.shutdown().await;
    assert_eq!((report.driver.replies, report.driver.failed), (1, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_that_answers_the_wrong_number_of_results_is_removed_and_its_round_runs_elsewhere()
{
    let server = TestServer::start(no_engine_with_metrics()).await.unwrap();
    let (liar, batch, round, stop) = hostile_holds_a_round(&server, 0.05).await;
    let mut wrong = chunks_of(&batch.run, 0.0);
    let extra = wrong.results[0].clone();
    wrong.results.push(extra);
    batch.answer(&wrong).await.unwrap();
    let reply = tokio::time::timeout(GIVE_UP, round).await.unwrap().unwrap();
    assert_finite(&reply);
    assert_removed(&server, &liar, worker_close::BATCH_LOST, "invalid_answer").await;
    let _ = stop.send(());
    let report = server.shutdown().await;
    assert_eq!((report.driver.replies, report.driver.failed), (1, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_workers_error_text_beyond_the_protocols_limit_is_an_unusable_answer() {
    let server = TestServer::start(no_engine_with_metrics()).await.unwrap();
    let (liar, batch, round, stop) = hostile_holds_a_round(&server, 0.05).await;
    let mut flood = chunks_of(&batch.run, 0.0);
    for result in &mut flood.results {
        *result = WorkResult {
            chunk: None,
            error: Some("x".repeat(100_000)),
        };
    }
    batch.answer(&flood).await.unwrap();
    // Not the 100,000-byte text: the round ran again on the healthy worker.
    let reply = tokio::time::timeout(GIVE_UP, round).await.unwrap().unwrap();
    assert_finite(&reply);
    assert_removed(&server, &liar, worker_close::BATCH_LOST, "invalid_answer").await;
    let _ = stop.send(());
    server.shutdown().await;
}

/// `[workers] max_batch_deadline_ms` for [`batch_deadlines_are_capped_whatever_a_worker_declares`].
const DEADLINE_CAP_MS: u32 = 2_000;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batch_deadlines_are_capped_whatever_a_worker_declares() {
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
            config.workers.min_batch_deadline_ms = 1_000;
            config.workers.max_batch_deadline_ms = DEADLINE_CAP_MS;
        },
        ..no_engine_with_metrics()
    })
    .await
    .unwrap();
    // A worker that says a batch takes 100 s would have had 400 s (× batch_deadline_factor).
    let (liar, batch, round, stop) = hostile_holds_a_round(&server, 100_000.0).await;
    assert!(
        batch.run.deadline_ms <= DEADLINE_CAP_MS,
        "deadline {} ms for a cap of {DEADLINE_CAP_MS} ms",
        batch.run.deadline_ms
    );
    // It never answers: at the capped deadline it is removed and the round runs elsewhere.
    let reply = tokio::time::timeout(GIVE_UP, round).await.unwrap().unwrap();
    assert_finite(&reply);
    assert_removed(&server, &liar, worker_close::DEADLINE, "deadline").await;
    drop(batch);
    let _ = stop.send(());
    server.shutdown().await;
}

/// A worker removed for NaN actions that registers again at once is refused (retryable, counted
/// under `readmit_delay`) while the round it spoiled waits for the healthy worker, which runs
/// it; once its delay has passed, the same worker may register again. Without the delay it came
/// back as a new, idle, fast-looking engine, took the spoiled round again and spent its attempts
/// until the robot got an error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_removed_for_nan_is_refused_until_its_delay_passes_and_the_retry_runs_on_the_healthy_one()
 {
    const DELAY: Duration = Duration::from_millis(300);
    let server = TestServer::start(ServerOptions {
        tweak: |config| {
            config.metrics.listen = Some("127.0.0.1:0".parse().unwrap());
            config.workers.readmit_after_invalid_ms = 300;
            // The hand-driven workers answer when the test says so, not within a deadline.
            config.workers.min_batch_deadline_ms = 600_000;
            config.workers.max_batch_deadline_ms = 600_000;
        },
        ..no_engine_with_metrics()
    })
    .await
    .unwrap();
    // The liar registers alone and takes robot task 1's round.
    let register = register_message(&server, "liar", 0.05).unwrap();
    let (liar, answer) = RawWorker::register(&server, &register).await.unwrap();
    assert!(matches!(answer, WorkerMessage::Registered(_)), "{answer:?}");
    wait_engines(&server, |e| live(e) == 1).await;
    let client = server.connect(&server.token).await.unwrap();
    let round = |task: u64| {
        let client = client.clone();
        tokio::spawn(async move { one_round(&client, task, 0).await })
    };
    let first = round(1);
    let spoiled = tokio::time::timeout(GIVE_UP, liar.next_batch())
        .await
        .unwrap()
        .unwrap();
    // A healthy worker (driven by hand, so that it is busy when the liar is removed) joins and
    // takes task 2's round.
    let honest_register = register_message(&server, "honest", 50.0).unwrap();
    let (honest, answer) = RawWorker::register(&server, &honest_register)
        .await
        .unwrap();
    assert!(matches!(answer, WorkerMessage::Registered(_)), "{answer:?}");
    wait_engines(&server, |e| live(e) == 2).await;
    let second = round(2);
    let busy = tokio::time::timeout(GIVE_UP, honest.next_batch())
        .await
        .unwrap()
        .unwrap();

    // The liar answers NaN: removed, its round back in the queue, no engine idle.
    let before_removal = tokio::time::Instant::now();
    let answer = chunks_of(&spoiled.run, f32::NAN);
    spoiled.answer(&answer).await.unwrap();
    assert_removed(&server, &liar, worker_close::BATCH_LOST, "invalid_answer").await;
    liar.close().await;
    // It registers again at once, as `kairos-hostile-worker` does: refused, retryable, counted.
    let (again, answer) = RawWorker::register(&server, &register).await.unwrap();
    match &answer {
        WorkerMessage::Refused(refused) => {
            assert!(refused.retryable, "{refused:?}");
            assert!(refused.reason.contains("unusable answer"), "{refused:?}");
        }
        other => panic!("the removed worker was readmitted at once: {other:?}"),
    }
    again.close().await;
    let text = scrape(server.server().metrics_addr.unwrap()).await;
    assert_eq!(
        sample(
            &text,
            r#"kairos_refusals_total{door="workers",reason="readmit_delay"}"#
        ),
        Some(1.0),
        "{text}"
    );

    // The healthy worker answers task 2, then gets task 1's spoiled round: its second dispatch.
    let answer = chunks_of(&busy.run, 0.0);
    busy.answer(&answer).await.unwrap();
    let retry = tokio::time::timeout(GIVE_UP, honest.next_batch())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(retry.run.attempt, 1, "the spoiled round, run again");
    let answer = chunks_of(&retry.run, 0.0);
    retry.answer(&answer).await.unwrap();
    for reply in [first, second] {
        let reply = tokio::time::timeout(GIVE_UP, reply)
            .await
            .unwrap()
            .unwrap()
            .expect("the round is answered");
        assert_finite(&reply);
    }

    // Once the delay has passed, the same worker may register again; until then it is refused.
    let readmitted = tokio::time::timeout(GIVE_UP, async {
        loop {
            let (worker, answer) = RawWorker::register(&server, &register).await.unwrap();
            match answer {
                WorkerMessage::Registered(_) => return worker,
                WorkerMessage::Refused(refused) => {
                    assert!(refused.retryable, "{refused:?}");
                    worker.close().await;
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                other => panic!("{other:?}"),
            }
        }
    })
    .await
    .expect("readmitted once the delay passed");
    assert!(
        before_removal.elapsed() >= DELAY,
        "readmitted before its delay ended"
    );
    readmitted.close().await;
    honest.close().await;
    client.close().await;
    let report = server.shutdown().await;
    assert_eq!((report.driver.replies, report.driver.failed), (2, 0));
}
