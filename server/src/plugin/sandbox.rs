//! The sandbox one plugin instance runs in: its store state, memory limiter and linker.
//!
//! A plugin gets nothing from the host but the arguments of each call. Components built by
//! toolchains that link a language runtime (componentize-py) import WASI 0.2; they are linked
//! against a WASI context that grants nothing:
//! - no preopened directories, no environment variables, no arguments, no network
//!   (TCP, UDP and name lookup disabled, every address refused);
//! - stdin is empty; stdout and stderr are discarded;
//! - both clocks are frozen at zero: a policy gets time only from its arguments (`now-us`),
//!   which keeps its decisions reproducible and removes a timing side channel; and the calls
//!   that would put the host thread to sleep (`subscribe-duration`, `subscribe-instant`) trap,
//!   because epoch deadlines interrupt guest code but not a host that is sleeping for it;
//! - `wasi:random` works (the Python runtime needs it; randomness reveals nothing about the
//!   host); the insecure seed is fixed so hash seeds are reproducible.

use std::time::Duration;

use wasmtime::component::{Linker, ResourceTable};
use wasmtime::{Engine, ResourceLimiter};
use wasmtime_wasi::{WasiCtx, WasiCtxView, WasiView};

/// Per-store state: the memory limiter and the (deny-all) WASI context.
pub struct HostState {
    /// Enforces the memory cap and records the peak.
    pub limiter: MemoryLimiter,
    wasi: WasiCtx,
    table: ResourceTable,
}

impl HostState {
    /// State for one instance with a memory cap of `memory_limit` bytes.
    pub fn new(memory_limit: usize) -> Self {
        HostState {
            limiter: MemoryLimiter::new(memory_limit),
            wasi: deny_all_wasi(),
            table: ResourceTable::new(),
        }
    }
}

impl WasiView for HostState {
    fn ctx(&mut self) -> WasiCtxView<'_> {
        WasiCtxView {
            ctx: &mut self.wasi,
            table: &mut self.table,
        }
    }
}

/// Caps linear memory and table growth, and remembers the largest memory it allowed.
#[derive(Debug, Clone)]
pub struct MemoryLimiter {
    limit: usize,
    peak: usize,
    refused: bool,
}

/// Most table elements an instance may have (function-pointer tables of C and Python runtimes
/// stay far below this).
const TABLE_ELEMENTS_LIMIT: usize = 1 << 20;

impl MemoryLimiter {
    /// A limiter allowing `limit` bytes of linear memory in total.
    pub fn new(limit: usize) -> Self {
        MemoryLimiter {
            limit,
            peak: 0,
            refused: false,
        }
    }

    /// The largest linear memory size allowed so far, in bytes.
    pub fn peak(&self) -> usize {
        self.peak
    }

    /// Whether a growth request was refused (the instance then trapped).
    pub fn refused(&self) -> bool {
        self.refused
    }
}

impl ResourceLimiter for MemoryLimiter {
    fn memory_growing(
        &mut self,
        _current: usize,
        desired: usize,
        _maximum: Option<usize>,
    ) -> wasmtime::Result<bool> {
        if desired > self.limit {
            self.refused = true;
            // Trapping (rather than returning -1 from `memory.grow`) stops a plugin that would
            // otherwise loop on failed growth until its deadline.
            return Err(wasmtime::Error::msg(format!(
                "memory limit exceeded: {desired} bytes requested, limit {} bytes",
                self.limit
            )));
        }
        self.peak = self.peak.max(desired);
        Ok(true)
    }

    fn table_growing(
        &mut self,
        _current: usize,
        desired: usize,
        _maximum: Option<usize>,
    ) -> wasmtime::Result<bool> {
        if desired > TABLE_ELEMENTS_LIMIT {
            self.refused = true;
            return Err(wasmtime::Error::msg(format!(
                "table limit exceeded: {desired} elements requested, limit {TABLE_ELEMENTS_LIMIT}"
            )));
        }
        Ok(true)
    }
}

/// The linker for components that import nothing: defines nothing.
pub fn plain_linker(engine: &Engine) -> Linker<HostState> {
    Linker::new(engine)
}

/// The linker for components that import WASI: every WASI 0.2 interface, backed by
/// [`deny_all_wasi`], with the sleeping calls replaced by traps.
pub fn wasi_linker(engine: &Engine) -> wasmtime::Result<Linker<HostState>> {
    let mut linker = Linker::new(engine);
    wasmtime_wasi::p2::add_to_linker_sync(&mut linker)?;
    linker.allow_shadowing(true);
    let mut clock = linker.instance("wasi:clocks/monotonic-clock@0.2.12")?;
    clock.func_wrap(
        "subscribe-duration",
        |_, _: (u64,)| -> wasmtime::Result<(wasmtime::component::Resource<wasmtime_wasi::p2::DynPollable>,)> {
            Err(wasmtime::Error::msg("plugins may not sleep (wasi:clocks subscribe-duration)"))
        },
    )?;
    clock.func_wrap(
        "subscribe-instant",
        |_, _: (u64,)| -> wasmtime::Result<(wasmtime::component::Resource<wasmtime_wasi::p2::DynPollable>,)> {
            Err(wasmtime::Error::msg("plugins may not sleep (wasi:clocks subscribe-instant)"))
        },
    )?;
    Ok(linker)
}

/// A WASI context that grants nothing (see the module documentation).
pub fn deny_all_wasi() -> WasiCtx {
    let mut builder = WasiCtx::builder();
    builder
        .allow_tcp(false)
        .allow_udp(false)
        .allow_ip_name_lookup(false)
        .wall_clock(FrozenClock)
        .monotonic_clock(FrozenClock)
        .insecure_random_seed(0);
    builder.build()
}

/// A clock that always reads zero.
struct FrozenClock;

impl wasmtime_wasi::HostWallClock for FrozenClock {
    fn resolution(&self) -> Duration {
        Duration::from_secs(1)
    }

    fn now(&self) -> Duration {
        Duration::ZERO
    }
}

impl wasmtime_wasi::HostMonotonicClock for FrozenClock {
    fn resolution(&self) -> u64 {
        1_000_000_000
    }

    fn now(&self) -> u64 {
        0
    }
}
