//! `kairos._kairos`: the Rust side of the `kairos-client` Python package.
//!
//! It wraps the Rust SDK ([`kairos_sdk::BlockingClient`], its [`Task`]s and the
//! [`ChunkExecutor`] execution rules) instead of speaking the protocol itself, so a Python robot
//! gets the same QUIC tuning, certificate pinning, reconnect-with-resume and Last Exec Info as a
//! Rust one. The connection runs on the SDK's own tokio runtime; Python threads wait with the GIL
//! released, and asyncio callers get a future resolved from that runtime.
//!
//! The Python-facing API and its documentation are in `kairos/__init__.pyi`.

mod errors;
mod observation;

use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use std::future::Future;

use kairos_sdk::client::{
    ClientConfig, ClientError, Clock, ObservationSource, RoundReply, RoundRequest, Task,
};
use kairos_sdk::protocol::{
    ChunkingSelection, ChunkingStrategy, FetchObservation, HorizonSelection, Observation,
    TaskOutcome, Tensor, Timing,
};
use kairos_sdk::robot::{Alignment, ChunkExecutor};
use kairos_sdk::{BlockingClient, Fingerprint, data_dir};
use numpy::PyArray1;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};

use crate::errors::{ConnectionFailed, InvalidRequest, KairosError, TaskError, client_error};

/// The task a client runs now: the SDK task handle and the execution rules that turn the chunks
/// it receives into the robot's action queue and the Last Exec Info it reports.
struct ActiveTask {
    id: u64,
    /// `None` while a round is in flight (the round owns the handle: one round per task).
    handle: Option<Task>,
    executor: ChunkExecutor,
    horizon: Option<HorizonSelection>,
    /// The chunking strategy sent with every round (`None`: the server's default).
    chunking: Option<ChunkingSelection>,
    /// Called for a fresh observation when the server re-fetches a stale one.
    source: Option<Arc<Py<PyAny>>>,
}

/// A round taken out of its task: the handle and what to send.
struct Round {
    handle: Task,
    request: RoundRequest,
    id: u64,
    source: Refetch,
}

/// Answers the server's `FetchObservation` by calling the task's Python observation source on a
/// blocking thread (the GIL is never taken on the runtime's worker), or with the observation
/// already sent when there is none or it fails.
struct Refetch {
    source: Option<Arc<Py<PyAny>>>,
    clock: Clock,
    task: Shared,
}

impl ObservationSource for Refetch {
    fn fresh_observation(
        &mut self,
        _fetch: &FetchObservation,
    ) -> impl Future<Output = Option<Observation>> + Send {
        let source = self.source.clone();
        let clock = self.clock;
        let task = self.task.clone();
        async move {
            let source = source?;
            let fresh = tokio::task::spawn_blocking(move || {
                Python::attach(|py| {
                    let captured_at_us = clock.now_us();
                    let result = source
                        .call0(py)
                        .and_then(|value| observation::from_python(value.bind(py), captured_at_us));
                    // A failing source must not fail the round: the submitted observation goes
                    // again, and Python reports the error as unraisable (to stderr).
                    result
                        .map_err(|error| error.write_unraisable(py, None))
                        .ok()
                })
            })
            .await
            .ok()??;
            if let Some(active) = lock(&task).as_mut() {
                active.executor.observation_refreshed();
            }
            Some(fresh)
        }
    }
}

type Shared = Arc<Mutex<Option<ActiveTask>>>;

fn lock(shared: &Shared) -> MutexGuard<'_, Option<ActiveTask>> {
    // A panic while holding the lock leaves consistent state (every update is one assignment).
    shared.lock().unwrap_or_else(|poison| poison.into_inner())
}

/// Sends `round` and waits for its reply; the handle comes back either way.
async fn run_round(mut round: Round) -> (Task, u64, Result<RoundReply, ClientError>) {
    let result = round.handle.submit(round.request, &mut round.source).await;
    (round.handle, round.id, result)
}

/// What the last completed round reported, for `Client.last_round`.
#[derive(Clone, Debug)]
struct RoundSummary {
    task: u64,
    round: u64,
    horizon: u32,
    chunk_len: u32,
    policy: String,
    timing: Timing,
    start: Option<u32>,
    delay: Option<u32>,
    chunking: Option<String>,
    attempts: u32,
    refetches: u32,
    latency_us: u64,
}

type LastRound = Arc<Mutex<Option<RoundSummary>>>;

/// Puts the task handle back, applies the reply's chunk to the action queue and records the
/// round's summary.
fn finish_round(
    shared: &Shared,
    last: &LastRound,
    handle: Task,
    round: u64,
    result: Result<RoundReply, ClientError>,
) -> Result<RoundReply, ClientError> {
    if let Ok(done) = &result {
        let summary = RoundSummary {
            task: done.reply.task,
            round: done.reply.round,
            horizon: done.reply.horizon,
            chunk_len: done.reply.chunk_len,
            policy: done.reply.policy.clone(),
            timing: done.reply.timing,
            start: done.reply.start,
            delay: done.reply.delay,
            chunking: done.reply.chunking.clone(),
            attempts: done.attempts,
            refetches: done.refetches,
            latency_us: done.received_at_us.saturating_sub(done.sent_at_us),
        };
        *last.lock().unwrap_or_else(|poison| poison.into_inner()) = Some(summary);
    }
    let mut slot = lock(shared);
    let Some(task) = slot.as_mut().filter(|task| task.id == handle.id()) else {
        // The task was abandoned while the round ran (`end_task` refuses that, but a new client
        // state cannot tell); the reply still goes to the caller.
        return result;
    };
    task.handle = Some(handle);
    match &result {
        Ok(reply) => match reply.reply.actions.to_f32() {
            Ok(values) => {
                let dim = (reply.reply.actions.shape.get(1).copied().unwrap_or(1) as usize).max(1);
                let actions = values.chunks(dim).map(<[f32]>::to_vec).collect();
                task.executor
                    .reply_arrived_from(round, actions, reply.reply.start);
            }
            Err(error) => {
                task.executor.request_failed();
                return Err(ClientError::Protocol(format!("Reply.actions: {error}")));
            }
        },
        Err(_) => task.executor.request_failed(),
    }
    result
}

/// A reply's `[H, D]` `f32` actions as a numpy array that owns the reply's buffer (no copy).
fn actions_array(py: Python<'_>, actions: Tensor) -> PyResult<Bound<'_, PyAny>> {
    let shape: Vec<usize> = actions.shape.iter().map(|&d| d as usize).collect();
    let bytes = PyArray1::from_vec(py, actions.data);
    // The wire is little-endian; "<f4" is right on any host.
    bytes
        .call_method1("view", ("<f4",))?
        .call_method1("reshape", (PyTuple::new(py, shape)?,))
}

fn outcome(text: &str) -> PyResult<TaskOutcome> {
    match text {
        "done" => Ok(TaskOutcome::Done),
        "failed" => Ok(TaskOutcome::Failed),
        other => Err(InvalidRequest::new_err(format!(
            "outcome: expected \"done\" or \"failed\", got {other:?}"
        ))),
    }
}

fn resolve(server: &str) -> PyResult<SocketAddr> {
    let bad = |why: String| ConnectionFailed::new_err(format!("server {server:?}: {why}"));
    server
        .to_socket_addrs()
        .map_err(|e| bad(e.to_string()))?
        .next()
        .ok_or_else(|| bad("resolves to no address".to_owned()))
}

fn seconds(what: &str, value: f64) -> PyResult<Duration> {
    Duration::try_from_secs_f64(value)
        .map_err(|_| InvalidRequest::new_err(format!("{what}: expected seconds ≥ 0, got {value}")))
}

/// A connection to a Kairos server for one robot (see `kairos/__init__.pyi`).
#[pyclass(frozen, module = "kairos")]
struct Client {
    inner: BlockingClient,
    task: Shared,
    last_round: LastRound,
}

#[pymethods]
impl Client {
    #[new]
    #[pyo3(signature = (server, fingerprint, token, *, connect_timeout = 5.0, round_timeout = None, reconnect_attempts = 8))]
    fn new(
        py: Python<'_>,
        server: &str,
        fingerprint: &str,
        token: String,
        connect_timeout: f64,
        round_timeout: Option<f64>,
        reconnect_attempts: u32,
    ) -> PyResult<Client> {
        let pin: Fingerprint = fingerprint
            .parse()
            .map_err(|e| InvalidRequest::new_err(format!("fingerprint: {e}")))?;
        let mut config = ClientConfig::pinned(resolve(server)?, pin, token);
        config.client_name = concat!("kairos-client-python/", env!("CARGO_PKG_VERSION")).into();
        config.connect_timeout = seconds("connect_timeout", connect_timeout)?;
        config.round_timeout = round_timeout
            .map(|t| seconds("round_timeout", t))
            .transpose()?;
        config.reconnect.max_attempts = reconnect_attempts;
        let inner = py
            .detach(|| BlockingClient::connect(config))
            .map_err(|e| client_error(py, e))?;
        Ok(Client {
            inner,
            task: Arc::new(Mutex::new(None)),
            last_round: Arc::new(Mutex::new(None)),
        })
    }

    /// Connects with the pin and a robot token that a local `kairos serve` wrote to its data
    /// directory.
    #[staticmethod]
    #[pyo3(signature = (path = PathBuf::from(data_dir::DEFAULT_DATA_DIR), server = "127.0.0.1:4433", *, robot = data_dir::DEFAULT_ROBOT, connect_timeout = 5.0, round_timeout = None, reconnect_attempts = 8))]
    fn from_data_dir(
        py: Python<'_>,
        path: PathBuf,
        server: &str,
        robot: &str,
        connect_timeout: f64,
        round_timeout: Option<f64>,
        reconnect_attempts: u32,
    ) -> PyResult<Client> {
        let config_error = |e: data_dir::CredentialsError| KairosError::new_err(e.to_string());
        let pin = data_dir::read_pin(&path).map_err(config_error)?;
        let token = data_dir::read_token(&path, robot).map_err(config_error)?;
        Client::new(
            py,
            server,
            &pin.to_string(),
            token,
            connect_timeout,
            round_timeout,
            reconnect_attempts,
        )
    }

    /// The served model: name, chunk_len, action_dim, state_dim, steps, max_images.
    #[getter]
    fn model<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let welcome = py
            .detach(|| self.inner.welcome())
            .ok_or_else(|| ConnectionFailed::new_err("not connected"))?;
        let model = &welcome.model;
        let dict = PyDict::new(py);
        dict.set_item("name", &model.name)?;
        dict.set_item("chunk_len", model.chunk_len)?;
        dict.set_item("action_dim", model.action_dim)?;
        dict.set_item("state_dim", model.state_dim)?;
        dict.set_item("steps", model.steps)?;
        dict.set_item("max_images", model.max_images)?;
        dict.set_item("robot", &welcome.robot)?;
        dict.set_item("server", &welcome.server)?;
        Ok(dict)
    }

    /// Counters: connects, zero_rtt_accepted, resent_rounds, refetches.
    #[getter]
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let stats = self.inner.client().stats();
        let dict = PyDict::new(py);
        dict.set_item("connects", stats.connects)?;
        dict.set_item("zero_rtt_accepted", stats.zero_rtt_accepted)?;
        dict.set_item("resent_rounds", stats.resent_rounds)?;
        dict.set_item("refetches", stats.refetches)?;
        Ok(dict)
    }

    /// The last completed round: task, round, horizon, chunk_len, policy, the server's timing
    /// (queue_us, refetch_us, inference_us, total_us, batch_size), the chunking facts (start:
    /// the index the server predicted for the arrival, delay: its predicted d, chunking: the
    /// strategy applied; None from a server that sends none), attempts, refetches and
    /// latency_us (client clock, from sending to the reply). None before the first.
    #[getter]
    fn last_round<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let Some(last) = self
            .last_round
            .lock()
            .unwrap_or_else(|poison| poison.into_inner())
            .clone()
        else {
            return Ok(None);
        };
        let dict = PyDict::new(py);
        dict.set_item("task", last.task)?;
        dict.set_item("round", last.round)?;
        dict.set_item("horizon", last.horizon)?;
        dict.set_item("chunk_len", last.chunk_len)?;
        dict.set_item("policy", last.policy)?;
        dict.set_item("queue_us", last.timing.queue_us)?;
        dict.set_item("refetch_us", last.timing.refetch_us)?;
        dict.set_item("inference_us", last.timing.inference_us)?;
        dict.set_item("total_us", last.timing.total_us)?;
        dict.set_item("batch_size", last.timing.batch_size)?;
        dict.set_item("start", last.start)?;
        dict.set_item("delay", last.delay)?;
        dict.set_item("chunking", last.chunking)?;
        dict.set_item("attempts", last.attempts)?;
        dict.set_item("refetches", last.refetches)?;
        dict.set_item("latency_us", last.latency_us)?;
        Ok(Some(dict))
    }

    /// Starts a task; returns its id. `chunking` names the server's chunking strategy for its
    /// rounds (`skip`, `from_start`, `arrival_state`, `rtc`, `rtc_vjp`, `inpaint`, `ensemble`;
    /// None: the server's default); `alignment` is where an arriving chunk starts executing:
    /// `executed` (the actions executed since its observation, counted here) or `server_start`
    /// (the reply's start index).
    #[pyo3(signature = (task_id = None, *, control_hz = 30.0, trigger = 0.5, horizon = None, horizon_params = None, observation_source = None, chunking = None, alignment = "executed"))]
    #[allow(clippy::too_many_arguments)]
    fn start_task(
        &self,
        task_id: Option<u64>,
        control_hz: f32,
        trigger: f32,
        horizon: Option<String>,
        horizon_params: Option<std::collections::BTreeMap<String, f64>>,
        observation_source: Option<Py<PyAny>>,
        chunking: Option<String>,
        alignment: &str,
    ) -> PyResult<u64> {
        let chunking = chunking
            .map(|name| {
                ChunkingStrategy::from_name(&name)
                    .map(ChunkingSelection::new)
                    .ok_or_else(|| {
                        let names: Vec<&str> =
                            ChunkingStrategy::ALL.iter().map(|s| s.as_str()).collect();
                        InvalidRequest::new_err(format!(
                            "chunking: `{name}` is not one of {}",
                            names.join(", ")
                        ))
                    })
            })
            .transpose()?;
        let alignment = match alignment {
            "executed" => Alignment::Executed,
            "server_start" => Alignment::ServerStart,
            other => {
                return Err(InvalidRequest::new_err(format!(
                    "alignment: `{other}` is not `executed` or `server_start`"
                )));
            }
        };
        if !(control_hz.is_finite() && control_hz > 0.0) {
            return Err(InvalidRequest::new_err(format!(
                "control_hz: expected a positive number, got {control_hz}"
            )));
        }
        if !(0.0..=1.0).contains(&trigger) {
            return Err(InvalidRequest::new_err(format!(
                "trigger: expected a fraction in [0, 1], got {trigger}"
            )));
        }
        let horizon = match (horizon, horizon_params) {
            (None, None) => None,
            (policy, params) => Some(HorizonSelection {
                policy: policy.unwrap_or_else(|| "threshold".to_owned()),
                params: params.unwrap_or_default(),
                samples: 1,
            }),
        };
        let mut slot = lock(&self.task);
        if let Some(task) = slot.as_ref() {
            return Err(TaskError::new_err(format!(
                "task {} is running; end_task() first",
                task.id
            )));
        }
        // Task ids are the robot's to choose; a random one cannot collide with an earlier run's.
        let id = task_id.unwrap_or_else(|| rand::random::<u64>() >> 12);
        *slot = Some(ActiveTask {
            id,
            handle: Some(self.inner.client().task(id)),
            executor: ChunkExecutor::new(control_hz, trigger).with_alignment(alignment),
            horizon,
            chunking,
            source: observation_source.map(Arc::new),
        });
        Ok(id)
    }

    /// The running task's id, or None.
    #[getter]
    fn task_id(&self) -> Option<u64> {
        lock(&self.task).as_ref().map(|task| task.id)
    }

    /// Runs one round: sends `observation` and returns the chunk's actions, `[H, action_dim]`
    /// float32. Blocks without holding the GIL.
    fn infer<'py>(
        &self,
        py: Python<'py>,
        observation: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let round = self.begin_round(observation)?;
        let handle = self.inner.handle();
        let result = py.detach(|| {
            let (task, id, result) = handle.block_on(run_round(round));
            finish_round(&self.task, &self.last_round, task, id, result)
        });
        match result {
            Ok(reply) => actions_array(py, reply.reply.actions),
            Err(error) => Err(client_error(py, error)),
        }
    }

    /// `infer` for asyncio: returns an awaitable resolved from the client's runtime.
    fn infer_async<'py>(
        &self,
        py: Python<'py>,
        observation: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let event_loop = py.import("asyncio")?.call_method0("get_running_loop")?;
        let future = event_loop.call_method0("create_future")?;
        let round = self.begin_round(observation)?;
        let shared = self.task.clone();
        let last = self.last_round.clone();
        let event_loop = event_loop.unbind();
        let target = future.clone().unbind();
        let handle = self.inner.handle().clone();
        self.inner.handle().spawn(async move {
            let (task, id, result) = run_round(round).await;
            let result = finish_round(&shared, &last, task, id, result);
            // Taking the GIL can wait for Python: not on the runtime's worker, which drives QUIC.
            handle.spawn_blocking(move || {
                Python::attach(|py| {
                    let (ok, value) = match result {
                        Ok(reply) => match actions_array(py, reply.reply.actions) {
                            Ok(array) => (true, array.unbind()),
                            Err(error) => (false, error.into_value(py).into_any()),
                        },
                        Err(error) => (false, client_error(py, error).into_value(py).into_any()),
                    };
                    let settle = py
                        .import("kairos._kairos")
                        .and_then(|module| module.getattr("_settle_future"));
                    let delivered = settle.and_then(|settle| {
                        event_loop.call_method1(
                            py,
                            "call_soon_threadsafe",
                            (settle, target, ok, value),
                        )
                    });
                    // The loop was closed before the round ended: nobody is waiting.
                    drop(delivered);
                });
            });
        });
        Ok(future)
    }

    /// Whether the next round is due: none in flight, and the running chunk has reached the
    /// trigger fraction or run out (LeRobot's `chunk_size_threshold`).
    fn wants_request(&self) -> bool {
        lock(&self.task)
            .as_ref()
            .is_none_or(|task| task.executor.wants_request())
    }

    /// Whether a round is in flight.
    #[getter]
    fn in_flight(&self) -> bool {
        lock(&self.task)
            .as_ref()
            .is_some_and(|task| task.handle.is_none())
    }

    /// Actions queued for execution.
    #[getter]
    fn queue_size(&self) -> usize {
        lock(&self.task)
            .as_ref()
            .map_or(0, |task| task.executor.remaining())
    }

    /// The next action to execute now, `[action_dim]` float32, or None when the queue is empty.
    /// Taking it records its execution: that is what the next round's Last Exec Info reports.
    fn next_action<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f32>>> {
        let now = self.inner.now_us();
        let mut slot = lock(&self.task);
        let step = slot.as_mut()?.executor.next_action(now)?;
        Some(PyArray1::from_slice(py, step.action))
    }

    /// Ends the running task and returns the server's record of it.
    #[pyo3(signature = (outcome = "done"))]
    fn end_task<'py>(&self, py: Python<'py>, outcome: &str) -> PyResult<Bound<'py, PyDict>> {
        let outcome = self::outcome(outcome)?;
        let (handle, last_exec) = {
            let mut slot = lock(&self.task);
            let Some(task) = slot.as_mut() else {
                return Err(TaskError::new_err("no task is running"));
            };
            let Some(handle) = task.handle.take() else {
                return Err(TaskError::new_err(format!(
                    "task {} has a round in flight; await it first",
                    task.id
                )));
            };
            let last_exec = task.executor.last_exec(self.inner.now_us());
            *slot = None;
            (handle, last_exec)
        };
        let runtime = self.inner.handle();
        let ended = py
            .detach(|| runtime.block_on(handle.end(outcome, last_exec)))
            .map_err(|e| client_error(py, e))?;
        let dict = PyDict::new(py);
        dict.set_item("task", ended.task)?;
        dict.set_item("rounds", ended.rounds)?;
        dict.set_item("wait_us", ended.wait_us)?;
        dict.set_item("attained_service_us", ended.attained_service_us)?;
        Ok(dict)
    }

    /// Microseconds on the client clock (the clock of every timestamp sent to the server).
    fn now_us(&self) -> u64 {
        self.inner.now_us()
    }

    /// Closes the connection.
    fn close(&self, py: Python<'_>) {
        let runtime = self.inner.handle();
        let client = self.inner.client();
        py.detach(|| runtime.block_on(client.close()));
    }

    fn __enter__(slf: Py<Client>) -> Py<Client> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, PyTuple>) {
        self.close(py);
    }

    fn __repr__(&self) -> String {
        format!("{:?}", self.inner.client())
    }
}

impl Client {
    /// Takes the running task's handle (starting a task with the defaults if none runs) and
    /// builds the round's request, Last Exec Info included.
    fn begin_round(&self, observation: &Bound<'_, PyAny>) -> PyResult<Round> {
        let captured_at_us = self.inner.now_us();
        let observation = observation::from_python(observation, captured_at_us)?;
        if lock(&self.task).is_none() {
            self.start_task(None, 30.0, 0.5, None, None, None, None, "executed")?;
        }
        let mut slot = lock(&self.task);
        let Some(task) = slot.as_mut() else {
            return Err(TaskError::new_err("no task is running"));
        };
        let Some(handle) = task.handle.take() else {
            return Err(TaskError::new_err(format!(
                "task {} has a round in flight; one round per task at a time",
                task.id
            )));
        };
        let id = handle.next_round();
        let last_exec = task.executor.request_sent(id, self.inner.now_us());
        Ok(Round {
            handle,
            request: RoundRequest {
                observation,
                last_exec,
                horizon: task.horizon.clone(),
                remaining: None,
                // The server accounts the first chunk's execution at this rate (no last_exec yet).
                control_hz: Some(task.executor.control_hz()),
                seed: None,
                chunking: task.chunking.clone(),
            },
            id,
            source: Refetch {
                source: task.source.clone(),
                clock: self.inner.client().clock(),
                task: self.task.clone(),
            },
        })
    }
}

/// Settles an asyncio future from the loop's thread, unless it was cancelled meanwhile.
#[pyfunction]
fn _settle_future(future: &Bound<'_, PyAny>, ok: bool, value: &Bound<'_, PyAny>) -> PyResult<()> {
    if future.call_method0("done")?.is_truthy()? {
        return Ok(());
    }
    let method = if ok { "set_result" } else { "set_exception" };
    future.call_method1(method, (value,))?;
    Ok(())
}

/// The extension module.
#[pymodule]
fn _kairos(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Client>()?;
    m.add_function(wrap_pyfunction!(_settle_future, m)?)?;
    errors::register(m)?;
    Ok(())
}
