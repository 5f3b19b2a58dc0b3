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

/// One call of an export with owned arguments, to run on a worker thread.
pub(crate) type OwnedCall<W, R> =
    Box<dyn FnOnce(&mut Store<HostState>, &<W as World>::Instance) -> wasmtime::Result<R> + Send>;

/// A thread that owns a plugin's [`Live`] and runs calls sent to it. Used for components
/// that import WASI (see the module documentation of `plugin`).
struct Worker<W: World> {
    jobs: mpsc::Sender<Job<W>>,
}

impl<W: World> Worker<W> {
    fn spawn(live: Live<W>) -> std::io::Result<Self> {
        let (jobs, inbox) = mpsc::channel::<Job<W>>();
        let name = format!("kairos-plugin-{}", live.plugin.meta.name);
        std::thread::Builder::new().name(name).spawn(move || {
            let mut live = live;
            // Ends when the `Worker` is dropped (its sender with it), after the job in hand:
            // an abandoned, stuck thread exits as soon as its host call returns.
            while let Ok(job) = inbox.recv() {
                job(&mut live);
            }
        })?;
        Ok(Worker { jobs })
    }

    /// Runs `job` on the worker and waits up to `patience` for its answer. `None` if the
    /// worker is gone or did not answer in time.
    fn run<R: Send + 'static>(
        &self,
        patience: Duration,
        job: impl FnOnce(&mut Live<W>) -> R + Send + 'static,
    ) -> Option<R> {
        let (reply, answer) = mpsc::sync_channel(1);
        self.post(move |live| {
            // The caller may have given up on this answer; nobody else wants it.
            let _ = reply.send(job(live));
        });
        answer.recv_timeout(patience).ok()
    }

    /// Queues `job` without waiting for it; jobs run in order, so the next call sees its effect.
    fn post(&self, job: impl FnOnce(&mut Live<W>) + Send + 'static) {
        // A send fails only if the thread is gone; the next `run` then reports it.
        let _ = self.jobs.send(Box::new(job));
    }
}

/// A worker thread and what is needed to start a replacement.
pub(crate) struct WorkerSlot<W: World> {
    /// `None` after a replacement could not be started; the next call tries again.
    worker: Option<Worker<W>>,
    plugin: Arc<Compiled<W>>,
    options: Arc<PluginOptions>,
    /// How long to wait for an answer before giving the worker up for lost.
    patience: Duration,
}

impl<W: World> WorkerSlot<W> {
    fn start(&mut self) -> Result<&Worker<W>, CallFailure> {
        if self.worker.is_none() {
            let live = Live::new(self.plugin.clone(), self.options.clone());
            let worker = Worker::spawn(live).map_err(|e| {
                CallFailure::new(
                    FailureKind::Instantiate,
                    format!("cannot start a worker thread: {e}"),
                )
            })?;
            self.worker = Some(worker);
        }
        self.worker
            .as_ref()
            .ok_or_else(|| CallFailure::new(FailureKind::Instantiate, "no worker thread"))
    }
}

/// Where a plugin's calls execute.
pub(crate) enum Exec<W: World> {
    /// On the caller's thread.
    Inline(Live<W>),
    /// On a dedicated worker thread.
    Worker(WorkerSlot<W>),
}

impl<W: World> Exec<W> {
    /// The right executor for `plugin`: a worker thread if it imports WASI, else the caller's.
    pub fn new(plugin: Arc<Compiled<W>>, options: Arc<PluginOptions>) -> Result<Self, LoadError> {
        if plugin.meta.info.imports_wasi {
            Self::worker(plugin, options)
        } else {
            Ok(Exec::Inline(Live::new(plugin, options)))
        }
    }

    /// An executor with a worker thread of its own, started now (so a thread that cannot start
    /// fails the load rather than a call).
    pub fn worker(
        plugin: Arc<Compiled<W>>,
        options: Arc<PluginOptions>,
    ) -> Result<Self, LoadError> {
        let name = plugin.meta.name.clone();
        let mut slot = WorkerSlot {
            worker: None,
            patience: worker_patience(&options),
            plugin,
            options,
        };
        slot.start().map_err(|failure| LoadError::Compile {
            name,
            message: failure.message,
        })?;
        Ok(Exec::Worker(slot))
    }

    /// The one way every export is called (horizon `choose`, priority `rank`/`order`,
    /// `task-finished`), so that every failure is handled alike:
    ///
    /// - the call runs under the deadline, memory cap and fuel budget ([`Live::call`]); a trap,
    ///   a timeout or an exceeded limit discards the instance;
    /// - `check` validates the answer; an invalid one discards the instance too;
    /// - on a worker thread that does not answer within its patience (stuck in a host call,
    ///   which an epoch deadline cannot interrupt), the thread is abandoned (it exits once its
    ///   host call returns; its late answer goes nowhere) and a fresh one with a fresh instance
    ///   replaces it, so the next call is not queued behind the stuck one.
    ///
    /// Every failure comes back as a [`CallFailure`] of its kind; counting it and quarantine
    /// are the policy's [`Health`](super::health::Health)'s business. `inline` runs the call on
    /// the caller's thread with borrowed arguments; `owned` makes the same call with owned
    /// arguments for a worker thread (only called for one).
    pub fn call<R: Send + 'static, T>(
        &mut self,
        inline: impl FnOnce(&mut Store<HostState>, &W::Instance) -> wasmtime::Result<R>,
        owned: impl FnOnce() -> OwnedCall<W, R>,
        check: impl FnOnce(R) -> Result<T, CallFailure>,
    ) -> Result<(T, CallCost), CallFailure> {
        let (answer, cost) = match self {
            Exec::Inline(live) => live.call(inline)?,
            Exec::Worker(slot) => {
                let job = owned();
                let patience = slot.patience;
                match slot.start()?.run(patience, move |live| live.call(job)) {
                    Some(result) => result?,
                    None => {
                        slot.worker = None;
                        let replaced = slot.start().is_ok();
                        return Err(CallFailure::new(
                            FailureKind::Stuck,
                            format!(
                                "its worker thread did not answer within {patience:?}; abandoned it{}",
                                if replaced {
                                    " and started a new one"
                                } else {
                                    " (a new one could not start yet)"
                                }
                            ),
                        ));
                    }
                }
            }
        };
        match check(answer) {
            Ok(value) => Ok((value, cost)),
            Err(failure) => {
                self.discard();
                Err(failure)
            }
        }
    }

    /// Drops the instance (the next call makes a new one).
    pub fn discard(&mut self) {
        match self {
            Exec::Inline(live) => live.discard(),
            Exec::Worker(slot) => {
                if let Some(worker) = &slot.worker {
                    worker.post(Live::discard);
                }
            }
        }
    }

    /// Swaps in a reloaded plugin; the old instance is dropped between calls.
    pub fn replace(&mut self, plugin: Arc<Compiled<W>>) {
        match self {
            Exec::Inline(live) => live.replace(plugin),
            Exec::Worker(slot) => {
                slot.plugin = plugin.clone();
                if let Some(worker) = &slot.worker {
                    worker.post(move |live| live.replace(plugin));
                }
            }
        }
    }
}

/// A worker that has not answered well after its deadline is stuck in the host.
fn worker_patience(options: &PluginOptions) -> Duration {
    options.deadline * 4 + options.instantiate_deadline + Duration::from_millis(250)
}

/// Test helpers shared by the wrappers' tests.
#[cfg(test)]
pub(crate) mod testing {
    use std::path::PathBuf;
    use std::sync::mpsc;
    use std::time::Duration;

    use super::{Exec, World};
    use crate::plugin::{PluginOptions, PluginSource};

    impl<W: World> Exec<W> {
        /// Blocks this executor's worker thread as a host call that never returns would, until
        /// the returned sender sends or is dropped. Returns once the thread is blocked.
        pub(crate) fn block_worker(&mut self) -> mpsc::Sender<()> {
            let Exec::Worker(slot) = self else {
                panic!("not a worker-thread executor")
            };
            let worker = slot.start().expect("a worker thread");
            let (entered_tx, entered) = mpsc::channel();
            let (release, released) = mpsc::channel::<()>();
            worker.post(move |_| {
                let _ = entered_tx.send(());
                let _ = released.recv();
            });
            entered
                .recv()
                .expect("the worker thread runs the blocking job");
            release
        }
    }

    /// A file under `plugins/build` (`plugins/build.sh` builds the shipped plugins there, as
    /// CI does first); a missing one fails the test.
    pub(crate) fn built(path: &str) -> PathBuf {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../plugins/build")
            .join(path);
        assert!(
            path.exists(),
            "{} is missing: build the shipped plugins first with `bash plugins/build.sh`",
            path.display()
        );
        path
    }

    /// `base` with a worker patience of 4 × 5 ms + 50 ms + 250 ms and no reload watcher, for
    /// tests of stuck workers. Their outcome does not depend on the patience: a blocked thread
    /// never answers before the test releases it; the patience only bounds how long they wait.
    pub(crate) fn short_patience(base: PluginOptions) -> PluginOptions {
        PluginOptions {
            deadline: Duration::from_millis(5),
            instantiate_deadline: Duration::from_millis(50),
            reload_poll: None,
            ..base
        }
    }

    /// The shipped plugin `name`.
    pub(crate) fn shipped(name: &str) -> PluginSource {
        PluginSource::File(built(&format!("{name}.wasm")))
    }
}
