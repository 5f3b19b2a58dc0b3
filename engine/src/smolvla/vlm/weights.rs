//! The VLM's tensors (SigLIP vision tower, connector, SmolLM2 text layers) under LeRobot's
//! parameter names. Weight matrices and the token embeddings stay as the checkpoint stores them
//! ([`StoredTensor`]: a bf16 checkpoint's bits, half the memory of `f32`) until they are packed;
//! norms, biases and the position embedding (small) are widened to `f32` (exactly).

use crate::EngineError;
use crate::smolvla::config::{LayerKind, VlmConfig};
use crate::smolvla::linear::LinearWeights;
use crate::smolvla::llama_layer::{LayerWeights, LlamaShape};
use crate::weights::{Checkpoint, StoredTensor};

/// Prefix of the VLM's parameters in a SmolVLA checkpoint.
pub const VLM_PREFIX: &str = "model.vlm_with_expert.vlm.model";

/// A `LayerNorm`: `weight` and `bias`, `[hidden]` each.
#[derive(Clone, Debug)]
pub struct NormWeights {
    /// Scale.
    pub weight: Vec<f32>,
    /// Shift.
    pub bias: Vec<f32>,
}

impl NormWeights {
    fn load(ckpt: &Checkpoint, key: &str, h: usize) -> Result<Self, EngineError> {
        Ok(NormWeights {
            weight: ckpt.tensor(&format!("{key}.weight"), &[h])?,
            bias: ckpt.tensor(&format!("{key}.bias"), &[h])?,
        })
    }

    fn random(seed: u64, h: usize) -> Self {
        let noise = crate::sampler::gaussian_noise(seed, 0, 2 * h);
        NormWeights {
            weight: noise[..h].iter().map(|v| 1.0 + 0.1 * v).collect(),
            bias: noise[h..].iter().map(|v| 0.1 * v).collect(),
        }
    }
}

/// One SigLIP encoder layer (pre-LN; all linears have biases).
#[derive(Clone, Debug)]
pub struct VisionLayerWeights {
    /// `layer_norm1`.
    pub norm1: NormWeights,
    /// `self_attn.q_proj`.
    pub q_proj: LinearWeights<StoredTensor>,
    /// `self_attn.k_proj`.
    pub k_proj: LinearWeights<StoredTensor>,
    /// `self_attn.v_proj`.
    pub v_proj: LinearWeights<StoredTensor>,
    /// `self_attn.out_proj`.
    pub out_proj: LinearWeights<StoredTensor>,
    /// `layer_norm2`.
    pub norm2: NormWeights,
    /// `mlp.fc1`: hidden -> intermediate.
    pub fc1: LinearWeights<StoredTensor>,
    /// `mlp.fc2`: intermediate -> hidden.
    pub fc2: LinearWeights<StoredTensor>,
}

/// Every VLM tensor the prefix needs.
#[derive(Clone, Debug)]
pub struct VlmWeights {
    /// Shapes.
    pub config: VlmConfig,
    /// Text layers kept (LeRobot's `num_vlm_layers`).
    pub text_layers: usize,
    /// `embeddings.patch_embedding` as a linear layer over unfolded patches: `[hidden][C*p*p]`
    /// (PyTorch's conv weight `[hidden][C][p][p]`, flattened), with its bias.
    pub patch_embedding: LinearWeights<StoredTensor>,
    /// `embeddings.position_embedding.weight`: `[(image_size/patch)^2][hidden]`.
    pub position_embedding: Vec<f32>,
    /// Encoder layers.
    pub vision_layers: Vec<VisionLayerWeights>,
    /// `post_layernorm`.
    pub post_layernorm: NormWeights,
    /// `connector.modality_projection.proj`: `vision_hidden * scale^2 -> text hidden`, no bias.
    pub connector: LinearWeights<StoredTensor>,
    /// `text_model.embed_tokens.weight`: `[vocab][text hidden]`, as stored (rows are widened
    /// when looked up; widening bf16 is exact).
    pub embed_tokens: StoredTensor,
    /// Text decoder layers (`kind` is always self-attention).
    pub layers: Vec<LayerWeights<StoredTensor>>,
}

impl VlmWeights {
    /// Read every VLM tensor; errors name the first missing or mis-shaped key.
    pub fn load(
        ckpt: &Checkpoint,
        config: &VlmConfig,
        text_layers: usize,
    ) -> Result<Self, EngineError> {
        let v = &config.vision_config;
        let t = &config.text_config;
        check_config(config, text_layers)?;
        let vp = format!("{VLM_PREFIX}.vision_model");
        let (vh, p, c) = (v.hidden_size, v.patch_size, v.num_channels);
        let conv = ckpt.tensor_stored(
            &format!("{vp}.embeddings.patch_embedding.weight"),
            &[vh, c, p, p],
        )?;
        let patch_embedding = LinearWeights {
            weight: conv,
            bias: Some(ckpt.tensor(&format!("{vp}.embeddings.patch_embedding.bias"), &[vh])?),
            out_dim: vh,
            in_dim: c * p * p,
        };
        let side = v.image_size / p;
        let position_embedding = ckpt.tensor(
            &format!("{vp}.embeddings.position_embedding.weight"),
            &[side * side, vh],
        )?;
        let vision_layers = (0..v.num_hidden_layers)
            .map(|l| {
                let lp = format!("{vp}.encoder.layers.{l}");
                let lin = |name: &str, out: usize, inp: usize| {
                    LinearWeights::load(ckpt, &format!("{lp}.{name}"), out, inp, true)
                };
                Ok(VisionLayerWeights {
                    norm1: NormWeights::load(ckpt, &format!("{lp}.layer_norm1"), vh)?,
                    q_proj: lin("self_attn.q_proj", vh, vh)?,
                    k_proj: lin("self_attn.k_proj", vh, vh)?,
                    v_proj: lin("self_attn.v_proj", vh, vh)?,
                    out_proj: lin("self_attn.out_proj", vh, vh)?,
                    norm2: NormWeights::load(ckpt, &format!("{lp}.layer_norm2"), vh)?,
                    fc1: lin("mlp.fc1", v.intermediate_size, vh)?,
                    fc2: lin("mlp.fc2", vh, v.intermediate_size)?,
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        let s2 = config.scale_factor * config.scale_factor;
        let shape = text_shape(config);
        let layers = (0..text_layers)
            .map(|l| {
                LayerWeights::load_llama(
                    ckpt,
                    &format!("{VLM_PREFIX}.text_model.layers.{l}"),
                    LayerKind::SelfAttention,
                    shape,
                )
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(VlmWeights {
            config: config.clone(),
            text_layers,
            patch_embedding,
            position_embedding,
            vision_layers,
            post_layernorm: NormWeights::load(ckpt, &format!("{vp}.post_layernorm"), vh)?,
            connector: LinearWeights::load(
                ckpt,
                &format!("{VLM_PREFIX}.connector.modality_projection.proj"),
                t.hidden_size,
                vh * s2,
                false,
            )?,
            embed_tokens: ckpt.tensor_stored(
                &format!("{VLM_PREFIX}.text_model.embed_tokens.weight"),
                &[t.vocab_size, t.hidden_size],
            )?,
            layers,
        })
    }

    /// Seeded random weights of the given shapes (benchmarks on full-size shapes).
    pub fn random(config: &VlmConfig, text_layers: usize, seed: u64) -> Result<Self, EngineError> {
        check_config(config, text_layers)?;
        let v = &config.vision_config;
        let t = &config.text_config;
        let (vh, p, c) = (v.hidden_size, v.patch_size, v.num_channels);
        let side = v.image_size / p;
        let mut s = seed.wrapping_mul(1000);
        let mut next = || {
            s = s.wrapping_add(1);
            s
        };
        let vision_layers = (0..v.num_hidden_layers)
            .map(|_| VisionLayerWeights {
                norm1: NormWeights::random(next(), vh),
                q_proj: LinearWeights::random(next(), vh, vh, true).into_stored(),
                k_proj: LinearWeights::random(next(), vh, vh, true).into_stored(),
                v_proj: LinearWeights::random(next(), vh, vh, true).into_stored(),
                out_proj: LinearWeights::random(next(), vh, vh, true).into_stored(),
                norm2: NormWeights::random(next(), vh),
                fc1: LinearWeights::random(next(), v.intermediate_size, vh, true).into_stored(),
                fc2: LinearWeights::random(next(), vh, v.intermediate_size, true).into_stored(),
            })
            .collect();
        let shape = text_shape(config);
        let layers = (0..text_layers)
            .map(|_| {
                LayerWeights::random_llama(next(), LayerKind::SelfAttention, shape).into_stored()
            })
            .collect();
        let s2 = config.scale_factor * config.scale_factor;
        Ok(VlmWeights {
            config: config.clone(),
            text_layers,
            patch_embedding: LinearWeights::random(next(), vh, c * p * p, true).into_stored(),
            position_embedding: crate::sampler::gaussian_noise(next(), 0, side * side * vh),
            vision_layers,
            post_layernorm: NormWeights::random(next(), vh),
            connector: LinearWeights::random(next(), t.hidden_size, vh * s2, false).into_stored(),
            embed_tokens: StoredTensor::F32(
                crate::sampler::gaussian_noise(next(), 0, t.vocab_size * t.hidden_size)
                    .into_iter()
                    .map(|x| x / (t.hidden_size as f32).sqrt())
                    .collect(),
            ),
            layers,
        })
    }
}

fn text_shape(config: &VlmConfig) -> LlamaShape {
    let t = &config.text_config;
    LlamaShape {
        hidden: t.hidden_size,
        q: t.num_attention_heads * t.head_dim,
        kv: t.num_key_value_heads * t.head_dim,
        kv_in: t.hidden_size,
        intermediate: t.intermediate_size,
    }
}

/// Reject configs the prefix cannot run, naming the field.
fn check_config(config: &VlmConfig, text_layers: usize) -> Result<(), EngineError> {
    let v = &config.vision_config;
    let t = &config.text_config;
    let bad = |reason: String| EngineError::Load {
        path: "vlm config".into(),
        reason,
    };
    if v.hidden_act != "gelu_pytorch_tanh" {
        return Err(bad(format!(
            "vision_config.hidden_act `{}` is not supported (gelu_pytorch_tanh only)",
            v.hidden_act
        )));
    }
    if v.patch_size == 0 || !v.image_size.is_multiple_of(v.patch_size) {
        return Err(bad(format!(
            "vision_config.image_size {} is not a multiple of patch_size {}",
            v.image_size, v.patch_size
        )));
    }
    if v.num_attention_heads == 0 || !v.hidden_size.is_multiple_of(v.num_attention_heads) {
        return Err(bad(format!(
            "vision_config.hidden_size {} is not a multiple of num_attention_heads {}",
            v.hidden_size, v.num_attention_heads
        )));
    }
    if config.scale_factor == 0
        || !(v.image_size / v.patch_size).is_multiple_of(config.scale_factor)
    {
        return Err(bad(format!(
            "scale_factor {} does not divide the {} patches per side",
            config.scale_factor,
            v.image_size / v.patch_size
        )));
    }
    if t.num_key_value_heads == 0
        || !t.num_attention_heads.is_multiple_of(t.num_key_value_heads)
        || !t.head_dim.is_multiple_of(2)
    {
        return Err(bad(
            "text_config: heads must be a multiple of KV heads and head_dim even".into(),
        ));
    }
    if text_layers == 0 || text_layers > t.num_hidden_layers {
        return Err(bad(format!(
            "num_vlm_layers {text_layers} is outside 1..={}",
            t.num_hidden_layers
        )));
    }
    Ok(())
}
