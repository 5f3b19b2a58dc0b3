//! Strided views of row-major matrices: the operands of the GEMM and attention kernels.
//!
//! A view is a slice plus its shape: `rows` rows of `cols` values, row `r` starting `r * stride`
//! values after the first. The bounds are checked once, when the view is made, so a kernel that
//! takes views needs no separate stride and length arguments (nor checks of its own) for them.
//! Views of part of a wider matrix (a head's columns of `[q | k | v]` rows) are made from the
//! slice starting at their first value, with the wider matrix's stride.

/// A read-only view of `rows x cols` values with row stride `stride`: `f32` values, or bf16
/// pairs (`u32`) as [`crate::kernels::bf16::round_pairs`] writes them.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a, T = f32> {
    data: &'a [T],
    rows: usize,
    cols: usize,
    stride: usize,
}

impl<'a, T> MatRef<'a, T> {
    /// `rows` rows of `cols` values, `stride` apart, from the start of `data`.
    ///
    /// # Panics
    /// If `stride < cols`, or `data` ends before the last row does.
    pub fn new(data: &'a [T], rows: usize, cols: usize, stride: usize) -> Self {
        check_bounds(data.len(), rows, cols, stride);
        MatRef {
            data,
            rows,
            cols,
            stride,
        }
    }

    /// `rows` rows of `cols` values back to back (stride `cols`).
    ///
    /// # Panics
    /// If `data` holds fewer than `rows * cols` values.
    pub fn dense(data: &'a [T], rows: usize, cols: usize) -> Self {
        Self::new(data, rows, cols, cols)
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Values per row.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Distance between the starts of consecutive rows, in values.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The values from the first one on (row `r`, column `j` at `r * stride + j`).
    pub fn data(&self) -> &'a [T] {
        self.data
    }

    /// The `rows x cols` block whose first value is row `row0`, column `col0` of this one.
    ///
    /// # Panics
    /// If the block reaches past this matrix's rows or columns.
    pub fn sub(&self, row0: usize, col0: usize, rows: usize, cols: usize) -> MatRef<'a, T> {
        assert!(
            row0 + rows <= self.rows && col0 + cols <= self.cols,
            "block {rows} x {cols} at ({row0}, {col0}) of a {} x {} matrix",
            self.rows,
            self.cols
        );
        let start = if rows == 0 {
            self.data.len()
        } else {
            row0 * self.stride + col0
        };
        MatRef::new(&self.data[start..], rows, cols, self.stride)
    }

    /// Row `r`'s `cols` values.
    ///
    /// # Panics
    /// If `r >= rows`.
    pub fn row(&self, r: usize) -> &'a [T] {
        assert!(r < self.rows, "row {r} of a {}-row matrix", self.rows);
        &self.data[r * self.stride..r * self.stride + self.cols]
    }
}

/// A mutable view of `rows x cols` `f32` values with row stride `stride` (a kernel's output).
#[derive(Debug)]
pub struct MatMut<'a> {
    data: &'a mut [f32],
    rows: usize,
    cols: usize,
    stride: usize,
}

impl<'a> MatMut<'a> {
    /// `rows` rows of `cols` values, `stride` apart, from the start of `data`.
    ///
    /// # Panics
    /// If `stride < cols`, or `data` ends before the last row does.
    pub fn new(data: &'a mut [f32], rows: usize, cols: usize, stride: usize) -> Self {
        check_bounds(data.len(), rows, cols, stride);
        MatMut {
            data,
            rows,
            cols,
            stride,
        }
    }

    /// `rows` rows of `cols` values back to back (stride `cols`).
    ///
    /// # Panics
    /// If `data` holds fewer than `rows * cols` values.
    pub fn dense(data: &'a mut [f32], rows: usize, cols: usize) -> Self {
        Self::new(data, rows, cols, cols)
    }

    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Values per row.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Distance between the starts of consecutive rows, in values.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// The same view, borrowed for a shorter time (to hand it to several kernels in turn).
    pub fn reborrow(&mut self) -> MatMut<'_> {
        MatMut {
            data: self.data,
            rows: self.rows,
            cols: self.cols,
            stride: self.stride,
        }
    }

    /// Row `r`'s `cols` values.
    ///
    /// # Panics
    /// If `r >= rows`.
    pub fn row_mut(&mut self, r: usize) -> &mut [f32] {
        assert!(r < self.rows, "row {r} of a {}-row matrix", self.rows);
        &mut self.data[r * self.stride..r * self.stride + self.cols]
    }

    /// The values from the first one on, mutable (row `r`, column `j` at `r * stride + j`).
    pub fn data_mut(&mut self) -> &mut [f32] {
        self.data
    }
}

/// Panics unless `len` values hold `rows` rows of `cols` values `stride` apart.
fn check_bounds(len: usize, rows: usize, cols: usize, stride: usize) {
    assert!(stride >= cols, "matrix stride {stride} < {cols} columns");
    if rows > 0 {
        let end = (rows - 1) * stride + cols;
        assert!(
            len >= end,
            "{rows} x {cols} matrix (stride {stride}) needs {end} values, has {len}"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_of_a_strided_view_skip_the_gap() {
        let data: Vec<f32> = (0..11).map(|v| v as f32).collect();
        let view = MatRef::new(&data[1..], 3, 2, 4);
        assert_eq!(view.row(0), &[1.0, 2.0]);
        assert_eq!(view.row(2), &[9.0, 10.0]);
        let mut out = data.clone();
        let mut view = MatMut::new(&mut out, 2, 3, 5);
        view.row_mut(1).fill(-1.0);
        assert_eq!(&out[4..9], &[4.0, -1.0, -1.0, -1.0, 8.0]);
    }

    #[test]
    #[should_panic(expected = "needs 11 values")]
    fn a_view_past_the_end_of_its_slice_is_refused() {
        let data = [0.0f32; 10];
        let _ = MatRef::new(&data, 3, 3, 4);
    }

    #[test]
    #[should_panic(expected = "stride 2 < 3 columns")]
    fn a_stride_narrower_than_a_row_is_refused() {
        let mut data = [0.0f32; 10];
        let _ = MatMut::new(&mut data, 2, 3, 2);
    }
}
