//! Packing the right-hand operand `B` into `NR`-column panels ([`PackedMatrix`]), in f32 or in
//! bf16 pairs, from `Linear` weights (once, at load) or from activations (attention keys and
//! values, per request).

use super::super::bf16::{bf16_pair, round_pairs};
use super::super::matrix::MatRef;
use super::super::{AlignedBuf, Isa, Precision, grown};
use super::{NR, depth, kc_of};

/// The right-hand operand of a GEMM, packed into `NR`-column panels.
///
/// Its [`Precision`] says how the values are stored: f32, or bf16 pairs (half the memory; the
/// GEMM then rounds `A` to bf16 too). bf16 pairs live in the same 32-bit buffer, as raw bits.
#[derive(Clone, Debug, Default)]
pub struct PackedMatrix {
    k: usize,
    n: usize,
    precision: Precision,
    buf: AlignedBuf,
}

impl PackedMatrix {
    /// Pack the weight of a PyTorch `Linear` (`w` is `[n][k]`, out x in, row-major) so that
    /// `A · B = A · wᵀ`, i.e. `y = x wᵀ`.
    pub fn from_linear_weight(w: &[f32], n: usize, k: usize) -> Self {
        Self::from_linear_weight_in(Precision::F32, w, n, k)
    }

    /// [`Self::from_linear_weight`] stored in `precision` (bf16 values are rounded to nearest).
    pub fn from_linear_weight_in(precision: Precision, w: &[f32], n: usize, k: usize) -> Self {
        Self::from_linear_fn_in(precision, n, k, |row, col| w[row * k + col])
    }

    /// Pack several `Linear` weights with the same input size side by side (`[w0; w1; ..]` along
    /// the output dimension), e.g. the q, k and v projections into one GEMM.
    pub fn from_linear_weights(ws: &[(&[f32], usize)], k: usize) -> Self {
        Self::from_linear_weights_in(Precision::F32, ws, k)
    }

    /// [`Self::from_linear_weights`] stored in `precision`.
    pub fn from_linear_weights_in(precision: Precision, ws: &[(&[f32], usize)], k: usize) -> Self {
        // Where each stacked row lives, so that the panels are packed straight from the parts
        // (no stacked copy of the weights, which briefly doubled them at load).
        let rows: Vec<&[f32]> = ws
            .iter()
            .flat_map(|&(w, n)| (0..n).map(move |r| &w[r * k..(r + 1) * k]))
            .collect();
        Self::from_linear_fn_in(precision, rows.len(), k, |j, kk| rows[j][kk])
    }

    /// An empty matrix that [`Self::pack_rows`] and [`Self::pack_transposed`] fill in
    /// `precision` (e.g. attention keys and values packed per request).
    pub fn empty_in(precision: Precision) -> Self {
        PackedMatrix {
            precision,
            ..PackedMatrix::default()
        }
    }

    /// How the values are stored.
    #[inline]
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Depth (rows of `B`).
    #[inline]
    pub fn k(&self) -> usize {
        self.k
    }

    /// Width (columns of `B`).
    #[inline]
    pub fn n(&self) -> usize {
        self.n
    }

    /// Number of `NR`-column panels.
    #[inline]
    pub(super) fn panels(&self) -> usize {
        self.n.div_ceil(NR)
    }

    fn resize(&mut self, k: usize, n: usize) {
        self.k = k;
        self.n = n;
        self.buf
            .ensure(n.div_ceil(NR) * NR * depth(self.precision, k));
    }

    /// Pack `B` given as its `k` rows of `n` values, in the matrix's precision (bf16 rounding
    /// with `isa`'s vector code). Reuses the allocation.
    pub fn pack_rows(&mut self, isa: Isa, b: MatRef<'_>) {
        let (k, n, ldb) = (b.rows(), b.cols(), b.stride());
        match self.precision {
            Precision::F32 => {
                let b = b.data();
                self.pack_with(k, n, |kk, j| b[kk * ldb + j]);
            }
            Precision::Bf16 => self.pack_rows_bf16(isa, b),
        }
    }

    /// [`Self::pack_rows`] in bf16: each pair of rows is interleaved (`b[2i][j], b[2i+1][j]`
    /// side by side), rounded into pairs by the vector code ([`round_pairs`]) and copied into the
    /// panels. Same bits as [`Self::pack_with`], which rounds element by element in scalar code:
    /// the attention's values are packed per request and head, so this packing is on the
    /// forward path.
    fn pack_rows_bf16(&mut self, isa: Isa, b: MatRef<'_>) {
        let (k, n, ldb, b) = (b.rows(), b.cols(), b.stride(), b.data());
        ROW_PAIRS.with(|buf| {
            // Every pair is written below, so the buffer is only grown: clearing and refilling
            // it would zero it again on every call (once per head of every image).
            let mut buf = buf.borrow_mut();
            let pairs = grown(&mut buf, k.div_ceil(2) * n);
            let mut both = vec![0.0f32; 2 * n];
            for (i, out) in pairs.chunks_exact_mut(n).enumerate() {
                let (kk, lo) = (2 * i, &b[2 * i * ldb..2 * i * ldb + n]);
                for (two, &v) in both.chunks_exact_mut(2).zip(lo) {
                    two[0] = v;
                    two[1] = 0.0;
                }
                if kk + 1 < k {
                    let hi = &b[(kk + 1) * ldb..(kk + 1) * ldb + n];
                    for (two, &v) in both.chunks_exact_mut(2).zip(hi) {
                        two[1] = v;
                    }
                }
                round_pairs(isa, &both, out);
            }
            self.store_pairs(k, n, |i, j| pairs[i * n + j]);
        });
    }

    /// Pack `B = wᵀ` where `w` has `n` rows of `k` values, in the matrix's precision (bf16
    /// rounding with `isa`'s vector code). Reuses the allocation.
    pub fn pack_transposed(&mut self, isa: Isa, w: MatRef<'_>) {
        let (n, k, ldw) = (w.rows(), w.cols(), w.stride());
        match self.precision {
            Precision::F32 => {
                let w = w.data();
                self.pack_with(k, n, |kk, j| w[j * ldw + kk]);
            }
            Precision::Bf16 => self.pack_transposed_bf16(isa, w),
        }
    }

    /// [`Self::pack_transposed`] in bf16: each row of `w` is rounded into pairs with the vector
    /// code ([`round_pairs`]), then the pairs are transposed into the panels, rather than rounding
    /// element by element while gathering down the columns of `w` (scalar code on strided
    /// loads). Same bits as [`Self::pack_with`].
    fn pack_transposed_bf16(&mut self, isa: Isa, w: MatRef<'_>) {
        let (n, k) = (w.rows(), w.cols());
        let kp = k.div_ceil(2);
        ROW_PAIRS.with(|buf| {
            // Every pair is written below (see `pack_rows_bf16`).
            let mut buf = buf.borrow_mut();
            let pairs = grown(&mut buf, n * kp);
            for (j, out) in pairs.chunks_exact_mut(kp).enumerate() {
                round_pairs(isa, w.row(j), out);
            }
            self.pack_transposed_pairs(MatRef::dense(pairs, n, kp), k);
        });
    }

    /// [`Self::pack_transposed`] of rows already rounded to bf16 pairs ([`round_pairs`]: `n`
    /// rows of `k` values as `ceil(k / 2)` pairs each): the same panels as packing the f32 rows
    /// they were rounded from, without rounding them again.
    ///
    /// # Panics
    /// If the matrix is not bf16, or `pairs` does not hold `ceil(k / 2)` pairs per row.
    pub fn pack_transposed_pairs(&mut self, pairs: MatRef<'_, u32>, k: usize) {
        assert_eq!(self.precision, Precision::Bf16, "pairs pack into bf16 only");
        assert_eq!(
            pairs.cols(),
            k.div_ceil(2),
            "{k} values make ceil({k} / 2) pairs"
        );
        let (n, ldp, pairs) = (pairs.rows(), pairs.stride(), pairs.data());
        self.store_pairs(k, n, |i, j| pairs[j * ldp + i]);
    }

    /// [`Self::pack_rows`] of rows already rounded to bf16 pairs ([`round_pairs`]: `k` rows
    /// of `n` values as `ceil(n / 2)` pairs each): a panel pairs two *rows*, so each value's 16
    /// bits move from its row's pair into the pair of its two rows. The same panels as packing
    /// the f32 rows they were rounded from.
    ///
    /// # Panics
    /// If the matrix is not bf16, or `pairs` does not hold `ceil(n / 2)` pairs per row.
    pub fn pack_rows_pairs(&mut self, pairs: MatRef<'_, u32>, n: usize) {
        assert_eq!(self.precision, Precision::Bf16, "pairs pack into bf16 only");
        assert_eq!(
            pairs.cols(),
            n.div_ceil(2),
            "{n} values make ceil({n} / 2) pairs"
        );
        let (k, ldp, pairs) = (pairs.rows(), pairs.stride(), pairs.data());
        let half = |r: usize, j: usize| (pairs[r * ldp + j / 2] >> (16 * (j % 2))) & 0xffff;
        self.store_pairs(k, n, |i, j| {
            let hi = if 2 * i + 1 < k { half(2 * i + 1, j) } else { 0 };
            half(2 * i, j) | hi << 16
        });
    }

    /// Fill the bf16 panels of a `k x n` matrix from already rounded pairs: `pair(i, j)` is
    /// the pair of rows `2i, 2i + 1` in column `j` (zero past `n`).
    fn store_pairs(&mut self, k: usize, n: usize, pair: impl Fn(usize, usize) -> u32) {
        debug_assert_eq!(self.precision, Precision::Bf16);
        self.resize(k, n);
        let panels = self.panels();
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            for i in 0..k.div_ceil(2) {
                let start = offset(Precision::Bf16, k, panels, p, 2 * i);
                let row = &mut dst[start..start + NR];
                for (jj, v) in row[..width].iter_mut().enumerate() {
                    *v = f32::from_bits(pair(i, c0 + jj));
                }
                row[width..].fill(0.0);
            }
        }
    }

    /// Pack the `k x n` matrix whose element `(kk, j)` is `at(kk, j)`.
    fn pack_with(&mut self, k: usize, n: usize, at: impl Fn(usize, usize) -> f32) {
        self.resize(k, n);
        let panels = self.panels();
        let precision = self.precision;
        let dst = self.buf.as_mut_slice();
        for p in 0..panels {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            // The precision and the panel's width are decided outside the inner loop, so that
            // it is a plain copy (vectorised when `at` reads a contiguous row).
            match precision {
                Precision::F32 => {
                    for kk in 0..k {
                        let start = offset(precision, k, panels, p, kk);
                        let row = &mut dst[start..start + NR];
                        for (j, v) in row[..width].iter_mut().enumerate() {
                            *v = at(kk, c0 + j);
                        }
                        row[width..].fill(0.0);
                    }
                }
                // bf16 rows are pairs of `k`; blocks start at multiples of the even `KC_BF16`, so a
                // pair never straddles two blocks.
                Precision::Bf16 => {
                    for kk in (0..k).step_by(2) {
                        let start = offset(precision, k, panels, p, kk);
                        let row = &mut dst[start..start + NR];
                        // A ragged `k` pairs its last row with zeros; decided per row, so the
                        // inner loop is branch-free.
                        if kk + 1 < k {
                            for (j, v) in row[..width].iter_mut().enumerate() {
                                *v = bf16_pair(at(kk, c0 + j), at(kk + 1, c0 + j));
                            }
                        } else {
                            for (j, v) in row[..width].iter_mut().enumerate() {
                                *v = bf16_pair(at(kk, c0 + j), 0.0);
                            }
                        }
                        row[width..].fill(0.0);
                    }
                }
            }
        }
    }

    /// The rows of panel `p` from row `k0` (a multiple of `KC`) to the end of its block,
    /// contiguous.
    #[inline]
    pub(super) fn panel_ptr(&self, p: usize, k0: usize) -> *const f32 {
        self.buf.as_slice()[offset(self.precision, self.k, self.panels(), p, k0)..].as_ptr()
    }

    /// Pack a `Linear` weight of `n` rows (outputs) of `k` (inputs) whose element `(row, col)`
    /// is `w(row, col)`, as [`Self::from_linear_weight_in`] packs the same values, but without a
    /// row-major `f32` copy of the weight: a loader reads each element straight from the stored
    /// tensor (a checkpoint's bf16 bits widen to `f32` exactly, and rounding them back to bf16
    /// is the identity, so bf16 panels hold the file's bits).
    pub fn from_linear_fn_in(
        precision: Precision,
        n: usize,
        k: usize,
        w: impl Fn(usize, usize) -> f32,
    ) -> Self {
        let mut p = Self::empty_in(precision);
        p.pack_with(k, n, |kk, j| w(j, kk));
        p
    }
}

/// Where row `kk` of panel `p` lives (`kk` even in bf16: the row of the pair it starts). The
/// matrix is stored in `KC`-row blocks, each block all panels one after another, so the
/// kernels' (block, panel) order reads memory sequentially and the hardware prefetcher streams
/// the weights.
#[inline]
fn offset(precision: Precision, k: usize, panels: usize, p: usize, kk: usize) -> usize {
    let kcb = kc_of(precision);
    let block = kk / kcb;
    let kc = kcb.min(k - block * kcb);
    let d = |rows| depth(precision, rows);
    block * d(kcb) * panels * NR + p * d(kc) * NR + d(kk - block * kcb) * NR
}

thread_local! {
    /// Per-thread buffer for the rounded rows of [`PackedMatrix::pack_transposed`] and
    /// [`PackedMatrix::pack_rows`] in bf16.
    static ROW_PAIRS: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

#[cfg(test)]
mod tests {
    use super::super::KC_BF16;
    use super::*;

    fn data(len: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..len)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32) - 0.5
            })
            .collect()
    }

    #[test]
    fn pack_rows_equals_pack_transposed() {
        let (k, n) = (9, 21);
        let w = data(n * k, 6);
        let mut bt = vec![0.0; k * n];
        for j in 0..n {
            for kk in 0..k {
                bt[kk * n + j] = w[j * k + kk];
            }
        }
        let mut p = PackedMatrix::default();
        p.pack_rows(Isa::detect(), MatRef::dense(&bt, k, n));
        let q = PackedMatrix::from_linear_weight(&w, n, k);
        assert_eq!(
            p.buf.as_slice()[..p.panels() * k * NR],
            q.buf.as_slice()[..q.panels() * k * NR]
        );
    }

    /// The bf16 transposed and row packings (rounded by the vector code) against the
    /// element-by-element packing, bit for bit, with ragged `k` (a lone last pair), ragged
    /// `n` (an edge panel), more than one `KC_BF16` block, and a row stride wider than `k`.
    #[test]
    fn bf16_pack_transposed_equals_elementwise_packing() {
        for &(n, k, ldw) in &[(21, 9, 9), (40, 64, 200), (17, KC_BF16 + 37, KC_BF16 + 40)] {
            let mut w = data(n * ldw, 13);
            w[3] = f32::NAN;
            w[4] = 1.0 + 2f32.powi(-8);
            w[5] = f32::from_bits(1);
            let want = {
                let mut m = PackedMatrix::empty_in(Precision::Bf16);
                m.pack_with(k, n, |kk, j| w[j * ldw + kk]);
                m
            };
            for isa in [Isa::Avx512, Isa::Avx2Fma, Isa::Portable]
                .into_iter()
                .filter(|i| i.available())
            {
                let mut got = PackedMatrix::empty_in(Precision::Bf16);
                got.pack_transposed(isa, MatRef::new(&w, n, k, ldw));
                let len = want.panels() * NR * depth(Precision::Bf16, k);
                let bits = |m: &PackedMatrix| -> Vec<u32> {
                    m.buf.as_slice()[..len]
                        .iter()
                        .map(|v| v.to_bits())
                        .collect()
                };
                assert_eq!(bits(&got), bits(&want), "{isa:?} n={n} k={k}");
                // The same matrix given row by row (`k` rows of `n`, stride `n + 3`).
                let ldb = n + 3;
                let mut rows = vec![0.0f32; k * ldb];
                for kk in 0..k {
                    for j in 0..n {
                        rows[kk * ldb + j] = w[j * ldw + kk];
                    }
                }
                let mut by_rows = PackedMatrix::empty_in(Precision::Bf16);
                by_rows.pack_rows(isa, MatRef::new(&rows, k, n, ldb));
                assert_eq!(bits(&by_rows), bits(&want), "rows {isa:?} n={n} k={k}");
                // From rows already rounded to pairs (row strides of 5 and 2 spare pairs): the
                // same panels, transposed and by rows.
                let round = |src: &[f32], count: usize, width: usize, ld: usize, ldp: usize| {
                    let mut pairs = vec![0u32; count * ldp];
                    for r in 0..count {
                        let dst = &mut pairs[r * ldp..r * ldp + width.div_ceil(2)];
                        round_pairs(isa, &src[r * ld..r * ld + width], dst);
                    }
                    pairs
                };
                let ldp = k.div_ceil(2) + 5;
                let mut from_pairs = PackedMatrix::empty_in(Precision::Bf16);
                let pairs = round(&w, n, k, ldw, ldp);
                from_pairs.pack_transposed_pairs(MatRef::new(&pairs, n, k.div_ceil(2), ldp), k);
                assert_eq!(bits(&from_pairs), bits(&want), "pairs {isa:?} n={n} k={k}");
                let ldp = n.div_ceil(2) + 2;
                let mut rows_pairs = PackedMatrix::empty_in(Precision::Bf16);
                let pairs = round(&rows, k, n, ldb, ldp);
                rows_pairs.pack_rows_pairs(MatRef::new(&pairs, k, n.div_ceil(2), ldp), n);
                assert_eq!(
                    bits(&rows_pairs),
                    bits(&want),
                    "row pairs {isa:?} n={n} k={k}"
                );
            }
        }
    }

    /// bf16 panels hold two values of `k` per 32-bit lane: half the memory of f32 panels.
    #[test]
    fn bf16_panels_take_half_the_memory_of_f32() {
        for &(n, k) in &[(1, 1), (33, 301), (17, 5)] {
            let w = data(n * k, 12);
            let p16 = PackedMatrix::from_linear_weight_in(Precision::Bf16, &w, n, k);
            let p32 = PackedMatrix::from_linear_weight(&w, n, k);
            assert_eq!(
                p16.buf.as_slice().len(),
                n.div_ceil(NR) * NR * k.div_ceil(2)
            );
            assert_eq!(p32.buf.as_slice().len(), n.div_ceil(NR) * NR * k);
        }
    }
}
