//! `kairos.toml`: the server's configuration file.
//!
//! Every field has a default, so `kairos serve` with no file works: it listens on
//! `127.0.0.1:4433`, keeps its state in `./kairos-data`, generates a self-signed certificate and
//! a token for a robot named `default` on first start, and serves the engine crate's built-in
//! model. Unknown keys are errors (a typo must not silently fall back to a default); every error
//! names the file and the offending key. Relative paths inside the file are resolved against the
//! directory that contains it. See `docs/SERVER.md` for a full example.

mod chunking;
mod overrides;

pub use chunking::ChunkingSection;
pub use overrides::Overrides;

use std::collections::{BTreeMap, HashSet};
use std::fs;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use kairos_engine::{DeviceKind, EngineError, EngineOptions, Kernels, Precision};
use kairos_sdk::protocol::Limits;
use serde::{Deserialize, Serialize};

use crate::credentials::parse_token_hash;
use kairos_core::scheduler::registry::PolicySpec;
use kairos_core::scheduler::{SchedulerConfig, Tier};

/// Default listen address: loopback only, so an unconfigured server is not reachable from the
/// network.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:4433";

/// Default data directory, relative to the working directory. A fixed relative path (rather than
/// an XDG directory) keeps `kairos serve` and `kairos robot` started from the same directory in
/// agreement without any configuration, and makes the state easy to find and delete. Defined
/// with the robot's side of the files, so server, robots and workers share one name.
pub use kairos_sdk::data_dir::DEFAULT_DATA_DIR;

/// Name of the robot whose token is generated when no robot is configured.
pub const DEFAULT_ROBOT: &str = kairos_sdk::data_dir::DEFAULT_ROBOT;

/// Everything that can be wrong with a configuration.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read or written.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is not valid TOML or has unknown/mistyped keys. The message names the key and
    /// the line.
    #[error("{}: {message}", .path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// What the TOML parser said (with line, column and key).
        message: String,
    },
    /// A key parsed but its value is not acceptable.
    #[error("{}: `{key}`: {reason}", .path.display())]
    Invalid {
        /// The file (or `<defaults>`).
        path: PathBuf,
        /// Dotted key, e.g. `engine[0].instances`.
        key: String,
        /// What is wrong.
        reason: String,
    },
}

/// The whole `kairos.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// UDP address to listen on.
    pub listen: SocketAddr,
    /// Where the certificate, key, fingerprint and generated tokens live.
    pub data_dir: PathBuf,
    /// Certificate and key files; absent = a self-signed certificate in the data dir.
    pub tls: TlsConfig,
    /// Robots allowed to connect, with their token hashes. Empty = one generated `default` robot.
    #[serde(rename = "robot")]
    pub robots: Vec<RobotConfig>,
    /// Engine instances. Empty = one edge instance of the built-in model.
    #[serde(rename = "engine")]
    pub engines: Vec<EngineConfig>,
    /// The scheduler.
    pub scheduler: SchedulerSection,
    /// The horizon policy used when a request names none, and as the fallback when one fails.
    pub horizon: HorizonSection,
    /// The chunking strategy used when a round names none, and real-time chunking's settings.
    pub chunking: ChunkingSection,
    /// Size limits on every message field (the protocol's `Limits`, sent to clients).
    #[serde(deserialize_with = "strict_limits")]
    pub limits: Limits,
    /// Connection limits.
    pub connections: ConnectionsConfig,
    /// Policy plugins (WebAssembly components) to load, each under a name that robots
    /// (horizon) or `[scheduler] policy` (priority) select it by.
    #[serde(rename = "plugin")]
    pub plugins: Vec<PluginConfig>,
    /// The openpi-compatible websocket endpoint (off unless `listen` is set).
    pub openpi: OpenpiConfig,
    /// Remote engine workers (`kairos worker`, ALPN `kairos-worker/1`).
    pub workers: WorkersConfig,
    /// The Prometheus `/metrics` and `/ready` endpoint (off unless `listen` is set).
    pub metrics: MetricsConfig,
}

/// `[workers]`: how the scheduler treats remote engine workers (docs/SERVER.md, "Remote
/// workers").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WorkersConfig {
    /// Whether workers may register at all (they also need the data directory's worker token).
    pub enabled: bool,
    /// How often a worker sends `Heartbeat`, ms; a worker silent for three of them is removed.
    pub heartbeat_ms: u32,
    /// A batch sent to a worker must be answered within `batch_deadline_factor` times its
    /// expected time (profile latency plus round trip) and at least `min_batch_deadline_ms`;
    /// after that the worker is removed and the batch runs again elsewhere.
    pub batch_deadline_factor: f64,
    /// See `batch_deadline_factor`.
    pub min_batch_deadline_ms: u32,
    /// The longest a batch sent to a worker may take, whatever the worker declared in its
    /// profile: the deadline is capped here.
    pub max_batch_deadline_ms: u32,
    /// Dispatches a round may get in all (the first included) before a lost batch fails it
    /// with a retryable error instead of running it again.
    pub max_attempts: u32,
    /// A round lost with a worker more than this long after it arrived is failed with a
    /// retryable error instead of being run again: its robot has waited too long already.
    pub redispatch_within_ms: u32,
    /// A worker that registers with tier `auto` is cloud when its measured round trip is at
    /// least this many ms and edge below it; it is re-classified as the moving average moves
    /// (25 % hysteresis around the threshold, `worker::remote::tier_from_rtt`).
    pub cloud_rtt_ms: u32,
    /// A worker removed for an unusable answer (NaN actions, wrong result count, oversized
    /// error text) is refused registration under the same `worker_id` from the same address
    /// for this long, so that the retries of the batch it spoiled go to other workers
    /// (`worker::readmission`); at least `redispatch_within_ms` keeps it from any round it
    /// spoiled. 0: readmitted at once.
    pub readmit_after_invalid_ms: u32,
}

impl Default for WorkersConfig {
    fn default() -> Self {
        WorkersConfig {
            enabled: true,
            heartbeat_ms: 500,
            batch_deadline_factor: 4.0,
            min_batch_deadline_ms: 2_000,
            max_batch_deadline_ms: 60_000,
            max_attempts: 3,
            redispatch_within_ms: 10_000,
            cloud_rtt_ms: 20,
            readmit_after_invalid_ms: 30_000,
        }
    }
}

impl WorkersConfig {
    /// The heartbeat period.
    pub fn heartbeat(&self) -> Duration {
        Duration::from_millis(u64::from(self.heartbeat_ms))
    }

    /// A worker silent this long is removed: about three heartbeats.
    pub fn idle_timeout(&self) -> Duration {
        self.heartbeat() * 3 + self.heartbeat() / 2
    }

    /// The deadline of a batch expected to take `expected`: `batch_deadline_factor` times it,
    /// at least `min_batch_deadline_ms` and at most `max_batch_deadline_ms`. `expected` comes
    /// from a worker's profile, so nothing here can overflow or panic, whatever it is.
    pub fn batch_deadline(&self, expected: Duration) -> Duration {
        let factor = self.batch_deadline_factor.max(1.0);
        let scaled =
            Duration::try_from_secs_f64(expected.as_secs_f64() * factor).unwrap_or(Duration::MAX);
        let min = Duration::from_millis(u64::from(self.min_batch_deadline_ms));
        let max = Duration::from_millis(u64::from(self.max_batch_deadline_ms));
        scaled.max(min).min(max.max(min))
    }

    /// The round trip from which an `auto` worker is cloud.
    pub fn cloud_rtt(&self) -> Duration {
        Duration::from_millis(u64::from(self.cloud_rtt_ms))
    }

    /// The re-dispatch window.
    pub fn redispatch_within(&self) -> Duration {
        Duration::from_millis(u64::from(self.redispatch_within_ms))
    }

    /// How long a worker removed for an unusable answer waits before it may register again.
    pub fn readmit_after_invalid(&self) -> Duration {
        Duration::from_millis(u64::from(self.readmit_after_invalid_ms))
    }
}

impl Default for Config {
    fn default() -> Self {
        Config {
            listen: DEFAULT_LISTEN
                .parse()
                .unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 4433))),
            data_dir: PathBuf::from(DEFAULT_DATA_DIR),
            tls: TlsConfig::default(),
            robots: Vec::new(),
            engines: Vec::new(),
            scheduler: SchedulerSection::default(),
            horizon: HorizonSection::default(),
            chunking: ChunkingSection::default(),
            limits: Limits::default(),
            connections: ConnectionsConfig::default(),
            plugins: Vec::new(),
            openpi: OpenpiConfig::default(),
            workers: WorkersConfig::default(),
            metrics: MetricsConfig::default(),
        }
    }
}

/// `[metrics]`: plain HTTP on a TCP port of its own serving `GET /metrics` (Prometheus,
/// OpenMetrics text) and `GET /ready` (200 once the server serves, 503 while it starts or
/// drains); docs/SERVER.md, "Metrics and readiness".
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsConfig {
    /// TCP address of the endpoint; absent = no endpoint.
    pub listen: Option<SocketAddr>,
}

/// `[tls]`: PEM (or DER, by extension `.der`) certificate chain and private key.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TlsConfig {
    /// Certificate chain file.
    pub cert: Option<PathBuf>,
    /// Private key file.
    pub key: Option<PathBuf>,
}

/// One `[[robot]]`: a name and the SHA-256 of its token (hex). The server never stores the
/// token itself; `printf %s "$TOKEN" | sha256sum` computes the hash.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Robot name, reported back in `Welcome` and in logs.
    pub name: String,
    /// Lower-case hex SHA-256 of the token's UTF-8 bytes.
    pub token_sha256: String,
}

/// One `[[plugin]]`: a policy plugin (see docs/PLUGINS.md). Its world (horizon or priority) is
/// read from the component itself.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PluginConfig {
    /// The `.wasm` component; watched for hot reload.
    pub file: PathBuf,
    /// The policy name it is registered under; default: the file stem. A plugin may shadow a
    /// native policy of the same name.
    #[serde(default)]
    pub name: Option<String>,
    /// The native policy that answers a decision the plugin fails; default `threshold`
    /// (horizon) or `kairos` (priority).
    #[serde(default)]
    pub fallback: Option<String>,
    /// Longest a call may run, in ms; default 5 (horizon) or 50 (priority), 500 for a component
    /// that imports WASI (`plugin::WASI_DEADLINE`).
    #[serde(default)]
    pub deadline_ms: Option<u64>,
    /// Most linear memory an instance may have, in MiB; default 64.
    #[serde(default)]
    pub memory_mib: Option<u64>,
    /// Reload the plugin when its file changes (default true).
    #[serde(default = "default_true")]
    pub hot_reload: bool,
}

fn default_true() -> bool {
    true
}

impl PluginConfig {
    /// The plugin at `file`, with every other setting at its default.
    pub fn file(file: impl Into<PathBuf>) -> Self {
        PluginConfig {
            file: file.into(),
            name: None,
            fallback: None,
            deadline_ms: None,
            memory_mib: None,
            hot_reload: true,
        }
    }

    /// The name the plugin is registered under.
    pub fn name(&self) -> String {
        self.name.clone().unwrap_or_else(|| {
            self.file
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| self.file.display().to_string())
        })
    }
}

/// One `[[engine]]`: a model served by one or more instances.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EngineConfig {
    /// `builtin` (the engine crate's default built-in model), `builtin:<preset>`, a path to a
    /// checkpoint, or `horizon-flow:DIR` (`kairos bench horizon`'s policy, saved in `DIR`).
    pub model: String,
    /// The task tokenizer (`tokenizer.json`) of a whole LeRobot SmolVLA checkpoint; absent: the
    /// `tokenizer.json` beside the checkpoint. Any other model refuses one.
    pub tokenizer: Option<PathBuf>,
    /// Edge (co-located) or cloud.
    pub tier: Tier,
    /// Identical instances to run, each on its own OS thread. 0: the model only fixes the
    /// site's shapes and remote workers (`kairos worker`) serve it (`kairos serve
    /// --local-engines 0`).
    pub instances: u32,
    /// A JSON `EngineProfile` file; absent = measured at start.
    pub profile: Option<PathBuf>,
    /// Caps the batch size below the profile's saturation point.
    pub max_batch: Option<u32>,
    /// For a cloud engine: the round trip added to every batch, in milliseconds. The instance
    /// runs on this machine behind an *emulated* link (`pool::EmulatedLinkEngine`), so the
    /// edge/cloud placement can be exercised on one machine; the scheduler plans with it.
    pub rtt_ms: f64,
    /// Largest batch size measured when profiling at start.
    pub profile_max_batch: u32,
    /// `cpu` (default), `cuda` or `cuda:N`. CUDA needs a server built with `--features cuda`.
    pub device: String,
    /// `auto` (default: the fast kernels on the CPU, Candle on CUDA), `fast`, `portable` or
    /// `candle` (see docs/ENGINE.md).
    pub kernels: String,
    /// CPU threads of each instance's kernels; 0 (default) = `KAIROS_ENGINE_THREADS`, else one
    /// per core.
    pub threads: usize,
    /// `f32` (default, exact) or `bf16`: the number format of the fast kernels' weight GEMMs
    /// (AVX512_BF16; a CPU without it runs f32 and logs a warning; see docs/ENGINE.md).
    pub precision: String,
    /// Replay SmolVLA's Euler loop as a CUDA graph per batch shape (CUDA devices only; off by
    /// default; see docs/ENGINE.md, "CUDA").
    pub cuda_graphs: bool,
}

impl Default for EngineConfig {
    fn default() -> Self {
        EngineConfig {
            model: "builtin".into(),
            tokenizer: None,
            tier: Tier::Edge,
            instances: 1,
            profile: None,
            max_batch: None,
            rtt_ms: 0.0,
            profile_max_batch: 16,
            device: "cpu".into(),
            kernels: "auto".into(),
            threads: 0,
            precision: "f32".into(),
            cuda_graphs: false,
        }
    }
}

impl EngineConfig {
    /// The emulated network round trip of this engine.
    pub fn rtt(&self) -> Duration {
        // `check` refuses a non-finite or negative `rtt_ms`; a huge one saturates.
        Duration::try_from_secs_f64(self.rtt_ms.max(0.0) / 1e3).unwrap_or(Duration::MAX)
    }

    /// How this engine's model runs: `device`, `kernels` and `threads` parsed. Whether the
    /// device exists (or this build supports CUDA) is only known when the model is loaded.
    pub fn options(&self) -> Result<EngineOptions, EngineError> {
        Ok(EngineOptions {
            device: self.device.parse()?,
            kernels: self.kernels.parse()?,
            threads: self.threads,
            precision: self.precision.parse()?,
            cuda_graphs: self.cuda_graphs,
        })
    }
}

/// `[scheduler]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SchedulerSection {
    /// Priority policy and its parameters, `name` or `name:key=value,...`
    /// (e.g. `kairos:buckets=10,aging=4`); `fifo`, `plas`, `kairos`, or a plugin's name.
    pub policy: PolicySpec,
    /// Whether stale observations are re-fetched before dispatch (Algorithm 1, line 16). Absent:
    /// the policy's default (on for `kairos`, `srw` and plugins, off for the `fifo` and `plas`
    /// baselines; `scheduler::refetch_by_default`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refetch: Option<bool>,
    /// With re-fetch on, an observation older than this at dispatch is re-fetched, in
    /// milliseconds.
    pub stale_after_ms: u64,
    /// A task with no request for this long ends as expired, in seconds.
    pub task_idle_timeout_s: u64,
    /// Most requests pending at once.
    pub max_pending: usize,
    /// Rounds of G/E history kept per task.
    pub history_rounds: usize,
    /// How long to wait for a re-fetched observation before using the queued one, in ms.
    pub refetch_timeout_ms: u64,
}

impl Default for SchedulerSection {
    fn default() -> Self {
        let core = SchedulerConfig::default();
        SchedulerSection {
            policy: PolicySpec::named("kairos"),
            refetch: None,
            stale_after_ms: u64::try_from(core.stale_after.as_millis()).unwrap_or(u64::MAX),
            task_idle_timeout_s: core.task_idle_timeout.as_secs(),
            max_pending: core.max_pending,
            history_rounds: core.history_rounds,
            refetch_timeout_ms: 50,
        }
    }
}

impl SchedulerSection {
    /// The scheduler core's tunables.
    pub fn core(&self) -> SchedulerConfig {
        SchedulerConfig {
            refetch: self
                .refetch
                .unwrap_or_else(|| kairos_core::scheduler::refetch_by_default(&self.policy.name)),
            stale_after: Duration::from_millis(self.stale_after_ms),
            task_idle_timeout: Duration::from_secs(self.task_idle_timeout_s),
            max_pending: self.max_pending,
            history_rounds: self.history_rounds,
            ..SchedulerConfig::default()
        }
    }

    /// The re-fetch deadline.
    pub fn refetch_timeout(&self) -> Duration {
        Duration::from_millis(self.refetch_timeout_ms)
    }
}

/// `[horizon]`: the server's default horizon policy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HorizonSection {
    /// Policy name; `threshold` is the paper's §3.1 rule.
    pub policy: String,
    /// Its parameters (for `threshold`: `t` and `h_min`).
    pub params: BTreeMap<String, f64>,
}

impl Default for HorizonSection {
    fn default() -> Self {
        HorizonSection {
            policy: "threshold".into(),
            params: BTreeMap::from([("t".to_string(), 0.4), ("h_min".to_string(), 8.0)]),
        }
    }
}

/// `[connections]`: what one client may hold on the server, and what an unauthenticated one may.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConnectionsConfig {
    /// Most concurrent authenticated connections; a robot over it is closed with a reason after
    /// its `Hello`. Connections still in the handshake count against `max_unauthenticated`
    /// instead, so clients that never authenticate cannot take robots' slots.
    pub max_connections: usize,
    /// Most concurrent connections between the first packet and an authenticated `Hello` (or,
    /// on the openpi endpoint, an accepted upgrade), per endpoint. Over it new connection
    /// attempts are refused without a handshake; over half of it, attempts from an address QUIC
    /// has not validated are answered with a Retry first.
    pub max_unauthenticated: usize,
    /// Most of those places one source address (an IPv4 address, an IPv6 /64) may hold at once.
    /// Counted for validated sources only: every openpi (TCP) connection, and QUIC attempts that
    /// answered a Retry (an unvalidated QUIC source may be spoofed).
    pub max_unauthenticated_per_source: usize,
    /// Most concurrent round streams per connection (QUIC stream credit).
    pub max_streams_per_connection: u32,
    /// Time a client has, from its first packet, to finish the handshake and send an accepted
    /// `Hello` (openpi: to finish its websocket upgrade), in ms.
    pub hello_timeout_ms: u64,
    /// Wrong tokens a source address (an IPv4 address or an IPv6 /64) may send in a burst,
    /// through any endpoint; after that its connections are refused before their token is looked
    /// at.
    pub failed_token_burst: u32,
    /// Wrong tokens a source regains per minute after its burst.
    pub failed_tokens_per_minute: u32,
    /// Sources the failed-token limiter remembers at most (bounded memory).
    pub failed_token_sources: usize,
    /// Slowest upload the server waits for, bytes per second: a stream whose frame (an openpi
    /// connection whose message, from its first byte) arrives slower, after `upload_grace_ms`,
    /// is stopped with a `too_slow` error.
    pub min_upload_bytes_per_s: u64,
    /// Time a stream has before `min_upload_bytes_per_s` applies, in ms.
    pub upload_grace_ms: u64,
    /// Frames of `[limits] max_frame` bytes one QUIC connection may have partly received at
    /// once; the connection's QUIC receive window is the same size, so a robot can hold at most
    /// twice this many frames' bytes in the server. On the openpi endpoint, where a robot spreads
    /// its requests over connections of one message each, the budget is the robot's: all its
    /// openpi connections together.
    pub upload_buffer_frames: u32,
    /// Receive and send buffer of the server's UDP socket, bytes (the kernel caps it at
    /// `net.core.rmem_max`/`wmem_max`). The default 4 MiB absorbs a burst of a thousand robots'
    /// packets (e.g. everyone reconnecting at once) where the usual 208 KiB would drop them.
    pub socket_buffer_bytes: usize,
    /// Most authenticated connections one robot (one token) may hold at once; over it the
    /// connection is closed with `AT_CAPACITY` after its `Hello`. Unset: an equal share of
    /// `max_connections` per configured robot (`max_connections / robots`, at least 1), so
    /// every robot can always get its share; with the one generated robot, whose token a whole
    /// fleet shares, that is every place.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_connections_per_robot: Option<usize>,
    /// Rounds one connection may submit per second, sustained (a token bucket refilled at this
    /// rate); a round over it is refused with a retryable `overloaded`.
    pub rounds_per_s_per_connection: f64,
    /// Rounds one connection may submit at once beyond its rate (the bucket's size).
    pub round_burst_per_connection: u32,
    /// Rounds one robot (one token), over all its connections, may submit per second,
    /// sustained; QUIC and openpi rounds alike.
    pub rounds_per_s_per_robot: f64,
    /// Rounds one robot may submit at once beyond its rate.
    pub round_burst_per_robot: u32,
}

impl Default for ConnectionsConfig {
    fn default() -> Self {
        ConnectionsConfig {
            max_connections: 4096,
            max_unauthenticated: 256,
            max_unauthenticated_per_source: 32,
            max_streams_per_connection: 64,
            hello_timeout_ms: 5_000,
            failed_token_burst: 10,
            failed_tokens_per_minute: 10,
            failed_token_sources: 65_536,
            min_upload_bytes_per_s: 8 << 10,
            upload_grace_ms: 5_000,
            upload_buffer_frames: 2,
            socket_buffer_bytes: 4 << 20,
            max_connections_per_robot: None,
            // Far above what a robot needs (one round per control step at 1 kHz) and what a
            // fleet of thousands on one token sends; they bound floods, not robots.
            rounds_per_s_per_connection: 1_000.0,
            round_burst_per_connection: 1_000,
            rounds_per_s_per_robot: 10_000.0,
            round_burst_per_robot: 10_000,
        }
    }
}

impl ConnectionsConfig {
    /// The deadline for the handshake and `Hello`.
    pub fn hello_timeout(&self) -> Duration {
        Duration::from_millis(self.hello_timeout_ms)
    }

    /// The grace period before the minimum upload rate applies.
    pub fn upload_grace(&self) -> Duration {
        Duration::from_millis(self.upload_grace_ms)
    }

    /// Bytes of partly received frames one connection may hold: `upload_buffer_frames` frames of
    /// `max_frame` (at least one).
    pub fn upload_buffer_bytes(&self, max_frame: u32) -> u64 {
        u64::from(self.upload_buffer_frames.max(1)) * u64::from(max_frame)
    }

    /// The minimum upload rate every endpoint reads with, if any.
    pub fn min_upload_rate(&self) -> Option<kairos_sdk::protocol::MinRate> {
        (self.min_upload_bytes_per_s > 0).then(|| kairos_sdk::protocol::MinRate {
            bytes_per_s: self.min_upload_bytes_per_s,
            grace: self.upload_grace(),
        })
    }
}

/// `[openpi]`: a websocket endpoint that speaks openpi's policy-server protocol, so that an
/// unmodified `openpi-client` (`WebsocketClientPolicy`) is served by this server's scheduler and
/// engines (docs/SERVER.md, "openpi endpoint").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpenpiConfig {
    /// TCP address of the websocket endpoint; absent = no endpoint.
    pub listen: Option<SocketAddr>,
    /// Observation keys of the model's cameras, in the model's camera order. Keys absent from a
    /// request are skipped.
    pub cameras: Vec<String>,
    /// Observation keys whose values, flattened and concatenated in this order, are the state.
    pub state: Vec<String>,
    /// Observation key of the instruction text (empty when absent).
    pub prompt: String,
    /// Horizon policy of openpi rounds; absent = `static` with `h` = the model's chunk length,
    /// so the reply holds the whole chunk, as openpi clients expect (they choose how many
    /// actions to execute themselves).
    pub horizon: Option<String>,
    /// Its parameters.
    pub horizon_params: BTreeMap<String, f64>,
    /// The robots' control rate, in Hz, reported to the scheduler; absent = estimated from the
    /// interval between a reply and the next request (`openpi::exec`).
    pub control_hz: Option<f32>,
}

impl Default for OpenpiConfig {
    fn default() -> Self {
        OpenpiConfig {
            listen: None,
            cameras: vec!["observation/image".into(), "observation/wrist_image".into()],
            state: vec!["observation/state".into()],
            prompt: "prompt".into(),
            horizon: None,
            horizon_params: BTreeMap::new(),
            control_hz: None,
        }
    }
}

/// Deserialises `[limits]` into the protocol's [`Limits`] (announced to clients in `Welcome`),
/// refusing keys it does not have: on the wire unknown keys are tolerated for forward
/// compatibility, but in a config file they are typos.
/// Whether `text` can be a model scheme (`horizon-flow` in `horizon-flow:DIR`): lower-case
/// letters, digits and dashes, starting with a letter. A one-letter scheme is refused so that
/// nothing resembling a drive letter is taken for one.
fn is_model_scheme(text: &str) -> bool {
    text.len() > 1
        && text.starts_with(|c: char| c.is_ascii_lowercase())
        && text
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
}

fn strict_limits<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Limits, D::Error> {
    use serde::de::Error;
    let table = toml::Table::deserialize(d)?;
    let known = toml::Table::try_from(Limits::default()).map_err(D::Error::custom)?;
    if let Some(key) = table.keys().find(|k| !known.contains_key(*k)) {
        let expected: Vec<&str> = known.keys().map(String::as_str).collect();
        return Err(D::Error::custom(format!(
            "unknown field `{key}`, expected one of {}",
            expected.join(", ")
        )));
    }
    toml::Value::Table(table)
        .try_into()
        .map_err(D::Error::custom)
}

impl Config {
    /// Reads, parses and checks a `kairos.toml`. Relative paths in it are resolved against the
    /// file's directory.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mut config = Config::parse(&text, path)?;
        let base = path.parent().unwrap_or(Path::new(""));
        config.resolve_paths(base);
        Ok(config)
    }

    /// Parses and checks TOML text; `path` is only used in error messages. Paths stay as written.
    pub fn parse(text: &str, path: &Path) -> Result<Config, ConfigError> {
        let config: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_path_buf(),
            message: e.to_string().trim_end().to_string(),
        })?;
        config.check(path)?;
        Ok(config)
    }

    fn resolve_paths(&mut self, base: &Path) {
        let resolve = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        resolve(&mut self.data_dir);
        if let Some(p) = self.tls.cert.as_mut() {
            resolve(p);
        }
        if let Some(p) = self.tls.key.as_mut() {
            resolve(p);
        }
        for plugin in &mut self.plugins {
            resolve(&mut plugin.file);
        }
        for engine in &mut self.engines {
            if let Some(p) = engine.profile.as_mut() {
                resolve(p);
            }
            if let Some(p) = engine.tokenizer.as_mut() {
                resolve(p);
            }
            // `scheme:PATH` (a model a tool registers, `pool::ModelSchemes`): the path is
            // relative to the file too.
            if let Some((scheme, dir)) = engine.model.split_once(':')
                && is_model_scheme(scheme)
                && scheme != "builtin"
            {
                let mut p = PathBuf::from(dir);
                resolve(&mut p);
                engine.model = format!("{scheme}:{}", p.to_string_lossy());
            } else if !engine.model.starts_with("builtin") {
                let mut p = PathBuf::from(&engine.model);
                resolve(&mut p);
                engine.model = p.to_string_lossy().into_owned();
            }
        }
    }

    /// Checks values the types cannot express. `path` names the source in errors.
    pub fn check(&self, path: &Path) -> Result<(), ConfigError> {
        let invalid = |key: String, reason: String| ConfigError::Invalid {
            path: path.to_path_buf(),
            key,
            reason,
        };
        if self.tls.cert.is_some() != self.tls.key.is_some() {
            return Err(invalid(
                "tls".into(),
                "set both `cert` and `key`, or neither".into(),
            ));
        }
        let mut names = HashSet::new();
        for (i, robot) in self.robots.iter().enumerate() {
            if robot.name.is_empty() {
                return Err(invalid(format!("robot[{i}].name"), "is empty".into()));
            }
            if !names.insert(robot.name.as_str()) {
                return Err(invalid(
                    format!("robot[{i}].name"),
                    format!("robot `{}` is listed twice", robot.name),
                ));
            }
            if parse_token_hash(&robot.token_sha256).is_none() {
                return Err(invalid(
                    format!("robot[{i}].token_sha256"),
                    "must be 64 hex digits (printf %s \"$TOKEN\" | sha256sum)".into(),
                ));
            }
        }
        for (i, engine) in self.engines.iter().enumerate() {
            if engine.max_batch == Some(0) {
                return Err(invalid(
                    format!("engine[{i}].max_batch"),
                    "must be at least 1".into(),
                ));
            }
            if engine.profile_max_batch == 0 {
                return Err(invalid(
                    format!("engine[{i}].profile_max_batch"),
                    "must be at least 1".into(),
                ));
            }
            match engine.device.parse::<DeviceKind>() {
                Err(e) => return Err(invalid(format!("engine[{i}].device"), e.to_string())),
                Ok(DeviceKind::Cpu) if engine.cuda_graphs => {
                    return Err(invalid(
                        format!("engine[{i}].cuda_graphs"),
                        "CUDA graphs need a CUDA device (`device = \"cuda:N\"`)".into(),
                    ));
                }
                Ok(_) => {}
            }
            if let Err(e) = engine.kernels.parse::<Kernels>() {
                return Err(invalid(format!("engine[{i}].kernels"), e.to_string()));
            }
            if let Err(e) = engine.precision.parse::<Precision>() {
                return Err(invalid(format!("engine[{i}].precision"), e.to_string()));
            }
            if !(engine.rtt_ms.is_finite() && engine.rtt_ms >= 0.0) {
                return Err(invalid(
                    format!("engine[{i}].rtt_ms"),
                    "must be a finite number >= 0".into(),
                ));
            }
            if engine.tier == Tier::Edge && engine.rtt_ms > 0.0 {
                return Err(invalid(
                    format!("engine[{i}].rtt_ms"),
                    "only a cloud engine has a link round trip (set tier = \"cloud\")".into(),
                ));
            }
        }
        if self.workers.heartbeat_ms == 0 {
            return Err(invalid(
                "workers.heartbeat_ms".into(),
                "must be at least 1".into(),
            ));
        }
        if self.workers.max_attempts == 0 {
            return Err(invalid(
                "workers.max_attempts".into(),
                "must be at least 1".into(),
            ));
        }
        let connections = &self.connections;
        if connections.max_connections_per_robot == Some(0) {
            return Err(invalid(
                "connections.max_connections_per_robot".into(),
                "must be at least 1".into(),
            ));
        }
        for (key, rate) in [
            (
                "connections.rounds_per_s_per_connection",
                connections.rounds_per_s_per_connection,
            ),
            (
                "connections.rounds_per_s_per_robot",
                connections.rounds_per_s_per_robot,
            ),
        ] {
            if !(rate.is_finite() && rate > 0.0) {
                return Err(invalid(key.into(), "must be a finite number > 0".into()));
            }
        }
        for (key, burst) in [
            (
                "connections.round_burst_per_connection",
                connections.round_burst_per_connection,
            ),
            (
                "connections.round_burst_per_robot",
                connections.round_burst_per_robot,
            ),
        ] {
            if burst == 0 {
                return Err(invalid(key.into(), "must be at least 1".into()));
            }
        }
        if self.workers.max_batch_deadline_ms < self.workers.min_batch_deadline_ms {
            return Err(invalid(
                "workers.max_batch_deadline_ms".into(),
                "must be at least workers.min_batch_deadline_ms".into(),
            ));
        }
        if !(self.workers.batch_deadline_factor.is_finite()
            && self.workers.batch_deadline_factor >= 1.0)
        {
            return Err(invalid(
                "workers.batch_deadline_factor".into(),
                "must be a finite number >= 1".into(),
            ));
        }
        if let Err((key, reason)) = self.chunking.defaults() {
            return Err(invalid(format!("chunking.{key}"), reason));
        }
        if let Some((name, _)) = self.horizon.params.iter().find(|(_, v)| !v.is_finite()) {
            return Err(invalid(
                format!("horizon.params.{name}"),
                "must be finite".into(),
            ));
        }
        if let Some((name, _)) = self
            .openpi
            .horizon_params
            .iter()
            .find(|(_, v)| !v.is_finite())
        {
            return Err(invalid(
                format!("openpi.horizon_params.{name}"),
                "must be finite".into(),
            ));
        }
        if let Some(hz) = self.openpi.control_hz
            && !(hz.is_finite() && hz > 0.0)
        {
            return Err(invalid(
                "openpi.control_hz".into(),
                "must be a finite number > 0".into(),
            ));
        }
        if self.openpi.state.is_empty() {
            return Err(invalid(
                "openpi.state".into(),
                "name at least one observation key".into(),
            ));
        }
        let mut plugin_names = HashSet::new();
        for (i, plugin) in self.plugins.iter().enumerate() {
            let name = plugin.name();
            if name.is_empty() || name.contains([':', ',', '=']) {
                return Err(invalid(
                    format!("plugin[{i}].name"),
                    format!("`{name}` must be non-empty and free of `:`, `,` and `=`"),
                ));
            }
            if !plugin_names.insert(name.clone()) {
                return Err(invalid(
                    format!("plugin[{i}].name"),
                    format!("plugin `{name}` is listed twice"),
                ));
            }
            if plugin.deadline_ms == Some(0) || plugin.memory_mib == Some(0) {
                return Err(invalid(
                    format!("plugin[{i}]"),
                    "deadline_ms and memory_mib must be at least 1".into(),
                ));
            }
        }
        if self.scheduler.max_pending == 0 {
            return Err(invalid(
                "scheduler.max_pending".into(),
                "must be at least 1".into(),
            ));
        }
        if self.scheduler.history_rounds == 0 {
            return Err(invalid(
                "scheduler.history_rounds".into(),
                "must be at least 1".into(),
            ));
        }
        let (l, c) = (&self.limits, &self.connections);
        for (key, value) in [
            ("limits.max_frame", u64::from(l.max_frame)),
            ("limits.max_samples", u64::from(l.max_samples)),
            ("limits.max_state_len", u64::from(l.max_state_len)),
            ("limits.max_image_pixels", u64::from(l.max_image_pixels)),
            ("connections.max_connections", c.max_connections as u64),
            (
                "connections.max_streams_per_connection",
                u64::from(c.max_streams_per_connection),
            ),
            (
                "connections.max_unauthenticated",
                c.max_unauthenticated as u64,
            ),
            (
                "connections.max_unauthenticated_per_source",
                c.max_unauthenticated_per_source as u64,
            ),
            (
                "connections.failed_token_sources",
                c.failed_token_sources as u64,
            ),
            (
                "connections.upload_buffer_frames",
                u64::from(c.upload_buffer_frames),
            ),
        ] {
            if value == 0 {
                return Err(invalid(key.into(), "must be at least 1".into()));
            }
        }
        if l.max_image_pixels as usize > kairos_engine::image_features::MAX_PIXELS {
            return Err(invalid(
                "limits.max_image_pixels".into(),
                format!(
                    "{} is over the most the engine decodes, {}",
                    l.max_image_pixels,
                    kairos_engine::image_features::MAX_PIXELS
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_is_the_default_config() {
        let c = Config::parse("", Path::new("k.toml")).unwrap();
        assert_eq!(c, Config::default());
        assert_eq!(c.listen.to_string(), DEFAULT_LISTEN);
        assert_eq!(c.horizon.policy, "threshold");
    }

    #[test]
    fn refetch_follows_the_policy_unless_configured() {
        let core = |text: &str| {
            Config::parse(text, Path::new("k.toml"))
                .unwrap()
                .scheduler
                .core()
        };
        assert!(core("").refetch, "the default policy is kairos");
        assert!(!core("[scheduler]\npolicy = \"fifo\"\n").refetch);
        assert!(!core("[scheduler]\npolicy = \"plas\"\n").refetch);
        assert!(core("[scheduler]\npolicy = \"srw\"\n").refetch);
        assert!(core("[scheduler]\npolicy = \"fifo\"\nrefetch = true\n").refetch);
        assert!(!core("[scheduler]\nrefetch = false\n").refetch);
    }

    #[test]
    fn cuda_graphs_reach_the_engine_options() {
        let text = "[[engine]]\ndevice = \"cuda:1\"\ncuda_graphs = true\n";
        let c = Config::parse(text, Path::new("k.toml")).unwrap();
        let options = c.engines[0].options().unwrap();
        assert_eq!(options.device, DeviceKind::Cuda(1));
        assert!(options.cuda_graphs);
        assert!(!EngineConfig::default().options().unwrap().cuda_graphs);

        // `kairos serve --cuda-graphs`: on with a CUDA device, refused with the CPU.
        let overrides = Overrides {
            device: Some("cuda:0".into()),
            cuda_graphs: true,
            ..Overrides::default()
        };
        let c = Config::load_with(None, &overrides).unwrap();
        assert!(c.engines[0].options().unwrap().cuda_graphs);
        let overrides = Overrides {
            cuda_graphs: true,
            ..Overrides::default()
        };
        match Config::load_with(None, &overrides).unwrap_err() {
            ConfigError::Invalid { key, .. } => assert_eq!(key, "engine[0].cuda_graphs"),
            other => panic!("expected Invalid, got {other}"),
        }
    }

    #[test]
    fn full_example_parses() {
        let text = r#"
            listen = "0.0.0.0:5000"
            data_dir = "/var/lib/kairos"
            [tls]
            cert = "cert.pem"
            key = "key.pem"
            [[robot]]
            name = "arm-1"
            token_sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
            [[engine]]
            model = "builtin:tiny"
            instances = 2
            device = "cpu"
            kernels = "portable"
            threads = 1
            precision = "bf16"
            [[engine]]
            model = "ckpt/model.safetensors"
            tier = "cloud"
            rtt_ms = 20
            profile = "profiles/cloud.json"
            [scheduler]
            policy = "kairos:buckets=10,aging=3"
            stale_after_ms = 50
            [horizon]
            policy = "static"
            params = { h = 10 }
            [limits]
            max_frame = 1000000
            [connections]
            max_connections = 10
        "#;
        let mut c = Config::parse(text, Path::new("/etc/kairos/kairos.toml")).unwrap();
        c.resolve_paths(Path::new("/etc/kairos"));
        assert_eq!(c.robots[0].name, "arm-1");
        assert_eq!(c.engines.len(), 2);
        assert_eq!(c.engines[1].tier, Tier::Cloud);
        assert_eq!(c.engines[1].rtt(), Duration::from_millis(20));
        assert_eq!(
            c.engines[1].model, "/etc/kairos/ckpt/model.safetensors",
            "relative checkpoint paths resolve against the config file's directory"
        );
        assert_eq!(c.engines[0].model, "builtin:tiny");
        // A `horizon-flow:DIR` model keeps its prefix; its directory resolves like a checkpoint.
        let mut h = c.clone();
        h.engines[1].model = "horizon-flow:horizon/model".into();
        h.resolve_paths(Path::new("/etc/kairos"));
        assert_eq!(h.engines[1].model, "horizon-flow:/etc/kairos/horizon/model");
        assert_eq!(
            c.engines[0].options().unwrap(),
            EngineOptions {
                device: DeviceKind::Cpu,
                kernels: Kernels::Portable,
                threads: 1,
                precision: Precision::Bf16,
                cuda_graphs: false,
            }
        );
        assert_eq!(
            c.engines[1].options().unwrap(),
            EngineOptions::default(),
            "device, kernels and threads default to the engine crate's defaults"
        );
        assert_eq!(
            c.tls.cert.as_deref(),
            Some(Path::new("/etc/kairos/cert.pem"))
        );
        assert_eq!(c.data_dir, PathBuf::from("/var/lib/kairos"));
        assert_eq!(c.scheduler.core().stale_after, Duration::from_millis(50));
        assert_eq!(c.scheduler.policy.name, "kairos");
        assert_eq!(c.scheduler.policy.params["aging"], "3");
        assert!(c.scheduler.core().refetch, "kairos re-fetches by default");
        assert_eq!(c.connections.max_connections, 10);
        assert_eq!(c.limits.max_frame, 1_000_000);
        assert_eq!(c.limits.max_image_bytes, Limits::default().max_image_bytes);
    }

    #[test]
    fn the_example_in_docs_server_md_parses() {
        let doc = include_str!("../../../docs/SERVER.md");
        let start = doc
            .find("```toml\n")
            .expect("docs/SERVER.md has a toml example");
        let body = &doc[start + "```toml\n".len()..];
        let example = &body[..body.find("```").expect("the example block ends")];
        let config = Config::parse(example, Path::new("docs/SERVER.md")).unwrap();
        assert_eq!(config.robots.len(), 2);
        assert_eq!(config.engines.len(), 2);
        assert_eq!(config.engines[1].tier, Tier::Cloud);
        assert_eq!(config.plugins.len(), 1);
        assert_eq!(config.plugins[0].name(), "wasm-threshold");
        assert_eq!(
            config.limits,
            Limits::default(),
            "the example lists the defaults"
        );
        assert_eq!(config.connections, ConnectionsConfig::default());
        assert_eq!(
            config.openpi.listen,
            Some("127.0.0.1:8000".parse().unwrap())
        );
        assert_eq!(
            OpenpiConfig {
                listen: None,
                ..config.openpi
            },
            OpenpiConfig::default(),
            "the example lists the defaults"
        );
    }

    #[test]
    fn openpi_section_is_checked() {
        let c = Config::parse(
            "[openpi]\nlisten = \"0.0.0.0:8000\"\nstate = [\"a\", \"b\"]\ncontrol_hz = 15.0\n",
            Path::new("k.toml"),
        )
        .unwrap();
        assert_eq!(c.openpi.state, ["a", "b"]);
        assert_eq!(c.openpi.control_hz, Some(15.0));
        assert_eq!(Config::default().openpi.listen, None, "off by default");
        for (bad, key) in [
            ("[openpi]\ncontrol_hz = 0.0\n", "openpi.control_hz"),
            ("[openpi]\nstate = []\n", "openpi.state"),
            (
                "[openpi]\nhorizon_params = { h = nan }\n",
                "openpi.horizon_params.h",
            ),
        ] {
            let err = Config::parse(bad, Path::new("k.toml"))
                .unwrap_err()
                .to_string();
            assert!(err.contains(key), "{bad}: {err}");
        }
        let err = Config::parse("[openpi]\nlisten_on = 1\n", Path::new("k.toml")).unwrap_err();
        assert!(err.to_string().contains("listen_on"), "{err}");
    }

    #[test]
    fn a_batch_deadline_is_scaled_and_bounded_whatever_the_worker_declared() {
        let workers = WorkersConfig {
            batch_deadline_factor: 4.0,
            min_batch_deadline_ms: 2_000,
            max_batch_deadline_ms: 60_000,
            ..WorkersConfig::default()
        };
        let ms = Duration::from_millis;
        assert_eq!(workers.batch_deadline(ms(100)), ms(2_000));
        assert_eq!(workers.batch_deadline(ms(1_000)), ms(4_000));
        assert_eq!(workers.batch_deadline(ms(100_000)), ms(60_000));
        // A profile's latency saturates at `Duration::MAX`: capped, no overflow.
        assert_eq!(workers.batch_deadline(Duration::MAX), ms(60_000));
    }

    #[test]
    fn unknown_key_error_names_file_and_key() {
        let err = Config::parse("[scheduler]\nstale_afterms = 5\n", Path::new("my.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("my.toml:"), "{err}");
        assert!(err.contains("stale_afterms"), "{err}");
    }

    #[test]
    fn unknown_limit_is_an_error() {
        let err = Config::parse("[limits]\nmax_fram = 5\n", Path::new("my.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("max_fram"), "{err}");
    }

    #[test]
    fn bad_values_are_rejected_with_their_key() {
        let cases = [
            ("[workers]\nheartbeat_ms = 0\n", "workers.heartbeat_ms"),
            ("[workers]\nmax_attempts = 0\n", "workers.max_attempts"),
            (
                "[workers]\nmin_batch_deadline_ms = 5000\nmax_batch_deadline_ms = 4000\n",
                "workers.max_batch_deadline_ms",
            ),
            (
                "[connections]\nmax_connections_per_robot = 0\n",
                "connections.max_connections_per_robot",
            ),
            (
                "[connections]\nrounds_per_s_per_robot = 0.0\n",
                "connections.rounds_per_s_per_robot",
            ),
            (
                "[connections]\nrounds_per_s_per_connection = inf\n",
                "connections.rounds_per_s_per_connection",
            ),
            (
                "[connections]\nround_burst_per_connection = 0\n",
                "connections.round_burst_per_connection",
            ),
            (
                "[connections]\nround_burst_per_robot = 0\n",
                "connections.round_burst_per_robot",
            ),
            (
                "[[robot]]\nname = \"a\"\ntoken_sha256 = \"abc\"\n",
                "robot[0].token_sha256",
            ),
            ("[tls]\ncert = \"c.pem\"\n", "tls"),
            ("[limits]\nmax_samples = 0\n", "limits.max_samples"),
            (
                "[limits]\nmax_image_pixels = 0\n",
                "limits.max_image_pixels",
            ),
            (
                "[limits]\nmax_image_pixels = 16777217\n",
                "limits.max_image_pixels",
            ),
            ("[[engine]]\nrtt_ms = -1\n", "engine[0].rtt_ms"),
            ("[[engine]]\nrtt_ms = 5\n", "engine[0].rtt_ms"),
            ("[[engine]]\ndevice = \"gpu\"\n", "engine[0].device"),
            ("[[engine]]\ndevice = \"cuda:x\"\n", "engine[0].device"),
            ("[[engine]]\nkernels = \"mkl\"\n", "engine[0].kernels"),
            ("[[engine]]\nprecision = \"fp8\"\n", "engine[0].precision"),
            ("[[engine]]\ncuda_graphs = true\n", "engine[0].cuda_graphs"),
        ];
        for (text, key) in cases {
            let err = Config::parse(text, Path::new("k.toml")).unwrap_err();
            match &err {
                ConfigError::Invalid { key: k, .. } => assert_eq!(k, key, "{err}"),
                other => panic!("expected Invalid for {key}, got {other}"),
            }
        }
        let dup = "[[robot]]\nname = \"a\"\ntoken_sha256 = \"9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08\"\n\
                   [[robot]]\nname = \"a\"\ntoken_sha256 = \"9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08\"\n";
        assert!(Config::parse(dup, Path::new("k.toml")).is_err());
        assert!(Config::parse("listen = \"nonsense\"\n", Path::new("k.toml")).is_err());
    }
}
