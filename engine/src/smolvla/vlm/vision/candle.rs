//! SmolVLM's SigLIP vision tower and connector in Candle ops, for any Candle device: the same
//! computation as the CPU tower (see the parent module), built from the shared Candle layers
//! ([`SiglipLayer`], [`Linear`], [`LayerNorm`]).
//!
//! All images of one size run as one batch: the patch unfold is one reshape and permute, every
//! projection one matrix product over all their patches, attention one batched product per
//! layer, and the pixel shuffle one permute.

use candle_core::{Device, Tensor};

use super::{VisionImage, VisionOutput, position_ids};
use crate::EngineError;
use crate::pi::layers::{LayerNorm, Linear};
use crate::pi::vision::SiglipLayer;
use crate::smolvla::candle_weights::{linear, vector};
use crate::smolvla::config::VlmConfig;
use crate::smolvla::vlm::weights::{NormWeights, VlmWeights};

/// The vision tower and connector on a Candle device.
pub(crate) struct CandleVision {
    config: VlmConfig,
    device: Device,
    /// The patch conv as a linear layer over `[C][p][p]` patches.
    patch: Linear,
    /// `[positions][vision hidden]`, f32.
    positions: Tensor,
    layers: Vec<SiglipLayer>,
    post: LayerNorm,
    connector: Linear,
}

fn layer_norm(n: &NormWeights, eps: f64, device: &Device) -> Result<LayerNorm, EngineError> {
    Ok(LayerNorm::from_parts(
        vector(&n.weight, device)?,
        vector(&n.bias, device)?,
        eps,
    ))
}

impl CandleVision {
    /// Put `w`'s vision tower and connector on `device`, the matrices in `dtype`.
    pub(crate) fn new(
        w: &VlmWeights,
        dtype: candle_core::DType,
        device: &Device,
    ) -> Result<Self, EngineError> {
        let v = &w.config.vision_config;
        let eps = v.layer_norm_eps;
        let layers = w
            .vision_layers
            .iter()
            .map(|l| {
                Ok(SiglipLayer::from_parts(
                    layer_norm(&l.norm1, eps, device)?,
                    linear(&l.q_proj, dtype, device)?,
                    linear(&l.k_proj, dtype, device)?,
                    linear(&l.v_proj, dtype, device)?,
                    linear(&l.out_proj, dtype, device)?,
                    layer_norm(&l.norm2, eps, device)?,
                    linear(&l.fc1, dtype, device)?,
                    linear(&l.fc2, dtype, device)?,
                ))
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        let side = v.image_size / v.patch_size;
        Ok(CandleVision {
            config: w.config.clone(),
            device: device.clone(),
            patch: linear(&w.patch_embedding, dtype, device)?,
            positions: Tensor::from_slice(
                &w.position_embedding,
                (side * side, v.hidden_size),
                device,
            )?,
            layers,
            post: layer_norm(&w.post_layernorm, eps, device)?,
            connector: linear(&w.connector, dtype, device)?,
        })
    }

    /// Run the tower and the connector on `images` (validated: `grids[i]` patches per side),
    /// the images of each size as one batch.
    pub(crate) fn forward(
        &self,
        images: &[VisionImage<'_>],
        grids: &[usize],
    ) -> Result<VisionOutput, EngineError> {
        let mut hidden = vec![Vec::new(); images.len()];
        let mut embeddings = vec![Vec::new(); images.len()];
        let mut sides: Vec<usize> = images.iter().map(|im| im.side).collect();
        sides.sort_unstable();
        sides.dedup();
        for side in sides {
            let members: Vec<usize> = (0..images.len())
                .filter(|&i| images[i].side == side)
                .collect();
            let Some(&first) = members.first() else {
                continue;
            };
            let g = grids[first];
            if g == 0 {
                continue;
            }
            let pixels: Vec<f32> = members
                .iter()
                .flat_map(|&i| images[i].pixels.iter().copied())
                .collect();
            let (h, e) = self.tower(pixels, members.len(), side, g)?;
            for ((i, h), e) in members.into_iter().zip(h).zip(e) {
                hidden[i] = h;
                embeddings[i] = e;
            }
        }
        Ok(VisionOutput { hidden, embeddings })
    }

    /// `n` images of `side x side` (`g x g` patches), `[n][C][side][side]` in `pixels`: each
    /// image's post-LayerNorm rows and connector tokens.
    #[allow(clippy::type_complexity)] // two per-image lists, as VisionOutput holds them
    fn tower(
        &self,
        pixels: Vec<f32>,
        n: usize,
        side: usize,
        g: usize,
    ) -> Result<(Vec<Vec<f32>>, Vec<Vec<f32>>), EngineError> {
        let v = &self.config.vision_config;
        let (c, p, vh) = (v.num_channels, v.patch_size, v.hidden_size);
        let images = Tensor::from_vec(pixels, (n, c, side, side), &self.device)?;
        // Unfold into patches `[n][g * g][C * p * p]` in the conv weight's `[c][ky][kx]` order.
        let patches = images
            .reshape((n, c, g, p, g, p))?
            .permute([0usize, 2, 4, 1, 3, 5])?
            .contiguous()?
            .reshape((n, g * g, c * p * p))?;
        let ids: Vec<u32> = position_ids(g, v.image_size / p)
            .into_iter()
            .map(|i| i as u32)
            .collect();
        let ids = Tensor::from_vec(ids, g * g, &self.device)?;
        let positions = self.positions.index_select(&ids, 0)?;
        let mut x = self.patch.forward(&patches)?.broadcast_add(&positions)?;
        for layer in &self.layers {
            x = layer.forward(&x, v.num_attention_heads)?;
        }
        let hidden = self.post.forward(&x)?;
        // Pixel shuffle: token (i2, j2) of the `g/s x g/s` grid is patches (i2 s + b, j2 s + a)
        // for b, a in 0..s, in that order.
        let s = self.config.scale_factor;
        let m = g / s;
        let shuffled = hidden
            .reshape((n, m, s, m, s, vh))?
            .permute([0usize, 1, 3, 2, 4, 5])?
            .contiguous()?
            .reshape((n, m * m, s * s * vh))?;
        let emb = self.connector.forward(&shuffled)?;
        let per_image = |t: &Tensor| -> Result<Vec<Vec<f32>>, EngineError> {
            let flat: Vec<f32> = t.flatten_all()?.to_vec1()?;
            let each = flat.len() / n;
            Ok(flat
                .chunks_exact(each.max(1))
                .map(<[f32]>::to_vec)
                .collect())
        };
        Ok((per_image(&hidden)?, per_image(&emb)?))
    }
}
