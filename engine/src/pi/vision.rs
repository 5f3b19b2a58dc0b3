//! PaliGemma's image path: the SigLIP so400m/14 tower (`SiglipVisionModel`, no pooling head)
//! and the multi-modal projector, as transformers 5.5 computes them for LeRobot's `embed_image`:
//!
//! ```text
//! [3][S][S] in [-1,1] -> patch conv (p x p, stride p, bias) + position embedding
//!   -> layers: x += out(attn(ln1 x)); x += fc2(gelu_tanh(fc1(ln2 x)))   (16 heads)
//!   -> post_layernorm                                     (the golden `vision`)
//!   -> projector linear (bias) -> [(S/p)^2][vlm width]    (the golden `image_emb`)
//! ```
//!
//! The image tokens are not scaled (PaliGemma's text embedding carries the `sqrt(width)`).

use candle_core::Tensor;

use super::config::{SiglipDims, keys};
use super::layers::{LayerNorm, Linear, batched_attention};
use super::vars::Vars;
use crate::EngineError;

/// One pre-LN SigLIP encoder layer: `x += out(attn(ln1 x)); x += fc2(gelu_tanh(fc1(ln2 x)))`
/// (transformers' `SiglipEncoderLayer`; SmolVLM's vision tower uses the same layer).
pub struct SiglipLayer {
    layer_norm1: LayerNorm,
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    out_proj: Linear,
    layer_norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
}

impl SiglipLayer {
    fn load(vars: &Vars<'_>, d: &SiglipDims) -> Result<Self, EngineError> {
        let (h, i) = (d.hidden, d.intermediate);
        let attn = vars.pp("self_attn");
        let mlp = vars.pp("mlp");
        Ok(SiglipLayer {
            layer_norm1: LayerNorm::load(&vars.pp("layer_norm1"), h, d.eps)?,
            q_proj: Linear::load(&attn.pp("q_proj"), h, h, true)?,
            k_proj: Linear::load(&attn.pp("k_proj"), h, h, true)?,
            v_proj: Linear::load(&attn.pp("v_proj"), h, h, true)?,
            out_proj: Linear::load(&attn.pp("out_proj"), h, h, true)?,
            layer_norm2: LayerNorm::load(&vars.pp("layer_norm2"), h, d.eps)?,
            fc1: Linear::load(&mlp.pp("fc1"), i, h, true)?,
            fc2: Linear::load(&mlp.pp("fc2"), h, i, true)?,
        })
    }

    /// From its parts: the two LayerNorms, the attention's `q`, `k`, `v` and `out` projections
    /// (`[hidden][hidden]` each, with biases) and the MLP's `fc1`, `fc2`.
    #[allow(clippy::too_many_arguments)] // one argument per submodule of the PyTorch layer
    pub fn from_parts(
        layer_norm1: LayerNorm,
        q_proj: Linear,
        k_proj: Linear,
        v_proj: Linear,
        out_proj: Linear,
        layer_norm2: LayerNorm,
        fc1: Linear,
        fc2: Linear,
    ) -> Self {
        SiglipLayer {
            layer_norm1,
            q_proj,
            k_proj,
            v_proj,
            out_proj,
            layer_norm2,
            fc1,
            fc2,
        }
    }

    /// `x` is `[images, patches, hidden]`, attention with `heads` heads per image (all images
    /// in one batched product).
    pub fn forward(&self, x: &Tensor, heads: usize) -> Result<Tensor, EngineError> {
        let (n, p, h) = x.dims3()?;
        let hd = h / heads;
        let y = self.layer_norm1.forward(x)?;
        // [images, patches, hidden] -> [images, heads, patches, hd]
        let split = |t: Tensor| -> Result<Tensor, EngineError> {
            Ok(t.reshape((n, p, heads, hd))?
                .transpose(1, 2)?
                .contiguous()?)
        };
        let q = split(self.q_proj.forward(&y)?)?;
        let k = split(self.k_proj.forward(&y)?)?;
        let v = split(self.v_proj.forward(&y)?)?;
        let scale = (hd as f64).powf(-0.5);
        let att = batched_attention(&q, &k, &v, scale, None)?;
        let x = (x + self.out_proj.forward(&att)?)?;
        let y = self.layer_norm2.forward(&x)?;
        let y = self.fc2.forward(&self.fc1.forward(&y)?.gelu()?)?;
        Ok((x + y)?)
    }
}

/// What the tower returns for a batch of images.
pub struct VisionOutput {
    /// SigLIP's `last_hidden_state`, `[images, patches, hidden]`.
    pub hidden: Tensor,
    /// The projector's output, `[images, patches, vlm width]`: the image tokens.
    pub embeddings: Tensor,
}

/// The SigLIP tower and PaliGemma's projector.
pub struct SiglipTower {
    dims: SiglipDims,
    /// The patch conv as a linear layer over `[3][p][p]` patches.
    patch_embedding: Linear,
    /// `[patches][hidden]`.
    position_embedding: Tensor,
    layers: Vec<SiglipLayer>,
    post_layernorm: LayerNorm,
    projector: Linear,
}

impl SiglipTower {
    /// Load from the checkpoint root; `vlm_width` is the projector's output.
    pub fn load(root: &Vars<'_>, d: &SiglipDims, vlm_width: usize) -> Result<Self, EngineError> {
        let vars = root.pp(keys::VISION);
        let emb = vars.pp("embeddings");
        let pd = 3 * d.patch * d.patch;
        let conv = emb
            .pp("patch_embedding")
            .get(&[d.hidden, 3, d.patch, d.patch], "weight")?
            .reshape((d.hidden, pd))?;
        let patch_embedding = Linear::from_parts(
            conv,
            Some(emb.pp("patch_embedding").get(&[d.hidden], "bias")?),
        )?;
        let layers = (0..d.layers)
            .map(|i| SiglipLayer::load(&vars.pp("encoder.layers").pp(i), d))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(SiglipTower {
            dims: d.clone(),
            patch_embedding,
            position_embedding: emb
                .pp("position_embedding")
                .get(&[d.patches(), d.hidden], "weight")?,
            layers,
            post_layernorm: LayerNorm::load(&vars.pp("post_layernorm"), d.hidden, d.eps)?,
            projector: Linear::load(&root.pp(keys::PROJECTOR), vlm_width, d.hidden, true)?,
        })
    }

    /// Run `images` `[n][3][S][S]` (values in `[-1, 1]`).
    pub fn forward(&self, images: &Tensor) -> Result<VisionOutput, EngineError> {
        let d = &self.dims;
        let (n, c, s, s2) = images.dims4()?;
        if c != 3 || s != d.image_size || s2 != s {
            return Err(EngineError::InvalidInput(format!(
                "images are [{c}][{s}][{s2}], the tower takes [3][{0}][{0}]",
                d.image_size
            )));
        }
        let (g, p) = (s / d.patch, d.patch);
        // Unfold into patches `[n * g * g][3 * p * p]` in the conv weight's `[c][ky][kx]` order.
        let patches = images
            .reshape((n, c, g, p, g, p))?
            .permute([0usize, 2, 4, 1, 3, 5])?
            .contiguous()?
            .reshape((n, g * g, c * p * p))?;
        let mut x = self
            .patch_embedding
            .forward(&patches)?
            .broadcast_add(&self.position_embedding)?;
        for layer in &self.layers {
            x = layer.forward(&x, d.heads)?;
        }
        let hidden = self.post_layernorm.forward(&x)?;
        let embeddings = self.projector.forward(&hidden)?;
        Ok(VisionOutput { hidden, embeddings })
    }
}
