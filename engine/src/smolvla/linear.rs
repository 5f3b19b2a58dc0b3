//! `Linear` layers: their weights as loaded ([`LinearWeights`], widened to `f32` or as the
//! checkpoint stores them) and packed for the GEMM with their bias (`Linear`), as the expert,
//! the vision tower and the text layers all use them.

use crate::EngineError;
use crate::kernels::{Init, PackedMatrix, Precision};
use crate::weights::{Checkpoint, StoredTensor};

/// How a weight matrix is held after loading: widened to `f32` (`Vec<f32>`, what the expert
/// and the Candle backend read), or as the checkpoint stores it ([`StoredTensor`]: bf16 bits
/// stay bf16 until they are packed).
pub trait WeightData: Sized {
    /// Read tensor `key` with `shape`; errors name the key.
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError>;
}

impl WeightData for Vec<f32> {
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError> {
        ckpt.tensor(key, shape)
    }
}

impl WeightData for StoredTensor {
    fn read(ckpt: &Checkpoint, key: &str, shape: &[usize]) -> Result<Self, EngineError> {
        ckpt.tensor_stored(key, shape)
    }
}

/// A `Linear` layer: `weight` is `[out][in]`, PyTorch's layout (as `f32`, or as stored).
#[derive(Clone, Debug)]
pub struct LinearWeights<W = Vec<f32>> {
    /// `[out][in]`.
    pub weight: W,
    /// `[out]`, if the layer has a bias.
    pub bias: Option<Vec<f32>>,
    /// Output features.
    pub out_dim: usize,
    /// Input features.
    pub in_dim: usize,
}

impl<W: WeightData> LinearWeights<W> {
    pub(crate) fn load(
        ckpt: &Checkpoint,
        key: &str,
        out_dim: usize,
        in_dim: usize,
        bias: bool,
    ) -> Result<Self, EngineError> {
        let weight = W::read(ckpt, &format!("{key}.weight"), &[out_dim, in_dim])?;
        let bias = if bias {
            Some(ckpt.tensor(&format!("{key}.bias"), &[out_dim])?)
        } else {
            None
        };
        Ok(LinearWeights {
            weight,
            bias,
            out_dim,
            in_dim,
        })
    }
}

impl LinearWeights {
    /// Seeded random weights (uniform, scaled by `1/sqrt(in)`), for benches and the stand-in.
    pub fn random(seed: u64, out_dim: usize, in_dim: usize, bias: bool) -> Self {
        let scale = 1.0 / (in_dim as f32).sqrt();
        let weight = crate::sampler::gaussian_noise(seed, 0, out_dim * in_dim)
            .into_iter()
            .map(|v| v * scale)
            .collect();
        let bias = bias.then(|| {
            crate::sampler::gaussian_noise(seed, 1, out_dim)
                .into_iter()
                .map(|v| 0.1 * v)
                .collect()
        });
        LinearWeights {
            weight,
            bias,
            out_dim,
            in_dim,
        }
    }

    /// The same layer with its weight held as a [`StoredTensor`] (`f32`).
    pub fn into_stored(self) -> LinearWeights<StoredTensor> {
        LinearWeights {
            weight: StoredTensor::F32(self.weight),
            bias: self.bias,
            out_dim: self.out_dim,
            in_dim: self.in_dim,
        }
    }
}

impl LinearWeights<StoredTensor> {
    /// Pack layers with the same input width side by side (`[w0; w1; ..]` along the output
    /// dimension, e.g. q, k and v into one GEMM) in `precision`, reading each element from the
    /// stored tensor: no `f32` copy of a bf16 weight is made, and bf16 panels hold its bits.
    /// The panels equal [`PackedMatrix::from_linear_weights_in`]'s of the widened weights.
    pub(crate) fn pack_stacked(precision: Precision, parts: &[&Self]) -> PackedMatrix {
        let k = parts.first().map_or(0, |p| p.in_dim);
        debug_assert!(
            parts
                .iter()
                .all(|p| p.in_dim == k && p.weight.len() == p.out_dim * k)
        );
        // Output row -> (part, offset of that row in the part's weight).
        let rows: Vec<(usize, usize)> = parts
            .iter()
            .enumerate()
            .flat_map(|(i, p)| (0..p.out_dim).map(move |r| (i, r * k)))
            .collect();
        PackedMatrix::from_linear_fn_in(precision, rows.len(), k, |j, kk| {
            let (part, row) = rows[j];
            parts[part].weight.get(row + kk)
        })
    }

    /// The layer packed for the GEMM in `precision` (see [`Self::pack_stacked`]); the stored
    /// weight is dropped.
    pub(crate) fn into_linear(self, precision: Precision) -> Linear {
        let w = Self::pack_stacked(precision, &[&self]);
        Linear { w, bias: self.bias }
    }
}

/// A `Linear` layer packed for the GEMM, with its bias.
pub(crate) struct Linear {
    pub(crate) w: PackedMatrix,
    pub(crate) bias: Option<Vec<f32>>,
}

impl Linear {
    /// Pack `l`'s weight in `precision`, keeping its bias.
    pub(crate) fn new(l: &LinearWeights, precision: Precision) -> Self {
        Linear {
            w: PackedMatrix::from_linear_weight_in(precision, &l.weight, l.out_dim, l.in_dim),
            bias: l.bias.clone(),
        }
    }

    /// What the GEMM's output starts from: the bias, or zero.
    pub(crate) fn init(&self) -> Init<'_> {
        self.bias.as_deref().map_or(Init::Zero, Init::Bias)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::gemm::gemm;
    use crate::kernels::{Isa, MatMut, MatRef};

    /// `A · B` for an `m x k` `A`.
    fn product(p: &PackedMatrix, a: &[f32], m: usize) -> Vec<f32> {
        let mut c = vec![f32::NAN; m * p.n()];
        let (a, out) = (MatRef::dense(a, m, p.k()), MatMut::dense(&mut c, m, p.n()));
        gemm(Isa::detect(), a, p, out, Init::Zero);
        c
    }

    /// The packed matrix's values, `B[kk][j]`, as `I_k · B` (exact in both precisions: every
    /// product is a value times 1 or 0).
    fn unpack(p: &PackedMatrix) -> Vec<f32> {
        let k = p.k();
        let mut eye = vec![0.0f32; k * k];
        for i in 0..k {
            eye[i * k + i] = 1.0;
        }
        product(p, &eye, k)
    }

    fn bits(len: usize, seed: u64) -> Vec<u16> {
        crate::sampler::gaussian_noise(seed, 0, len)
            .into_iter()
            .map(|v| half::bf16::from_f32(v).to_bits())
            .collect()
    }

    /// Packing bf16 bits straight from a stored tensor gives exactly the panels of packing the
    /// widened `f32` weight (the old path), in f32 and bf16 panels, for odd shapes, a depth that
    /// spans two cache blocks, and stacked layers of mixed dtypes.
    #[test]
    fn packing_from_bf16_bits_equals_packing_the_widened_f32() {
        for &(n, k) in &[(1, 1), (21, 37), (33, 259), (17, 128)] {
            let w = bits(n * k, n as u64 * 1000 + k as u64);
            let widened: Vec<f32> = w.iter().map(|&b| crate::weights::bf16_to_f32(b)).collect();
            let stored = LinearWeights {
                weight: StoredTensor::Bf16(w),
                bias: None,
                out_dim: n,
                in_dim: k,
            };
            let a = crate::sampler::gaussian_noise(7, 0, 5 * k);
            for precision in [Precision::F32, Precision::Bf16] {
                let ours = LinearWeights::pack_stacked(precision, &[&stored]);
                let old = PackedMatrix::from_linear_weight_in(precision, &widened, n, k);
                assert_eq!((ours.n(), ours.k(), ours.precision()), (n, k, precision));
                let values = unpack(&ours);
                assert_eq!(values, unpack(&old), "{n}x{k} {precision:?}");
                // ...and they are the file's values: B[kk][j] = w[j][kk].
                for kk in 0..k {
                    for j in 0..n {
                        assert_eq!(values[kk * n + j], widened[j * k + kk]);
                    }
                }
                assert_eq!(product(&ours, &a, 5), product(&old, &a, 5));
            }
        }
        // q (bf16), k (f32) and v (bf16) stacked, odd widths.
        let k = 45;
        let q = bits(7 * k, 1);
        let kf = crate::sampler::gaussian_noise(2, 0, 3 * k);
        let v = bits(5 * k, 3);
        let lin = |weight: StoredTensor, n: usize| LinearWeights {
            weight,
            bias: None,
            out_dim: n,
            in_dim: k,
        };
        let parts = [
            lin(StoredTensor::Bf16(q.clone()), 7),
            lin(StoredTensor::F32(kf.clone()), 3),
            lin(StoredTensor::Bf16(v.clone()), 5),
        ];
        let widen =
            |b: &[u16]| -> Vec<f32> { b.iter().map(|&x| crate::weights::bf16_to_f32(x)).collect() };
        let (qw, vw) = (widen(&q), widen(&v));
        for precision in [Precision::F32, Precision::Bf16] {
            let ours = LinearWeights::pack_stacked(precision, &[&parts[0], &parts[1], &parts[2]]);
            let old =
                PackedMatrix::from_linear_weights_in(precision, &[(&qw, 7), (&kf, 3), (&vw, 5)], k);
            assert_eq!(unpack(&ours), unpack(&old), "stacked {precision:?}");
        }
    }

    /// `into_linear` keeps the bias and packs like `Linear::new` on the widened weight.
    #[test]
    fn into_linear_matches_linear_new_on_the_widened_weight() {
        let (n, k) = (19, 31);
        let w = bits(n * k, 9);
        let bias = Some(crate::sampler::gaussian_noise(10, 0, n));
        let f32_weights = LinearWeights {
            weight: w.iter().map(|&b| crate::weights::bf16_to_f32(b)).collect(),
            bias: bias.clone(),
            out_dim: n,
            in_dim: k,
        };
        let stored = LinearWeights {
            weight: StoredTensor::Bf16(w),
            bias,
            out_dim: n,
            in_dim: k,
        };
        for precision in [Precision::F32, Precision::Bf16] {
            let old = Linear::new(&f32_weights, precision);
            let ours = stored.clone().into_linear(precision);
            assert_eq!(ours.bias, old.bias);
            assert_eq!(unpack(&ours.w), unpack(&old.w), "{precision:?}");
        }
    }
}
