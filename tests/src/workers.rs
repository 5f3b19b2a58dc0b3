//! Remote workers for tests: a well-behaved one ([`spawn_worker`], the real `kairos worker`
//! library serving [`TestFlow`]) and a hand-driven one ([`RawWorker`]: real QUIC and TLS with the
//! worker ALPN, but every message written by the test), to play a worker that lies, stalls or
//! answers nonsense.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use kairos_engine::{ActionModel, EngineProfile, ProfilePoint};
use kairos_sdk::protocol::worker::{
    Chunks, Heartbeat, ProfilePointWire, ProfileWire, Register, RunBatch, WORKER_MAX_FRAME,
    WORKER_PROTOCOL_VERSION, WorkerMessage, WorkerTier,
};
use kairos_sdk::protocol::{Limits, read_frame, write_body};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, worker_client_config};
use kairos_server::data_dir::DataDir;
use kairos_server::metrics::Metrics;
use kairos_server::pool::{EngineInstance, LocalEngine};
use kairos_server::worker::wire::model_info;
use kairos_server::worker::{WorkerError, WorkerOptions, WorkerReport, run};
use quinn::{RecvStream, SendStream, VarInt};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::harness::TestServer;
use crate::model::TestFlow;

/// The worker token of `server` (from its data directory).
pub fn worker_token(server: &TestServer) -> anyhow::Result<String> {
    Ok(DataDir::new(server.dir.path().join("data")).read_worker_token()?)
}

/// A [`TestFlow`] engine on its own thread, as `kairos worker` runs one, named `name`.
pub fn test_flow_engine(name: &str) -> Arc<dyn EngineInstance> {
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

/// A worker running in this process: send on the sender to stop it (it drains), then await
/// its report.
pub type RunningWorker = (
    oneshot::Sender<()>,
    JoinHandle<Result<WorkerReport, WorkerError>>,
);

/// A well-behaved edge worker named `id` serving [`TestFlow`] for `server`, until the sender is
/// used (then it drains and returns its report).
pub fn spawn_worker(server: &TestServer, id: &str) -> anyhow::Result<RunningWorker> {
    let options = WorkerOptions {
        server: server.addr.to_string(),
        trust: ServerTrust::Pinned(server.pin),
        token: worker_token(server)?,
        worker_id: id.to_owned(),
        tier: WorkerTier::Edge,
        max_batch: 2,
        metrics: Metrics::for_worker(),
    };
    let (stop, stopped) = oneshot::channel::<()>();
    let task = tokio::spawn(run(options, test_flow_engine(id), async {
        let _ = stopped.await;
    }));
    Ok((stop, task))
}

/// A `Register` for [`TestFlow`]'s shapes with the worker token of `server`, as worker `id`,
/// edge, with a one-point profile of `latency_ms` at batch 1.
pub fn register_message(
    server: &TestServer,
    id: &str,
    latency_ms: f64,
) -> anyhow::Result<Register> {
    let model = model_info(TestFlow::new().spec());
    Ok(Register {
        protocol: WORKER_PROTOCOL_VERSION,
        token: worker_token(server)?,
        worker_id: id.to_owned(),
        profile: ProfileWire {
            model: model.name.clone(),
            device: "a hand-driven test worker".into(),
            points: vec![ProfilePointWire {
                batch: 1,
                latency_ms,
            }],
            max_batch: 1,
        },
        model,
        max_batch: 1,
        tier: WorkerTier::Edge,
    })
}

/// A worker connection driven by hand: it registers with any `Register`, heartbeats on its own,
/// and hands the test every batch the scheduler sends, to answer (or not) as the test likes.
pub struct RawWorker {
    /// The connection.
    pub connection: quinn::Connection,
    endpoint: quinn::Endpoint,
    heartbeat: Option<JoinHandle<()>>,
}

/// A batch the scheduler sent to a [`RawWorker`], with the stream to answer it on.
pub struct RawBatch {
    /// What the scheduler asked.
    pub run: RunBatch,
    send: SendStream,
    _recv: RecvStream,
}

impl RawBatch {
    /// Sends `chunks` as the batch's answer and finishes the stream.
    pub async fn answer(mut self, chunks: &Chunks) -> anyhow::Result<()> {
        write_body(&mut self.send, chunks, WORKER_MAX_FRAME).await?;
        self.send.finish()?;
        // Wait until the scheduler has read it (or gave up on the stream).
        let _ = tokio::time::timeout(Duration::from_secs(5), self.send.stopped()).await;
        Ok(())
    }
}

impl RawWorker {
    /// Dials `server` with the worker ALPN and sends `register`. Returns the worker and the
    /// scheduler's answer (`Registered` or `Refused`). Once registered, it heartbeats every
    /// `heartbeat_ms` the scheduler asked for.
    pub async fn register(
        server: &TestServer,
        register: &Register,
    ) -> anyhow::Result<(RawWorker, WorkerMessage)> {
        let config = worker_client_config(
            &ServerTrust::Pinned(server.pin),
            &TransportTuning::default(),
        )?;
        let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse()?)?;
        endpoint.set_default_client_config(config);
        let connection = endpoint.connect(server.addr, "kairos")?.await?;
        let (mut send, mut recv) = connection.open_bi().await?;
        write_body(&mut send, register, WORKER_MAX_FRAME).await?;
        let frame = read_frame(&mut recv, &Limits::default())
            .await?
            .context("the scheduler finished the registration stream without answering")?;
        let answer = WorkerMessage::decode(&frame)?;
        let heartbeat = match &answer {
            WorkerMessage::Registered(registered) => {
                let period = Duration::from_millis(u64::from(registered.heartbeat_ms.max(1)));
                Some(tokio::spawn(async move {
                    let mut ticker = tokio::time::interval(period);
                    let mut batches = 0;
                    loop {
                        ticker.tick().await;
                        let beat = Heartbeat { load: 0, batches };
                        if write_body(&mut send, &beat, WORKER_MAX_FRAME)
                            .await
                            .is_err()
                        {
                            return;
                        }
                        batches += 1;
                    }
                }))
            }
            _ => None,
        };
        Ok((
            RawWorker {
                connection,
                endpoint,
                heartbeat,
            },
            answer,
        ))
    }

    /// The next batch the scheduler sends.
    pub async fn next_batch(&self) -> anyhow::Result<RawBatch> {
        let (send, mut recv) = self.connection.accept_bi().await?;
        let limits = Limits {
            max_frame: WORKER_MAX_FRAME,
            ..Limits::default()
        };
        let frame = read_frame(&mut recv, &limits)
            .await?
            .context("the batch stream ended before RunBatch")?;
        match WorkerMessage::decode(&frame)? {
            WorkerMessage::RunBatch(run) => Ok(RawBatch {
                run,
                send,
                _recv: recv,
            }),
            other => bail!("expected RunBatch, got {}", other.kind()),
        }
    }

    /// Waits until the scheduler closes the connection; its close code and reason.
    pub async fn closed(&self) -> (u64, String) {
        match self.connection.closed().await {
            quinn::ConnectionError::ApplicationClosed(close) => (
                close.error_code.into_inner(),
                String::from_utf8_lossy(&close.reason).into_owned(),
            ),
            other => (u64::MAX, other.to_string()),
        }
    }

    /// Closes the connection.
    pub async fn close(mut self) {
        if let Some(heartbeat) = self.heartbeat.take() {
            heartbeat.abort();
        }
        self.connection.close(VarInt::from_u32(0), b"done");
        let _ = tokio::time::timeout(Duration::from_secs(1), self.endpoint.wait_idle()).await;
    }
}

impl Drop for RawWorker {
    fn drop(&mut self) {
        if let Some(heartbeat) = self.heartbeat.take() {
            heartbeat.abort();
        }
    }
}
