//! Where the micro-kernels read `A` ([`ASource`]), and packing a bf16 `A`: rounded into pairs,
//! `MC x KC_BF16` block by block, each tile row contiguous.

use super::super::bf16::round_pairs;
use super::super::matrix::MatRef;
use super::super::{AlignedBuf, Isa, Pool, Precision, SharedMut};
use super::{KC_BF16, MC, MR, depth};

/// Where the micro-kernels read `A`.
#[derive(Clone, Copy)]
pub(super) enum ASource<'a> {
    /// `rows` rows packed by [`pack_a_blocks`] (bf16 pairs).
    Packed { values: &'a [f32], rows: usize },
    /// f32 rows read in place: packing them would only copy each row (and take a parallel
    /// region per GEMM to do it in).
    Rows(MatRef<'a>),
    /// bf16 pair rows read in place, pair `(A[r][2i], A[r][2i + 1])` in row `r`, column `i`.
    Pairs(MatRef<'a, u32>),
}

impl ASource<'_> {
    /// Rows of `A`.
    pub(super) fn rows(&self) -> usize {
        match self {
            ASource::Packed { rows, .. } => *rows,
            ASource::Rows(a) => a.rows(),
            ASource::Pairs(a) => a.rows(),
        }
    }

    /// Row tile `t` of the cache block `(m0, k0)` of a `k`-deep `A` (the block `kc` deep): its
    /// first row, and how far apart its rows are (in 32-bit values). The micro-kernel reads
    /// the tile's rows through pointers that advance together.
    #[inline(always)]
    pub(super) fn tile(&self, k: usize, m0: usize, k0: usize, kc: usize, t: usize) -> TileRows {
        let r0 = t * MR;
        match *self {
            ASource::Packed { values, rows } => {
                let d = depth(Precision::Bf16, kc);
                let start = a_block(k, rows, m0, k0) + t * d * MR;
                (values[start..].as_ptr(), d)
            }
            ASource::Rows(a) => {
                let lda = a.stride();
                (a.data()[(m0 + r0) * lda + k0..].as_ptr(), lda)
            }
            // k0 is even (a multiple of KC_BF16): pair k0 / 2 starts the block.
            ASource::Pairs(a) => {
                let ldp = a.stride();
                let first = &a.data()[(m0 + r0) * ldp + k0 / 2..];
                (first.as_ptr().cast::<f32>(), ldp)
            }
        }
    }
}

/// A tile's first row of `A` and the distance between its rows, in 32-bit values.
pub(super) type TileRows = (*const f32, usize);

thread_local! {
    /// Per-thread buffer for packed `A` of single-threaded calls.
    pub(super) static A_PACK: std::cell::RefCell<AlignedBuf> =
        std::cell::RefCell::new(AlignedBuf::default());
}

/// Rows of the `MC` block starting at `m0`, rounded up to whole tiles.
#[inline]
fn padded_rows(m: usize, m0: usize) -> usize {
    MC.min(m - m0).div_ceil(MR) * MR
}

/// Where block `(m0, k0)` of packed (bf16) `A` starts: blocks are stored `MC` rows at a time,
/// each as its `KC_BF16`-deep slices one after another (see [`pack_a_bf16`] for one slice).
/// Only bf16 `A` is packed: f32 rows are read in place ([`ASource::Rows`]).
#[inline]
fn a_block(k: usize, m: usize, m0: usize, k0: usize) -> usize {
    m0 * depth(Precision::Bf16, k) + depth(Precision::Bf16, k0) * padded_rows(m, m0)
}

/// Pack all of `a` into `buf` in [`a_block`] order, as bf16 pairs.
pub(super) fn pack_a_blocks<'a>(isa: Isa, a: MatRef<'_>, buf: &'a mut AlignedBuf) -> ASource<'a> {
    let (m, k) = (a.rows(), a.cols());
    let (units, len) = a_layout(m, k);
    buf.ensure(len);
    let out = &mut buf.as_mut_slice()[..len];
    for unit in 0..units {
        let u = AUnit::new(m, k, unit);
        pack_a_unit(isa, a, &u, &mut out[u.start..u.start + u.size]);
    }
    ASource::Packed {
        values: &buf.as_slice()[..len],
        rows: m,
    }
}

/// Below this many values of `A`, packing stays on the calling thread: waking the pool costs
/// more than the copy.
const PAR_PACK_MIN: usize = 32 * 1024;

/// [`pack_a_blocks`] with its `(MC, KC)` blocks split over the pool's threads. Each block is
/// written by one part, the same way as on one thread, so the result is identical.
pub(super) fn pack_a_blocks_par<'a>(
    pool: &Pool,
    a: MatRef<'_>,
    buf: &'a mut AlignedBuf,
) -> ASource<'a> {
    let (m, k) = (a.rows(), a.cols());
    let (units, len) = a_layout(m, k);
    if m * k < PAR_PACK_MIN || units == 1 || pool.threads() == 1 {
        return pack_a_blocks(pool.isa(), a, buf);
    }
    buf.ensure(len);
    let out = SharedMut::new(&mut buf.as_mut_slice()[..len]);
    let parts = pool.parts(units);
    pool.run(parts, |t| {
        for unit in units * t / parts..units * (t + 1) / parts {
            let u = AUnit::new(m, k, unit);
            // SAFETY: the units' ranges are disjoint and inside the `len` values of `out`
            // (see `AUnit`); each is written by the one part that owns the unit.
            let dst = unsafe { std::slice::from_raw_parts_mut(out.ptr().add(u.start), u.size) };
            pack_a_unit(pool.isa(), a, &u, dst);
        }
    });
    ASource::Packed {
        values: &buf.as_slice()[..len],
        rows: m,
    }
}

/// How many `(MC, KC_BF16)` blocks packed `A` has, and how many values it takes.
fn a_layout(m: usize, k: usize) -> (usize, usize) {
    (
        m.div_ceil(MC) * k.div_ceil(KC_BF16),
        m.div_ceil(MR) * MR * depth(Precision::Bf16, k),
    )
}

/// One block of packed `A`: rows `m0..m0 + mb`, columns `k0..k0 + kc`, stored at
/// `start..start + size` (see [`a_block`]).
struct AUnit {
    m0: usize,
    k0: usize,
    mb: usize,
    kc: usize,
    start: usize,
    size: usize,
}

impl AUnit {
    /// Block number `unit`, `k`-blocks fastest.
    fn new(m: usize, k: usize, unit: usize) -> Self {
        let kcb = KC_BF16;
        let kblocks = k.div_ceil(kcb);
        let (m0, k0) = ((unit / kblocks) * MC, (unit % kblocks) * kcb);
        let (mb, kc) = (MC.min(m - m0), kcb.min(k - k0));
        AUnit {
            m0,
            k0,
            mb,
            kc,
            start: a_block(k, m, m0, k0),
            size: padded_rows(m, m0) * depth(Precision::Bf16, kc),
        }
    }
}

/// Pack block `u` of `a` into `dst`, which holds exactly that block.
fn pack_a_unit(isa: Isa, a: MatRef<'_>, u: &AUnit, dst: &mut [f32]) {
    pack_a_bf16(isa, a.sub(u.m0, u.k0, u.mb, u.kc), dst);
}

/// Pack `a` (`rows x kc`, `kc <= KC_BF16`) into row tiles of `MR` bf16 pairs: row `r` of tile
/// `t` (row `t*MR + r` of `a`) is the `ceil(kc / 2)` pairs `(a[r][2i], a[r][2i+1])`, contiguous,
/// rounded straight into place (16 values per instruction with AVX-512F); zero rows past
/// `rows`. The kernel reads a tile's rows through pointers that move together.
fn pack_a_bf16(isa: Isa, a: MatRef<'_>, out: &mut [f32]) {
    let (rows, kc) = (a.rows(), a.cols());
    debug_assert!(kc <= KC_BF16);
    let kp = kc.div_ceil(2);
    for t in 0..rows.div_ceil(MR) {
        let tile = &mut out[t * kp * MR..(t + 1) * kp * MR];
        for (r, dst) in tile.chunks_exact_mut(kp).enumerate() {
            let row = t * MR + r;
            if row < rows {
                round_pairs(isa, a.row(row), as_pair_bits(dst));
            } else {
                dst.fill(0.0);
            }
        }
    }
}

/// The packed bf16 pairs of a tile row as the `u32` bit patterns [`round_pairs`] writes.
fn as_pair_bits(values: &mut [f32]) -> &mut [u32] {
    // SAFETY: f32 and u32 have the same size and alignment, and every bit pattern is valid for
    // both; the returned slice borrows `values` exclusively for its lifetime.
    unsafe { std::slice::from_raw_parts_mut(values.as_mut_ptr().cast::<u32>(), values.len()) }
}
