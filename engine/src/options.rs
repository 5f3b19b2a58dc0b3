//! Where and how a model runs: device, kernels, threads.

use crate::EngineError;
use crate::kernels::{Isa, Pool, Precision};

/// The device a model runs on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeviceKind {
    /// The host CPU (default).
    #[default]
    Cpu,
    /// CUDA device with this ordinal; needs the `cuda` cargo feature.
    Cuda(usize),
}

impl std::str::FromStr for DeviceKind {
    type Err = EngineError;

    /// `cpu`, `cuda` or `cuda:N`.
    fn from_str(s: &str) -> Result<Self, EngineError> {
        match s {
            "cpu" => Ok(DeviceKind::Cpu),
            "cuda" => Ok(DeviceKind::Cuda(0)),
            _ => s
                .strip_prefix("cuda:")
                .and_then(|n| n.parse().ok())
                .map(DeviceKind::Cuda)
                .ok_or_else(|| {
                    EngineError::InvalidInput(format!("unknown device `{s}` (cpu, cuda, cuda:N)"))
                }),
        }
    }
}

/// Which implementation of the model's maths to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kernels {
    /// The fast CPU kernels on the CPU, Candle on CUDA (default).
    #[default]
    Auto,
    /// The fast CPU kernels with the best instruction set (AVX2+FMA when present).
    Fast,
    /// The fast CPU kernels without SIMD intrinsics (what a CPU without AVX2 runs).
    Portable,
    /// Plain Candle tensor ops (the reference implementation; the only one on CUDA).
    Candle,
}

impl std::str::FromStr for Kernels {
    type Err = EngineError;

    /// `auto`, `fast`, `portable` or `candle`.
    fn from_str(s: &str) -> Result<Self, EngineError> {
        match s {
            "auto" => Ok(Kernels::Auto),
            "fast" => Ok(Kernels::Fast),
            "portable" => Ok(Kernels::Portable),
            "candle" => Ok(Kernels::Candle),
            _ => Err(EngineError::InvalidInput(format!(
                "unknown kernels `{s}` (auto, fast, portable, candle)"
            ))),
        }
    }
}

/// How to run a model.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct EngineOptions {
    /// Device.
    pub device: DeviceKind,
    /// Kernels.
    pub kernels: Kernels,
    /// CPU threads for the fast kernels (0: one per core, or `KAIROS_ENGINE_THREADS`).
    pub threads: usize,
    /// Number format of the fast kernels' weight GEMMs (SmolVLA's and π's): `f32`
    /// (default, exact) or `bf16` (AVX512_BF16; other CPUs fall back to f32 with a warning).
    #[serde(default)]
    pub precision: Precision,
    /// Replay SmolVLA's Euler loop on CUDA as a captured CUDA graph, one per batch shape (see
    /// docs/ENGINE.md, "CUDA"); off by default. Needs a CUDA device: asking for it on the CPU
    /// is an error at load. Other models run their loops uncaptured.
    #[serde(default)]
    pub cuda_graphs: bool,
}

/// A resolved execution target.
pub(crate) enum Target {
    /// The fast CPU kernels on this pool.
    Fast(Pool),
    /// Candle ops on this device.
    Candle(candle_core::Device),
}

impl EngineOptions {
    /// What these options run on, e.g. `cpu, fast kernels Avx2Fma, 2 threads` (for profiles).
    pub fn describe(&self) -> Result<String, EngineError> {
        Ok(self.target()?.describe())
    }

    /// The path of a model that runs on Candle ops wherever these options put it (the CPU
    /// for every CPU kernel choice): `candle:cpu` or `candle:cuda:N`.
    pub fn candle_path(&self) -> String {
        match self.device {
            DeviceKind::Cpu => "candle:cpu".into(),
            DeviceKind::Cuda(i) => format!("candle:cuda:{i}"),
        }
    }

    pub(crate) fn target(&self) -> Result<Target, EngineError> {
        if self.cuda_graphs && self.device == DeviceKind::Cpu {
            return Err(cuda_graphs_need_cuda());
        }
        match (self.device, self.kernels) {
            (DeviceKind::Cpu, Kernels::Auto | Kernels::Fast) => {
                Ok(Target::Fast(Pool::new(self.threads)?))
            }
            (DeviceKind::Cpu, Kernels::Portable) => {
                Ok(Target::Fast(Pool::with_isa(self.threads, Isa::Portable)?))
            }
            (DeviceKind::Cpu, Kernels::Candle) => Ok(Target::Candle(candle_core::Device::Cpu)),
            (DeviceKind::Cuda(i), Kernels::Auto | Kernels::Candle) => {
                Ok(Target::Candle(cuda_device(i)?))
            }
            (DeviceKind::Cuda(_), k) => Err(EngineError::InvalidInput(format!(
                "{k:?} kernels run on the CPU only; use auto or candle on CUDA"
            ))),
        }
    }
}

impl Target {
    /// The path a stage runs on here, in `precision`, as `kairos predict` reports it:
    /// `fast:<isa>` (`avx512`, `avx2-fma`, `portable`) or `candle:<device>` (`cpu`, `cuda:N`),
    /// with `-bf16` when the weight products run in bf16 (for the fast kernels: when this CPU
    /// runs them natively; otherwise they fall back to f32 and the path says so).
    pub(crate) fn path(&self, precision: Precision) -> String {
        let (base, precision) = match self {
            Target::Fast(pool) => {
                let isa = match pool.isa() {
                    Isa::Avx512 => "avx512",
                    Isa::Avx2Fma => "avx2-fma",
                    Isa::Portable => "portable",
                };
                (format!("fast:{isa}"), precision.resolve(pool.isa()))
            }
            Target::Candle(d) => {
                let device = match d.location() {
                    candle_core::DeviceLocation::Cpu => "cpu".to_string(),
                    candle_core::DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}"),
                    other => format!("{other:?}").to_lowercase(),
                };
                (format!("candle:{device}"), precision)
            }
        };
        match precision {
            Precision::F32 => base,
            Precision::Bf16 => format!("{base}-bf16"),
        }
    }

    /// Human-readable description, e.g. `cpu fast avx2 (2 threads)`.
    pub(crate) fn describe(&self) -> String {
        match self {
            Target::Fast(pool) => format!(
                "cpu, fast kernels {:?}, {} threads",
                pool.isa(),
                pool.threads()
            ),
            Target::Candle(candle_core::Device::Cpu) => "cpu, candle".to_string(),
            // The ordinal, not `Device`'s Debug form, whose id is Candle's internal counter
            // (a profile from an H200 read `Cuda(CudaDevice(DeviceId(2)))` for `cuda:0`).
            Target::Candle(d) => match d.location() {
                candle_core::DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}, candle"),
                other => format!("{other:?}, candle"),
            },
        }
    }
}

/// The refusal of [`EngineOptions::cuda_graphs`] without a CUDA device.
pub(crate) fn cuda_graphs_need_cuda() -> EngineError {
    EngineError::InvalidInput(
        "CUDA graphs need a CUDA device (--device cuda:N); the CPU paths have no graphs".into(),
    )
}

#[cfg(feature = "cuda")]
fn cuda_device(ordinal: usize) -> Result<candle_core::Device, EngineError> {
    let device = candle_core::Device::new_cuda(ordinal)?;
    if let candle_core::Device::Cuda(cuda) = &device {
        keep_freed_device_memory(cuda)?;
    }
    Ok(device)
}

/// Makes the device's default memory pool keep the memory Candle frees, instead of handing it
/// back to the driver.
///
/// Candle allocates every op's output with cudarc's stream-ordered allocator
/// (`cuMemAllocAsync` on the device's default pool) and frees it with `cuMemFreeAsync`. The
/// pool's release threshold is 0 unless set (cudarc 0.19 never sets it), so at every
/// synchronisation (each batch's copy of its results to the host) the pool returns its free
/// memory to the driver, and the next batch maps it again. With the threshold at `u64::MAX`
/// the pool keeps what it has: every batch after the first of a shape is served from memory the
/// pool already holds, and the pool's footprint is the largest working set a batch has needed.
/// The pool is the device's, shared by every model on it in this process; memory another
/// process needs is not given back until this one exits, which a server that owns its GPU
/// wants anyway.
#[cfg(feature = "cuda")]
fn keep_freed_device_memory(cuda: &candle_core::CudaDevice) -> Result<(), EngineError> {
    use candle_core::cuda_backend::WrapErr;
    use candle_core::cuda_backend::cudarc::driver::{result, sys};
    let stream = cuda.cuda_stream();
    let context = stream.context();
    context.bind_to_thread().w()?;
    let mut threshold: u64 = u64::MAX;
    // SAFETY: `cu_device()` is the device of a live context (Candle holds it), as
    // `cuDeviceGetDefaultMemPool` requires; `CU_MEMPOOL_ATTR_RELEASE_THRESHOLD` takes a
    // `cuuint64_t`, and `threshold` is a live `u64` for the duration of the call.
    unsafe {
        let pool = result::device::get_default_mem_pool(context.cu_device()).w()?;
        result::mem_pool::set_attribute(
            pool,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
            (&raw mut threshold).cast(),
        )
        .w()?;
    }
    Ok(())
}

#[cfg(not(feature = "cuda"))]
fn cuda_device(ordinal: usize) -> Result<candle_core::Device, EngineError> {
    Err(EngineError::InvalidInput(format!(
        "cuda:{ordinal} requested, but this build has no CUDA support: rebuild with \
         `--features cuda` (needs the CUDA toolkit's nvcc; see docs/ENGINE.md)"
    )))
}

/// The environment variable through which Candle's CPU ops learn their thread count.
pub const CANDLE_THREADS_VAR: &str = "RAYON_NUM_THREADS";

/// The thread count Candle's CPU ops use when [`CANDLE_THREADS_VAR`] is unset, for a process to
/// pin once at start-up.
///
/// Candle (0.11) works this count out again on every CPU matmul when the variable is unset, from
/// sysfs and `/proc/cpuinfo`: on the small matrices of a served model that reading costs more
/// CPU time than the arithmetic (docs/BENCHMARKS.md, "Candle path"). A binary sets the variable
/// to this value before it starts any thread; the count Candle uses does not change, only how
/// often it is worked out.
pub fn candle_cpu_threads() -> usize {
    candle_core::utils::get_num_threads()
}
