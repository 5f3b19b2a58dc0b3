//! Checkpoint tensors read by name from a safetensors file.
//!
//! Every model loads through [`Checkpoint::tensor`], which checks the key, the shape and the
//! dtype and turns any mismatch into an [`EngineError`] that names the key. Weights are kept
//! as `f32` on the host; each model converts them to its own layout (packed panels for the CPU
//! kernels, Candle tensors for other devices).

use std::path::Path;

use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, Metadata, TensorInfo};

use crate::EngineError;

/// A parsed safetensors file held in memory.
pub struct Checkpoint {
    path: String,
    bytes: Vec<u8>,
    data_start: usize,
    metadata: Metadata,
}

impl std::fmt::Debug for Checkpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Checkpoint")
            .field("path", &self.path)
            .field("bytes", &self.bytes.len())
            .finish()
    }
}

impl Checkpoint {
    /// Read and validate a safetensors file. A truncated or corrupt file is a [`EngineError::Load`].
    pub fn open(path: &Path) -> Result<Self, EngineError> {
        let bytes = std::fs::read(path).map_err(|e| EngineError::Load {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        Self::from_bytes(&path.display().to_string(), bytes)
    }

    /// Parse safetensors bytes; `name` is used in error messages.
    pub fn from_bytes(name: &str, bytes: Vec<u8>) -> Result<Self, EngineError> {
        let (header_len, metadata) =
            SafeTensors::read_metadata(&bytes).map_err(|e| EngineError::Load {
                path: name.to_string(),
                reason: format!("not a valid safetensors file: {e:?}"),
            })?;
        Ok(Self {
            path: name.to_string(),
            bytes,
            data_start: 8 + header_len,
            metadata,
        })
    }

    /// The file this checkpoint came from.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// Whether the checkpoint has a tensor named `key`.
    pub fn contains(&self, key: &str) -> bool {
        self.metadata.info(key).is_some()
    }

    /// The shape of tensor `key`, if present.
    pub fn shape(&self, key: &str) -> Option<&[usize]> {
        self.metadata.info(key).map(|i| i.shape.as_slice())
    }

    /// All tensor names, sorted.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = self.metadata.tensors().into_keys().collect();
        keys.sort();
        keys
    }

    /// The header entry of tensor `key`, which must exist with exactly `shape`.
    fn info(&self, key: &str, shape: &[usize]) -> Result<&TensorInfo, EngineError> {
        let info = self
            .metadata
            .info(key)
            .ok_or_else(|| EngineError::MissingTensor {
                key: key.to_string(),
            })?;
        if info.shape != shape {
            return Err(EngineError::ShapeMismatch {
                key: key.to_string(),
                expected: shape.to_vec(),
                found: info.shape.clone(),
            });
        }
        Ok(info)
    }

    /// Tensor `key` as row-major `f32`, checked against `shape`.
    ///
    /// Accepts F32, F64, BF16 and F16 (converted exactly or by rounding to nearest).
    pub fn tensor(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>, EngineError> {
        let info = self.info(key, shape)?;
        let (start, end) = info.data_offsets;
        let data = &self.bytes[self.data_start + start..self.data_start + end];
        let values = match info.dtype {
            Dtype::F32 => data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
            Dtype::F64 => data
                .chunks_exact(8)
                .map(|b| {
                    f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
                })
                .collect(),
            Dtype::BF16 => data
                .chunks_exact(2)
                .map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            Dtype::F16 => data
                .chunks_exact(2)
                .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect(),
            other => {
                return Err(EngineError::DtypeMismatch {
                    key: key.to_string(),
                    expected: "F32, F64, BF16 or F16".to_string(),
                    found: format!("{other:?}"),
                });
            }
        };
        Ok(values)
    }

    /// Tensor `key` as raw `u8` values (masks), checked against `shape`.
    pub fn tensor_u8(&self, key: &str, shape: &[usize]) -> Result<Vec<u8>, EngineError> {
        let info = self.info(key, shape)?;
        if !matches!(info.dtype, Dtype::U8 | Dtype::BOOL) {
            return Err(EngineError::DtypeMismatch {
                key: key.to_string(),
                expected: "U8 or BOOL".to_string(),
                found: format!("{:?}", info.dtype),
            });
        }
        let (start, end) = info.data_offsets;
        Ok(self.bytes[self.data_start + start..self.data_start + end].to_vec())
    }
}

/// Serialize named `f32` tensors to safetensors bytes (used to write checkpoints).
pub fn serialize_f32(tensors: &[(String, Vec<usize>, &[f32])]) -> Result<Vec<u8>, EngineError> {
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .iter()
        .map(|(k, s, v)| {
            (
                k.clone(),
                s.clone(),
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            )
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(k, s, b)| {
            safetensors::tensor::TensorView::new(Dtype::F32, s.clone(), b)
                .map(|v| (k.clone(), v))
                .map_err(|e| EngineError::InvalidInput(format!("tensor `{k}`: {e:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    safetensors::serialize(views, None)
        .map_err(|e| EngineError::InvalidInput(format!("serialize: {e:?}")))
}
