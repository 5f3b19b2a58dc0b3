//! SmolVLA configuration: LeRobot's `config.json` and the VLM text config the expert derives from.

use std::collections::BTreeMap;
use std::path::Path;

use crate::EngineError;

/// The fields of LeRobot's `SmolVLAConfig` (`config.json` of a SmolVLA checkpoint) that the
/// action expert depends on. Unknown fields are ignored; defaults are LeRobot 0.6.1's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct SmolVlaConfig {
    /// Policy type; must be `smolvla`.
    #[serde(rename = "type")]
    pub policy_type: String,
    /// Actions per chunk.
    pub chunk_size: usize,
    /// Padded state width (`state_proj` input).
    pub max_state_dim: usize,
    /// Padded action width (noise, `action_in_proj` input, `action_out_proj` output).
    pub max_action_dim: usize,
    /// Flow-matching steps.
    pub num_steps: usize,
    /// The VLM whose text config sizes the expert.
    pub vlm_model_name: String,
    /// Expert layers (`<= 0`: as many as VLM layers).
    pub num_expert_layers: i64,
    /// VLM layers kept.
    pub num_vlm_layers: usize,
    /// Every n-th layer self-attends; the others cross-attend (with `cross` attention modes).
    pub self_attn_every_n_layers: i64,
    /// Expert hidden size relative to the VLM's.
    pub expert_width_multiplier: f64,
    /// `cross_attn` (SmolVLA) or `self_attn`.
    pub attention_mode: String,
    /// Smallest period of the sinusoidal time embedding.
    pub min_period: f64,
    /// Largest period of the sinusoidal time embedding.
    pub max_period: f64,
    /// Whether the prefix wraps each image in special tokens (not supported; LeRobot's default
    /// is `false`).
    pub add_image_special_tokens: bool,
    /// Pad the prefix to this many tokens (`<= 0`: no padding, LeRobot's default).
    pub prefix_length: i64,
    /// LeRobot's input features (`observation.state` gives the real state size), in file order:
    /// the order of the `VISUAL` ones is the camera order of the prefix.
    pub input_features: FeatureMap,
    /// LeRobot's output features (`action` gives the real action size).
    pub output_features: FeatureMap,
    /// Normalisation mode per feature type (`VISUAL`, `STATE`, `ACTION`). The processors'
    /// own files carry the map that is applied; this is the policy's copy.
    pub normalization_mapping: BTreeMap<String, String>,
    /// Image size the cameras are resized (with padding) to, as LeRobot stores it:
    /// `[width, height]`. `None`: images are used at their own size.
    pub resize_imgs_with_padding: Option<[usize; 2]>,
    /// How many missing cameras become an all-`-1` image with a false mask.
    pub empty_cameras: usize,
    /// The tokenizer's maximum length (the preprocessor's tokenizer step has its own copy).
    pub tokenizer_max_length: usize,
}

/// A JSON object of [`Feature`]s that keeps the file's key order (LeRobot's `dict` order: the
/// camera order of the prefix follows it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FeatureMap(Vec<(String, Feature)>);

impl FeatureMap {
    /// The feature named `key`.
    pub fn get(&self, key: &str) -> Option<&Feature> {
        self.0.iter().find(|(k, _)| k == key).map(|(_, f)| f)
    }

    /// Insert or replace `key` (a new key goes last).
    pub fn insert(&mut self, key: String, feature: Feature) {
        match self.0.iter_mut().find(|(k, _)| *k == key) {
            Some(slot) => slot.1 = feature,
            None => self.0.push((key, feature)),
        }
    }

    /// Features in file order.
    pub fn iter(&self) -> impl Iterator<Item = (&String, &Feature)> {
        self.0.iter().map(|(k, f)| (k, f))
    }

    /// Features in file order.
    pub fn values(&self) -> impl Iterator<Item = &Feature> {
        self.0.iter().map(|(_, f)| f)
    }

    /// Number of features.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl serde::Serialize for FeatureMap {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (k, f) in &self.0 {
            map.serialize_entry(k, f)?;
        }
        map.end()
    }
}

impl<'de> serde::Deserialize<'de> for FeatureMap {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = FeatureMap;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("an object of features")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut access: A,
            ) -> Result<FeatureMap, A::Error> {
                let mut map = FeatureMap::default();
                while let Some((k, f)) = access.next_entry::<String, Feature>()? {
                    map.insert(k, f);
                }
                Ok(map)
            }
        }
        d.deserialize_map(Visit)
    }
}

/// One LeRobot policy feature.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Feature {
    /// `STATE`, `VISUAL`, `ACTION`, ...
    #[serde(rename = "type")]
    pub kind: String,
    /// Tensor shape.
    pub shape: Vec<usize>,
}

impl Default for SmolVlaConfig {
    fn default() -> Self {
        SmolVlaConfig {
            policy_type: "smolvla".into(),
            chunk_size: 50,
            max_state_dim: 32,
            max_action_dim: 32,
            num_steps: 10,
            vlm_model_name: SMOLVLM2_500M.into(),
            num_expert_layers: -1,
            num_vlm_layers: 16,
            self_attn_every_n_layers: 2,
            expert_width_multiplier: 0.75,
            attention_mode: "cross_attn".into(),
            min_period: 4e-3,
            max_period: 4.0,
            add_image_special_tokens: false,
            prefix_length: -1,
            input_features: FeatureMap::default(),
            output_features: FeatureMap::default(),
            normalization_mapping: [
                ("VISUAL", "IDENTITY"),
                ("STATE", "MEAN_STD"),
                ("ACTION", "MEAN_STD"),
            ]
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v.to_owned()))
            .collect(),
            resize_imgs_with_padding: Some([512, 512]),
            empty_cameras: 0,
            tokenizer_max_length: 48,
        }
    }
}

impl SmolVlaConfig {
    /// The camera keys (`VISUAL` input features) in the order LeRobot feeds them to the VLM.
    pub fn image_keys(&self) -> Vec<String> {
        self.input_features
            .iter()
            .filter(|(_, f)| f.kind == "VISUAL")
            .map(|(k, _)| k.clone())
            .collect()
    }
}

/// LeRobot's default VLM.
pub const SMOLVLM2_500M: &str = "HuggingFaceTB/SmolVLM2-500M-Video-Instruct";

/// The VLM text-model fields the expert copies (`text_config` of the SmolVLM config).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VlmTextConfig {
    /// VLM hidden size (state_proj output).
    pub hidden_size: usize,
    /// Query heads (shared by VLM and expert).
    pub num_attention_heads: usize,
    /// Key/value heads.
    pub num_key_value_heads: usize,
    /// Head width.
    pub head_dim: usize,
    /// RMSNorm epsilon.
    pub rms_norm_eps: f64,
    /// VLM layers before LeRobot truncates to `num_vlm_layers`.
    pub num_hidden_layers: usize,
    /// Width of the text layers' SwiGLU MLP.
    pub intermediate_size: usize,
    /// Rows of `embed_tokens`.
    pub vocab_size: usize,
}

impl VlmTextConfig {
    /// SmolVLM2-500M-Video-Instruct's text model (SmolLM2-360M-like), from its hub config.json.
    pub fn smolvlm2_500m() -> Self {
        VlmTextConfig {
            hidden_size: 960,
            num_attention_heads: 15,
            num_key_value_heads: 5,
            head_dim: 64,
            rms_norm_eps: 1e-5,
            num_hidden_layers: 32,
            intermediate_size: 2560,
            vocab_size: 49280,
        }
    }

    /// Read `text_config` from a SmolVLM `config.json` (as `SmolVLMConfig.save_pretrained` writes).
    pub fn from_vlm_config_file(path: &Path) -> Result<Self, EngineError> {
        Ok(VlmConfig::from_file(path)?.text_config)
    }
}

/// The SigLIP vision tower's config (`vision_config` of the SmolVLM config). Missing fields take
/// the defaults of transformers' `SmolVLMVisionConfig`, as `from_pretrained` would.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct VlmVisionConfig {
    /// Width of the patch embeddings and encoder layers.
    pub hidden_size: usize,
    /// Width of the encoder MLP.
    pub intermediate_size: usize,
    /// Encoder layers.
    pub num_hidden_layers: usize,
    /// Attention heads (`hidden_size / heads` wide each).
    pub num_attention_heads: usize,
    /// Image channels.
    pub num_channels: usize,
    /// Side of the square image the position embeddings were trained for.
    pub image_size: usize,
    /// Side of a square patch (the patch conv's kernel and stride).
    pub patch_size: usize,
    /// MLP activation; only `gelu_pytorch_tanh` (SigLIP's) is supported.
    pub hidden_act: String,
    /// LayerNorm epsilon.
    pub layer_norm_eps: f64,
}

impl Default for VlmVisionConfig {
    fn default() -> Self {
        VlmVisionConfig {
            hidden_size: 1152,
            intermediate_size: 3072,
            num_hidden_layers: 12,
            num_attention_heads: 16,
            num_channels: 3,
            image_size: 224,
            patch_size: 32,
            hidden_act: "gelu_pytorch_tanh".into(),
            layer_norm_eps: 1e-6,
        }
    }
}

/// The whole SmolVLM config the prefix needs: text model, vision tower and the connector's pixel
/// shuffle factor.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VlmConfig {
    /// The text model (SmolLM2).
    pub text_config: VlmTextConfig,
    /// The vision tower (SigLIP).
    #[serde(default)]
    pub vision_config: VlmVisionConfig,
    /// Pixel-shuffle factor of the connector (transformers' default 2).
    #[serde(default = "default_scale_factor")]
    pub scale_factor: usize,
}

fn default_scale_factor() -> usize {
    2
}

impl VlmConfig {
    /// SmolVLM2-500M-Video-Instruct, from its hub `config.json`.
    pub fn smolvlm2_500m() -> Self {
        VlmConfig {
            text_config: VlmTextConfig::smolvlm2_500m(),
            vision_config: VlmVisionConfig {
                hidden_size: 768,
                intermediate_size: 3072,
                num_hidden_layers: 12,
                num_attention_heads: 12,
                num_channels: 3,
                image_size: 512,
                patch_size: 16,
                hidden_act: "gelu_pytorch_tanh".into(),
                layer_norm_eps: 1e-6,
            },
            scale_factor: 4,
        }
    }

    /// Read a SmolVLM `config.json` (as `SmolVLMConfig.save_pretrained` writes it).
    pub fn from_file(path: &Path) -> Result<Self, EngineError> {
        read_json(path)
    }

    /// The VLM config of a SmolVLA checkpoint directory: its `vlm_config.json` when present,
    /// else the built-in config of LeRobot's default VLM.
    pub fn for_checkpoint(dir: &Path, cfg: &SmolVlaConfig) -> Result<Self, EngineError> {
        let path = dir.join("vlm_config.json");
        if path.exists() {
            Self::from_file(&path)
        } else if cfg.vlm_model_name == SMOLVLM2_500M {
            Ok(Self::smolvlm2_500m())
        } else {
            Err(EngineError::Load {
                path: path.display().to_string(),
                reason: format!(
                    "VLM `{}` has no built-in config; provide its config.json here",
                    cfg.vlm_model_name
                ),
            })
        }
    }
}

/// Whether an expert layer attends to itself and the prefix, or to the prefix only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum LayerKind {
    /// Keys/values: `[VLM prefix K/V of this layer ; the expert's own K/V]`, causal over actions.
    SelfAttention,
    /// Keys/values: the VLM prefix K/V projected by the expert's `k_proj`/`v_proj`.
    CrossAttention,
}

/// Everything that sizes the expert, resolved from both configs.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExpertDims {
    /// VLM hidden size (`state_proj` output).
    pub vlm_hidden: usize,
    /// Expert hidden size.
    pub hidden: usize,
    /// Expert MLP width.
    pub intermediate: usize,
    /// Query heads.
    pub heads: usize,
    /// Key/value heads.
    pub kv_heads: usize,
    /// Head width.
    pub head_dim: usize,
    /// RMSNorm epsilon.
    pub rms_eps: f32,
    /// Kind of each expert layer.
    pub layers: Vec<LayerKind>,
    /// Actions per chunk.
    pub chunk: usize,
    /// Padded action width.
    pub action_pad: usize,
    /// Padded state width.
    pub state_pad: usize,
    /// Real action width returned to the robot.
    pub action_dim: usize,
    /// Real state width.
    pub state_dim: usize,
    /// Euler steps.
    pub steps: usize,
    /// Time-embedding periods.
    pub min_period: f64,
    /// Time-embedding periods.
    pub max_period: f64,
}

impl ExpertDims {
    /// Resolve the expert's shapes the way `SmolVLMWithExpertModel.__init__` does.
    pub fn resolve(cfg: &SmolVlaConfig, text: &VlmTextConfig) -> Result<Self, EngineError> {
        let bad = |m: String| EngineError::Load {
            path: "config.json".into(),
            reason: m,
        };
        if cfg.policy_type != "smolvla" {
            return Err(bad(format!(
                "policy type is `{}`, expected `smolvla`",
                cfg.policy_type
            )));
        }
        let vlm_layers = kept_vlm_layers(cfg, text);
        if cfg.num_expert_layers > 0 && cfg.num_expert_layers as usize != vlm_layers {
            return Err(bad(format!(
                "num_expert_layers = {} differs from num_vlm_layers = {vlm_layers}; only equal layer counts are supported",
                cfg.num_expert_layers
            )));
        }
        let cross = cfg.attention_mode.contains("cross");
        let every = cfg.self_attn_every_n_layers;
        let layers = (0..vlm_layers)
            .map(|i| {
                if !cross || (every > 0 && i as i64 % every == 0) {
                    LayerKind::SelfAttention
                } else {
                    LayerKind::CrossAttention
                }
            })
            .collect();
        let hidden = (text.hidden_size as f64 * cfg.expert_width_multiplier) as usize;
        if !text
            .num_attention_heads
            .is_multiple_of(text.num_key_value_heads.max(1))
            || !text.head_dim.is_multiple_of(2)
            || !hidden.is_multiple_of(2)
        {
            return Err(bad(
                "heads must be a multiple of KV heads; head_dim and hidden even".into(),
            ));
        }
        let feature_dim = |map: &FeatureMap, key: &str, default: usize| {
            map.get(key)
                .and_then(|f| f.shape.first().copied())
                .unwrap_or(default)
        };
        let action_dim = feature_dim(&cfg.output_features, "action", cfg.max_action_dim);
        let state_dim = feature_dim(&cfg.input_features, "observation.state", cfg.max_state_dim);
        if action_dim > cfg.max_action_dim || state_dim > cfg.max_state_dim {
            return Err(bad(
                "action/state feature wider than max_action_dim/max_state_dim".into(),
            ));
        }
        Ok(ExpertDims {
            vlm_hidden: text.hidden_size,
            hidden,
            intermediate: intermediate_size(hidden),
            heads: text.num_attention_heads,
            kv_heads: text.num_key_value_heads,
            head_dim: text.head_dim,
            rms_eps: text.rms_norm_eps as f32,
            layers,
            chunk: cfg.chunk_size,
            action_pad: cfg.max_action_dim,
            state_pad: cfg.max_state_dim,
            action_dim,
            state_dim,
            steps: cfg.num_steps,
            min_period: cfg.min_period,
            max_period: cfg.max_period,
        })
    }

    /// The full-size expert of `lerobot/smolvla_base` (SmolVLM2-500M, 16 layers, hidden 720).
    pub fn smolvla_base() -> Self {
        let mut cfg = SmolVlaConfig::default();
        cfg.output_features.insert(
            "action".into(),
            Feature {
                kind: "ACTION".into(),
                shape: vec![6],
            },
        );
        cfg.input_features.insert(
            "observation.state".into(),
            Feature {
                kind: "STATE".into(),
                shape: vec![6],
            },
        );
        // The default config resolves by construction.
        match Self::resolve(&cfg, &VlmTextConfig::smolvlm2_500m()) {
            Ok(d) => d,
            Err(e) => unreachable!("default SmolVLA config: {e}"),
        }
    }

    /// Width of the VLM's (and the expert's) key/value vectors: `kv_heads * head_dim`.
    pub fn kv_width(&self) -> usize {
        self.kv_heads * self.head_dim
    }

    /// Width of the query vectors: `heads * head_dim`.
    pub fn q_width(&self) -> usize {
        self.heads * self.head_dim
    }
}

/// The text layers LeRobot keeps: `num_vlm_layers`, or (`<= 0`) all of the text model's.
pub fn kept_vlm_layers(cfg: &SmolVlaConfig, text: &VlmTextConfig) -> usize {
    if cfg.num_vlm_layers > 0 {
        cfg.num_vlm_layers
    } else {
        text.num_hidden_layers
    }
}

/// LeRobot's `get_intermediate_size(hidden)` (multiplier 4, multiple of 256).
pub fn intermediate_size(hidden: usize) -> usize {
    let h = (2 * hidden) / 3;
    let h = 4 * h;
    256 * h.div_ceil(256)
}

pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, EngineError> {
    let text = std::fs::read_to_string(path).map_err(|e| EngineError::Load {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    serde_json::from_str(&text).map_err(|e| EngineError::Load {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smolvla_base_shapes() {
        let d = ExpertDims::smolvla_base();
        assert_eq!(
            (d.hidden, d.intermediate, d.heads, d.kv_heads, d.head_dim),
            (720, 2048, 15, 5, 64)
        );
        assert_eq!(d.layers.len(), 16);
        assert_eq!(d.layers[0], LayerKind::SelfAttention);
        assert_eq!(d.layers[1], LayerKind::CrossAttention);
        assert_eq!((d.chunk, d.action_pad, d.steps), (50, 32, 10));
    }

    #[test]
    fn intermediate_matches_lerobot() {
        assert_eq!(intermediate_size(720), 2048);
        assert_eq!(intermediate_size(72), 256);
        assert_eq!(intermediate_size(480), 1280);
    }
}
