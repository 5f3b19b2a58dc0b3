//! The expert's input from the VLM: the prefix key/value cache of one observation.

use super::config::ExpertDims;
use crate::EngineError;

/// The VLM prefix of one observation as LeRobot's `DynamicCache` holds it after the prefill:
/// for every VLM layer, the (post-RoPE) keys and the values of every prefix token, plus the
/// prefix pad mask (`false` for padding, e.g. short instructions).
///
/// Layout per layer: `[len][kv_heads][head_dim]`, i.e. LeRobot's `[batch, seq, heads, dim]` for
/// one batch element. Positions follow LeRobot's `cumsum(pad_mask) - 1`; the expert's action
/// tokens continue at `valid_len()`.
#[derive(Clone, Debug, PartialEq)]
pub struct PrefixKv {
    len: usize,
    valid: Vec<bool>,
    keys: Vec<Vec<f32>>,
    values: Vec<Vec<f32>>,
}

impl PrefixKv {
    /// Check shapes against `dims` and build. Needs one key and one value tensor per expert
    /// layer and at least one valid token.
    pub fn new(
        dims: &ExpertDims,
        valid: Vec<bool>,
        keys: Vec<Vec<f32>>,
        values: Vec<Vec<f32>>,
    ) -> Result<Self, EngineError> {
        let len = valid.len();
        let layers = dims.layers.len();
        if keys.len() != layers || values.len() != layers {
            return Err(EngineError::InvalidInput(format!(
                "prefix has {} key and {} value layers, the expert has {layers}",
                keys.len(),
                values.len()
            )));
        }
        let want = len * dims.kv_width();
        if let Some((l, t)) = keys
            .iter()
            .chain(&values)
            .enumerate()
            .find(|(_, t)| t.len() != want)
        {
            return Err(EngineError::InvalidInput(format!(
                "prefix tensor {} has {} values, expected {len} tokens x {} = {want}",
                l % layers,
                t.len(),
                dims.kv_width()
            )));
        }
        if !valid.iter().any(|&v| v) {
            return Err(EngineError::InvalidInput(
                "prefix has no valid token".into(),
            ));
        }
        if keys
            .iter()
            .chain(&values)
            .any(|t| t.iter().any(|v| !v.is_finite()))
        {
            return Err(EngineError::InvalidInput(
                "prefix contains a non-finite value".into(),
            ));
        }
        Ok(PrefixKv {
            len,
            valid,
            keys,
            values,
        })
    }

    /// Tokens, padding included.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the prefix has no tokens (never true for a constructed prefix).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The pad mask.
    pub fn valid(&self) -> &[bool] {
        &self.valid
    }

    /// Number of non-padding tokens (the position of the first action token).
    pub fn valid_len(&self) -> usize {
        self.valid.iter().filter(|&&v| v).count()
    }

    /// Keys of layer `l`, `[len][kv_heads][head_dim]`.
    pub fn keys(&self, l: usize) -> &[f32] {
        &self.keys[l]
    }

    /// Values of layer `l`, `[len][kv_heads][head_dim]`.
    pub fn values(&self, l: usize) -> &[f32] {
        &self.values[l]
    }

    /// Layer `l`'s keys and values with padding tokens removed.
    pub(crate) fn compact(&self, l: usize, width: usize) -> (Vec<f32>, Vec<f32>) {
        let pick = |t: &[f32]| -> Vec<f32> {
            t.chunks_exact(width)
                .zip(&self.valid)
                .filter(|(_, v)| **v)
                .flat_map(|(row, _)| row.iter().copied())
                .collect()
        };
        (pick(&self.keys[l]), pick(&self.values[l]))
    }
}
