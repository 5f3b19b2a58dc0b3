//! SmolVLM's text layers (SmolLM2) over the SmolVLA prefix in Candle ops, for any Candle device:
//! the same computation as the CPU text layers (see `text` for LeRobot's positions, RoPE and
//! mask), built from the shared Candle layers ([`Linear`], [`RmsNorm`], [`SwiGlu`],
//! [`batched_attention`]).
//!
//! The batch's observations are stacked, their valid tokens first and padding after, so every
//! projection is one matrix product and attention one batched product per layer; the mask keeps
//! padding out of every valid token. The keys and values of all layers come back to the host
//! in one copy at the end.

use candle_core::{DType, Device, Tensor};

use super::text::{ValidKv, ValidPrefix};
use crate::EngineError;
use crate::candle_ops;
use crate::kernels::vecmath;
use crate::pi::layers::{Linear, RmsNorm, SwiGlu, batched_attention};
use crate::smolvla::candle_weights::{linear, vector};
use crate::smolvla::config::VlmTextConfig;
use crate::smolvla::llama_layer::LayerWeights;
use crate::weights::StoredTensor;

struct TextLayer {
    input_norm: RmsNorm,
    post_norm: RmsNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    mlp: SwiGlu,
}

/// The text layers on a Candle device.
pub(crate) struct CandleText {
    config: VlmTextConfig,
    device: Device,
    layers: Vec<TextLayer>,
}

impl CandleText {
    /// Put `layers` on `device`, the matrices in `dtype`.
    pub(crate) fn new(
        config: &VlmTextConfig,
        layers: &[LayerWeights<StoredTensor>],
        dtype: DType,
        device: &Device,
    ) -> Result<Self, EngineError> {
        let eps = config.rms_norm_eps;
        let layers = layers
            .iter()
            .map(|l| {
                Ok(TextLayer {
                    input_norm: RmsNorm::from_parts(vector(&l.input_norm, device)?, eps),
                    post_norm: RmsNorm::from_parts(vector(&l.post_norm, device)?, eps),
                    q: linear(&l.q_proj, dtype, device)?,
                    k: linear(&l.k_proj, dtype, device)?,
                    v: linear(&l.v_proj, dtype, device)?,
                    o: linear(&l.o_proj, dtype, device)?,
                    mlp: SwiGlu::from_parts(
                        linear(&l.gate_proj, dtype, device)?,
                        linear(&l.up_proj, dtype, device)?,
                        linear(&l.down_proj, dtype, device)?,
                    ),
                })
            })
            .collect::<Result<Vec<_>, EngineError>>()?;
        Ok(CandleText {
            config: config.clone(),
            device: device.clone(),
            layers,
        })
    }

    /// Number of text layers.
    pub(crate) fn layers(&self) -> usize {
        self.layers.len()
    }

    /// Run the layers over every observation's valid tokens at once.
    pub(crate) fn forward(
        &self,
        prefixes: &[ValidPrefix<'_>],
    ) -> Result<Vec<ValidKv>, EngineError> {
        let c = &self.config;
        let (h, hd) = (c.hidden_size, c.head_dim);
        let (heads, kvh) = (c.num_attention_heads, c.num_key_value_heads);
        let kvw = kvh * hd;
        let dev = &self.device;
        let counts: Vec<usize> = prefixes.iter().map(|p| p.embeddings.len() / h).collect();
        let b = counts.len();
        let longest = counts.iter().copied().max().unwrap_or(0);
        if b == 0 || longest == 0 || self.layers.is_empty() {
            return Ok(counts
                .iter()
                .map(|_| ValidKv {
                    keys: vec![Vec::new(); self.layers.len()],
                    values: vec![Vec::new(); self.layers.len()],
                })
                .collect());
        }
        let mut x = vec![0.0f32; b * longest * h];
        for (o, p) in prefixes.iter().enumerate() {
            x[o * longest * h..][..p.embeddings.len()].copy_from_slice(p.embeddings);
        }
        let mut x = Tensor::from_vec(x, (b, longest, h), dev)?;
        // Token i of an observation with n valid tokens sees tokens 0..n-1 (the state token
        // n-1 only if i is the state token); a padding row sees token 0 (its output is never
        // read, and a row with no visible key would be NaN).
        let mut mask = vec![f32::NEG_INFINITY; b * longest * longest];
        for (o, &n) in counts.iter().enumerate() {
            for i in 0..longest {
                let row = &mut mask[(o * longest + i) * longest..][..longest];
                if i >= n {
                    row[0] = 0.0;
                    continue;
                }
                let seen = if i + 1 == n { n } else { n - 1 };
                row[..seen].fill(0.0);
            }
        }
        let mask = Tensor::from_vec(mask, (b, 1, longest, longest), dev)?;
        // RoPE tables: valid token t is at position t.
        let half = hd / 2;
        let (mut cos, mut sin) = (vec![0.0f32; longest * half], vec![0.0f32; longest * half]);
        for t in 0..longest {
            vecmath::rope_table(
                t as f32,
                hd,
                &mut cos[t * half..(t + 1) * half],
                &mut sin[t * half..(t + 1) * half],
            );
        }
        let cos = Tensor::from_vec(cos, (longest, half), dev)?;
        let sin = Tensor::from_vec(sin, (longest, half), dev)?;
        let split = |t: Tensor, nh: usize| -> Result<Tensor, EngineError> {
            Ok(t.reshape((b, longest, nh, hd))?
                .transpose(1, 2)?
                .contiguous()?)
        };
        let scale = (hd as f64).powf(-0.5);
        let (mut keys, mut values) = (Vec::new(), Vec::new());
        let last = self.layers.len() - 1;
        for (l, layer) in self.layers.iter().enumerate() {
            let hn = layer.input_norm.forward(&x)?;
            let k = split(layer.k.forward(&hn)?, kvh)?;
            let k = candle_ops::rope(&k, &cos, &sin)?;
            let v = split(layer.v.forward(&hn)?, kvh)?;
            // `[b, kv heads, tokens, hd]` -> `[b, tokens, kv width]`, the cache's layout.
            let rows = |t: &Tensor| -> Result<Tensor, EngineError> {
                Ok(t.transpose(1, 2)?
                    .contiguous()?
                    .reshape((b, longest, kvw))?)
            };
            keys.push(rows(&k)?);
            values.push(rows(&v)?);
            // The expert reads the last layer's keys and values only.
            if l == last {
                break;
            }
            let q = split(layer.q.forward(&hn)?, heads)?;
            let q = candle_ops::rope(&q, &cos, &sin)?;
            let att = batched_attention(&q, &k, &v, scale, Some(&mask))?;
            x = (layer.o.forward(&att)? + &x)?;
            x = (layer.mlp.forward(&layer.post_norm.forward(&x)?)? + &x)?;
        }
        // One copy of every layer's keys and values: `[layers, b, tokens, kv width]` each.
        let to_host = |t: Vec<Tensor>| -> Result<Vec<f32>, EngineError> {
            Ok(Tensor::stack(&t, 0)?.flatten_all()?.to_vec1()?)
        };
        let (keys, values) = (to_host(keys)?, to_host(values)?);
        let layers = self.layers.len();
        Ok(counts
            .iter()
            .enumerate()
            .map(|(o, &n)| {
                let take = |all: &[f32]| -> Vec<Vec<f32>> {
                    (0..layers)
                        .map(|l| all[((l * b + o) * longest) * kvw..][..n * kvw].to_vec())
                        .collect()
                };
                ValidKv {
                    keys: take(&keys),
                    values: take(&values),
                }
            })
            .collect())
    }
}
