//! A synchronous client for robot loops that are not async.
//!
//! [`BlockingClient`] owns a small tokio runtime (one worker thread) on which the QUIC connection
//! keeps running between calls, so keep-alives, ACKs and migration work while the robot executes;
//! each call blocks the calling thread until its answer. Do not call it from inside an async
//! context (tokio refuses to block a runtime thread); use [`Client`] there.

use std::net::UdpSocket;

use tokio::runtime::Runtime;

use crate::client::{
    Client, ClientConfig, ClientError, ObservationSource, RoundReply, RoundRequest, Task,
};
use crate::protocol::{LastExecInfo, TaskEnded, TaskOutcome, Welcome};

/// A [`Client`] driven by its own runtime, with blocking methods.
pub struct BlockingClient {
    // Declared before `runtime` so the connection is closed while the runtime still runs.
    client: Client,
    runtime: Runtime,
}

impl std::fmt::Debug for BlockingClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlockingClient")
            .field("client", &self.client)
            .finish_non_exhaustive()
    }
}

impl BlockingClient {
    /// Connects like [`Client::connect`], blocking until `Welcome`.
    pub fn connect(config: ClientConfig) -> Result<BlockingClient, ClientError> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("kairos-client")
            .enable_all()
            .build()
            .map_err(ClientError::Runtime)?;
        let client = runtime.block_on(Client::connect(config))?;
        Ok(BlockingClient { client, runtime })
    }

    /// Microseconds on the client clock (see [`Client::now_us`]).
    pub fn now_us(&self) -> u64 {
        self.client.now_us()
    }

    /// The current connection's `Welcome`.
    pub fn welcome(&self) -> Option<std::sync::Arc<Welcome>> {
        self.runtime.block_on(self.client.welcome())
    }

    /// Moves the connection to a new local socket (see [`Client::rebind`]).
    pub fn rebind(&self, socket: UdpSocket) -> std::io::Result<()> {
        let _guard = self.runtime.enter();
        self.client.rebind(socket)
    }

    /// A handle for task `task`, starting at round 0.
    pub fn task(&self, task: u64) -> BlockingTask<'_> {
        BlockingTask {
            runtime: &self.runtime,
            task: self.client.task(task),
        }
    }

    /// The runtime the connection runs on, for callers that drive the async [`Client`] from
    /// threads of their own (e.g. a bridge to another event loop) without blocking on it.
    pub fn handle(&self) -> &tokio::runtime::Handle {
        self.runtime.handle()
    }

    /// The async client underneath.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// Closes the connection.
    pub fn close(self) {
        self.runtime.block_on(self.client.close());
    }
}

/// A task of a [`BlockingClient`].
#[derive(Debug)]
pub struct BlockingTask<'a> {
    runtime: &'a Runtime,
    task: Task,
}

impl BlockingTask<'_> {
    /// The task id.
    pub fn id(&self) -> u64 {
        self.task.id()
    }

    /// The id the next round will get.
    pub fn next_round(&self) -> u64 {
        self.task.next_round()
    }

    /// Runs one round (see [`Task::submit`]), blocking until its reply.
    pub fn submit(
        &mut self,
        request: RoundRequest,
        source: &mut impl ObservationSource,
    ) -> Result<RoundReply, ClientError> {
        self.runtime.block_on(self.task.submit(request, source))
    }

    /// Ends the task (see [`Task::end`]).
    pub fn end(
        self,
        outcome: TaskOutcome,
        last_exec: Option<LastExecInfo>,
    ) -> Result<TaskEnded, ClientError> {
        self.runtime.block_on(self.task.end(outcome, last_exec))
    }
}
