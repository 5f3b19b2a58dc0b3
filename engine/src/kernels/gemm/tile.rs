//! The micro-kernels' common contract ([`Tile`]) and the choice of a kernel for a tile: by
//! instruction set and precision ([`Kernel`]), by row count (a const generic), and for an edge
//! panel narrower than `NR` (a scratch tile).

use super::super::{Isa, Precision};
use super::{MR, NR};

#[cfg(target_arch = "x86_64")]
use super::avx2::kernel_avx2;
#[cfg(target_arch = "x86_64")]
use super::avx512::kernel_avx512;
#[cfg(target_arch = "x86_64")]
use super::bf16_avx512::{kernel_bf16_avx512, kernel_bf16_avx512_pair};
use super::portable::{kernel_bf16_portable, kernel_portable};

/// A pointer and the distance between the rows that start from it, in values: row `r` at
/// `ptr + r * stride`. Two words, so a micro-kernel takes it in two registers.
#[derive(Clone, Copy)]
pub(super) struct Rows<P> {
    /// Row 0.
    pub(super) ptr: P,
    /// Distance between consecutive rows.
    pub(super) stride: usize,
}

/// Where a micro-kernel's accumulators start: zero (`None`), or row `r` from `ptr + r * stride`
/// (`C` itself to accumulate into it; a bias, stride 0, for every row).
pub(super) type Start = Option<Rows<*const f32>>;

/// The operands of one micro-kernel call: `C = S + A · B` over `kc` values of `k` on a tile of
/// `C`, where `S` is `start`'s rows (zero for `None`).
#[derive(Clone, Copy)]
pub(super) struct Tile {
    /// Depth: values of `k` (bf16: the panel has `ceil(kc / 2)` pair rows).
    pub(super) kc: usize,
    /// The tile's rows of `A`, in 32-bit values: f32 rows in place, or bf16 pair rows (packed,
    /// or in place).
    pub(super) a: Rows<*const f32>,
    /// The panel: `kc` rows of `NR` values (pair rows in bf16), 64-byte aligned.
    pub(super) b: *const f32,
    /// The tile's rows of `C`.
    pub(super) c: Rows<*mut f32>,
    /// What the accumulators start from.
    pub(super) start: Start,
}

impl Tile {
    /// `f` on these operands. The micro-kernels take them as separate arguments, in registers:
    /// a call per tile through memory would cost the driver loop stores and the kernel loads.
    ///
    /// # Safety
    /// As [`tile`] for the tile `f` is written for.
    #[inline(always)]
    pub(super) unsafe fn run(self, f: TileFn) {
        // SAFETY: the caller's contract.
        unsafe { f(self.kc, self.a, self.b, self.c, self.start) }
    }

    /// `f` on these operands and a second panel `b2` (see [`Self::run`]).
    ///
    /// # Safety
    /// As [`tile_pair`] for the tile `f` is written for.
    #[inline(always)]
    pub(super) unsafe fn run_pair(self, f: PairFn, b2: *const f32) {
        // SAFETY: the caller's contract.
        unsafe { f(self.kc, self.a, self.b, b2, self.c, self.start) }
    }
}

/// Which micro-kernel multiplies a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Kernel {
    /// f32 panels with this instruction set's kernel.
    F32(Isa),
    /// bf16 panels with `vdpbf16ps` (AVX512_BF16).
    Bf16Avx512,
    /// bf16 panels in portable code.
    Bf16Portable,
}

impl Kernel {
    /// The kernel for panels in `precision` with `isa`'s instructions.
    pub(super) fn choose(isa: Isa, precision: Precision) -> Kernel {
        match precision {
            Precision::F32 => Kernel::F32(isa),
            Precision::Bf16 if isa == Isa::Avx512 && super::super::cpu_has_avx512_bf16() => {
                Kernel::Bf16Avx512
            }
            Precision::Bf16 => Kernel::Bf16Portable,
        }
    }

    /// Whether [`tile_pair`] has a kernel for two panels at once: the AVX512_BF16 one. There
    /// one panel row is a single register, so a one-panel tile has only `MR` (x 2 for even and
    /// odd pairs) accumulators and spends a load of `A` on every product; two panels share
    /// each broadcast `A` pair between two products and double the independent chains. f32
    /// keeps one panel per call: an f32 AVX-512 pair kernel was no faster on large `M` and
    /// slower on the expert's 50 rows.
    pub(super) fn pairs(self) -> bool {
        matches!(self, Kernel::Bf16Avx512)
    }
}

/// `$step!(kk)` for `kk` in `0..$n`, in order, four per loop iteration (the f32 kernels' loop).
macro_rules! unroll4 {
    ($n:expr, $step:ident) => {{
        let mut kk = 0;
        while kk + 4 <= $n {
            $step!(kk);
            $step!(kk + 1);
            $step!(kk + 2);
            $step!(kk + 3);
            kk += 4;
        }
        while kk < $n {
            $step!(kk);
            kk += 1;
        }
    }};
}
pub(super) use unroll4;

/// One `rows x w` tile (`rows <= MR`, `w <= NR`) with `kernel`.
///
/// # Safety
/// `t.a` has `rows` rows of `t.kc` values (bf16: `ceil(kc / 2)` pairs), `t.b` has `t.kc` rows
/// of `NR` values (pair rows in bf16), `t.c` has `rows` rows with `w` values, and so has
/// `t.start` when given.
pub(super) unsafe fn tile(kernel: Kernel, rows: usize, w: usize, t: Tile) {
    if w < NR {
        // Edge panel: run the full-width kernel on a scratch tile, copy the valid columns.
        let mut scratch = [0.0f32; MR * NR];
        if let Some(Rows { ptr: src, stride }) = t.start {
            for r in 0..rows {
                for j in 0..w {
                    // SAFETY: inside the caller's start rows (`w` values each).
                    scratch[r * NR + j] = unsafe { *src.add(r * stride + j) };
                }
            }
        }
        let full = Tile {
            c: Rows {
                ptr: scratch.as_mut_ptr(),
                stride: NR,
            },
            start: t.start.map(|_| Rows {
                ptr: scratch.as_ptr(),
                stride: NR,
            }),
            ..t
        };
        // SAFETY: scratch is a full MR x NR tile; `A` and `B` are the caller's.
        unsafe { tile(kernel, rows, NR, full) };
        for r in 0..rows {
            for j in 0..w {
                // SAFETY: inside the caller's C tile.
                unsafe { *t.c.ptr.add(r * t.c.stride + j) = scratch[r * NR + j] };
            }
        }
        return;
    }
    // SAFETY: the caller's contract, for a full-width tile of `rows` rows.
    unsafe { t.run(full_tile_fn(kernel, rows)) }
}

/// A micro-kernel on a full-width tile: [`Tile`]'s fields, in its order.
pub(super) type TileFn = unsafe fn(usize, Rows<*const f32>, *const f32, Rows<*mut f32>, Start);

/// The micro-kernel of `kernel` for full-width tiles of `rows` rows (`1..=MR`). The driver
/// loop looks it up once per GEMM for whole tiles and calls it directly, rather than going
/// through [`tile`]'s dispatch (and its large stack frame, kept for the edge panels' scratch
/// tile) for every tile.
pub(super) fn full_tile_fn(kernel: Kernel, rows: usize) -> TileFn {
    macro_rules! pick {
        ($f:ident) => {
            match rows {
                6 => $f::<6> as TileFn,
                5 => $f::<5>,
                4 => $f::<4>,
                3 => $f::<3>,
                2 => $f::<2>,
                _ => $f::<1>,
            }
        };
    }
    // Each kernel's CPU requirement holds for the `Kernel` it is picked for: `Isa::Avx2Fma`
    // and `Isa::Avx512` are only reported on CPUs with those features, and `Kernel::choose`
    // picks `Bf16Avx512` only on a CPU with AVX-512F and AVX512_BF16.
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::F32(Isa::Avx2Fma) => pick!(kernel_avx2),
        #[cfg(target_arch = "x86_64")]
        Kernel::F32(Isa::Avx512) => pick!(kernel_avx512),
        #[cfg(target_arch = "x86_64")]
        Kernel::Bf16Avx512 => pick!(kernel_bf16_avx512),
        Kernel::Bf16Portable => pick!(kernel_bf16_portable),
        _ => pick!(kernel_portable),
    }
}

/// A micro-kernel on two full-width panels side by side: [`Tile`]'s fields with the second
/// panel after the first.
pub(super) type PairFn =
    unsafe fn(usize, Rows<*const f32>, *const f32, *const f32, Rows<*mut f32>, Start);

/// The two-panel micro-kernel of `kernel` for `rows` rows, where it has one
/// ([`Kernel::pairs`]; the CPU requirement as in [`full_tile_fn`]).
pub(super) fn pair_tile_fn(kernel: Kernel, rows: usize) -> Option<PairFn> {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Bf16Avx512 => Some(match rows {
            6 => kernel_bf16_avx512_pair::<6> as PairFn,
            5 => kernel_bf16_avx512_pair::<5>,
            4 => kernel_bf16_avx512_pair::<4>,
            3 => kernel_bf16_avx512_pair::<3>,
            2 => kernel_bf16_avx512_pair::<2>,
            _ => kernel_bf16_avx512_pair::<1>,
        }),
        _ => None,
    }
}

/// Two full-width panels side by side (`C` columns `0..2 * NR`), `rows <= MR` rows: the same
/// products in the same order per output value as two [`tile`] calls, so the same bits.
///
/// # Safety
/// As [`tile`] for each panel (`t.b` and `b2` each hold `t.kc` rows of `NR` values); `t.c` has
/// `rows` rows of `2 * NR` values, and so has `t.start` when given.
pub(super) unsafe fn tile_pair(kernel: Kernel, rows: usize, t: Tile, b2: *const f32) {
    match pair_tile_fn(kernel, rows) {
        // SAFETY: the caller's contract.
        Some(f) => unsafe { t.run_pair(f, b2) },
        _ => {
            let second = Tile {
                b: b2,
                c: Rows {
                    ptr: t.c.ptr.wrapping_add(NR),
                    ..t.c
                },
                start: t.start.map(|s| Rows {
                    ptr: s.ptr.wrapping_add(NR),
                    ..s
                }),
                ..t
            };
            // SAFETY: the caller's contract, one panel at a time.
            unsafe {
                tile(kernel, rows, NR, t);
                tile(kernel, rows, NR, second);
            }
        }
    }
}
