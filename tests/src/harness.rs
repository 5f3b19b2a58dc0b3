//! Starting a real server in-process and driving simulated robots against it.
//!
//! [`TestServer::start`] runs the whole server (QUIC with TLS 1.3, the driver, the scheduler, an
//! engine pool) on `127.0.0.1:0` with a temporary data dir, through the server's fleet harness
//! (`kairos_bench::fleet`, which `kairos demo` and `kairos bench live` use too).
//! [`run_task`] plays one robot through a multi-round task with asynchronous inference (the next
//! request goes out while the current chunk still executes) and logs, on the robot's own clock,
//! what it did: when each request was sent and answered, when each chunk started executing, and
//! how many actions were left when the next request went out. That log is what the server's G/E
//! records are compared against.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use kairos_bench::fleet::{self, LocalServer};
use kairos_engine::{ActionModel, EngineProfile, ProfilePoint};
use kairos_sdk::client::{Client, ClientConfig, NoRefetch, RoundRequest};
use kairos_sdk::protocol::{
    HorizonSelection, LastExecInfo, Observation, TaskEnded, TaskOutcome, Tensor,
};
use kairos_sdk::tls::Fingerprint;
use kairos_server::config::{Config, PluginConfig, RobotConfig};
use kairos_server::credentials::hash_token;
use kairos_server::pool::{EngineInstance, EnginePool, LocalEngine};
use kairos_server::transport::launch::{Policies, RunningServer, ServerReport};

use crate::model::TestFlow;

/// How to start a test server.
#[derive(Clone, Debug)]
pub struct ServerOptions {
    /// Robots as `(name, token)`; empty = the generated `default` robot.
    pub robots: Vec<(String, String)>,
    /// Engine instances (edge, local threads); 0: none, remote workers serve the model.
    pub engines: usize,
    /// Largest batch per instance.
    pub max_batch: u32,
    /// `[[plugin]]` entries, put in the config before `tweak` runs.
    pub plugins: Vec<PluginConfig>,
    /// Policies registered in code, beside the natives and the plugins.
    pub policies: Policies,
    /// Applied to the config last.
    pub tweak: fn(&mut Config),
}

impl Default for ServerOptions {
    fn default() -> Self {
        ServerOptions {
            robots: Vec::new(),
            engines: 1,
            max_batch: 8,
            plugins: Vec::new(),
            policies: Policies::default(),
            tweak: |_| {},
        }
    }
}

/// A server running in this process.
pub struct TestServer {
    server: Option<LocalServer>,
    /// The `default` robot's token (when robots were generated) or the first configured one.
    pub token: String,
    /// The certificate pin.
    pub pin: Fingerprint,
    /// Where it listens.
    pub addr: SocketAddr,
    /// The data dir, removed on drop.
    pub dir: tempfile::TempDir,
}

impl TestServer {
    /// Starts a server with the [`TestFlow`] model.
    pub async fn start(options: ServerOptions) -> anyhow::Result<TestServer> {
        Self::start_with_model(options, Arc::new(TestFlow::new())).await
    }

    /// Starts a server serving `model`.
    pub async fn start_with_model(
        options: ServerOptions,
        model: Arc<dyn ActionModel>,
    ) -> anyhow::Result<TestServer> {
        let dir = tempfile::tempdir()?;
        let server = launch(dir.path(), "127.0.0.1:0".parse()?, &options, model).await?;
        let token = match options.robots.first() {
            Some((_, token)) => token.clone(),
            None => server
                .token
                .clone()
                .context("no token for the generated robot")?,
        };
        Ok(TestServer {
            addr: server.addr(),
            pin: server.pin,
            server: Some(server),
            token,
            dir,
        })
    }

    /// Shuts the server down and starts a new one (the [`TestFlow`] model, `options`) on the same
    /// address and data directory, so with the same certificate pin and tokens: a scheduler
    /// restart as robots and workers see it. Returns what the first one did.
    pub async fn restart(&mut self, options: ServerOptions) -> anyhow::Result<ServerReport> {
        let report = match self.server.take() {
            Some(server) => server.shutdown().await,
            None => ServerReport::default(),
        };
        // The old endpoint's socket is released when its last connection handle is dropped,
        // which may be a moment after the shutdown returned: wait for the port (bounded).
        let mut attempts = 0;
        let server = loop {
            match launch(
                self.dir.path(),
                self.addr,
                &options,
                Arc::new(TestFlow::new()),
            )
            .await
            {
                Ok(server) => break server,
                Err(error) if attempts < 200 && format!("{error:#}").contains("in use") => {
                    attempts += 1;
                    tokio::time::sleep(Duration::from_millis(25)).await;
                }
                Err(error) => return Err(error),
            }
        };
        anyhow::ensure!(
            server.pin == self.pin,
            "the restarted server has another certificate"
        );
        self.server = Some(server);
        Ok(report)
    }

    /// The running server.
    pub fn server(&self) -> &RunningServer {
        // Present until `shutdown` consumes `self`.
        &self.server.as_ref().expect("server running").server
    }

    /// A client config pinned to this server, for `token`, connecting to `addr` (the server
    /// itself or a proxy in front of it).
    pub fn client_config(&self, addr: SocketAddr, token: &str) -> ClientConfig {
        let mut config = ClientConfig::pinned(addr, self.pin, token);
        config.connect_timeout = fleet::CONNECT_TIMEOUT;
        config
    }

    /// Connects a robot directly.
    pub async fn connect(&self, token: &str) -> anyhow::Result<Client> {
        Ok(Client::connect(self.client_config(self.addr, token)).await?)
    }

    /// Checks the server's side of "exactly once": the ended task `task` had exactly one chunk
    /// generated for each of its rounds `0..rounds`.
    pub async fn assert_generated_once(&self, task: u64, rounds: u64) {
        let snapshot = self
            .server()
            .driver
            .snapshot(kairos_core::scheduler::TaskId(task))
            .await
            .expect("driver running")
            .unwrap_or_else(|| panic!("no record of task {task}"));
        assert!(snapshot.ended, "task {task} has ended");
        let once: std::collections::BTreeMap<u64, u32> = (0..rounds).map(|r| (r, 1)).collect();
        assert_eq!(
            snapshot.generated, once,
            "task {task}: generations per round"
        );
    }

    /// Waits for the server to stop by itself (without being told to) and returns what it did.
    pub async fn stopped(mut self) -> ServerReport {
        match self.server.take() {
            Some(server) => server.server.stopped().await,
            None => ServerReport::default(),
        }
    }

    /// Shuts the server down gracefully and returns what it did.
    pub async fn shutdown(mut self) -> ServerReport {
        match self.server.take() {
            Some(server) => server.shutdown().await,
            None => ServerReport::default(),
        }
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(server) = self.server.as_ref() {
            server.server.begin_shutdown();
        }
    }
}

/// A server on `listen` with its data directory in `dir` (created, or reused as it is).
async fn launch(
    dir: &std::path::Path,
    listen: SocketAddr,
    options: &ServerOptions,
    model: Arc<dyn ActionModel>,
) -> anyhow::Result<LocalServer> {
    let mut config = Config {
        listen,
        data_dir: dir.join("data"),
        ..Config::default()
    };
    config.robots = options
        .robots
        .iter()
        .map(|(name, token)| RobotConfig {
            name: name.clone(),
            token_sha256: hex::encode(hash_token(token)),
        })
        .collect();
    config.plugins = options.plugins.clone();
    (options.tweak)(&mut config);
    let profile = EngineProfile {
        model: model.spec().name.clone(),
        device: "cpu (test flow, microseconds per batch)".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms: 0.05,
            },
            ProfilePoint {
                batch: options.max_batch.max(1),
                latency_ms: 0.1,
            },
        ],
        max_batch: options.max_batch.max(1),
    };
    let instances: Vec<Arc<dyn EngineInstance>> = (0..options.engines)
        .map(|i| {
            Arc::new(LocalEngine::start(
                format!("edge-{i}"),
                model.clone(),
                profile.clone(),
            )) as Arc<dyn EngineInstance>
        })
        .collect();
    // No engine: a scheduler served only by remote workers (`--local-engines 0`).
    let pool = EnginePool::with_spec(model.spec().clone(), instances)?;
    Ok(LocalServer::start(&config, pool, options.policies.clone()).await?)
}

/// One simulated robot's task.
#[derive(Clone, Debug)]
pub struct RobotPlan {
    /// Task id.
    pub task: u64,
    /// Rounds to run.
    pub rounds: u64,
    /// Actions per second the robot executes.
    pub control_hz: f32,
    /// The next request goes out when this many actions of the current chunk are left.
    pub send_ahead: u32,
    /// Horizon policy; `None` = the server default.
    pub horizon: Option<HorizonSelection>,
    /// `state[1]` of every observation (how far [`TestFlow`]'s chunks converge).
    pub state1: f32,
}

impl RobotPlan {
    /// A robot at 200 Hz that sends its next request 3 actions before its chunk runs out and
    /// asks for a static horizon of `h`: short, regular rounds for transport tests.
    pub fn static_horizon(task: u64, rounds: u64, h: u32) -> RobotPlan {
        RobotPlan {
            task,
            rounds,
            control_hz: 200.0,
            send_ahead: 3,
            horizon: Some(HorizonSelection {
                policy: "static".into(),
                params: [("h".to_string(), f64::from(h))].into(),
                samples: 1,
            }),
            state1: 0.0,
        }
    }
}

/// What the robot did in one round, on its own clock (µs).
#[derive(Clone, Debug, PartialEq)]
pub struct RoundLog {
    /// Round id.
    pub round: u64,
    /// When the request was sent (first attempt).
    pub sent_at_us: u64,
    /// When the reply arrived.
    pub received_at_us: u64,
    /// Horizon granted.
    pub horizon: u32,
    /// Policy that chose it.
    pub policy: String,
    /// Times the round was sent.
    pub attempts: u32,
    /// When executing this round's chunk began.
    pub exec_start_us: u64,
    /// Actions of this chunk left when the next request (or the task end) was sent.
    pub remaining_at_next: u32,
    /// When the next request (or the task end) was sent.
    pub next_sent_at_us: u64,
    /// Server timing of the round.
    pub timing: kairos_sdk::protocol::Timing,
}

/// A robot's whole task.
#[derive(Clone, Debug)]
pub struct TaskLog {
    /// Task id.
    pub task: u64,
    /// Rounds, in order.
    pub rounds: Vec<RoundLog>,
    /// The server's record from `EndTask`.
    pub ended: TaskEnded,
    /// The control frequency used.
    pub control_hz: f32,
}

/// An observation of [`TestFlow`]'s shape captured now.
pub fn observation(client: &Client, state1: f32) -> Observation {
    Observation {
        captured_at_us: client.now_us(),
        state: Tensor::from_f32(vec![6], &[0.5, state1, -0.25, 0.0, 0.1, 0.2])
            .unwrap_or_else(|_| unreachable!("6 values for shape [6]")),
        images: Vec::new(),
        instruction: "reach the target".into(),
    }
}

/// Runs every plan as its own robot (one QUIC connection each, the server's token),
/// concurrently, and returns their logs in plan order.
pub async fn run_fleet(server: &TestServer, plans: Vec<RobotPlan>) -> anyhow::Result<Vec<TaskLog>> {
    // One handshake at a time, not `fleet::connect`: each robot's estimate of the server clock
    // comes from its own handshake, and uncontended handshakes keep that estimate within the
    // tolerance the record comparisons (`compare_records`) allow.
    let mut clients = Vec::with_capacity(plans.len());
    for _ in &plans {
        clients.push(server.connect(&server.token).await?);
    }
    let starts = vec![Duration::ZERO; plans.len()];
    let outcomes = fleet::run_from(tokio::time::Instant::now(), &starts, |index| {
        let (client, plan) = (clients[index].clone(), plans[index].clone());
        async move {
            let log = run_task(&client, &plan, None).await;
            client.close().await;
            log
        }
    })
    .await;
    outcomes.into_iter().map(|outcome| outcome?).collect()
}

/// Something to do between rounds (e.g. rebind the client's socket), given the round just done.
pub type Hook = Arc<dyn Fn(&Client, u64) + Send + Sync>;

/// Runs one task with asynchronous inference: the robot executes each chunk at `control_hz`
/// and sends the next request when `send_ahead` actions are left; the next chunk starts when
/// both the reply is in and the current chunk is done.
pub async fn run_task(
    client: &Client,
    plan: &RobotPlan,
    between_rounds: Option<Hook>,
) -> anyhow::Result<TaskLog> {
    let us_per_action = 1e6 / f64::from(plan.control_hz);
    let mut task = client.task(plan.task);
    let mut rounds: Vec<RoundLog> = Vec::new();
    // (start, horizon) of the chunk executing now.
    let mut executing: Option<(u64, u32)> = None;
    let exec_info = |executing: Option<(u64, u32)>, now: u64| {
        executing.map(|(start, horizon)| {
            let done = ((now.saturating_sub(start)) as f64 / us_per_action).floor() as u32;
            LastExecInfo {
                exec_started_at_us: start.min(now),
                actions_remaining: horizon.saturating_sub(done),
                control_hz: plan.control_hz,
                round: None,
                delay: None,
            }
        })
    };
    for round in 0..plan.rounds {
        if let Some((start, horizon)) = executing {
            let send_at =
                start + (f64::from(horizon.saturating_sub(plan.send_ahead)) * us_per_action) as u64;
            sleep_until_us(client, send_at).await;
        }
        let last_exec = exec_info(executing, client.now_us());
        let mut request = RoundRequest::new(observation(client, plan.state1));
        request.last_exec = last_exec;
        request.horizon = plan.horizon.clone();
        request.control_hz = Some(plan.control_hz);
        let reply = task
            .submit(request, &mut NoRefetch)
            .await
            .with_context(|| format!("task {} round {round}", plan.task))?;
        if reply.reply.round != task.next_round() - 1 || reply.reply.task != plan.task {
            bail!(
                "reply for task {} round {} answered task {} round {}",
                plan.task,
                task.next_round() - 1,
                reply.reply.task,
                reply.reply.round
            );
        }
        if let (Some(previous), Some(info)) = (rounds.last_mut(), last_exec) {
            previous.remaining_at_next = info.actions_remaining;
            previous.next_sent_at_us = reply.sent_at_us;
        }
        let previous_end = executing
            .map(|(start, h)| start + (f64::from(h) * us_per_action) as u64)
            .unwrap_or(0);
        let start = reply.received_at_us.max(previous_end);
        sleep_until_us(client, start).await;
        rounds.push(RoundLog {
            round: reply.reply.round,
            sent_at_us: reply.sent_at_us,
            received_at_us: reply.received_at_us,
            horizon: reply.reply.horizon,
            policy: reply.reply.policy.clone(),
            attempts: reply.attempts,
            exec_start_us: start,
            remaining_at_next: 0,
            next_sent_at_us: 0,
            timing: reply.reply.timing,
        });
        executing = Some((start, reply.reply.horizon));
        if let Some(hook) = &between_rounds {
            hook(client, reply.reply.round);
        }
    }
    // Let the last chunk run halfway, then end the task with what is left.
    if let Some((start, horizon)) = executing {
        sleep_until_us(
            client,
            start + (f64::from(horizon / 2) * us_per_action) as u64,
        )
        .await;
    }
    let now = client.now_us();
    let last_exec = exec_info(executing, now);
    if let (Some(last), Some(info)) = (rounds.last_mut(), last_exec) {
        last.remaining_at_next = info.actions_remaining;
        last.next_sent_at_us = now;
    }
    let ended = task
        .end(TaskOutcome::Done, last_exec)
        .await
        .with_context(|| format!("ending task {}", plan.task))?;
    Ok(TaskLog {
        task: plan.task,
        rounds,
        ended,
        control_hz: plan.control_hz,
    })
}

async fn sleep_until_us(client: &Client, at_us: u64) {
    let now = client.now_us();
    if at_us > now {
        tokio::time::sleep(Duration::from_micros(at_us - now)).await;
    }
}

/// How far the server's record of a task is from what the robot did, in µs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RecordError {
    /// Largest amount by which a `G` interval started before its request was sent or ended after
    /// its reply arrived.
    pub generation_outside_us: u64,
    /// Largest difference between a server `E.start` and the robot's chunk start.
    pub exec_start_us: u64,
    /// Largest difference between a server `E.end` and `next_sent + remaining / hz`.
    pub exec_end_us: u64,
}

impl RecordError {
    /// The element-wise maximum.
    pub fn max(self, other: RecordError) -> RecordError {
        RecordError {
            generation_outside_us: self.generation_outside_us.max(other.generation_outside_us),
            exec_start_us: self.exec_start_us.max(other.exec_start_us),
            exec_end_us: self.exec_end_us.max(other.exec_end_us),
        }
    }
}

/// Compares the server's `TaskEnded` record with the robot's log. Structural mismatches (round
/// ids, horizons, counts, missing intervals) are errors; timing differences are measured.
pub fn compare_records(log: &TaskLog) -> anyhow::Result<RecordError> {
    let ended = &log.ended;
    if ended.task != log.task {
        bail!(
            "TaskEnded for task {} in task {}'s log",
            ended.task,
            log.task
        );
    }
    if ended.rounds as usize != log.rounds.len() {
        bail!(
            "task {}: server counts {} rounds, robot did {}",
            log.task,
            ended.rounds,
            log.rounds.len()
        );
    }
    if ended.history.len() != log.rounds.len() {
        bail!(
            "task {}: history has {} rounds, robot did {}",
            log.task,
            ended.history.len(),
            log.rounds.len()
        );
    }
    let us_per_action = 1e6 / f64::from(log.control_hz);
    let mut error = RecordError::default();
    for (server, robot) in ended.history.iter().zip(&log.rounds) {
        if server.round != robot.round {
            bail!(
                "task {}: server round {} vs robot round {}",
                log.task,
                server.round,
                robot.round
            );
        }
        if server.horizon != Some(robot.horizon) {
            bail!(
                "task {} round {}: server horizon {:?}, robot got {}",
                log.task,
                robot.round,
                server.horizon,
                robot.horizon
            );
        }
        let g = server
            .generation
            .with_context(|| format!("task {} round {}: no G", log.task, robot.round))?;
        let e = server
            .execution
            .with_context(|| format!("task {} round {}: no E", log.task, robot.round))?;
        let before = robot.sent_at_us.saturating_sub(g.start_us);
        let after = g.end_us.saturating_sub(robot.received_at_us);
        let expected_end = robot.next_sent_at_us
            + (f64::from(robot.remaining_at_next) * us_per_action).round() as u64;
        error = error.max(RecordError {
            generation_outside_us: before.max(after),
            exec_start_us: e.start_us.abs_diff(robot.exec_start_us),
            exec_end_us: e.end_us.abs_diff(expected_end),
        });
    }
    Ok(error)
}

/// Checks the facts of the server's `TaskEnded` record that hold exactly, whatever the machine's
/// load: they compare durations measured on one clock, or apply one clock mapping both ways, so
/// no timing tolerance is involved (beyond 2 µs of integer rounding).
///
/// - Every `G` fits inside its round's round trip: generation happens after the request left the
///   robot and before the reply reached it, so `|G| ≤ received − sent` (a wrong round's interval,
///   or a generation interval in the wrong unit, breaks it).
/// - The last round's `E` was reported with the task end and is mapped back with that same
///   message's clock mapping: `E.start` is the robot's chunk start exactly, and `E.end`, stamped
///   when the server read the end, is no earlier than `end sent + remaining / hz` (a missing
///   `remaining / control_hz` or a unit slip breaks it).
///
/// [`compare_records`] measures the rest (absolute positions, which move with the clock mapping's
/// error under load) without judging it.
pub fn check_exact_records(log: &TaskLog) -> anyhow::Result<()> {
    const ROUNDING_US: u64 = 2;
    compare_records(log)?;
    let us_per_action = 1e6 / f64::from(log.control_hz);
    for (server, robot) in log.ended.history.iter().zip(&log.rounds) {
        let g = server
            .generation
            .with_context(|| format!("task {} round {}: no G", log.task, robot.round))?;
        let generation = g.end_us.saturating_sub(g.start_us);
        let round_trip = robot.received_at_us.saturating_sub(robot.sent_at_us);
        if generation > round_trip + ROUNDING_US {
            bail!(
                "task {} round {}: |G| = {generation} µs exceeds the robot's round trip of {round_trip} µs",
                log.task,
                robot.round
            );
        }
    }
    let (Some(server), Some(robot)) = (log.ended.history.last(), log.rounds.last()) else {
        bail!("task {}: no rounds", log.task);
    };
    let e = server
        .execution
        .with_context(|| format!("task {}: the last round has no E", log.task))?;
    if e.start_us.abs_diff(robot.exec_start_us) > ROUNDING_US {
        bail!(
            "task {}: last E.start {} µs, the robot started its chunk at {} µs",
            log.task,
            e.start_us,
            robot.exec_start_us
        );
    }
    let earliest_end =
        robot.next_sent_at_us + (f64::from(robot.remaining_at_next) * us_per_action).round() as u64;
    if e.end_us + ROUNDING_US < earliest_end {
        bail!(
            "task {}: last E.end {} µs is before the end was even sent plus the remaining actions ({earliest_end} µs)",
            log.task,
            e.end_us
        );
    }
    Ok(())
}

/// A hand-driven protocol connection: real QUIC and TLS (pinned), but frames written byte by
/// byte by the test, for malformed-input and authentication tests.
pub struct RawConnection {
    /// The connection.
    pub connection: quinn::Connection,
    endpoint: quinn::Endpoint,
}

impl RawConnection {
    /// Connects to `server` without saying `Hello`.
    pub async fn open(server: &TestServer) -> anyhow::Result<RawConnection> {
        let trust = kairos_sdk::tls::ServerTrust::Pinned(server.pin);
        let config = kairos_sdk::transport::client_config(
            &trust,
            &kairos_sdk::transport::TransportTuning::default(),
        )?;
        let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse()?)?;
        endpoint.set_default_client_config(config);
        let connection = endpoint.connect(server.addr, "kairos")?.await?;
        Ok(RawConnection {
            connection,
            endpoint,
        })
    }

    /// Connects and authenticates with `token`; returns the connection and the server's answer
    /// to `Hello` (`Welcome` or `Error`).
    pub async fn hello(
        server: &TestServer,
        token: &str,
    ) -> anyhow::Result<(RawConnection, kairos_sdk::protocol::Message)> {
        use kairos_sdk::protocol::{Hello, Message, PROTOCOL_VERSION};
        let raw = RawConnection::open(server).await?;
        let hello = Message::Hello(Hello {
            protocol: PROTOCOL_VERSION,
            token: token.to_string(),
            client: "raw-test".into(),
        });
        let answer = raw.exchange(&hello.encode(u32::MAX)?, true).await?;
        Ok((raw, answer))
    }

    /// Opens a stream, writes `bytes` (finishing the stream if `finish`) and reads one message.
    pub async fn exchange(
        &self,
        bytes: &[u8],
        finish: bool,
    ) -> anyhow::Result<kairos_sdk::protocol::Message> {
        let (mut send, mut recv) = self.connection.open_bi().await?;
        send.write_all(bytes).await?;
        if finish {
            send.finish()?;
        }
        let limits = kairos_sdk::protocol::Limits::default();
        let message = kairos_sdk::protocol::read_message(&mut recv, &limits)
            .await?
            .context("the server finished the stream without answering")?;
        Ok(message)
    }

    /// Closes the connection.
    pub async fn close(self) {
        self.connection.close(quinn::VarInt::from_u32(0), b"done");
        let _ = tokio::time::timeout(Duration::from_secs(1), self.endpoint.wait_idle()).await;
    }
}

/// Runs one round of robot `client` (task `task`, round id `round` via a fresh task handle) and
/// returns its reply: a check that the server still serves.
pub async fn one_round(
    client: &Client,
    task: u64,
    round: u64,
) -> Result<kairos_sdk::client::RoundReply, kairos_sdk::client::ClientError> {
    let mut handle = client.task_from(task, round);
    handle
        .submit(RoundRequest::new(observation(client, 0.0)), &mut NoRefetch)
        .await
}
