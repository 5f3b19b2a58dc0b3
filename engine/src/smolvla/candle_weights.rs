//! SmolVLA's weights on a Candle device, in the dtype the chosen precision multiplies in.
//!
//! In `f32` every weight becomes f32 (a bf16 weight widens exactly). In `bf16` the matrices of
//! the linear layers are bf16 on the device: the VLM's go up as the checkpoint stores them
//! (bf16 bits, no f32 copy on the host or the device), the expert's f32 ones are rounded once
//! on the host. Norm weights, biases, embeddings and position tables stay f32: the norms,
//! softmax and residual stream compute in f32 (see [`crate::pi::layers::Linear`]).

use candle_core::{DType, Device, Tensor};

use super::linear::LinearWeights;
use crate::EngineError;
use crate::kernels::Precision;
use crate::pi::layers::Linear;
use crate::weights::StoredTensor;

/// The dtype the weight matrices of the linear layers take in `precision`.
pub(crate) fn matmul_dtype(precision: Precision) -> DType {
    match precision {
        Precision::F32 => DType::F32,
        Precision::Bf16 => DType::BF16,
    }
}

/// Host weights that can go to a device.
pub(crate) trait HostWeights {
    /// As a tensor of `shape` and `dtype` on `device`.
    fn to_device(
        &self,
        shape: &[usize],
        dtype: DType,
        device: &Device,
    ) -> Result<Tensor, EngineError>;
}

impl HostWeights for Vec<f32> {
    fn to_device(
        &self,
        shape: &[usize],
        dtype: DType,
        device: &Device,
    ) -> Result<Tensor, EngineError> {
        Ok(match dtype {
            DType::BF16 => {
                let v: Vec<half::bf16> = self.iter().map(|&x| half::bf16::from_f32(x)).collect();
                Tensor::from_vec(v, shape, device)?
            }
            _ => Tensor::from_slice(self, shape, device)?.to_dtype(dtype)?,
        })
    }
}

impl HostWeights for StoredTensor {
    fn to_device(
        &self,
        shape: &[usize],
        dtype: DType,
        device: &Device,
    ) -> Result<Tensor, EngineError> {
        match self {
            StoredTensor::F32(v) => v.to_device(shape, dtype, device),
            StoredTensor::Bf16(bits) if dtype == DType::BF16 => {
                let v: Vec<half::bf16> = bits.iter().map(|&b| half::bf16::from_bits(b)).collect();
                Ok(Tensor::from_vec(v, shape, device)?)
            }
            StoredTensor::Bf16(bits) => {
                let v: Vec<f32> = bits
                    .iter()
                    .map(|&b| half::bf16::from_bits(b).to_f32())
                    .collect();
                Ok(Tensor::from_vec(v, shape, device)?.to_dtype(dtype)?)
            }
        }
    }
}

/// A linear layer on `device`, its matrix in `dtype`, its bias (if any) in f32.
pub(crate) fn linear<W: HostWeights>(
    l: &LinearWeights<W>,
    dtype: DType,
    device: &Device,
) -> Result<Linear, EngineError> {
    let w = l.weight.to_device(&[l.out_dim, l.in_dim], dtype, device)?;
    let bias = l
        .bias
        .as_ref()
        .map(|b| Tensor::from_slice(b, l.out_dim, device))
        .transpose()?;
    Linear::from_parts(w, bias)
}

/// An f32 vector on `device`.
pub(crate) fn vector(v: &[f32], device: &Device) -> Result<Tensor, EngineError> {
    Ok(Tensor::from_slice(v, v.len(), device)?)
}
