//! Remote engine workers against a scheduler with no local engine, in this process: who may
//! register (the worker token, never a robot's; the scheduler's pinned certificate), and a
//! worker behind a delayed link (the userspace UDP impairment proxy on loopback: this kernel has
//! no netem, and the test does not use a network namespace) measured at about the injected
//! round trip and used only when the near worker is full. Process-level runs (`kairos worker`,
//! SIGKILL, SIGTERM) are in `server/tests/it/workers.rs`.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::sync::Arc;
use std::time::Duration;

use kairos_engine::{EngineProfile, ProfilePoint};
use kairos_sdk::client::{Client, ClientError};
use kairos_sdk::protocol::worker::WorkerTier;
use kairos_sdk::tls::{Fingerprint, ServerTrust};
use kairos_server::data_dir::DataDir;
use kairos_server::driver::EngineView;
use kairos_server::pool::{EngineInstance, LocalEngine};
use kairos_server::worker::{WorkerError, WorkerOptions, WorkerReport, run};
use kairos_tests::harness::{RobotPlan, ServerOptions, TestServer, run_fleet};
use kairos_tests::model::TestFlow;
use kairos_tests::proxy::{Impairment, Proxy, ProxyConfig};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

const GIVE_UP: Duration = Duration::from_secs(60);

fn engine(name: &str) -> Arc<dyn EngineInstance> {
    let profile = EngineProfile {
        model: "test-flow".into(),
        device: "cpu (test flow)".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms: 0.05,
            },
            ProfilePoint {
                batch: 2,
                latency_ms: 0.1,
            },
        ],
        max_batch: 2,
    };
    Arc::new(LocalEngine::start(name, Arc::new(TestFlow::new()), profile))
}

fn options(
    server: &TestServer,
    addr: std::net::SocketAddr,
    token: &str,
    id: &str,
) -> WorkerOptions {
    WorkerOptions {
        server: addr,
        trust: ServerTrust::Pinned(server.pin),
        token: token.to_owned(),
        worker_id: id.to_owned(),
        tier: WorkerTier::Edge,
        max_batch: 2,
    }
}

fn worker_token(server: &TestServer) -> String {
    DataDir::new(server.dir.path().join("data"))
        .read_worker_token()
        .unwrap()
}

/// A worker running until the sender is used (then it drains and returns its report).
fn spawn_worker(
    options: WorkerOptions,
) -> (
    oneshot::Sender<()>,
    JoinHandle<Result<WorkerReport, WorkerError>>,
) {
    let (stop, stopped) = oneshot::channel::<()>();
    let id = options.worker_id.clone();
    let task = tokio::spawn(run(options, engine(&id), async {
        let _ = stopped.await;
    }));
    (stop, task)
}

async fn wait_engines(
    server: &TestServer,
    done: impl Fn(&[EngineView]) -> bool,
) -> Vec<EngineView> {
    tokio::time::timeout(GIVE_UP, async {
        loop {
            let engines = server.server().driver.engines().await.unwrap();
            if done(&engines) {
                return engines;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    })
    .await
    .expect("the engines reached the state waited for")
}

fn no_engine() -> ServerOptions {
    ServerOptions {
        engines: 0,
        max_batch: 2,
        ..ServerOptions::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_worker_token_registers_and_the_worker_checks_the_pin() {
    let server = TestServer::start(no_engine()).await.unwrap();
    let worker_token = worker_token(&server);
    assert_ne!(worker_token, server.token);

    // A robot's token cannot register a worker.
    let refused = run(
        options(&server, server.addr, &server.token, "robot-token"),
        engine("r"),
        std::future::pending::<()>(),
    )
    .await;
    assert!(
        matches!(&refused, Err(WorkerError::Refused(reason)) if reason.contains("token")),
        "{refused:?}"
    );
    // A worker that does not find its pinned certificate refuses the scheduler.
    let mut wrong_pin = options(&server, server.addr, &worker_token, "wrong-pin");
    wrong_pin.trust = ServerTrust::Pinned(Fingerprint([7; 32]));
    let refused = run(wrong_pin, engine("p"), std::future::pending::<()>()).await;
    assert!(
        matches!(&refused, Err(WorkerError::Connect { .. })),
        "{refused:?}"
    );
    assert!(server.server().driver.engines().await.unwrap().is_empty());
    // The worker token does not act as a robot.
    let as_robot = Client::connect(server.client_config(server.addr, &worker_token)).await;
    assert!(
        matches!(as_robot, Err(ClientError::Unauthorized(_))),
        "{:?}",
        as_robot.err()
    );

    // With the worker token it registers and serves robots.
    let (stop, task) = spawn_worker(options(&server, server.addr, &worker_token, "ok"));
    wait_engines(&server, |e| e.iter().any(|e| e.live)).await;
    let plans = (0..2).map(|t| RobotPlan::static_horizon(t, 3, 4)).collect();
    let logs = run_fleet(&server, plans).await.unwrap();
    assert_eq!(logs.len(), 2);
    let _ = stop.send(());
    let report = task.await.unwrap().unwrap();
    assert!(report.batches >= 1, "{report:?}");
    server.shutdown().await;
}

/// Two edge workers: one direct, one behind a 15 ms each way delay relay. The far one's
/// measured round trip is about the injected 30 ms; the near one (registered last, so with the
/// higher id) takes every batch while it has room, and the far one only what does not fit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_delayed_worker_is_measured_and_placement_prefers_the_near_one() {
    let server = TestServer::start(no_engine()).await.unwrap();
    let token = worker_token(&server);
    let delay = Duration::from_millis(15);
    let proxy = Proxy::start(
        server.addr,
        ProxyConfig::symmetric(
            Impairment {
                delay,
                ..Impairment::NONE
            },
            1,
        ),
    )
    .await
    .unwrap();
    let (stop_far, far) = spawn_worker(options(&server, proxy.addr(), &token, "far"));
    wait_engines(&server, |e| e.iter().filter(|e| e.live).count() == 1).await;
    let (stop_near, near) = spawn_worker(options(&server, server.addr, &token, "near"));
    let engines = wait_engines(&server, |e| e.iter().filter(|e| e.live).count() == 2).await;
    let rtt_of = |engines: &[EngineView], id: &str| {
        engines
            .iter()
            .find(|e| e.name.starts_with(&format!("worker:{id}@")))
            .unwrap()
            .rtt
    };
    let injected = delay * 2;
    let far_rtt = rtt_of(&engines, "far");
    assert!(
        far_rtt >= injected && far_rtt < injected * 3,
        "seeded from QUIC's estimate: {far_rtt:?} for {injected:?} injected"
    );
    assert!(rtt_of(&engines, "near") < injected / 2, "{engines:?}");

    // One robot at a time: the near worker is always idle, so it takes everything.
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(1, 6, 4)])
        .await
        .unwrap();
    assert_eq!(logs.len(), 1);
    // Many at once: the near one fills, the far one takes what does not fit.
    let plans = (10..18)
        .map(|t| RobotPlan::static_horizon(t, 4, 4))
        .collect();
    run_fleet(&server, plans).await.unwrap();
    let engines = server.server().driver.engines().await.unwrap();
    let far_rtt = rtt_of(&engines, "far");
    let _ = (stop_far.send(()), stop_near.send(()));
    let far = far.await.unwrap().unwrap();
    let near = near.await.unwrap().unwrap();
    assert!(
        near.batches > far.batches,
        "near {} batches, far {}",
        near.batches,
        far.batches
    );
    if far.batches > 0 {
        // Measured from its batches: end-to-end time less the compute it reported.
        assert!(
            far_rtt >= injected && far_rtt < injected * 3,
            "{far_rtt:?} after {} batches",
            far.batches
        );
    }
    server.shutdown().await;
}
