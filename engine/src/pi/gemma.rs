//! The two Gemma stacks: the PaliGemma prefix, which fills the KV cache, and the action expert,
//! which attends to it (LeRobot's `PiGemmaModel` layers, `GemmaAttention`, eager attention).
//!
//! Layer (both stacks): `h, g = norm1(x)`; `x = x + o(attn(h)) [* g]`; `h, g = norm2(x)`;
//! `x = x + mlp(h) [* g]`, the gates only with π0.5's adaptive expert norms. Attention has one
//! KV head of `head_dim` shared by the query heads, RoPE on queries and keys, scale
//! `head_dim^-1/2`.
//!
//! The prefix runs on the **valid** tokens of each observation only. LeRobot's prefix-LM mask
//! (`make_att_2d_masks` with all-zero `att_masks`) lets every valid image and language token see
//! every other valid one and nothing see padding, so padding never reaches a valid token; the
//! valid tokens' positions (`cumsum(pad) - 1`) are then `0..n`. The cache keeps the valid keys
//! and values (post-RoPE, as `DynamicCache` holds them); the expert's masks exclude the padded
//! ones, so they are never read. The last prefix layer's attention output and MLP feed nothing
//! the expert reads and are skipped.

use candle_core::{D, Device, Tensor};

use super::config::GemmaDims;
use super::layers::{
    GeGlu, GemmaNorm, Linear, Modulation, Rope, attention, gated_residual, split_heads,
};
use super::vars::Vars;
use crate::EngineError;

/// One decoder layer.
struct GemmaLayer {
    input_layernorm: GemmaNorm,
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    o_proj: Linear,
    post_attention_layernorm: GemmaNorm,
    mlp: GeGlu,
}

impl GemmaLayer {
    fn load(vars: &Vars<'_>, d: &GemmaDims, adaptive: bool) -> Result<Self, EngineError> {
        let attn = vars.pp("self_attn");
        Ok(GemmaLayer {
            input_layernorm: GemmaNorm::load(
                &vars.pp("input_layernorm"),
                d.width,
                d.eps,
                adaptive,
            )?,
            q_proj: Linear::load(&attn.pp("q_proj"), d.q_width(), d.width, false)?,
            k_proj: Linear::load(&attn.pp("k_proj"), d.kv_width(), d.width, false)?,
            v_proj: Linear::load(&attn.pp("v_proj"), d.kv_width(), d.width, false)?,
            o_proj: Linear::load(&attn.pp("o_proj"), d.width, d.q_width(), false)?,
            post_attention_layernorm: GemmaNorm::load(
                &vars.pp("post_attention_layernorm"),
                d.width,
                d.eps,
                adaptive,
            )?,
            mlp: GeGlu::load(&vars.pp("mlp"), d.width, d.mlp)?,
        })
    }
}

/// One observation's prefix cache: per layer, the keys and values of its valid tokens,
/// `[len][kv_heads * head_dim]`, post-RoPE.
#[derive(Clone, Debug)]
pub struct PrefixCache {
    /// Valid prefix tokens.
    pub len: usize,
    /// The embeddings the prefix layers started from, `[len][vlm width]`.
    pub embeddings: Tensor,
    /// Per layer.
    pub keys: Vec<Tensor>,
    /// Per layer.
    pub values: Vec<Tensor>,
}

/// The PaliGemma prefix's decoder layers.
pub struct GemmaPrefix {
    dims: GemmaDims,
    layers: Vec<GemmaLayer>,
}

impl GemmaPrefix {
    /// `vars` at the language model (`...paligemma.model.language_model`).
    pub fn load(vars: &Vars<'_>, d: &GemmaDims) -> Result<Self, EngineError> {
        let layers = (0..d.depth)
            .map(|i| GemmaLayer::load(&vars.pp("layers").pp(i), d, false))
            .collect::<Result<_, _>>()?;
        Ok(GemmaPrefix {
            dims: d.clone(),
            layers,
        })
    }

    /// The cache of one observation from its valid tokens' embeddings `[n][width]`.
    pub fn cache(&self, embeddings: Tensor) -> Result<PrefixCache, EngineError> {
        let d = &self.dims;
        let n = embeddings.dim(0)?;
        let rope = Rope::new(0..n, d.head_dim, d.rope_theta, embeddings.device())?;
        let scale = (d.head_dim as f64).powf(-0.5);
        let (mut keys, mut values) = (Vec::new(), Vec::new());
        let mut x = embeddings.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            let (h, _) = layer.input_layernorm.forward(&x, None)?;
            let k = rope.apply(&split_heads(
                &layer.k_proj.forward(&h)?,
                d.kv_heads,
                d.head_dim,
            )?)?;
            let v = split_heads(&layer.v_proj.forward(&h)?, d.kv_heads, d.head_dim)?;
            keys.push(merge_heads(&k)?);
            values.push(merge_heads(&v)?);
            if i + 1 == self.layers.len() {
                break;
            }
            let q = rope.apply(&split_heads(
                &layer.q_proj.forward(&h)?,
                d.heads,
                d.head_dim,
            )?)?;
            let att = attention(&q, &k, &v, scale, None)?;
            x = (&x + layer.o_proj.forward(&att)?)?;
            let (h, _) = layer.post_attention_layernorm.forward(&x, None)?;
            x = (&x + layer.mlp.forward(&h)?)?;
        }
        Ok(PrefixCache {
            len: n,
            embeddings,
            keys,
            values,
        })
    }
}

/// `[heads, rows, hd]` -> `[rows, heads * hd]`.
fn merge_heads(x: &Tensor) -> Result<Tensor, EngineError> {
    let (heads, rows, hd) = x.dims3()?;
    Ok(x.transpose(0, 1)?
        .contiguous()?
        .reshape((rows, heads * hd))?)
}

/// What the expert needs of one request's prefix, made once and reused by every step and
/// sample: the cached keys and values by head, the RoPE table of the suffix positions (after
/// the prefix's valid tokens) and the suffix's attention mask.
pub struct SuffixContext {
    /// Per layer, `[kv_heads][prefix len][head_dim]`.
    pub keys: Vec<Tensor>,
    /// Per layer, `[kv_heads][prefix len][head_dim]`.
    pub values: Vec<Tensor>,
    /// RoPE for positions `prefix.len + 0..suffix`.
    pub rope: Rope,
    /// Additive `[suffix][prefix.len + suffix]`, or `None` when every suffix token sees every
    /// key.
    pub mask: Option<Tensor>,
}

impl SuffixContext {
    /// LeRobot's suffix masks (`make_att_2d_masks` of the suffix after the prefix pad mask):
    /// every suffix token sees every valid prefix token; within the suffix, token `i` sees token
    /// `j` iff `cumsum(att)[j] <= cumsum(att)[i]`. `blocks[i]` is that cumsum.
    pub fn new(
        prefix: &PrefixCache,
        blocks: &[u32],
        d: &GemmaDims,
        device: &Device,
    ) -> Result<Self, EngineError> {
        let (p, s) = (prefix.len, blocks.len());
        if s == 0 || prefix.keys.len() != d.depth || prefix.values.len() != d.depth {
            return Err(EngineError::InvalidInput(format!(
                "a prefix of {} layers and a suffix of {s} tokens for an expert of {} layers",
                prefix.keys.len(),
                d.depth
            )));
        }
        let by_head = |t: &Vec<Tensor>| -> Result<Vec<Tensor>, EngineError> {
            t.iter()
                .map(|x| split_heads(x, d.kv_heads, d.head_dim))
                .collect()
        };
        let (keys, values) = (by_head(&prefix.keys)?, by_head(&prefix.values)?);
        let rope = Rope::new(p..p + s, d.head_dim, d.rope_theta, device)?;
        let sees_all = blocks.iter().all(|&b| b == blocks[s - 1]);
        let mask = if sees_all {
            None
        } else {
            let mut m = vec![0.0f32; s * (p + s)];
            for (i, &bi) in blocks.iter().enumerate() {
                for (j, &bj) in blocks.iter().enumerate() {
                    if bj > bi {
                        m[i * (p + s) + p + j] = f32::NEG_INFINITY;
                    }
                }
            }
            Some(Tensor::from_vec(m, (s, p + s), device)?)
        };
        Ok(SuffixContext {
            keys,
            values,
            rope,
            mask,
        })
    }
}

/// The action expert's decoder layers and final norm.
pub struct GemmaExpert {
    dims: GemmaDims,
    layers: Vec<GemmaLayer>,
    norm: GemmaNorm,
}

impl GemmaExpert {
    /// `vars` at the expert's model (`...gemma_expert.model`); `adaptive` for π0.5.
    pub fn load(vars: &Vars<'_>, d: &GemmaDims, adaptive: bool) -> Result<Self, EngineError> {
        let layers = (0..d.depth)
            .map(|i| GemmaLayer::load(&vars.pp("layers").pp(i), d, adaptive))
            .collect::<Result<_, _>>()?;
        Ok(GemmaExpert {
            dims: d.clone(),
            layers,
            norm: GemmaNorm::load(&vars.pp("norm"), d.width, d.eps, adaptive)?,
        })
    }

    /// The expert's output (after the final norm) for suffix embeddings `x` `[rows][s][width]`,
    /// row `r` attending to `contexts[r]`; `cond` `[1 or rows][width]` conditions the adaptive
    /// norms (π0.5).
    pub fn forward(
        &self,
        x: &Tensor,
        contexts: &[&SuffixContext],
        cond: Option<&Tensor>,
    ) -> Result<Tensor, EngineError> {
        let d = &self.dims;
        let (rows, s, _) = x.dims3()?;
        if contexts.len() != rows {
            return Err(EngineError::InvalidInput(format!(
                "{rows} suffix rows but {} prefixes",
                contexts.len()
            )));
        }
        let scale = (d.head_dim as f64).powf(-0.5);
        let modulations = |norm: &GemmaNorm| -> Result<Option<Modulation>, EngineError> {
            match cond {
                Some(c) => norm.modulation(c),
                None => Ok(None),
            }
        };
        let mut x = x.clone();
        for (li, layer) in self.layers.iter().enumerate() {
            let m1 = modulations(&layer.input_layernorm)?;
            let (h, gate) = layer.input_layernorm.forward(&x, m1.as_ref())?;
            let (q, k, v) = (
                layer.q_proj.forward(&h)?,
                layer.k_proj.forward(&h)?,
                layer.v_proj.forward(&h)?,
            );
            let mut outs = Vec::with_capacity(rows);
            for (r, ctx) in contexts.iter().enumerate() {
                let q = ctx
                    .rope
                    .apply(&split_heads(&q.get(r)?, d.heads, d.head_dim)?)?;
                let k = ctx
                    .rope
                    .apply(&split_heads(&k.get(r)?, d.kv_heads, d.head_dim)?)?;
                let v = split_heads(&v.get(r)?, d.kv_heads, d.head_dim)?;
                let keys = Tensor::cat(&[&ctx.keys[li], &k], 1)?;
                let values = Tensor::cat(&[&ctx.values[li], &v], 1)?;
                outs.push(attention(&q, &keys, &values, scale, ctx.mask.as_ref())?);
            }
            let att = Tensor::stack(&outs, 0)?;
            x = gated_residual(&x, &layer.o_proj.forward(&att)?, gate.as_ref())?;
            let m2 = modulations(&layer.post_attention_layernorm)?;
            let (h, gate) = layer.post_attention_layernorm.forward(&x, m2.as_ref())?;
            x = gated_residual(&x, &layer.mlp.forward(&h)?, gate.as_ref())?;
        }
        let m = modulations(&self.norm)?;
        let (out, _) = self.norm.forward(&x, m.as_ref())?;
        debug_assert_eq!(out.dim(D::Minus2)?, s);
        Ok(out)
    }
}
