//! CPU kernels of the fast path: packed f32 GEMM, attention, and the vector maths around them.
//!
//! Candle's CPU matmul (the `gemm` crate) repacks both operands on every call and its other ops
//! allocate a fresh tensor each; in the denoise loop the same weights are multiplied 10 times
//! by a 50-row activation, so the fast path packs every weight once at load into the layout
//! the micro-kernel streams ([`PackedMatrix`]), reuses one workspace for all steps, and splits
//! each GEMM's output columns across a fixed thread pool ([`Pool`]).
//!
//! Everything is exact IEEE f32 arithmetic (FMA accumulation in a fixed order); only the
//! summation order differs from PyTorch's. The micro-kernels use AVX-512F or AVX2+FMA when the
//! CPU has them (runtime detection, best first) and portable Rust otherwise; both give the same results up to rounding,
//! and each output element is computed in an order that does not depend on the batch size or the
//! thread count, so a request gets bit-identical results alone or in a batch.
//!
//! The kernel modules use each other in one direction only: [`bf16`] (rounding) and
//! [`matrix`] (operand views) use no other, [`vecmath`] (element-wise maths) uses [`bf16`],
//! [`gemm`] uses those three, and [`attention`] all of them.

pub mod attention;
pub mod bf16;
pub mod gemm;
pub mod matrix;
pub mod pool;
pub mod vecmath;

pub use gemm::{Init, PackedMatrix};
pub use matrix::{MatMut, MatRef};

/// Which instruction set the kernels use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// x86-64 AVX-512F (512-bit vectors; one vector per packed panel row).
    Avx512,
    /// x86-64 AVX2 with FMA (256-bit vectors).
    Avx2Fma,
    /// Portable Rust, any CPU.
    Portable,
}

impl Isa {
    /// The best instruction set this CPU supports, or the one `KAIROS_ISA` (`avx512`, `avx2`,
    /// `portable`) names when this CPU has it (to compare kernels on one machine).
    pub fn detect() -> Isa {
        let forced = match std::env::var("KAIROS_ISA").as_deref() {
            Ok("avx512") => Some(Isa::Avx512),
            Ok("avx2") => Some(Isa::Avx2Fma),
            Ok("portable") => Some(Isa::Portable),
            _ => None,
        };
        if let Some(isa) = forced.filter(|i| i.available()) {
            return isa;
        }
        if Isa::Avx512.available() {
            Isa::Avx512
        } else if Isa::Avx2Fma.available() {
            Isa::Avx2Fma
        } else {
            Isa::Portable
        }
    }

    /// Whether this CPU can run `self`.
    pub fn available(self) -> bool {
        match self {
            Isa::Portable => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2Fma => {
                std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
            }
            #[cfg(target_arch = "x86_64")]
            // AVX2 and FMA too: the element-wise maths use their AVX2 build on this ISA.
            Isa::Avx512 => {
                std::arch::is_x86_feature_detected!("avx512f") && Isa::Avx2Fma.available()
            }
            #[cfg(not(target_arch = "x86_64"))]
            Isa::Avx2Fma | Isa::Avx512 => false,
        }
    }
}

/// The number format of a model's weight GEMMs.
///
/// `F32` (default) is exact IEEE f32 throughout. `Bf16` stores the packed weights as bf16 (half
/// the memory) and rounds each GEMM's activations to bf16, accumulating in f32 (AVX512_BF16's
/// `vdpbf16ps`); everything else (norms, softmax, activations, RoPE, attention) stays f32.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// f32 weights and products.
    #[default]
    F32,
    /// bf16 weights and GEMM inputs, f32 accumulation.
    Bf16,
}

impl std::str::FromStr for Precision {
    type Err = crate::EngineError;

    /// `f32` or `bf16`.
    fn from_str(s: &str) -> Result<Self, crate::EngineError> {
        match s {
            "f32" => Ok(Precision::F32),
            "bf16" => Ok(Precision::Bf16),
            _ => Err(crate::EngineError::InvalidInput(format!(
                "unknown precision `{s}` (f32, bf16)"
            ))),
        }
    }
}

impl Precision {
    /// What a model asked to run in `self` runs in with kernels of `isa` on this CPU: `Bf16`
    /// only where the bf16 kernel is native (AVX-512 kernels on a CPU with AVX512_BF16, and
    /// `KAIROS_DISABLE_BF16` unset or `0`); otherwise `F32`, with a warning (once a process).
    pub fn resolve(self, isa: Isa) -> Precision {
        let disabled =
            std::env::var("KAIROS_DISABLE_BF16").is_ok_and(|v| !v.is_empty() && v != "0");
        self.resolve_for(isa == Isa::Avx512 && cpu_has_avx512_bf16() && !disabled)
    }

    /// [`Self::resolve`] given whether the native bf16 kernel can run.
    pub fn resolve_for(self, bf16_native: bool) -> Precision {
        match self {
            Precision::Bf16 if !bf16_native => {
                static WARNED: std::sync::Once = std::sync::Once::new();
                WARNED.call_once(|| {
                    tracing::warn!(
                        "precision bf16 needs AVX-512 kernels on a CPU with AVX512_BF16 (and \
                         KAIROS_DISABLE_BF16 unset); this one runs in f32"
                    )
                });
                Precision::F32
            }
            p => p,
        }
    }
}

/// Whether this CPU has AVX-512F and AVX512_BF16 (`vdpbf16ps`).
pub(crate) fn cpu_has_avx512_bf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// A fixed set of worker threads that run the parts of one kernel call.
///
/// Work is split into exactly `threads()` parts by the caller (output-column ranges of a GEMM,
/// heads of an attention), so the partition, and with it every result, is deterministic.
pub struct Pool {
    team: pool::Team,
    threads: usize,
    isa: Isa,
    /// Buffers for packed GEMM operands, one per concurrent caller: taken for a call and put
    /// back after it, never held while waiting for workers.
    scratch: FreeList<AlignedBuf>,
}

impl std::fmt::Debug for Pool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pool")
            .field("threads", &self.threads)
            .field("isa", &self.isa)
            .finish()
    }
}

impl Pool {
    /// A pool of `threads` workers (0 = [`default_threads`]) using the best instruction set.
    pub fn new(threads: usize) -> Result<Pool, crate::EngineError> {
        Pool::with_isa(threads, Isa::detect())
    }

    /// A pool whose kernels use `isa` (tests compare the portable and SIMD kernels).
    pub fn with_isa(threads: usize, isa: Isa) -> Result<Pool, crate::EngineError> {
        if !isa.available() {
            return Err(crate::EngineError::InvalidInput(format!(
                "this CPU cannot run {isa:?} kernels"
            )));
        }
        let threads = if threads == 0 {
            default_threads()
        } else {
            threads
        };
        let team = pool::Team::new(threads, "kairos-engine").map_err(|e| {
            crate::EngineError::InvalidInput(format!("cannot start {threads} engine threads: {e}"))
        })?;
        Ok(Pool {
            team,
            threads,
            isa,
            scratch: FreeList::default(),
        })
    }

    pub(crate) fn take_scratch(&self) -> AlignedBuf {
        self.scratch.take(AlignedBuf::default)
    }

    pub(crate) fn put_scratch(&self, buf: AlignedBuf) {
        self.scratch.put(buf);
    }

    /// The instruction set of the kernels run on this pool.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// How many parts to cut `units` independent pieces of work into: a few per thread, so that
    /// a thread that gets less CPU time (a shared machine) hands its share to the others instead
    /// of holding everyone up. Which thread runs a part never changes its result.
    pub fn parts(&self, units: usize) -> usize {
        if self.threads == 1 {
            1
        } else {
            units.min(4 * self.threads).max(1)
        }
    }

    /// [`Pool::parts`] for units of equal, sizeable cost (an attention head): one part per
    /// unit, so that threads claiming them one at a time end at most one unit apart. Cutting 12
    /// heads into `parts(12)` = 8 parts of one or two heads could leave one thread two heads
    /// behind the other.
    pub fn parts_per_unit(&self, units: usize) -> usize {
        if self.threads == 1 {
            1
        } else {
            units.clamp(1, 64)
        }
    }

    /// Number of worker threads.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Run `f(part)` for `part in 0..parts` on the pool's threads and the calling thread, and
    /// wait for all (see [`pool::Team::run`]).
    pub fn run(&self, parts: usize, f: impl Fn(usize) + Sync) {
        self.team.run(parts, &f);
    }
}

impl Pool {
    /// Split `out` (rows of `row_len` values) into one contiguous run of rows per thread and
    /// call `f(first_row, rows)` on each, in parallel. Small outputs stay on the calling thread.
    pub fn for_row_chunks<T: Send>(
        &self,
        out: &mut [T],
        row_len: usize,
        f: impl Fn(usize, &mut [T]) + Sync,
    ) {
        let rows = out.len() / row_len.max(1);
        // Below ~16k values a wake-up costs more than the work.
        let parts = if rows * row_len < 16 * 1024 {
            1
        } else {
            self.threads.min(rows).max(1)
        };
        if parts == 1 {
            f(0, out);
            return;
        }
        let base = SharedMut::new(out);
        self.run(parts, |p| {
            let (r0, r1) = (rows * p / parts, rows * (p + 1) / parts);
            // SAFETY: parts cover disjoint row ranges of `out`.
            let chunk = unsafe {
                std::slice::from_raw_parts_mut(base.ptr().add(r0 * row_len), (r1 - r0) * row_len)
            };
            f(r0, chunk);
        });
    }
}

/// One per available core, or `KAIROS_ENGINE_THREADS` when set.
pub fn default_threads() -> usize {
    std::env::var("KAIROS_ENGINE_THREADS")
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|&n: &usize| n > 0)
        .unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        })
}

/// A raw pointer that worker threads may share; every user writes a disjoint region.
pub(crate) struct SharedMut<T = f32>(*mut T);
// Not derived: a derive would ask `T: Clone` / `T: Copy`, but the pointer is always copyable.
impl<T> Clone for SharedMut<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for SharedMut<T> {}
// SAFETY: callers partition the pointee so that no two threads touch the same element.
unsafe impl<T: Send> Send for SharedMut<T> {}
// SAFETY: as above.
unsafe impl<T: Send> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    pub(crate) fn new(s: &mut [T]) -> Self {
        SharedMut(s.as_mut_ptr())
    }

    /// The pointer (a method, so that closures capture the whole `Sync` wrapper).
    pub(crate) fn ptr(&self) -> *mut T {
        self.0
    }
}

impl<T: Copy> SharedMut<T> {
    /// Copy `src`, rows of `width` values, into rows `row0..` of the shared matrix (row stride
    /// `ld`) at column `col`.
    ///
    /// # Safety
    /// Those rows and columns are inside the matrix, and no other thread touches them meanwhile.
    pub(crate) unsafe fn write_rows(
        &self,
        src: &[T],
        width: usize,
        ld: usize,
        row0: usize,
        col: usize,
    ) {
        for (t, row) in src.chunks_exact(width).enumerate() {
            // SAFETY: the caller guarantees bounds and exclusive access to this block.
            let dst =
                unsafe { std::slice::from_raw_parts_mut(self.0.add((row0 + t) * ld + col), width) };
            dst.copy_from_slice(row);
        }
    }
}

/// An `f32` buffer whose first element is 64-byte aligned (one cache line), so packed panel rows
/// never straddle cache lines.
#[derive(Clone, Default)]
pub struct AlignedBuf {
    raw: Vec<f32>,
    offset: usize,
    len: usize,
}

impl std::fmt::Debug for AlignedBuf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AlignedBuf")
            .field("len", &self.len)
            .finish()
    }
}

impl AlignedBuf {
    /// `len` zeros.
    pub fn zeros(len: usize) -> Self {
        let raw = vec![0.0f32; len + 16];
        let misalign = (raw.as_ptr() as usize / 4) % 16;
        let offset = if misalign == 0 { 0 } else { 16 - misalign };
        AlignedBuf { raw, offset, len }
    }

    /// Grow (never shrink) to at least `len` elements; contents are unspecified afterwards.
    pub fn ensure(&mut self, len: usize) {
        if self.len < len {
            *self = AlignedBuf::zeros(len);
        }
    }

    /// The buffer.
    pub fn as_slice(&self) -> &[f32] {
        &self.raw[self.offset..self.offset + self.len]
    }

    /// The buffer, mutable.
    pub fn as_mut_slice(&mut self) -> &mut [f32] {
        &mut self.raw[self.offset..self.offset + self.len]
    }
}

/// Reusable values (scratch buffers kept between calls), one per user at a time: [`take`]
/// pops a free one or makes one, [`put`] returns it. The lock is held only to pop or push,
/// never while a value is in use, so as many values exist as users ever overlapped; a user
/// that panics drops its value instead of returning it (a poisoned lock is used as is: the
/// list holds whole values only).
///
/// [`take`]: FreeList::take
/// [`put`]: FreeList::put
pub(crate) struct FreeList<T>(std::sync::Mutex<Vec<T>>);

impl<T> Default for FreeList<T> {
    fn default() -> Self {
        FreeList(std::sync::Mutex::new(Vec::new()))
    }
}

impl<T> FreeList<T> {
    /// A free value, or `make()` when none is.
    pub(crate) fn take(&self, make: impl FnOnce() -> T) -> T {
        let popped = self.0.lock().unwrap_or_else(|e| e.into_inner()).pop();
        popped.unwrap_or_else(make)
    }

    /// Return `value` for the next [`FreeList::take`].
    pub(crate) fn put(&self, value: T) {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).push(value);
    }
}

/// The first `len` values of `buf`, grown (with default values) where it is shorter: reusable
/// scratch for a caller that writes every value before reading it, which a `clear` and refill
/// would zero again on every call.
pub(crate) fn grown<T: Copy + Default>(buf: &mut Vec<T>, len: usize) -> &mut [T] {
    if buf.len() < len {
        buf.resize(len, T::default());
    }
    &mut buf[..len]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bf16_falls_back_to_f32_without_the_native_kernel() {
        assert_eq!(Precision::Bf16.resolve_for(false), Precision::F32);
        assert_eq!(Precision::Bf16.resolve_for(true), Precision::Bf16);
        assert_eq!(Precision::F32.resolve_for(true), Precision::F32);
        // Portable or AVX2 kernels never run the bf16 path natively.
        assert_eq!(Precision::Bf16.resolve(Isa::Portable), Precision::F32);
        assert_eq!(Precision::Bf16.resolve(Isa::Avx2Fma), Precision::F32);
        assert_eq!("bf16".parse::<Precision>().unwrap(), Precision::Bf16);
        assert!("fp16".parse::<Precision>().is_err());
    }
}
