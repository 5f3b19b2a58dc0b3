//! SmolVLA's Euler loop replayed as a CUDA graph, one graph per batch shape
//! ([`crate::EngineOptions::cuda_graphs`]).
//!
//! At B = 1 the loop's ten steps are thousands of small kernels, each launched from the host,
//! and the launches may cost more than the work. A CUDA graph records the launches once and replays
//! them with one call. A graph replays fixed device addresses, so each batch shape (rows, prefix
//! length) gets its own: persistent input tensors (the noise and the attention context: prefix
//! keys and values, masks, RoPE tables) that each call's inputs are copied into, the time
//! embeddings (the same for every call), persistent output tensors (the final sample, every
//! step's velocity and update) that the graph writes, and the graph itself.
//!
//! The first call of a shape runs the loop uncaptured (which loads Candle's kernels, sets up
//! cuBLAS and fills Candle's upload cache, below) and returns that result; then the loop is
//! captured with cudarc's stream capture on Candle's stream, reading the persistent inputs.
//! Candle allocates every op's output with `cuMemAllocAsync`: inside the capture those become
//! the graph's own allocation nodes, and every intermediate is dropped (a `cuMemFreeAsync`
//! node) before the capture ends, so a replay leaves no allocation behind. Candle uploads
//! small host arrays (the shapes and strides of a strided kernel) while it runs an op, which a
//! capture cannot record; [`candle_core::CudaDevice::enable_cuda_graph_htod_cache`] keeps every
//! such upload of up to 4 KiB on the device, keyed by its bytes, so the capture reuses what the
//! uncaptured run uploaded. Candle refuses device-to-host copies during a capture, and the
//! loop makes none.
//!
//! Graphs belong to the thread that captured them. Candle's upload cache is thread-local, and
//! a graph's copies read the cached buffers at every replay, so a graph must not outlive the
//! thread whose cache it reads; and Candle's stream is the calling thread's default stream, so
//! two threads are two streams, each with its own graph and buffers. Each thread keeps its
//! graphs in a thread-local map (an engine serves from one thread, so it captures once per
//! shape), and they are freed with the thread, or at the thread's next call once their expert
//! is gone.
//!
//! Any error while capturing or launching a shape's graph sends that shape back to the
//! uncaptured loop (on that thread) for the rest of the process, with one warning: a graph that
//! cannot be captured never fails a batch.

use std::cell::RefCell;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Weak};

use candle_core::cuda_backend::WrapErr;
use candle_core::cuda_backend::cudarc::driver::{CudaGraph, sys};
use candle_core::{CudaDevice, Tensor};

use super::CudaGraphStats;
use super::candle_backend::{AttentionContext, DeviceLoop, HostLoop};
use crate::EngineError;

/// What one graph is captured for: the batch's rows and its padded prefix length (every tensor
/// of the loop has a shape fixed by these two and the model's dimensions).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct Shape {
    rows: usize,
    prefix_len: usize,
}

/// The CUDA graphs of one expert's Euler loop. The graphs themselves are in [`THREAD_GRAPHS`].
pub(super) struct EulerGraphs {
    device: CudaDevice,
    /// Shared with the thread-local maps (as a `Weak`): it names the expert there, and a map
    /// whose expert is gone is dropped.
    counters: Arc<Counters>,
}

#[derive(Default)]
struct Counters {
    captured: AtomicUsize,
    uncaptured: AtomicUsize,
    replays: AtomicU64,
}

/// One expert's graphs on one thread.
struct ThreadGraphs {
    expert: Weak<Counters>,
    shapes: HashMap<Shape, Slot>,
}

thread_local! {
    static THREAD_GRAPHS: RefCell<Vec<ThreadGraphs>> = const { RefCell::new(Vec::new()) };
}

enum Slot {
    Captured(Box<CapturedLoop>),
    /// Capturing or launching failed once: the uncaptured loop from now on.
    Uncaptured,
}

/// One shape's graph and the tensors it reads and writes.
struct CapturedLoop {
    graph: CudaGraph,
    x0: Tensor,
    /// Read by the graph, never rewritten: the time embeddings are the same for every call.
    _temb: Tensor,
    context: AttentionContext,
    output: DeviceLoop,
}

impl EulerGraphs {
    /// Graphs on `device`: every tensor of the expert lives there and uses its one stream.
    pub(super) fn new(device: CudaDevice) -> Self {
        EulerGraphs {
            device,
            counters: Arc::default(),
        }
    }

    /// How many shapes have been captured, how many fell back, and how many replays there were
    /// (over every thread).
    pub(super) fn stats(&self) -> CudaGraphStats {
        let c = &self.counters;
        CudaGraphStats {
            captured: c.captured.load(Ordering::Relaxed),
            uncaptured: c.uncaptured.load(Ordering::Relaxed),
            replays: c.replays.load(Ordering::Relaxed),
        }
    }

    /// `f` with this thread's graphs of this expert (made empty on first use).
    fn with_thread_graphs<T>(&self, f: impl FnOnce(&mut HashMap<Shape, Slot>) -> T) -> T {
        THREAD_GRAPHS.with(|all| {
            let mut all = all.borrow_mut();
            all.retain(|g| g.expert.strong_count() > 0);
            let mine = Arc::downgrade(&self.counters);
            let index = match all.iter().position(|g| g.expert.ptr_eq(&mine)) {
                Some(i) => i,
                None => {
                    all.push(ThreadGraphs {
                        expert: mine,
                        shapes: HashMap::new(),
                    });
                    all.len() - 1
                }
            };
            f(&mut all[index].shapes)
        })
    }

    /// The loop from `x0` with `context`, on the host: replayed from this shape's graph when
    /// there is one, otherwise `run` uncaptured (the first call of a shape then captures the
    /// graph; its own result is the uncaptured one). `run` is the loop: it reads its three
    /// arguments and allocates everything it returns.
    pub(super) fn sample(
        &self,
        x0: &Tensor,
        temb: &Tensor,
        context: &AttentionContext,
        run: &dyn Fn(&Tensor, &Tensor, &AttentionContext) -> Result<DeviceLoop, EngineError>,
    ) -> Result<HostLoop, EngineError> {
        let (rows, _, _, prefix_len) = context.cross_mask.dims4()?;
        let shape = Shape { rows, prefix_len };
        self.with_thread_graphs(|shapes| {
            let replayed = match shapes.get(&shape) {
                None => None,
                Some(Slot::Uncaptured) => return run(x0, temb, context)?.to_host(),
                // A failed launch may only show at the copy to the host, which waits for it.
                Some(Slot::Captured(captured)) => Some(
                    captured
                        .replay(x0, context)
                        .and_then(|()| captured.output.to_host()),
                ),
            };
            match replayed {
                Some(Ok(host)) => {
                    self.counters.replays.fetch_add(1, Ordering::Relaxed);
                    return Ok(host);
                }
                Some(Err(e)) => {
                    tracing::warn!(
                        "SmolVLA expert: replaying the CUDA graph of {rows} rows x {prefix_len} \
                         prefix tokens failed ({e}); that shape runs uncaptured from now on"
                    );
                    shapes.insert(shape, Slot::Uncaptured);
                    self.counters.captured.fetch_sub(1, Ordering::Relaxed);
                    self.counters.uncaptured.fetch_add(1, Ordering::Relaxed);
                    return run(x0, temb, context)?.to_host();
                }
                None => {}
            }
            // First call of this shape: uncaptured, with Candle's small uploads kept for the
            // capture.
            let cache = self.device.enable_cuda_graph_htod_cache();
            let result = run(x0, temb, context)?;
            let slot = match self.capture(x0, temb, context, &result, run) {
                Ok(captured) => {
                    self.counters.captured.fetch_add(1, Ordering::Relaxed);
                    Slot::Captured(Box::new(captured))
                }
                Err(e) => {
                    tracing::warn!(
                        "SmolVLA expert: capturing the Euler loop of {rows} rows x {prefix_len} \
                         prefix tokens as a CUDA graph failed ({e}); that shape runs uncaptured"
                    );
                    self.counters.uncaptured.fetch_add(1, Ordering::Relaxed);
                    Slot::Uncaptured
                }
            };
            drop(cache);
            shapes.insert(shape, slot);
            result.to_host()
        })
    }

    /// Capture `run` on this call's inputs, which become the graph's persistent inputs (the
    /// caller drops its own references after the call).
    fn capture(
        &self,
        x0: &Tensor,
        temb: &Tensor,
        context: &AttentionContext,
        like: &DeviceLoop,
        run: &dyn Fn(&Tensor, &Tensor, &AttentionContext) -> Result<DeviceLoop, EngineError>,
    ) -> Result<CapturedLoop, EngineError> {
        let output = DeviceLoop {
            x: like.x.zeros_like()?,
            velocities: like.velocities.zeros_like()?,
            updates: like.updates.zeros_like()?,
        };
        let (x0, temb, context) = (x0.clone(), temb.clone(), context.clone());
        let stream = self.device.cuda_stream();
        stream
            .begin_capture(sys::CUstreamCaptureMode::CU_STREAM_CAPTURE_MODE_THREAD_LOCAL)
            .w()?;
        // Every intermediate of the loop is freed inside this call, before the capture ends.
        let body = (|| -> Result<(), EngineError> {
            let step = run(&x0, &temb, &context)?;
            output.x.slice_set(&step.x, 0, 0)?;
            output.velocities.slice_set(&step.velocities, 0, 0)?;
            output.updates.slice_set(&step.updates, 0, 0)?;
            Ok(())
        })();
        // The capture must end even when the body failed, or the stream stays in capture mode.
        let ended = stream.end_capture(sys::CUgraphInstantiate_flags(0)).w();
        body?;
        let graph = ended?.ok_or_else(|| {
            EngineError::InvalidInput("the captured Euler loop is an empty graph".into())
        })?;
        Ok(CapturedLoop {
            graph,
            x0,
            _temb: temb,
            context,
            output,
        })
    }
}

impl CapturedLoop {
    /// Copy this call's inputs into the graph's and replay it (the outputs are then in
    /// `self.output`, once the stream gets there).
    fn replay(&self, x0: &Tensor, context: &AttentionContext) -> Result<(), EngineError> {
        self.x0.slice_set(x0, 0, 0)?;
        for (persistent, new) in self.context.tensors().into_iter().zip(context.tensors()) {
            persistent.slice_set(new, 0, 0)?;
        }
        self.graph.launch().w()?;
        Ok(())
    }
}
