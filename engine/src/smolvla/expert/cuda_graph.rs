//! SmolVLA's Euler loop replayed as a CUDA graph, one graph per batch shape
//! ([`crate::EngineOptions::cuda_graphs`]).
//!
//! At B = 1 the loop's ten steps are some 3,000 small kernels, and launching them one by one from
//! the host costs more than running them. A CUDA graph records the launches once and replays
//! them with one call. A graph replays fixed device addresses, so each batch shape (rows, prefix
//! length) gets its own: persistent input tensors (the noise, the time embeddings and the
//! attention context: prefix keys and values, masks, RoPE tables) that each call's inputs are
//! copied into, persistent output tensors (the final sample, every step's velocity and update)
//! that the graph writes, and the graph itself.
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
//! Any error while capturing or launching a shape's graph sends that shape back to the
//! uncaptured loop for the rest of the process, with one warning: a graph that cannot be
//! captured never fails a batch.

use std::collections::HashMap;
use std::sync::Mutex;

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

/// The captured loops of one expert, by shape.
pub(super) struct EulerGraphs {
    device: CudaDevice,
    state: Mutex<GraphState>,
}

#[derive(Default)]
struct GraphState {
    shapes: HashMap<Shape, Slot>,
    replays: u64,
}

enum Slot {
    Captured(Box<CapturedLoop>),
    /// Capturing or launching failed once: the uncaptured loop from now on.
    Uncaptured,
}

/// One shape's graph and the tensors it reads and writes.
struct CapturedLoop {
    graph: ReplayableGraph,
    x0: Tensor,
    context: AttentionContext,
    output: DeviceLoop,
}

/// A [`CudaGraph`] that can move between threads.
struct ReplayableGraph(CudaGraph);

// SAFETY: a CUDA graph and its executable graph are driver handles that any thread of the
// process may use; the driver requires only that calls on one graph be serialised, and every use
// of a `ReplayableGraph` happens under `EulerGraphs::state`'s mutex.
unsafe impl Send for ReplayableGraph {}

impl EulerGraphs {
    /// Graphs on `device`: every tensor of the expert lives there and uses its one stream.
    pub(super) fn new(device: CudaDevice) -> Self {
        EulerGraphs {
            device,
            state: Mutex::new(GraphState::default()),
        }
    }

    /// How many shapes have a graph, how many fell back, and how many replays there were.
    pub(super) fn stats(&self) -> CudaGraphStats {
        let state = self.lock();
        let captured = state
            .shapes
            .values()
            .filter(|s| matches!(s, Slot::Captured(_)))
            .count();
        CudaGraphStats {
            captured,
            uncaptured: state.shapes.len() - captured,
            replays: state.replays,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, GraphState> {
        // A panic while the lock was held left at worst a shape half set up; the slots are
        // replaced whole, so the map itself is consistent.
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
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
        // Held to the end: the graph's inputs and outputs are shared by every call of the shape.
        let mut state = self.lock();
        let replayed = match state.shapes.get(&shape) {
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
                state.replays += 1;
                return Ok(host);
            }
            Some(Err(e)) => {
                tracing::warn!(
                    "SmolVLA expert: replaying the CUDA graph of {rows} rows x {prefix_len} \
                     prefix tokens failed ({e}); that shape runs uncaptured from now on"
                );
                state.shapes.insert(shape, Slot::Uncaptured);
                return run(x0, temb, context)?.to_host();
            }
            None => {}
        }
        // First call of this shape: uncaptured, with Candle's small uploads kept for the capture.
        let cache = self.device.enable_cuda_graph_htod_cache();
        let result = run(x0, temb, context)?;
        let slot = match self.capture(x0, temb, context, &result, run) {
            Ok(captured) => Slot::Captured(Box::new(captured)),
            Err(e) => {
                tracing::warn!(
                    "SmolVLA expert: capturing the Euler loop of {rows} rows x {prefix_len} \
                     prefix tokens as a CUDA graph failed ({e}); that shape runs uncaptured"
                );
                Slot::Uncaptured
            }
        };
        drop(cache);
        state.shapes.insert(shape, slot);
        result.to_host()
    }

    /// Capture `run` on this call's inputs, which become the graph's persistent inputs (the
    /// caller drops its own references after the call; `temb` is the same for every call).
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
            graph: ReplayableGraph(graph),
            x0,
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
        self.graph.0.launch().w()?;
        Ok(())
    }
}
