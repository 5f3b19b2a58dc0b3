//! Observation tokens to a per-layer prefix K/V cache, as one attention projection per layer.
//!
//! The expert attends to a prefix K/V per layer. With a VLM that cache comes from the VLM's
//! layers; without one (the flow head, and the clearly labelled SmolVLA stand-in) a
//! [`PrefixEncoder`] makes it from a few observation tokens: for layer `l`,
//! `K_l = rope(T W_k,l^T)` at positions `cumsum(valid) - 1` (as the VLM applies RoPE before
//! caching), and `V_l = T W_v,l^T`.

use crate::EngineError;
use crate::kernels::gemm::gemm;
use crate::kernels::{Init, Isa, MatMut, MatRef, PackedMatrix, vecmath};
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::{ExpertDims, PrefixKv};
use crate::weights::Checkpoint;

/// Per-layer key/value projections of observation tokens.
pub struct PrefixEncoder {
    token_dim: usize,
    dims: ExpertDims,
    weights: Vec<(LinearWeights, LinearWeights)>,
    packed: Vec<(PackedMatrix, PackedMatrix)>,
}

impl std::fmt::Debug for PrefixEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PrefixEncoder")
            .field("token_dim", &self.token_dim)
            .field("layers", &self.weights.len())
            .finish()
    }
}

impl PrefixEncoder {
    fn from_weights(
        token_dim: usize,
        dims: &ExpertDims,
        weights: Vec<(LinearWeights, LinearWeights)>,
    ) -> Self {
        let packed = weights
            .iter()
            .map(|(k, v)| {
                (
                    PackedMatrix::from_linear_weight(&k.weight, k.out_dim, k.in_dim),
                    PackedMatrix::from_linear_weight(&v.weight, v.out_dim, v.in_dim),
                )
            })
            .collect();
        PrefixEncoder {
            token_dim,
            dims: dims.clone(),
            weights,
            packed,
        }
    }

    /// Seeded random projections (`1/sqrt(token_dim)`-scaled normal).
    pub fn random(seed: u64, token_dim: usize, dims: &ExpertDims) -> Self {
        let weights = (0..dims.layers.len() as u64)
            .map(|l| {
                (
                    LinearWeights::random(
                        seed.wrapping_add(2 * l),
                        dims.kv_width(),
                        token_dim,
                        false,
                    ),
                    LinearWeights::random(
                        seed.wrapping_add(2 * l + 1),
                        dims.kv_width(),
                        token_dim,
                        false,
                    ),
                )
            })
            .collect();
        Self::from_weights(token_dim, dims, weights)
    }

    /// Load `{prefix}.{l}.k_proj.weight` and `{prefix}.{l}.v_proj.weight` for every layer.
    pub fn load(
        ckpt: &Checkpoint,
        prefix: &str,
        token_dim: usize,
        dims: &ExpertDims,
    ) -> Result<Self, EngineError> {
        let kv = dims.kv_width();
        let weights = (0..dims.layers.len())
            .map(|l| {
                let load = |name: &str| -> Result<LinearWeights, EngineError> {
                    let weight =
                        ckpt.tensor(&format!("{prefix}.{l}.{name}.weight"), &[kv, token_dim])?;
                    Ok(LinearWeights {
                        weight,
                        bias: None,
                        out_dim: kv,
                        in_dim: token_dim,
                    })
                };
                Ok((load("k_proj")?, load("v_proj")?))
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(Self::from_weights(token_dim, dims, weights))
    }

    /// The tensors under `{prefix}.{l}.{k,v}_proj.weight`, for saving.
    pub fn tensors(&self, prefix: &str) -> Vec<(String, Vec<usize>, &[f32])> {
        self.weights
            .iter()
            .enumerate()
            .flat_map(|(l, (k, v))| {
                [
                    (
                        format!("{prefix}.{l}.k_proj.weight"),
                        vec![k.out_dim, k.in_dim],
                        k.weight.as_slice(),
                    ),
                    (
                        format!("{prefix}.{l}.v_proj.weight"),
                        vec![v.out_dim, v.in_dim],
                        v.weight.as_slice(),
                    ),
                ]
            })
            .collect()
    }

    /// Width of one token.
    pub fn token_dim(&self) -> usize {
        self.token_dim
    }

    /// Encode `tokens` (`[len][token_dim]`) with pad mask `valid` into a prefix cache.
    pub fn encode(&self, tokens: &[f32], valid: Vec<bool>) -> Result<PrefixKv, EngineError> {
        let len = valid.len();
        if tokens.len() != len * self.token_dim {
            return Err(EngineError::InvalidInput(format!(
                "{} token values for {len} tokens of {}",
                tokens.len(),
                self.token_dim
            )));
        }
        let (kv, hd, half) = (
            self.dims.kv_width(),
            self.dims.head_dim,
            self.dims.head_dim / 2,
        );
        let isa = Isa::detect();
        let mut positions = Vec::with_capacity(len);
        let mut next = 0usize;
        for &v in &valid {
            positions.push(next.saturating_sub(usize::from(!v)) as f32);
            next += usize::from(v);
        }
        let (mut cos, mut sin) = (vec![0.0; half], vec![0.0; half]);
        let mut keys = Vec::with_capacity(self.packed.len());
        let mut values = Vec::with_capacity(self.packed.len());
        for (wk, wv) in &self.packed {
            let mut k = vec![0.0; len * kv];
            let mut v = vec![0.0; len * kv];
            let inputs = MatRef::dense(tokens, len, self.token_dim);
            gemm(isa, inputs, wk, MatMut::dense(&mut k, len, kv), Init::Zero);
            gemm(isa, inputs, wv, MatMut::dense(&mut v, len, kv), Init::Zero);
            for (t, row) in k.chunks_exact_mut(kv).enumerate() {
                vecmath::rope_table(positions[t], hd, &mut cos, &mut sin);
                for head in row.chunks_exact_mut(hd) {
                    vecmath::rope(isa, head, &cos, &sin);
                }
            }
            keys.push(k);
            values.push(v);
        }
        PrefixKv::new(&self.dims, valid, keys, values)
    }
}
