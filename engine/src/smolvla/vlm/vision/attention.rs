//! The vision tower's attention: bidirectional, within each image, per head, from the
//! `[q | k | v]` rows of the group, in f32 or from rows rounded to bf16 pairs.

use super::CpuVision;
use crate::kernels::attention::{AttendScratch, KvSegment, Queries, QueryPositions, attend};
use crate::kernels::bf16::round_pairs;
use crate::kernels::{Isa, MatMut, MatRef, PackedMatrix, Pool, Precision, SharedMut};

/// What the vision attention reads: the `[q | k | v]` rows in f32, or rounded to bf16 pairs
/// (`hd` even, so each head's columns are whole pairs).
#[derive(Clone, Copy)]
pub(super) enum AttentionIn<'a> {
    F32(&'a [f32]),
    Pairs(&'a [u32]),
}

/// Where the vision attention writes its output: f32 rows, or bf16 pair rows (the out
/// projection's `A`, rounded as each head's rows are made).
pub(super) enum AttentionOut<'a> {
    F32(&'a mut [f32]),
    Pairs(&'a mut [u32]),
}

impl AttentionOut<'_> {
    /// The output as a pointer the attention's parts share (each writes its own heads' columns).
    fn shared(self) -> SharedOut {
        match self {
            AttentionOut::F32(rows) => SharedOut::F32(SharedMut::new(rows)),
            AttentionOut::Pairs(rows) => SharedOut::Pairs(SharedMut::new(rows)),
        }
    }
}

/// [`AttentionOut`] shared by the attention's parts.
#[derive(Clone, Copy)]
enum SharedOut {
    F32(SharedMut<f32>),
    Pairs(SharedMut<u32>),
}

/// The buffers of one attention head of one image: its scores, its output rows and its packed
/// keys and values. Every value is written before it is read, so reuse changes no result.
pub(super) struct HeadScratch {
    scores: AttendScratch,
    out: Vec<f32>,
    keys_t: PackedMatrix,
    values: PackedMatrix,
}

impl HeadScratch {
    /// Empty buffers, for keys and values packed in `precision`. They are kept in a
    /// [`crate::kernels::FreeList`] rather than allocated by each attention part (~1 MB for a
    /// 1 024-patch image, which `malloc` takes from `mmap` and the kernel zeroes page by page,
    /// twelve times a layer).
    pub(super) fn new(precision: Precision) -> Self {
        HeadScratch {
            scores: AttendScratch::default(),
            out: Vec::new(),
            keys_t: PackedMatrix::empty_in(precision),
            values: PackedMatrix::empty_in(precision),
        }
    }
}

/// One head of one image: the image's `n` rows from row `start`.
#[derive(Clone, Copy)]
struct HeadTask {
    start: usize,
    n: usize,
    head: usize,
}

/// Query rows per attention call: 96 x 1024 scores = 384 KiB.
const QUERY_BLOCK: usize = 96;

impl CpuVision {
    /// Bidirectional multi-head attention within each image: `attn = softmax(q kᵀ / sqrt(d)) v`
    /// per head, from the `[q | k | v]` rows; image `i` is `counts[i]` rows from `starts[i]`.
    pub(super) fn attention(
        &self,
        pool: &Pool,
        qkv: AttentionIn<'_>,
        counts: &[usize],
        starts: &[usize],
        attn: AttentionOut<'_>,
    ) {
        let heads = self.config.vision_config.num_attention_heads;
        let tasks = counts.len() * heads;
        let parts = pool.parts_per_unit(tasks);
        let out = attn.shared();
        pool.run(parts, |part| {
            let mut scratch = self.head_scratch.take(|| HeadScratch::new(self.precision));
            for task in tasks * part / parts..tasks * (part + 1) / parts {
                let (img, head) = (task / heads, task % heads);
                let task = HeadTask {
                    start: starts[img],
                    n: counts[img],
                    head,
                };
                self.attend_head(pool.isa(), qkv, task, &mut scratch, out);
            }
            self.head_scratch.put(scratch);
        });
    }

    /// One head of one image: pack its keys and values, attend its queries block by block, and
    /// write its columns of the output rows.
    fn attend_head(
        &self,
        isa: Isa,
        qkv: AttentionIn<'_>,
        task: HeadTask,
        scratch: &mut HeadScratch,
        out: SharedOut,
    ) {
        let vh = self.config.vision_config.hidden_size;
        let hd = vh / self.config.vision_config.num_attention_heads;
        let scale = (hd as f64).powf(-0.5) as f32;
        let ld = 3 * vh;
        let HeadTask { start, n, head } = task;
        let HeadScratch {
            scores,
            out: tmp,
            keys_t: kt,
            values: vv,
        } = scratch;
        match qkv {
            AttentionIn::F32(qkv) => {
                let base = &qkv[start * ld..(start + n) * ld];
                kt.pack_transposed(isa, MatRef::new(&base[vh + head * hd..], n, hd, ld));
                vv.pack_rows(isa, MatRef::new(&base[2 * vh + head * hd..], n, hd, ld));
            }
            AttentionIn::Pairs(pairs) => {
                let (base, ldp) = (&pairs[start * ld / 2..(start + n) * ld / 2], ld / 2);
                let keys = MatRef::new(&base[(vh + head * hd) / 2..], n, hd / 2, ldp);
                kt.pack_transposed_pairs(keys, hd);
                let values = MatRef::new(&base[(2 * vh + head * hd) / 2..], n, hd / 2, ldp);
                vv.pack_rows_pairs(values, hd);
            }
        }
        tmp.resize(n * hd, 0.0);
        let segment = KvSegment {
            keys_t: kt,
            values: vv,
            causal: false,
        };
        // Queries in blocks, so that a block's scores (`QUERY_BLOCK x n`) stay in L2; every
        // query row is computed the same way whatever the block.
        for r0 in (0..n).step_by(QUERY_BLOCK) {
            let rows = QUERY_BLOCK.min(n - r0);
            let first = (start + r0) * ld + head * hd;
            let queries = match qkv {
                AttentionIn::F32(qkv) => Queries::F32(MatRef::new(&qkv[first..], rows, hd, ld)),
                AttentionIn::Pairs(pairs) => {
                    Queries::Pairs(MatRef::new(&pairs[first / 2..], rows, hd / 2, ld / 2))
                }
            };
            let positions = QueryPositions {
                offset: 0,
                period: rows,
            };
            let block = MatMut::dense(&mut tmp[r0 * hd..(r0 + rows) * hd], rows, hd);
            attend(isa, queries, &[segment], positions, scale, scores, block);
        }
        match out {
            // SAFETY: this image's rows of this head's columns are written by this task only.
            SharedOut::F32(out) => unsafe { out.write_rows(tmp, hd, vh, start, head * hd) },
            SharedOut::Pairs(pairs) => {
                let (kp, ldp) = (hd / 2, vh / 2);
                for (t, row) in tmp.chunks_exact(hd).enumerate() {
                    // SAFETY: as above, this head's `hd / 2` pairs of the row (`hd` is even, so
                    // they are whole pairs of this head's columns only).
                    let dst = unsafe {
                        std::slice::from_raw_parts_mut(
                            pairs.ptr().add((start + t) * ldp + head * kp),
                            kp,
                        )
                    };
                    round_pairs(isa, row, dst);
                }
            }
        }
    }
}
