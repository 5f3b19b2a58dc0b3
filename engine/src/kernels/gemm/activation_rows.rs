//! `A` made row by row by a producer (a norm, an activation) for the GEMMs it feeds: f32 rows,
//! or rows rounded into bf16 pairs while each is still in L1 ([`ActivationRows`]).

use super::super::bf16::round_pairs;
use super::super::matrix::{MatMut, MatRef};
use super::super::{Pool, Precision};
use super::{Init, PackedMatrix, gemm_par, gemm_par_pairs};

/// Make the `A` of a [`gemm_par_pairs`] on the pool's threads: `f(r, row)` writes f32 row `r`
/// (`width` values) into `row`, which is rounded into row `r` of `pairs` (rows of
/// `ceil(width / 2)` pairs, back to back) while it is in L1. A layer norm or an activation
/// that feeds a bf16 GEMM thus never writes its f32 output to memory, nor does the GEMM read
/// it back to round it.
pub fn round_rows_par(
    pool: &Pool,
    width: usize,
    pairs: &mut [u32],
    f: impl Fn(usize, &mut [f32]) + Sync,
) {
    let kp = width.div_ceil(2);
    let isa = pool.isa();
    pool.for_row_chunks(pairs, kp, |r0, chunk| {
        let mut row = vec![0.0f32; width];
        for (i, dst) in chunk.chunks_exact_mut(kp).enumerate() {
            f(r0 + i, &mut row);
            round_pairs(isa, &row, dst);
        }
    });
}

/// The `A` of GEMMs in some precision, made row by row by a producer (a norm, an
/// activation): f32 rows for f32 weights; for bf16 weights, rows rounded into bf16 pairs as
/// they are made ([`round_rows_par`]), so the f32 values never go to memory. The results are
/// the same as giving the f32 rows to [`gemm_par`].
#[derive(Debug)]
pub struct ActivationRows {
    width: usize,
    rows: usize,
    precision: Precision,
    values: Vec<f32>,
    pairs: Vec<u32>,
}

impl ActivationRows {
    /// Room for `rows` rows of `width` values, for GEMMs whose `B` is in `precision`.
    pub fn new(precision: Precision, rows: usize, width: usize) -> Self {
        let (values, pairs) = match precision {
            Precision::F32 => (vec![0.0; rows * width], Vec::new()),
            Precision::Bf16 => (Vec::new(), vec![0; rows * width.div_ceil(2)]),
        };
        ActivationRows {
            width,
            rows,
            precision,
            values,
            pairs,
        }
    }

    /// Whether this holds at least `rows` rows of `width` values for `precision` weights (and
    /// can be filled again for them instead of allocating new rows).
    pub fn fits(&self, precision: Precision, rows: usize, width: usize) -> bool {
        self.precision == precision && self.width == width && self.rows >= rows
    }

    /// Make the first `m` rows: `f(r, row)` writes row `r`'s `width` f32 values, on the pool's
    /// threads.
    ///
    /// # Panics
    /// If `m` exceeds the rows this was made for.
    pub fn fill(&mut self, pool: &Pool, m: usize, f: impl Fn(usize, &mut [f32]) + Sync) {
        assert!(m <= self.rows, "activation rows: {m} > {}", self.rows);
        let width = self.width;
        match self.precision {
            Precision::F32 => {
                pool.for_row_chunks(&mut self.values[..m * width], width, |r0, chunk| {
                    for (i, row) in chunk.chunks_exact_mut(width.max(1)).enumerate() {
                        f(r0 + i, row);
                    }
                });
            }
            Precision::Bf16 => {
                round_rows_par(pool, width, &mut self.pairs[..m * width.div_ceil(2)], f);
            }
        }
    }

    /// `C = init + A · B` over the first `c.rows()` rows, split over the pool's threads.
    ///
    /// # Panics
    /// If `b`'s precision or input size is not this matrix's, or as [`gemm_par`].
    pub fn gemm_par(&self, pool: &Pool, b: &PackedMatrix, c: MatMut<'_>, init: Init<'_>) {
        assert!(
            b.precision() == self.precision && b.k() == self.width,
            "activation rows ({:?}, width {}) vs B ({:?}, k {})",
            self.precision,
            self.width,
            b.precision(),
            b.k()
        );
        let m = c.rows();
        match self.precision {
            Precision::F32 => {
                let a = MatRef::dense(&self.values[..m * self.width], m, self.width);
                gemm_par(pool, a, b, c, init);
            }
            Precision::Bf16 => {
                let kp = self.width.div_ceil(2);
                let a = MatRef::dense(&self.pairs[..m * kp], m, kp);
                gemm_par_pairs(pool, a, b, c, init);
            }
        }
    }
}
