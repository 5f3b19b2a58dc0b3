//! Building and reading [`Tensor`]s with checked sizes.
//!
//! Every size computation here is overflow-checked: a shape read off the wire can multiply to more
//! than `usize::MAX`, and that must be an error, not a wrapped length or a panic.

use half::{bf16, f16};

use super::messages::{DType, Tensor};

/// A tensor whose bytes do not match its shape and dtype.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TensorError {
    /// `product(shape) × dtype.size()` does not fit in `usize`.
    #[error("shape {shape:?} of {dtype:?} overflows the address space")]
    Overflow {
        /// The shape.
        shape: Vec<u32>,
        /// The element type.
        dtype: DType,
    },
    /// The data length is not `product(shape) × dtype.size()`.
    #[error("{actual} bytes of data for shape {shape:?} of {dtype:?}, which needs {expected}")]
    LengthMismatch {
        /// The shape.
        shape: Vec<u32>,
        /// The element type.
        dtype: DType,
        /// Bytes the shape needs.
        expected: usize,
        /// Bytes present.
        actual: usize,
    },
    /// Values given for a shape of another size.
    #[error("{actual} values for shape {shape:?}, which holds {expected}")]
    ValueCount {
        /// The shape.
        shape: Vec<u32>,
        /// Elements the shape holds.
        expected: usize,
        /// Values given.
        actual: usize,
    },
}

impl Tensor {
    /// Elements the shape holds (1 for a scalar, rank 0).
    pub fn element_count(&self) -> Result<usize, TensorError> {
        element_count(&self.shape).ok_or_else(|| TensorError::Overflow {
            shape: self.shape.clone(),
            dtype: self.dtype,
        })
    }

    /// Bytes the shape and dtype need.
    pub fn expected_len(&self) -> Result<usize, TensorError> {
        self.element_count()?
            .checked_mul(self.dtype.size())
            .ok_or_else(|| TensorError::Overflow {
                shape: self.shape.clone(),
                dtype: self.dtype,
            })
    }

    /// `Ok(elements)` if `data` is exactly the bytes the shape and dtype need.
    pub fn check_len(&self) -> Result<usize, TensorError> {
        let expected = self.expected_len()?;
        if self.data.len() != expected {
            return Err(TensorError::LengthMismatch {
                shape: self.shape.clone(),
                dtype: self.dtype,
                expected,
                actual: self.data.len(),
            });
        }
        self.element_count()
    }

    /// An `f32` tensor of `shape` holding `values` (row-major).
    pub fn from_f32(shape: Vec<u32>, values: &[f32]) -> Result<Tensor, TensorError> {
        let expected = element_count(&shape).ok_or_else(|| TensorError::Overflow {
            shape: shape.clone(),
            dtype: DType::F32,
        })?;
        if values.len() != expected {
            return Err(TensorError::ValueCount {
                shape,
                expected,
                actual: values.len(),
            });
        }
        let mut data = Vec::with_capacity(values.len() * 4);
        for value in values {
            data.extend_from_slice(&value.to_le_bytes());
        }
        Ok(Tensor {
            dtype: DType::F32,
            shape,
            data,
        })
    }

    /// A `u8` tensor of `shape` holding `data` (row-major), e.g. raw RGB pixels `[h, w, 3]`.
    pub fn from_u8(shape: Vec<u32>, data: Vec<u8>) -> Result<Tensor, TensorError> {
        let tensor = Tensor {
            dtype: DType::U8,
            shape,
            data,
        };
        tensor.check_len()?;
        Ok(tensor)
    }

    /// The elements as `f32`, whatever the dtype (`u8` values convert exactly, `f16`/`bf16`
    /// widen exactly).
    pub fn to_f32(&self) -> Result<Vec<f32>, TensorError> {
        self.check_len()?;
        let values = match self.dtype {
            DType::F32 => self
                .data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            DType::F16 => self
                .data
                .chunks_exact(2)
                .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            DType::Bf16 => self
                .data
                .chunks_exact(2)
                .map(|b| bf16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            DType::U8 => self.data.iter().map(|&b| f32::from(b)).collect(),
        };
        Ok(values)
    }
}

/// `product(shape)`, or `None` on overflow.
fn element_count(shape: &[u32]) -> Option<usize> {
    shape
        .iter()
        .try_fold(1usize, |acc, &dim| acc.checked_mul(dim as usize))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_round_trip() {
        let values = [1.0f32, -2.5, 3.25, 0.0, f32::MAX, f32::MIN_POSITIVE];
        let tensor = Tensor::from_f32(vec![2, 3], &values).unwrap();
        assert_eq!(tensor.data.len(), 24);
        assert_eq!(tensor.to_f32().unwrap(), values);
    }

    #[test]
    fn wrong_value_count_is_refused() {
        let error = Tensor::from_f32(vec![2, 3], &[1.0; 5]).unwrap_err();
        assert_eq!(
            error,
            TensorError::ValueCount {
                shape: vec![2, 3],
                expected: 6,
                actual: 5
            }
        );
    }

    #[test]
    fn overflowing_shape_is_an_error_not_a_panic() {
        let tensor = Tensor {
            dtype: DType::F32,
            shape: vec![u32::MAX, u32::MAX, u32::MAX],
            data: vec![],
        };
        assert!(matches!(tensor.to_f32(), Err(TensorError::Overflow { .. })));
    }

    #[test]
    fn data_length_must_match_shape() {
        let tensor = Tensor {
            dtype: DType::F16,
            shape: vec![3],
            data: vec![0; 5],
        };
        assert!(matches!(
            tensor.check_len(),
            Err(TensorError::LengthMismatch {
                expected: 6,
                actual: 5,
                ..
            })
        ));
    }

    #[test]
    fn half_precision_and_bytes_widen_exactly() {
        let halves = [f16::from_f32(1.5), f16::from_f32(-0.25)];
        let tensor = Tensor {
            dtype: DType::F16,
            shape: vec![2],
            data: halves.iter().flat_map(|h| h.to_le_bytes()).collect(),
        };
        assert_eq!(tensor.to_f32().unwrap(), [1.5, -0.25]);
        let brains = [bf16::from_f32(2.0), bf16::from_f32(-8.0)];
        let tensor = Tensor {
            dtype: DType::Bf16,
            shape: vec![2],
            data: brains.iter().flat_map(|h| h.to_le_bytes()).collect(),
        };
        assert_eq!(tensor.to_f32().unwrap(), [2.0, -8.0]);
        let pixels = Tensor::from_u8(vec![1, 1, 3], vec![0, 128, 255]).unwrap();
        assert_eq!(pixels.to_f32().unwrap(), [0.0, 128.0, 255.0]);
    }
}
