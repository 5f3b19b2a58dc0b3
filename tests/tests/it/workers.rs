//! Remote engine workers against a scheduler with no local engine, in this process: who may
//! register (the worker token, never a robot's; the scheduler's pinned certificate), and a
//! worker in a network namespace of its own behind a userspace UDP delay relay (this kernel has
//! no netem): measured at the injected round trip, classified cloud from it, and used only when
//! the near worker is gone; the worker's own `/metrics`. Process-level runs (`kairos worker`,
//! SIGKILL, SIGTERM) are in `server/tests/it/workers.rs`.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::net::SocketAddr;
use std::time::Duration;

use kairos_core::scheduler::Tier;
use kairos_sdk::client::{Client, ClientError};
use kairos_sdk::protocol::worker::WorkerTier;
use kairos_sdk::tls::{Fingerprint, ServerTrust};
use kairos_server::data_dir::DataDir;
use kairos_server::driver::EngineView;
use kairos_server::metrics::{Metrics, Readiness};
use kairos_server::transport::refusals::{Door, Reason};
use kairos_server::worker::{WorkerError, WorkerOptions, WorkerReport, run};
use kairos_tests::harness::{RobotPlan, ServerOptions, TestServer, run_fleet};
use kairos_tests::netns::NetNs;
use kairos_tests::proxy::{Impairment, Proxy, ProxyConfig};
use kairos_tests::workers::test_flow_engine;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

const GIVE_UP: Duration = Duration::from_secs(60);

fn options(
    server: &TestServer,
    addr: std::net::SocketAddr,
    token: &str,
    id: &str,
) -> WorkerOptions {
    WorkerOptions {
        server: addr.to_string(),
        trust: ServerTrust::Pinned(server.pin),
        token: token.to_owned(),
        worker_id: id.to_owned(),
        tier: WorkerTier::Edge,
        max_batch: 2,
        metrics: Metrics::for_worker(),
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
    let task = tokio::spawn(run(options, test_flow_engine(&id), async {
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
        test_flow_engine("r"),
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
    let refused = run(
        wrong_pin,
        test_flow_engine("p"),
        std::future::pending::<()>(),
    )
    .await;
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
    let report = server.shutdown().await;
    // The robot token's registration was a refusal at the workers' door; the robot connection
    // with the worker token one at the robots'.
    assert_eq!(report.refusals.get(Door::Workers, Reason::Unauthorized), 1);
    assert_eq!(report.refusals.get(Door::Quic, Reason::Unauthorized), 1);
}

/// GETs `path` from a metrics endpoint (real TCP, `Connection: close`); the body.
async fn scrape(addr: SocketAddr, path: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream
        .write_all(format!("GET {path} HTTP/1.1\r\nHost: kairos\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).await.unwrap();
    assert!(response.starts_with("HTTP/1.1 200"), "{response}");
    response
}

/// The value of the sample `series` (name and labels as exported; a trailing `@` in a label
/// value matches any suffix) in `text`.
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|line| {
        let rest = match series.split_once('@') {
            Some((head, tail)) => {
                let rest = line.strip_prefix(head)?.strip_prefix('@')?;
                rest.split_once(tail).map(|(_, after)| after)?
            }
            None => line.strip_prefix(series)?,
        };
        rest.strip_prefix(' ')?.parse().ok()
    })
}

/// Serves `metrics` as `kairos worker --metrics-listen` does; its address.
async fn serve_metrics(metrics: &Metrics) -> SocketAddr {
    let listener = kairos_server::metrics::http::bind("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let addr = listener.local_addr().unwrap();
    let ready = Readiness::new();
    ready.set(true);
    tokio::spawn(kairos_server::metrics::http::serve(
        listener,
        metrics.clone(),
        ready,
        std::future::pending(),
    ));
    addr
}

/// Injected one-way delay of the relay in front of the far worker.
const ONE_WAY: Duration = Duration::from_millis(40);
/// What the scheduler may measure beyond the injected round trip. A round trip through the
/// relay is at least the injected 80 ms (the relay never sends early; QUIC subtracts only the
/// peer's own ack delay; a batch sample is end-to-end time less the compute inside it), so the
/// lower bound is exact. Above it come wake-ups: about six per round trip (the relay's reader
/// and timer each way, the scheduler's and the worker's tasks), each of which can wait for a
/// core on this loaded 2-core machine (load 2–12 while seven engineers build). Allowing 20 ms a
/// wake-up gives 120 ms.
const RTT_SLACK: Duration = Duration::from_millis(120);

/// A far worker in a network namespace of its own whose only way to the scheduler is a veth
/// pair and a userspace UDP relay adding 40 ms each way (this kernel has no netem), and a near
/// worker on loopback. The far one registers with tier `auto` and becomes cloud from its
/// measured round trip; that round trip, from QUIC's handshake and then from its batches, is
/// at least the injected 80 ms and within [`RTT_SLACK`] of it, on the scheduler's `/metrics`.
/// With one robot the near (edge) worker runs every batch; only once it has drained does the
/// far one run any. The near worker's own `/metrics` counts what it ran.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_in_a_network_namespace_behind_a_delay_relay_is_measured_and_placed_last() {
    let ns = NetNs::create().unwrap_or_else(|error| {
        panic!("this test needs a network namespace (root and iproute2; it does not skip): {error}")
    });
    let server = TestServer::start(ServerOptions {
        tweak: |config| config.metrics.listen = Some("127.0.0.1:0".parse().unwrap()),
        ..no_engine()
    })
    .await
    .unwrap();
    let scheduler_metrics = server.server().metrics_addr.unwrap();
    let token = worker_token(&server);
    let relay = Proxy::start_on(
        SocketAddr::new(ns.host_ip.into(), 0),
        server.addr,
        ProxyConfig::symmetric(
            Impairment {
                delay: ONE_WAY,
                ..Impairment::NONE
            },
            1,
        ),
    )
    .await
    .unwrap();

    // The far worker: its thread, runtime and sockets are in the namespace.
    let far_metrics = Metrics::for_worker();
    let mut far_options = options(&server, relay.addr(), &token, "far");
    far_options.tier = WorkerTier::Auto;
    far_options.metrics = far_metrics.clone();
    let (stop_far, far_stopped) = oneshot::channel::<()>();
    let far = ns.spawn(move || {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        runtime.block_on(run(far_options, test_flow_engine("far"), async {
            let _ = far_stopped.await;
        }))
    });
    wait_engines(&server, |e| e.iter().filter(|e| e.live).count() == 1).await;
    let clients = relay.stats().clients.lock().unwrap().clone();
    assert!(
        !clients.is_empty() && clients.iter().all(|c| c.ip() == ns.ns_ip),
        "the far worker reached the relay from the namespace ({}): {clients:?}",
        ns.ns_ip
    );

    // The near worker, on loopback, declared edge.
    let near_metrics = Metrics::for_worker();
    let near_endpoint = serve_metrics(&near_metrics).await;
    let mut near_options = options(&server, server.addr, &token, "near");
    near_options.metrics = near_metrics.clone();
    let (stop_near, near) = spawn_worker(near_options);
    let engines = wait_engines(&server, |e| e.iter().filter(|e| e.live).count() == 2).await;
    let view = |engines: &[EngineView], id: &str| {
        engines
            .iter()
            .find(|e| e.name.starts_with(&format!("worker:{id}@")))
            .cloned()
            .unwrap()
    };
    let injected = ONE_WAY * 2;
    let (far_view, near_view) = (view(&engines, "far"), view(&engines, "near"));
    assert_eq!(far_view.tier, Tier::Cloud, "auto, from QUIC's estimate");
    assert_eq!(near_view.tier, Tier::Edge);
    assert!(
        far_view.rtt >= injected && far_view.rtt <= injected + RTT_SLACK,
        "seeded from QUIC's estimate: {:?} for {injected:?} injected",
        far_view.rtt
    );
    assert!(near_view.rtt < far_view.rtt, "{engines:?}");

    // One robot: the near worker is idle whenever a round comes, and edge goes first.
    let rounds = 6;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(1, rounds, 4)])
        .await
        .unwrap();
    assert_eq!(logs[0].rounds.len() as u64, rounds);
    assert_eq!(
        far_metrics.worker_batches(),
        0,
        "the far worker ran nothing"
    );
    assert_eq!(near_metrics.worker_batches(), rounds, "one batch a round");
    // The near worker's own `/metrics`, scraped as Prometheus would.
    let text = scrape(near_endpoint, "/metrics").await;
    for (series, value) in [
        (r#"kairos_worker_connection{state="registered"}"#, 1.0),
        (r#"kairos_worker_connection{state="connecting"}"#, 0.0),
        ("kairos_worker_batches_total", rounds as f64),
        ("kairos_worker_failed_batches_total", 0.0),
        ("kairos_worker_compute_seconds_count", rounds as f64),
        ("kairos_batch_size_count", rounds as f64),
        ("kairos_batch_size_sum", rounds as f64),
    ] {
        assert_eq!(sample(&text, series), Some(value), "{series} in\n{text}");
    }
    let heartbeats = sample(&text, "kairos_worker_heartbeats_total").unwrap();
    assert!(
        heartbeats >= 1.0,
        "the first heartbeat goes at once\n{text}"
    );
    let busy = sample(&text, r#"kairos_engine_busy_seconds_total{engine="near"}"#).unwrap();
    assert!(busy > 0.0, "{text}");

    // The near worker drains; now every batch goes to the far one.
    let _ = stop_near.send(());
    let near_report = near.await.unwrap().unwrap();
    assert_eq!(near_report.batches, rounds);
    let text = scrape(near_endpoint, "/metrics").await;
    assert_eq!(
        sample(&text, r#"kairos_worker_connection{state="disconnected"}"#),
        Some(1.0),
        "{text}"
    );
    wait_engines(&server, |e| e.iter().filter(|e| e.live).count() == 1).await;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(2, rounds, 4)])
        .await
        .unwrap();
    assert_eq!(logs[0].rounds.len() as u64, rounds);
    assert_eq!(far_metrics.worker_batches(), rounds);

    // Its round trip, now a moving average over its batches, on the scheduler's `/metrics`.
    let text = scrape(scheduler_metrics, "/metrics").await;
    let rtt = sample(&text, r#"kairos_worker_rtt_seconds{worker="worker:far@"}"#)
        .unwrap_or_else(|| panic!("no RTT of the far worker in\n{text}"));
    let rtt = Duration::try_from_secs_f64(rtt).unwrap();
    eprintln!(
        "netns relay: injected {injected:?}, measured {rtt:?} (seed {:?}) after {rounds} batches; \
         near worker on loopback, no relay (the baseline): {:?}",
        far_view.rtt, near_view.rtt
    );
    assert!(
        rtt >= injected && rtt <= injected + RTT_SLACK,
        "{rtt:?} measured for {injected:?} injected"
    );
    assert_eq!(
        sample(&text, r#"kairos_workers{tier="cloud",state="ready"}"#),
        Some(1.0),
        "{text}"
    );
    assert_eq!(
        sample(&text, r#"kairos_workers{tier="edge",state="ready"}"#),
        Some(0.0),
        "{text}"
    );

    let _ = stop_far.send(());
    let far_report = far
        .join()
        .unwrap()
        .expect("the thread entered the namespace")
        .unwrap();
    assert_eq!(far_report.batches, rounds);
    server.shutdown().await;
    drop(relay);
    drop(ns);
}

/// A worker whose scheduler restarts (its connection closed, no drain) dials again with backoff,
/// by name (`localhost:PORT`, resolved by the worker at every attempt), registers with the new
/// scheduler (same address and data directory, so the same pin and worker token) and serves
/// its robots; its report and `/metrics` count both connections' batches.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_reconnects_by_name_after_its_scheduler_restarts() {
    let mut server = TestServer::start(no_engine()).await.unwrap();
    let token = worker_token(&server);
    let metrics = Metrics::for_worker();
    let mut by_name = options(&server, server.addr, &token, "phoenix");
    by_name.server = format!("localhost:{}", server.addr.port());
    by_name.metrics = metrics.clone();
    let (stop, task) = spawn_worker(by_name);
    wait_engines(&server, |e| e.iter().any(|e| e.live)).await;
    let rounds = 3;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(1, rounds, 4)])
        .await
        .unwrap();
    assert_eq!(logs[0].rounds.len() as u64, rounds);
    assert_eq!(metrics.worker_batches(), rounds);

    server.restart(no_engine()).await.unwrap();
    // The new scheduler starts with no engine; the worker registers again by itself.
    wait_engines(&server, |e| e.iter().any(|e| e.live)).await;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(2, rounds, 4)])
        .await
        .unwrap();
    assert_eq!(logs[0].rounds.len() as u64, rounds);
    let _ = stop.send(());
    let report = task.await.unwrap().unwrap();
    assert_eq!(report.registrations, 2, "{report:?}");
    assert_eq!(report.batches, 2 * rounds, "{report:?}");
    assert_eq!(metrics.worker_batches(), 2 * rounds);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_without_a_batch_cap_registers_with_its_profiles_largest_batch() {
    // `kairos worker` without `--max-batch` passes u32::MAX, over the protocol's 1..=1024: the
    // Register must carry the profile's largest batch instead, or every such worker is refused.
    let server = TestServer::start(no_engine()).await.unwrap();
    let mut uncapped = options(&server, server.addr, &worker_token(&server), "uncapped");
    uncapped.max_batch = u32::MAX;
    let (stop, task) = spawn_worker(uncapped);
    wait_engines(&server, |e| e.iter().any(|e| e.live)).await;
    let logs = run_fleet(&server, vec![RobotPlan::static_horizon(0, 2, 4)])
        .await
        .unwrap();
    assert_eq!(logs.len(), 1);
    let _ = stop.send(());
    let report = task.await.unwrap().unwrap();
    assert!(report.batches >= 1, "{report:?}");
    server.shutdown().await;
}
