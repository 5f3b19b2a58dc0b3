//! Loading a component and running calls into it: compilation, instantiation, deadlines, and
//! where calls execute (inline or on a worker thread).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use sha2::{Digest, Sha256};
use wasmtime::component::{Component, Linker};
use wasmtime::{Engine, Store};

use super::bindings::WitVersion;
use super::cache::CodeSource;
use super::health::FailureKind;
use super::inspect::{ComponentInfo, InspectError};
use super::sandbox::{self, HostState};
use super::{InstanceMode, PluginKind, PluginOptions, PluginSource, engine};

/// One world's bindings across every supported WIT version.
pub(crate) trait World: 'static {
    /// Which world.
    const KIND: PluginKind;
    /// A pre-linked component, ready to instantiate cheaply.
    type Pre: Send + Sync + 'static;
    /// A live instance's typed exports.
    type Instance: Send + 'static;

    /// Links `component`, built against `version` (already checked to be supported).
    fn pre(
        version: WitVersion,
        linker: &Linker<HostState>,
        component: &Component,
    ) -> wasmtime::Result<Self::Pre>;

    /// Instantiates into `store`.
    fn instantiate(
        pre: &Self::Pre,
        store: &mut Store<HostState>,
    ) -> wasmtime::Result<Self::Instance>;
}

/// Why a plugin could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The file could not be read.
    #[error("cannot read plugin {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The component is not a usable plugin of the requested kind.
    #[error("plugin `{name}` {source}")]
    Inspect {
        /// The plugin.
        name: String,
        /// What is wrong.
        source: InspectError,
    },
    /// Compiling, linking or a trial instantiation failed.
    #[error("plugin `{name}`: {message}")]
    Compile {
        /// The plugin.
        name: String,
        /// What failed.
        message: String,
    },
}

/// What is known about a loaded plugin.
#[derive(Clone, Debug)]
pub struct PluginMeta {
    /// Name for logs (file stem or given name).
    pub name: String,
    /// The file it was loaded from, if any.
    pub path: Option<PathBuf>,
    /// Its world.
    pub kind: PluginKind,
    /// The `kairos:policy` version it was built against.
    pub version: WitVersion,
    /// SHA-256 of the component bytes.
    pub sha256: [u8; 32],
    /// Size of the component in bytes.
    pub size: usize,
    /// What it exports and imports.
    pub info: ComponentInfo,
    /// Whether the code came from the cache.
    pub code: CodeSource,
    /// Time spent compiling (or loading from the cache) and linking.
    pub load_time: Duration,
}

/// A compiled, linked plugin of world `W`, shared by every instance of it.
pub(crate) struct Compiled<W: World> {
    pub meta: PluginMeta,
    pub engine: Engine,
    pub pre: W::Pre,
}

/// Reads and compiles the plugin in `source` as world `W`.
pub(crate) fn load<W: World>(
    source: &PluginSource,
    options: &PluginOptions,
) -> Result<Arc<Compiled<W>>, LoadError> {
    let name = options.name.clone().unwrap_or_else(|| source.name());
    let (wasm, path) = match source {
        PluginSource::File(path) => (
            std::fs::read(path).map_err(|source| LoadError::Read {
                path: path.clone(),
                source,
            })?,
            Some(path.clone()),
        ),
        PluginSource::Bytes { wasm, .. } => (wasm.clone(), None),
    };
    compile::<W>(name, path, &wasm, options)
}

pub(crate) fn compile<W: World>(
    name: String,
    path: Option<PathBuf>,
    wasm: &[u8],
    options: &PluginOptions,
) -> Result<Arc<Compiled<W>>, LoadError> {
    let started = Instant::now();
    let inspect_error = |source| LoadError::Inspect {
        name: name.clone(),
        source,
    };
    let info = super::inspect::inspect(wasm).map_err(inspect_error)?;
    let version = info.check(W::KIND).map_err(inspect_error)?;
    let compile_error = |stage: &str, e: wasmtime::Error| LoadError::Compile {
        name: name.clone(),
        message: format!("{stage}: {e:#}"),
    };
    let engine = engine::shared(options.fuel.is_some()).map_err(|e| compile_error("engine", e))?;
    let (component, code) = match &options.cache {
        Some(cache) => cache.load_or_compile(&engine, wasm),
        None => Component::new(&engine, wasm).map(|c| (c, CodeSource::Uncached)),
    }
    .map_err(|e| compile_error("compilation failed", e))?;
    let linker = if info.imports_wasi {
        sandbox::wasi_linker(&engine).map_err(|e| compile_error("WASI linker", e))?
    } else {
        sandbox::plain_linker(&engine)
    };
    let pre =
        W::pre(version, &linker, &component).map_err(|e| compile_error("linking failed", e))?;
    let meta = PluginMeta {
        name,
        path,
        kind: W::KIND,
        version,
        sha256: Sha256::digest(wasm).into(),
        size: wasm.len(),
        info,
        code,
        load_time: started.elapsed(),
    };
    Ok(Arc::new(Compiled { meta, engine, pre }))
}

/// A failed call into a plugin.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{kind}: {message}")]
pub struct CallFailure {
    /// What went wrong.
    pub kind: FailureKind,
    /// Details for the log.
    pub message: String,
}

impl CallFailure {
    /// A failure of `kind`.
    pub fn new(kind: FailureKind, message: impl Into<String>) -> Self {
        CallFailure {
            kind,
            message: message.into(),
        }
    }
}

/// The plugin's live instance and everything needed to make a new one. Lives on whichever
/// thread runs the calls.
pub(crate) struct Live<W: World> {
    plugin: Arc<Compiled<W>>,
    options: Arc<PluginOptions>,
    instance: Option<(Store<HostState>, W::Instance)>,
    peak_memory: usize,
}

/// What one successful call cost.
#[derive(Clone, Copy, Debug, Default)]
pub struct CallCost {
    /// Wall time of the call (not counting an instantiation before it).
    pub elapsed: Duration,
    /// Largest linear memory of the instance so far.
    pub peak_memory: usize,
}

impl<W: World> Live<W> {
    pub fn new(plugin: Arc<Compiled<W>>, options: Arc<PluginOptions>) -> Self {
        Live {
            plugin,
            options,
            instance: None,
            peak_memory: 0,
        }
    }

    /// Swaps in a reloaded plugin; the old instance is dropped between calls.
    pub fn replace(&mut self, plugin: Arc<Compiled<W>>) {
        self.plugin = plugin;
        self.instance = None;
        self.peak_memory = 0;
    }

    /// Runs `f` against an instance under the deadline, memory cap and fuel budget. On any
    /// error the instance is discarded: after a trap it cannot be entered again.
    pub fn call<R>(
        &mut self,
        f: impl FnOnce(&mut Store<HostState>, &W::Instance) -> wasmtime::Result<R>,
    ) -> Result<(R, CallCost), CallFailure> {
        if self.instance.is_none() {
            self.instantiate()?;
        }
        let started = Instant::now();
        let Some((store, instance)) = &mut self.instance else {
            return Err(CallFailure::new(FailureKind::Instantiate, "no instance"));
        };
        // The call's own deadline starts now: instantiating (the guest's start code, the
        // Python runtime's set-up) has its own budget and is not charged to the call.
        store.set_epoch_deadline(engine::deadline_ticks(self.options.deadline));
        let instance = &*instance;
        if let Some(fuel) = self.options.fuel {
            store
                .set_fuel(fuel)
                .map_err(|e| CallFailure::new(FailureKind::Trap, format!("{e:#}")))?;
        }
        let deadline = self.options.deadline;
        let outcome =
            f(store, instance).map_err(|e| classify(store, &e, FailureKind::Trap, deadline));
        let peak = store.data().limiter.peak();
        self.note_peak(peak);
        match outcome {
            Ok(value) => {
                if self.options.instance_mode == InstanceMode::Fresh {
                    self.instance = None;
                }
                Ok((
                    value,
                    CallCost {
                        elapsed: started.elapsed(),
                        peak_memory: self.peak_memory,
                    },
                ))
            }
            Err(failure) => {
                self.instance = None;
                Err(failure)
            }
        }
    }

    /// Makes a new instance under the instantiation deadline.
    fn instantiate(&mut self) -> Result<(), CallFailure> {
        let mut store = Store::new(
            &self.plugin.engine,
            HostState::new(self.options.memory_limit),
        );
        store.limiter(|state| &mut state.limiter);
        store.epoch_deadline_trap();
        store.set_epoch_deadline(engine::deadline_ticks(self.options.instantiate_deadline));
        if let Some(fuel) = self.options.fuel {
            store
                .set_fuel(fuel)
                .map_err(|e| CallFailure::new(FailureKind::Instantiate, format!("{e:#}")))?;
        }
        match W::instantiate(&self.plugin.pre, &mut store) {
            Ok(instance) => {
                self.note_peak(store.data().limiter.peak());
                self.instance = Some((store, instance));
                Ok(())
            }
            Err(e) => {
                let mut failure = classify(
                    &store,
                    &e,
                    FailureKind::Instantiate,
                    self.options.instantiate_deadline,
                );
                failure.message = format!("instantiation failed: {}", failure.message);
                self.note_peak(store.data().limiter.peak());
                Err(failure)
            }
        }
    }

    /// Drops the instance, e.g. after it gave an invalid answer.
    pub fn discard(&mut self) {
        self.instance = None;
    }

    fn note_peak(&mut self, peak: usize) {
        self.peak_memory = self.peak_memory.max(peak);
    }
}

fn classify(
    store: &Store<HostState>,
    error: &wasmtime::Error,
    otherwise: FailureKind,
    deadline: Duration,
) -> CallFailure {
    let kind = match error.downcast_ref::<wasmtime::Trap>() {
        Some(wasmtime::Trap::Interrupt) => {
            let kind = if otherwise == FailureKind::Instantiate {
                FailureKind::Instantiate
            } else {
                FailureKind::Timeout
            };
            return CallFailure::new(kind, format!("interrupted at its deadline of {deadline:?}"));
        }
        Some(wasmtime::Trap::OutOfFuel) => FailureKind::OutOfFuel,
        _ if store.data().limiter.refused() => FailureKind::OverLimit,
        _ => otherwise,
    };
    // `{:#}` is the error chain without wasmtime's multi-line backtrace.
    CallFailure::new(kind, format!("{error:#}"))
}

type Job<W> = Box<dyn FnOnce(&mut Live<W>) + Send>;

/// A thread that owns a plugin's [`Live`] and runs calls sent to it. Used for components
/// that import WASI (see the module documentation of `plugin`).
pub(crate) struct Worker<W: World> {
    jobs: mpsc::Sender<Job<W>>,
    /// How long to wait for an answer before giving the worker up for lost.
    patience: Duration,
}

impl<W: World> Worker<W> {
    pub fn spawn(live: Live<W>, patience: Duration) -> std::io::Result<Self> {
        let (jobs, inbox) = mpsc::channel::<Job<W>>();
        let name = format!("kairos-plugin-{}", live.plugin.meta.name);
        std::thread::Builder::new().name(name).spawn(move || {
            let mut live = live;
            while let Ok(job) = inbox.recv() {
                job(&mut live);
            }
        })?;
        Ok(Worker { jobs, patience })
    }

    /// Runs `job` on the worker and waits for its answer. `None` if the worker is gone or
    /// did not answer within its patience (a host call that hung); the caller then replaces
    /// the worker.
    pub fn run<R: Send + 'static>(
        &self,
        job: impl FnOnce(&mut Live<W>) -> R + Send + 'static,
    ) -> Option<R> {
        let (reply, answer) = mpsc::sync_channel(1);
        let job: Job<W> = Box::new(move |live| {
            let _ = reply.send(job(live));
        });
        self.jobs.send(job).ok()?;
        answer.recv_timeout(self.patience).ok()
    }
}

/// Where a plugin's calls execute.
pub(crate) enum Exec<W: World> {
    /// On the caller's thread.
    Inline(Live<W>),
    /// On a dedicated worker thread.
    Worker(Worker<W>),
}

impl<W: World> Exec<W> {
    /// The right executor for `plugin`.
    pub fn new(plugin: Arc<Compiled<W>>, options: Arc<PluginOptions>) -> Result<Self, LoadError> {
        let wasi = plugin.meta.info.imports_wasi;
        let name = plugin.meta.name.clone();
        let live = Live::new(plugin, options.clone());
        if !wasi {
            return Ok(Exec::Inline(live));
        }
        Worker::spawn(live, worker_patience(&options))
            .map(Exec::Worker)
            .map_err(|e| LoadError::Compile {
                name,
                message: format!("cannot start its worker thread: {e}"),
            })
    }
}

impl<W: World> Exec<W> {
    /// Drops the instance (the next call makes a new one).
    pub fn discard(&mut self) {
        match self {
            Exec::Inline(live) => live.discard(),
            Exec::Worker(worker) => {
                let _ = worker.run(|live| live.discard());
            }
        }
    }
}

/// A worker that has not answered well after its deadline is stuck in the host.
fn worker_patience(options: &PluginOptions) -> Duration {
    options.deadline * 4 + options.instantiate_deadline + Duration::from_millis(250)
}
