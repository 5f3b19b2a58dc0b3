//! PaliGemma's SigLIP tower and projector on the engine's CPU kernels: SmolVLA's fast tower
//! ([`CpuVision`]), which is SigLIP at any size, given π's tensors. PaliGemma's image path is
//! that tower at native resolution (so the position ids are the plain patch grid) with no pixel
//! shuffle (scale factor 1) and a projector with a bias where SmolVLM's connector has none.

use crate::EngineError;
use crate::kernels::Precision;
use crate::pi::config::{PiDims, keys};
use crate::pi::vars::Vars;
use crate::smolvla::config::{VlmConfig, VlmTextConfig, VlmVisionConfig};
use crate::smolvla::vlm::vision::CpuVision;
use crate::smolvla::vlm::weights::{NormWeights, VisionLayerWeights, VlmWeights};
use crate::weights::StoredTensor;

/// Load the tower and projector from the checkpoint root and pack them in `precision`.
pub(crate) fn load(
    root: &Vars<'_>,
    dims: &PiDims,
    precision: Precision,
) -> Result<CpuVision, EngineError> {
    let d = &dims.vision;
    let (h, i, p) = (d.hidden, d.intermediate, d.patch);
    let vars = root.pp(keys::VISION);
    let emb = vars.pp("embeddings");
    let norm = |v: &Vars<'_>| -> Result<NormWeights, EngineError> {
        Ok(NormWeights {
            weight: v.values(&[h], "weight")?,
            bias: v.values(&[h], "bias")?,
        })
    };
    let layers = (0..d.layers)
        .map(|l| {
            let lv = vars.pp("encoder.layers").pp(l);
            let (attn, mlp) = (lv.pp("self_attn"), lv.pp("mlp"));
            Ok(VisionLayerWeights {
                norm1: norm(&lv.pp("layer_norm1"))?,
                q_proj: attn.pp("q_proj").linear_weights(h, h, true)?,
                k_proj: attn.pp("k_proj").linear_weights(h, h, true)?,
                v_proj: attn.pp("v_proj").linear_weights(h, h, true)?,
                out_proj: attn.pp("out_proj").linear_weights(h, h, true)?,
                norm2: norm(&lv.pp("layer_norm2"))?,
                fc1: mlp.pp("fc1").linear_weights(i, h, true)?,
                fc2: mlp.pp("fc2").linear_weights(h, i, true)?,
            })
        })
        .collect::<Result<Vec<_>, EngineError>>()?;
    let patch = emb.pp("patch_embedding");
    let patch_embedding = crate::smolvla::linear::LinearWeights {
        // The conv weight `[hidden][3][p][p]`, read as the linear layer over unfolded patches
        // it is (`[hidden][3 p p]`, same bytes).
        weight: patch.stored(&[h, 3, p, p], "weight")?,
        bias: Some(patch.values(&[h], "bias")?),
        out_dim: h,
        in_dim: 3 * p * p,
    };
    let g = &dims.vlm;
    let weights = VlmWeights {
        config: VlmConfig {
            // The language model's sizes, as PaliGemma's config has them; the tower reads
            // only the vision config and the projector's output width.
            text_config: VlmTextConfig {
                hidden_size: g.width,
                num_attention_heads: g.heads,
                num_key_value_heads: g.kv_heads,
                head_dim: g.head_dim,
                rms_norm_eps: g.eps,
                num_hidden_layers: g.depth,
                intermediate_size: g.mlp,
                vocab_size: dims.vocab,
            },
            vision_config: VlmVisionConfig {
                hidden_size: h,
                intermediate_size: i,
                num_hidden_layers: d.layers,
                num_attention_heads: d.heads,
                num_channels: 3,
                image_size: d.image_size,
                patch_size: p,
                hidden_act: "gelu_pytorch_tanh".into(),
                layer_norm_eps: d.eps,
            },
            scale_factor: 1,
        },
        // The Gemma layers and the token embedding are packed by the prefix, not here.
        text_layers: 0,
        patch_embedding,
        position_embedding: emb
            .pp("position_embedding")
            .values(&[d.patches(), h], "weight")?,
        vision_layers: layers,
        post_layernorm: norm(&vars.pp("post_layernorm"))?,
        connector: root.pp(keys::PROJECTOR).linear_weights(g.width, h, true)?,
        embed_tokens: StoredTensor::default(),
        layers: Vec::new(),
    };
    Ok(CpuVision::new(weights, precision))
}
