//! A seeded random SmolVLA checkpoint folder, shaped like a real one: the tensors, dtypes and
//! JSON files LeRobot 0.6.1's `save_pretrained` writes (`config.json`, `model.safetensors`
//! with the VLM in bf16 and the rest in f32, the two processor pipelines and their stats
//! files), plus the `vlm_config.json` and `tokenizer.json` a machine without the hub needs.
//!
//! It exists to measure full-size models where no checkpoint can be downloaded (GPU machines
//! without a network): [`RandomCheckpoint::smolvla_base`] is `lerobot/smolvla_base`'s shape
//! (SmolVLM2-500M with 16 kept text layers, a 720-wide expert, two 512x512 cameras, chunk
//! 50). The weights are random (unit-gain matrices, norms near 1), so its actions mean
//! nothing; its cost is the real model's. The JSON files start from the committed
//! `smolvla_tiny` fixture, which LeRobot wrote, with the sizes replaced; the tokenizer is the
//! fixture's small one (its ids are valid in any larger vocabulary).

use std::path::Path;

use serde_json::{Value, json};

use super::config::{ExpertDims, SmolVlaConfig, VlmConfig};
use super::expert::weights::EXPERT_PREFIX;
use super::vlm::weights::VLM_PREFIX;
use crate::EngineError;
use crate::sampler::gaussian_noise;

const CONFIG: &str = include_str!("../../tests/fixtures/smolvla_tiny/config.json");
const VLM_CONFIG: &str = include_str!("../../tests/fixtures/smolvla_tiny/vlm_config.json");
const PREPROCESSOR: &str =
    include_str!("../../tests/fixtures/smolvla_tiny/policy_preprocessor.json");
const POSTPROCESSOR: &str =
    include_str!("../../tests/fixtures/smolvla_tiny/policy_postprocessor.json");
const TOKENIZER: &str = include_str!("../../tests/fixtures/smolvla_tiny/tokenizer.json");

/// The shape of a random SmolVLA checkpoint and its seed.
#[derive(Clone, Debug, PartialEq)]
pub struct RandomCheckpoint {
    /// The VLM (written to `vlm_config.json`).
    pub vlm: VlmConfig,
    /// Text layers kept (`num_vlm_layers`; the expert has as many).
    pub num_vlm_layers: usize,
    /// Robot state width.
    pub state_dim: usize,
    /// Robot action width.
    pub action_dim: usize,
    /// Cameras (`observation.images.camera1`, `camera2`, ...).
    pub cameras: usize,
    /// Side of the square the cameras are resized to (`resize_imgs_with_padding`).
    pub image_side: usize,
    /// Actions per chunk.
    pub chunk: usize,
    /// Tokens of the instruction (`tokenizer_max_length`).
    pub tokenizer_max_length: usize,
    /// Seed of every weight.
    pub seed: u64,
}

impl RandomCheckpoint {
    /// `lerobot/smolvla_base`'s shapes, a 6-wide state and action (an SO-100 arm) and two
    /// cameras.
    pub fn smolvla_base(seed: u64) -> Self {
        RandomCheckpoint {
            vlm: VlmConfig::smolvlm2_500m(),
            num_vlm_layers: 16,
            state_dim: 6,
            action_dim: 6,
            cameras: 2,
            image_side: 512,
            chunk: 50,
            tokenizer_max_length: 48,
            seed,
        }
    }

    /// Write the folder into `dir` (created if missing).
    pub fn write(&self, dir: &Path) -> Result<(), EngineError> {
        let io = |path: &Path, e: std::io::Error| EngineError::Load {
            path: path.display().to_string(),
            reason: e.to_string(),
        };
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
        let config = self.config()?;
        let cfg: SmolVlaConfig = serde_json::from_value(config.clone()).map_err(json_error)?;
        let dims = ExpertDims::resolve(&cfg, &self.vlm.text_config)?;
        let write = |name: &str, bytes: &[u8]| -> Result<(), EngineError> {
            let path = dir.join(name);
            std::fs::write(&path, bytes).map_err(|e| io(&path, e))
        };
        let pretty = |v: &Value| -> Result<Vec<u8>, EngineError> {
            Ok(serde_json::to_string_pretty(v)
                .map_err(json_error)?
                .into_bytes())
        };
        write("config.json", &pretty(&config)?)?;
        write("vlm_config.json", &pretty(&self.vlm_config()?)?)?;
        write("tokenizer.json", TOKENIZER.as_bytes())?;
        let (pre, post) = self.processors(&config)?;
        for (pipeline, name) in [
            (&pre, "policy_preprocessor.json"),
            (&post, "policy_postprocessor.json"),
        ] {
            write(name, &pretty(pipeline)?)?;
            for step in pipeline["steps"].as_array().into_iter().flatten() {
                if let Some(file) = step["state_file"].as_str() {
                    let stats = self.stats(&step["config"]["features"]);
                    write(file, &serialize(&stats)?)?;
                }
            }
        }
        write("model.safetensors", &serialize(&self.weights(&dims))?)?;
        Ok(())
    }

    /// `config.json`: the fixture's, with this shape's features and sizes.
    fn config(&self) -> Result<Value, EngineError> {
        let mut c: Value = parse(CONFIG)?;
        c["input_features"] = self.input_features();
        c["output_features"] = json!({"action": {"type": "ACTION", "shape": [self.action_dim]}});
        c["chunk_size"] = json!(self.chunk);
        c["n_action_steps"] = json!(self.chunk);
        c["resize_imgs_with_padding"] = json!([self.image_side, self.image_side]);
        c["empty_cameras"] = json!(0);
        c["tokenizer_max_length"] = json!(self.tokenizer_max_length);
        c["num_vlm_layers"] = json!(self.num_vlm_layers);
        c["num_expert_layers"] = json!(-1);
        Ok(c)
    }

    fn input_features(&self) -> Value {
        let mut f = serde_json::Map::new();
        f.insert(
            "observation.state".into(),
            json!({"type": "STATE", "shape": [self.state_dim]}),
        );
        for c in 1..=self.cameras {
            f.insert(
                format!("observation.images.camera{c}"),
                json!({"type": "VISUAL", "shape": [3, self.image_side, self.image_side]}),
            );
        }
        Value::Object(f)
    }

    /// `vlm_config.json`: the fixture's, with this VLM's sizes.
    fn vlm_config(&self) -> Result<Value, EngineError> {
        let mut v: Value = parse(VLM_CONFIG)?;
        for (section, values) in [
            (
                "text_config",
                serde_json::to_value(&self.vlm.text_config).map_err(json_error)?,
            ),
            (
                "vision_config",
                serde_json::to_value(&self.vlm.vision_config).map_err(json_error)?,
            ),
        ] {
            if let (Some(dst), Value::Object(src)) = (v[section].as_object_mut(), values) {
                dst.extend(src);
            }
        }
        v["scale_factor"] = json!(self.vlm.scale_factor);
        Ok(v)
    }

    /// The two processor pipelines: the fixture's, with this shape's features, no renaming and
    /// this tokenizer length.
    fn processors(&self, config: &Value) -> Result<(Value, Value), EngineError> {
        let mut pre: Value = parse(PREPROCESSOR)?;
        let mut post: Value = parse(POSTPROCESSOR)?;
        let mut all = config["input_features"].clone();
        if let (Some(all), Some(out)) = (all.as_object_mut(), config["output_features"].as_object())
        {
            all.extend(out.clone());
        }
        for step in pre["steps"].as_array_mut().into_iter().flatten() {
            match step["registry_name"].as_str() {
                Some("rename_observations_processor") => step["config"]["rename_map"] = json!({}),
                Some("tokenizer_processor") => {
                    step["config"]["max_length"] = json!(self.tokenizer_max_length);
                }
                Some("normalizer_processor") => step["config"]["features"] = all.clone(),
                _ => {}
            }
        }
        for step in post["steps"].as_array_mut().into_iter().flatten() {
            if step["registry_name"].as_str() == Some("unnormalizer_processor") {
                step["config"]["features"] = config["output_features"].clone();
            }
        }
        Ok((pre, post))
    }

    /// Seeded statistics of every feature (`mean`, `std`, `min`, `max`, `q01`, `q99`, `count`;
    /// `[C][1][1]` per camera), as LeRobot's normaliser stores them.
    fn stats(&self, features: &Value) -> Vec<(String, Stored)> {
        let mut out = Vec::new();
        for (i, (name, f)) in features.as_object().into_iter().flatten().enumerate() {
            let shape: Vec<usize> = f["shape"]
                .as_array()
                .into_iter()
                .flatten()
                .filter_map(|d| d.as_u64().map(|d| d as usize))
                .collect();
            let (shape, n) = if f["type"] == "VISUAL" {
                let c = shape.first().copied().unwrap_or(3);
                (vec![c, 1, 1], c)
            } else {
                let n = shape.iter().product();
                (vec![n], n)
            };
            let noise = gaussian_noise(self.seed ^ 0x57A7, i, n);
            let mean: Vec<f32> = noise.iter().map(|v| 0.1 * v).collect();
            let std: Vec<f32> = noise.iter().map(|v| 1.0 + 0.1 * v.abs()).collect();
            let around =
                |k: f32| -> Vec<f32> { mean.iter().zip(&std).map(|(m, s)| m + k * s).collect() };
            for (stat, values) in [
                ("min", around(-3.0)),
                ("max", around(3.0)),
                ("q01", around(-2.3)),
                ("q99", around(2.3)),
                ("mean", mean.clone()),
                ("std", std.clone()),
            ] {
                out.push((
                    format!("{name}.{stat}"),
                    Stored::f32(shape.clone(), &values),
                ));
            }
            if f["type"] != "VISUAL" {
                out.push((format!("{name}.count"), Stored::f32(vec![1], &[1000.0])));
            }
        }
        out
    }

    /// Every tensor of `model.safetensors`: the VLM's (vision tower, connector, token
    /// embeddings, the kept text layers, final norm, LM head) in bf16, the expert's and the
    /// projections in f32, under LeRobot's names.
    fn weights(&self, d: &ExpertDims) -> Vec<(String, Stored)> {
        let (v, t) = (&self.vlm.vision_config, &self.vlm.text_config);
        let mut specs: Vec<(String, Vec<usize>, bool)> = Vec::new();
        let mut add = |name: String, shape: Vec<usize>, bf16: bool| specs.push((name, shape, bf16));
        let vp = format!("{VLM_PREFIX}.vision_model");
        let (vh, vi, p) = (v.hidden_size, v.intermediate_size, v.patch_size);
        add(
            format!("{vp}.embeddings.patch_embedding.weight"),
            vec![vh, v.num_channels, p, p],
            true,
        );
        add(
            format!("{vp}.embeddings.patch_embedding.bias"),
            vec![vh],
            true,
        );
        let side = v.image_size / p;
        add(
            format!("{vp}.embeddings.position_embedding.weight"),
            vec![side * side, vh],
            true,
        );
        for l in 0..v.num_hidden_layers {
            let lp = format!("{vp}.encoder.layers.{l}");
            for norm in ["layer_norm1", "layer_norm2"] {
                add(format!("{lp}.{norm}.weight"), vec![vh], true);
                add(format!("{lp}.{norm}.bias"), vec![vh], true);
            }
            for proj in ["q_proj", "k_proj", "v_proj", "out_proj"] {
                add(format!("{lp}.self_attn.{proj}.weight"), vec![vh, vh], true);
                add(format!("{lp}.self_attn.{proj}.bias"), vec![vh], true);
            }
            add(format!("{lp}.mlp.fc1.weight"), vec![vi, vh], true);
            add(format!("{lp}.mlp.fc1.bias"), vec![vi], true);
            add(format!("{lp}.mlp.fc2.weight"), vec![vh, vi], true);
            add(format!("{lp}.mlp.fc2.bias"), vec![vh], true);
        }
        add(format!("{vp}.post_layernorm.weight"), vec![vh], true);
        add(format!("{vp}.post_layernorm.bias"), vec![vh], true);
        let s2 = self.vlm.scale_factor * self.vlm.scale_factor;
        let th = t.hidden_size;
        add(
            format!("{VLM_PREFIX}.connector.modality_projection.proj.weight"),
            vec![th, vh * s2],
            true,
        );
        add(
            format!("{VLM_PREFIX}.text_model.embed_tokens.weight"),
            vec![t.vocab_size, th],
            true,
        );
        let (q, kv) = (
            t.num_attention_heads * t.head_dim,
            t.num_key_value_heads * t.head_dim,
        );
        let llama = |add: &mut dyn FnMut(String, Vec<usize>, bool),
                     p: &str,
                     (h, q, kv, kv_in, i): (usize, usize, usize, usize, usize),
                     bf16: bool| {
            add(format!("{p}.input_layernorm.weight"), vec![h], bf16);
            add(
                format!("{p}.post_attention_layernorm.weight"),
                vec![h],
                bf16,
            );
            add(format!("{p}.self_attn.q_proj.weight"), vec![q, h], bf16);
            add(
                format!("{p}.self_attn.k_proj.weight"),
                vec![kv, kv_in],
                bf16,
            );
            add(
                format!("{p}.self_attn.v_proj.weight"),
                vec![kv, kv_in],
                bf16,
            );
            add(format!("{p}.self_attn.o_proj.weight"), vec![h, q], bf16);
            add(format!("{p}.mlp.gate_proj.weight"), vec![i, h], bf16);
            add(format!("{p}.mlp.up_proj.weight"), vec![i, h], bf16);
            add(format!("{p}.mlp.down_proj.weight"), vec![h, i], bf16);
        };
        for l in 0..self.num_vlm_layers {
            let p = format!("{VLM_PREFIX}.text_model.layers.{l}");
            llama(&mut add, &p, (th, q, kv, th, t.intermediate_size), true);
        }
        add(
            format!("{VLM_PREFIX}.text_model.norm.weight"),
            vec![th],
            true,
        );
        let lm_head = VLM_PREFIX.trim_end_matches(".model");
        add(
            format!("{lm_head}.lm_head.weight"),
            vec![t.vocab_size, th],
            true,
        );
        let h = d.hidden;
        for (l, kind) in d.layers.iter().enumerate() {
            let kv_in = match kind {
                super::config::LayerKind::SelfAttention => h,
                super::config::LayerKind::CrossAttention => d.kv_width(),
            };
            let p = format!("{EXPERT_PREFIX}.layers.{l}");
            llama(
                &mut add,
                &p,
                (h, d.q_width(), d.kv_width(), kv_in, d.intermediate),
                false,
            );
        }
        add(format!("{EXPERT_PREFIX}.norm.weight"), vec![h], false);
        for (name, out, inp) in [
            ("model.state_proj", d.vlm_hidden, d.state_pad),
            ("model.action_in_proj", h, d.action_pad),
            ("model.action_out_proj", d.action_pad, h),
            ("model.action_time_mlp_in", h, 2 * h),
            ("model.action_time_mlp_out", h, h),
        ] {
            add(format!("{name}.weight"), vec![out, inp], false);
            add(format!("{name}.bias"), vec![out], false);
        }
        specs
            .into_iter()
            .enumerate()
            .map(|(i, (name, shape, bf16))| {
                let n: usize = shape.iter().product();
                let noise = gaussian_noise(self.seed, i, n);
                let values: Vec<f32> = if shape.len() >= 2 {
                    // Unit-gain matrices: activations keep their scale through the layers.
                    let fan_in = (n / shape[0]).max(1) as f32;
                    noise.iter().map(|v| v / fan_in.sqrt()).collect()
                } else if name.contains("norm") {
                    noise.iter().map(|v| 1.0 + 0.1 * v).collect()
                } else {
                    noise.iter().map(|v| 0.1 * v).collect()
                };
                let stored = if bf16 {
                    Stored::bf16(shape, &values)
                } else {
                    Stored::f32(shape, &values)
                };
                (name, stored)
            })
            .collect()
    }
}

/// A committed fixture JSON file.
fn parse(text: &str) -> Result<Value, EngineError> {
    serde_json::from_str(text).map_err(json_error)
}

fn json_error(e: serde_json::Error) -> EngineError {
    EngineError::InvalidInput(format!("checkpoint JSON: {e}"))
}

/// One tensor's dtype, shape and little-endian bytes.
struct Stored {
    dtype: safetensors::Dtype,
    shape: Vec<usize>,
    bytes: Vec<u8>,
}

impl Stored {
    fn f32(shape: Vec<usize>, values: &[f32]) -> Self {
        Stored {
            dtype: safetensors::Dtype::F32,
            shape,
            bytes: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    fn bf16(shape: Vec<usize>, values: &[f32]) -> Self {
        Stored {
            dtype: safetensors::Dtype::BF16,
            shape,
            bytes: values
                .iter()
                .flat_map(|&v| half::bf16::from_f32(v).to_le_bytes())
                .collect(),
        }
    }
}

/// A safetensors file of `tensors`.
fn serialize(tensors: &[(String, Stored)]) -> Result<Vec<u8>, EngineError> {
    let views = tensors
        .iter()
        .map(|(name, t)| {
            safetensors::tensor::TensorView::new(t.dtype, t.shape.clone(), &t.bytes)
                .map(|view| (name.clone(), view))
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| EngineError::InvalidInput(format!("safetensors: {e}")))?;
    safetensors::tensor::serialize(views, None)
        .map_err(|e| EngineError::InvalidInput(format!("safetensors: {e}")))
}
