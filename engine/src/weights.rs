//! Checkpoint tensors read by name from a safetensors file.
//!
//! Every model loads through [`Checkpoint::tensor`] (widened to `f32`) or
//! [`Checkpoint::tensor_stored`] (bf16 kept as its bits), which check the key, the shape and the
//! dtype and turn any mismatch into an [`EngineError`] that names the key. Each model converts
//! the tensors to its own layout (packed panels for the CPU kernels, Candle tensors for other
//! devices).
//!
//! A checkpoint opened from a file reads only its header up front; each tensor's bytes are read
//! from the file when the tensor is asked for, so that loading a model never holds the whole file
//! in memory next to the model (a 1.1 GB smolvla_base file would otherwise double the peak).

use std::borrow::Cow;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::ops::Range;
use std::path::Path;
use std::sync::{Mutex, PoisonError};

use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, Metadata, TensorInfo};

use crate::EngineError;

/// The largest header accepted (safetensors' own limit).
const MAX_HEADER: u64 = 100_000_000;
/// Bytes read from the file per step when decoding a tensor (a multiple of every element size),
/// so that a tensor is never in memory twice (its bytes and its values) as a whole.
const READ_CHUNK: usize = 1 << 20;

/// Where a checkpoint's tensor bytes are.
enum Source {
    /// The whole file, in memory ([`Checkpoint::from_bytes`]).
    Memory(Vec<u8>),
    /// The open file ([`Checkpoint::open`]): tensors are read when asked for. The lock makes a
    /// seek and the read after it one step.
    File(Mutex<File>),
}

/// A tensor as the checkpoint stores it: bf16 values keep their bits (exact, half the memory of
/// `f32`, and what the bf16 GEMM panels hold); every other float dtype is widened to `f32` (F16
/// and F64 as [`Checkpoint::tensor`] converts them).
#[derive(Clone, Debug, PartialEq)]
pub enum StoredTensor {
    /// `f32` values (the file's F32, or F16/F64 converted).
    F32(Vec<f32>),
    /// bf16 values as their 16 bits.
    Bf16(Vec<u16>),
}

impl Default for StoredTensor {
    fn default() -> Self {
        StoredTensor::F32(Vec::new())
    }
}

impl From<Vec<f32>> for StoredTensor {
    fn from(values: Vec<f32>) -> Self {
        StoredTensor::F32(values)
    }
}

/// A bf16 value (its bits) as `f32`: exact (bf16 is the top half of an `f32`).
#[inline]
pub fn bf16_to_f32(bits: u16) -> f32 {
    half::bf16::from_bits(bits).to_f32()
}

impl StoredTensor {
    /// Number of values.
    pub fn len(&self) -> usize {
        match self {
            StoredTensor::F32(v) => v.len(),
            StoredTensor::Bf16(v) => v.len(),
        }
    }

    /// Whether it holds no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Value `i` as `f32` (exact: bf16 widens without rounding). Panics if `i` is out of range,
    /// like indexing a slice.
    #[inline]
    pub fn get(&self, i: usize) -> f32 {
        match self {
            StoredTensor::F32(v) => v[i],
            StoredTensor::Bf16(v) => bf16_to_f32(v[i]),
        }
    }

    /// Values `range` as `f32`: borrowed when stored as `f32`, widened (exactly) otherwise.
    pub fn widened(&self, range: Range<usize>) -> Cow<'_, [f32]> {
        match self {
            StoredTensor::F32(v) => Cow::Borrowed(&v[range]),
            StoredTensor::Bf16(v) => Cow::Owned(v[range].iter().map(|&b| bf16_to_f32(b)).collect()),
        }
    }

    /// All values as `f32`.
    pub fn into_f32(self) -> Vec<f32> {
        match self {
            StoredTensor::F32(v) => v,
            StoredTensor::Bf16(v) => v.into_iter().map(bf16_to_f32).collect(),
        }
    }
}

/// A parsed safetensors file: its header, and its tensors in memory or read on demand.
pub struct Checkpoint {
    path: String,
    source: Source,
    data_start: usize,
    metadata: Metadata,
}

impl std::fmt::Debug for Checkpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let source = match &self.source {
            Source::Memory(bytes) => format!("{} bytes in memory", bytes.len()),
            Source::File(_) => "read from the file on demand".to_string(),
        };
        f.debug_struct("Checkpoint")
            .field("path", &self.path)
            .field("source", &source)
            .finish()
    }
}

impl Checkpoint {
    /// Open a safetensors file and read and validate its header; tensors are read from the file
    /// when asked for. A truncated or corrupt file is a [`EngineError::Load`] naming it.
    pub fn open(path: &Path) -> Result<Self, EngineError> {
        let name = path.display().to_string();
        let load = |reason: String| EngineError::Load {
            path: name.clone(),
            reason,
        };
        let invalid = |reason: &str| load(format!("not a valid safetensors file: {reason}"));
        let mut file = File::open(path).map_err(|e| load(e.to_string()))?;
        let file_len = file.metadata().map_err(|e| load(e.to_string()))?.len();
        let mut n = [0u8; 8];
        file.read_exact(&mut n).map_err(|e| match e.kind() {
            std::io::ErrorKind::UnexpectedEof => invalid("shorter than its 8-byte header length"),
            _ => load(e.to_string()),
        })?;
        let n = u64::from_le_bytes(n);
        if n > MAX_HEADER || 8 + n > file_len {
            return Err(invalid(&format!(
                "header length {n} does not fit the file's {file_len} bytes"
            )));
        }
        // Checked above: at most MAX_HEADER, so it fits a usize.
        let header_len = n as usize;
        let mut header = vec![0u8; header_len];
        file.read_exact(&mut header)
            .map_err(|e| load(e.to_string()))?;
        let header = std::str::from_utf8(&header).map_err(|e| invalid(&e.to_string()))?;
        let metadata: Metadata =
            serde_json::from_str(header).map_err(|e| invalid(&e.to_string()))?;
        let data_len = metadata.data_len() as u64;
        if (8 + n).checked_add(data_len) != Some(file_len) {
            return Err(invalid(&format!(
                "the header describes {data_len} bytes of tensors but {} follow it",
                file_len - 8 - n
            )));
        }
        Ok(Self {
            path: name,
            source: Source::File(Mutex::new(file)),
            data_start: 8 + header_len,
            metadata,
        })
    }

    /// Parse safetensors bytes held in memory; `name` is used in error messages.
    pub fn from_bytes(name: &str, bytes: Vec<u8>) -> Result<Self, EngineError> {
        let (header_len, metadata) =
            SafeTensors::read_metadata(&bytes).map_err(|e| EngineError::Load {
                path: name.to_string(),
                reason: format!("not a valid safetensors file: {e:?}"),
            })?;
        Ok(Self {
            path: name.to_string(),
            source: Source::Memory(bytes),
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

    /// Give the bytes of tensor `key` (header entry `info`) to `sink`, in pieces of whole
    /// elements (at most [`READ_CHUNK`] bytes each when read from the file).
    fn read_bytes(
        &self,
        key: &str,
        info: &TensorInfo,
        mut sink: impl FnMut(&[u8]),
    ) -> Result<(), EngineError> {
        let (start, end) = info.data_offsets;
        match &self.source {
            // In bounds: `read_metadata` checked the offsets against the buffer.
            Source::Memory(bytes) => sink(&bytes[self.data_start + start..self.data_start + end]),
            Source::File(file) => {
                // A panic elsewhere while holding the lock leaves nothing half done: every read
                // seeks first.
                let mut file = file.lock().unwrap_or_else(PoisonError::into_inner);
                let io = |e: std::io::Error| EngineError::Load {
                    path: self.path.clone(),
                    reason: format!("reading tensor `{key}`: {e}"),
                };
                file.seek(SeekFrom::Start((self.data_start + start) as u64))
                    .map_err(io)?;
                let mut left = end - start;
                let mut buf = vec![0u8; left.min(READ_CHUNK)];
                while left > 0 {
                    let step = left.min(READ_CHUNK);
                    file.read_exact(&mut buf[..step]).map_err(io)?;
                    sink(&buf[..step]);
                    left -= step;
                }
            }
        }
        Ok(())
    }

    /// Tensor `key` as row-major `f32`, checked against `shape`.
    ///
    /// Accepts F32, F64, BF16 and F16 (converted exactly or by rounding to nearest).
    pub fn tensor(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>, EngineError> {
        let info = self.info(key, shape)?;
        let decode: fn(&[u8], &mut Vec<f32>) = match info.dtype {
            Dtype::F32 => |d, out| {
                out.extend(
                    d.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                );
            },
            Dtype::F64 => |d, out| {
                out.extend(d.chunks_exact(8).map(|b| {
                    f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
                }));
            },
            Dtype::BF16 => |d, out| {
                out.extend(
                    d.chunks_exact(2)
                        .map(|b| bf16_to_f32(u16::from_le_bytes([b[0], b[1]]))),
                );
            },
            Dtype::F16 => |d, out| {
                out.extend(
                    d.chunks_exact(2)
                        .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()),
                );
            },
            other => {
                return Err(EngineError::DtypeMismatch {
                    key: key.to_string(),
                    expected: "F32, F64, BF16 or F16".to_string(),
                    found: format!("{other:?}"),
                });
            }
        };
        let mut values = Vec::with_capacity(shape.iter().product());
        self.read_bytes(key, info, |d| decode(d, &mut values))?;
        Ok(values)
    }

    /// Tensor `key` as stored, checked against `shape`: a BF16 tensor keeps its bits (no `f32`
    /// copy is made), F32, F64 and F16 are read as [`Self::tensor`] reads them.
    pub fn tensor_stored(&self, key: &str, shape: &[usize]) -> Result<StoredTensor, EngineError> {
        let info = self.info(key, shape)?;
        if info.dtype != Dtype::BF16 {
            return self.tensor(key, shape).map(StoredTensor::F32);
        }
        let mut bits = Vec::with_capacity(shape.iter().product());
        self.read_bytes(key, info, |d| {
            bits.extend(d.chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])));
        })?;
        Ok(StoredTensor::Bf16(bits))
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
        let mut bytes = Vec::with_capacity(shape.iter().product());
        self.read_bytes(key, info, |d| bytes.extend_from_slice(d))?;
        Ok(bytes)
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

#[cfg(test)]
mod tests {
    use super::*;
    use safetensors::tensor::TensorView;

    /// Finite bf16 values of both signs (bits `0x3f00..0x4300`, sign from bit 10 of `i`).
    fn bf16_sample(i: usize) -> u16 {
        (0x3f00 + (i % 0x400) + ((i >> 10) & 1) * 0x8000) as u16
    }

    /// A file with every dtype the loaders read, one tensor larger than a read chunk (so it is
    /// decoded in several pieces), and an I32 one no loader accepts.
    fn sample() -> Vec<u8> {
        let big: Vec<f32> = (0..(READ_CHUNK / 4 + 1001))
            .map(|i| i as f32 * 0.25 - 7.0)
            .collect();
        let bf16: Vec<u16> = (0..(READ_CHUNK / 2 + 3)).map(bf16_sample).collect();
        let tensors: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            (
                "big",
                Dtype::F32,
                vec![big.len()],
                big.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
            (
                "bf16",
                Dtype::BF16,
                vec![bf16.len()],
                bf16.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
            (
                "f16",
                Dtype::F16,
                vec![2],
                [half::f16::from_f32(1.5), half::f16::from_f32(-2.0)]
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect(),
            ),
            (
                "f64",
                Dtype::F64,
                vec![1, 2],
                [0.1f64, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
            ("mask", Dtype::U8, vec![3], vec![1, 0, 1]),
            ("ints", Dtype::I32, vec![2], vec![0; 8]),
        ];
        let views: Vec<(String, TensorView<'_>)> = tensors
            .iter()
            .map(|(k, d, s, b)| (k.to_string(), TensorView::new(*d, s.clone(), b).unwrap()))
            .collect();
        safetensors::serialize(views, None).unwrap()
    }

    fn on_disk(bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.safetensors");
        std::fs::write(&path, bytes).unwrap();
        (dir, path)
    }

    /// A checkpoint read from the file on demand gives exactly what the same bytes in memory give,
    /// for every dtype, and a bf16 tensor as stored keeps its bits.
    #[test]
    fn file_and_memory_checkpoints_read_the_same_tensors() {
        let bytes = sample();
        let (_dir, path) = on_disk(&bytes);
        let file = Checkpoint::open(&path).unwrap();
        let memory = Checkpoint::from_bytes("sample", bytes).unwrap();
        assert_eq!(file.keys(), memory.keys());
        for key in ["big", "bf16", "f16", "f64"] {
            let shape = file.shape(key).unwrap().to_vec();
            let a = file.tensor(key, &shape).unwrap();
            assert_eq!(a, memory.tensor(key, &shape).unwrap(), "{key}");
            let stored = file.tensor_stored(key, &shape).unwrap();
            assert_eq!(stored, memory.tensor_stored(key, &shape).unwrap(), "{key}");
            assert_eq!(stored.len(), a.len());
            assert_eq!(stored.clone().into_f32(), a, "{key}: widening is exact");
            assert_eq!(stored.widened(1..a.len()).as_ref(), &a[1..]);
        }
        let n = READ_CHUNK / 4 + 1001;
        assert_eq!(
            file.tensor("big", &[n]).unwrap()[n - 1],
            (n - 1) as f32 * 0.25 - 7.0
        );
        match file.tensor_stored("bf16", &[READ_CHUNK / 2 + 3]).unwrap() {
            StoredTensor::Bf16(bits) => {
                assert_eq!(bits.len(), READ_CHUNK / 2 + 3);
                assert!(bits.iter().enumerate().all(|(i, &b)| b == bf16_sample(i)));
            }
            other => panic!("bf16 must stay bf16, got {:?}", other.len()),
        }
        assert!(
            matches!(file.tensor_stored("f16", &[2]).unwrap(), StoredTensor::F32(v) if v == [1.5, -2.0])
        );
        assert_eq!(file.tensor_u8("mask", &[3]).unwrap(), [1, 0, 1]);
        assert_eq!(memory.tensor_u8("mask", &[3]).unwrap(), [1, 0, 1]);
    }

    /// Wrong dtypes and shapes name the key, as stored or widened; a missing key is named.
    #[test]
    fn stored_tensors_name_wrong_dtypes_shapes_and_keys() {
        let (_dir, path) = on_disk(&sample());
        let c = Checkpoint::open(&path).unwrap();
        for e in [
            c.tensor_stored("ints", &[2]).unwrap_err(),
            c.tensor("ints", &[2]).unwrap_err(),
        ] {
            assert!(
                matches!(&e, EngineError::DtypeMismatch { key, found, .. } if key == "ints" && found == "I32"),
                "{e:?}"
            );
        }
        let e = c.tensor_stored("bf16", &[4, 4]).unwrap_err();
        assert!(
            matches!(&e, EngineError::ShapeMismatch { key, expected, .. } if key == "bf16" && expected == &[4, 4]),
            "{e:?}"
        );
        let e = c.tensor_stored("nope", &[1]).unwrap_err();
        assert!(
            matches!(&e, EngineError::MissingTensor { key } if key == "nope"),
            "{e:?}"
        );
        let e = c.tensor_u8("f16", &[2]).unwrap_err();
        assert!(
            matches!(&e, EngineError::DtypeMismatch { key, .. } if key == "f16"),
            "{e:?}"
        );
    }

    /// A file cut short, or with a header longer than the file, or garbage, is a load error that
    /// names the file, found when it is opened (not when a tensor is read).
    #[test]
    fn truncated_and_corrupt_files_are_named_load_errors() {
        let bytes = sample();
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("cut", bytes[..bytes.len() - 1].to_vec()),
            ("longer", [bytes.as_slice(), &[0u8]].concat()),
            ("tiny", bytes[..5].to_vec()),
            ("header past the end", {
                let mut b = bytes[..64].to_vec();
                b[..8].copy_from_slice(&1000u64.to_le_bytes());
                b
            }),
            (
                "not json",
                [8u64.to_le_bytes().as_slice(), b"notjson!"].concat(),
            ),
        ];
        for (what, b) in cases {
            let (_dir, path) = on_disk(&b);
            let e = Checkpoint::open(&path).unwrap_err();
            assert!(
                matches!(&e, EngineError::Load { path: p, .. } if p.ends_with("model.safetensors")),
                "{what}: {e:?}"
            );
            assert!(Checkpoint::from_bytes("x", b).is_err(), "{what}");
        }
        let e = Checkpoint::open(Path::new("/nonexistent/model.safetensors")).unwrap_err();
        assert!(matches!(e, EngineError::Load { .. }), "{e:?}");
        let dir = tempfile::tempdir().unwrap();
        let e = Checkpoint::open(dir.path()).unwrap_err();
        assert!(matches!(e, EngineError::Load { .. }), "a directory: {e:?}");
    }
}
