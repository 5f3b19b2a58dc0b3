//! π0 / π0.5 configuration: LeRobot's `config.json` and the model's sizes.
//!
//! LeRobot 0.6.1 does not write the architecture into `config.json`: `paligemma_variant` and
//! `action_expert_variant` name openpi's Gemma variants (`gemma_2b`, `gemma_300m`), whose sizes
//! are hard-coded in `get_gemma_config`, and SigLIP so400m/14 is hard-coded in
//! `PaliGemmaWithExpertModel`. [`PiDims::from_checkpoint`] therefore reads every size from the
//! tensors' shapes and takes only what shapes cannot tell from LeRobot's constants (16 SigLIP
//! heads, one KV head per Gemma layer, the norms' epsilons, RoPE's base), so a checkpoint whose
//! tensors disagree with each other is an error naming the tensor, and one at any width loads.

use std::collections::BTreeMap;

use super::vars::resolve_key;
use crate::EngineError;
use crate::smolvla::config::FeatureMap;
use crate::weights::Checkpoint;

/// Which of the two policies a checkpoint is, from `config.json`'s `type`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum PiFamily {
    /// `pi0`: a continuous state token in the suffix; action and time fused by an MLP.
    Pi0,
    /// `pi05`: the state discretised into the prompt; the time conditions every expert norm.
    Pi05,
}

impl PiFamily {
    /// The family a LeRobot policy `type` names; `None` for any other type.
    pub fn from_type(policy_type: &str) -> Option<Self> {
        match policy_type {
            "pi0" => Some(PiFamily::Pi0),
            "pi05" => Some(PiFamily::Pi05),
            _ => None,
        }
    }

    /// LeRobot's `type` for this family.
    pub fn policy_type(self) -> &'static str {
        match self {
            PiFamily::Pi0 => "pi0",
            PiFamily::Pi05 => "pi05",
        }
    }
}

/// The fields of LeRobot's `PI0Config` / `PI05Config` (`config.json`) that inference reads.
/// Unknown fields are ignored; defaults are LeRobot 0.6.1's `PI0Config`'s.
#[derive(Clone, Debug, PartialEq, serde::Deserialize)]
#[serde(default)]
pub struct PiConfig {
    /// Policy type: `pi0` or `pi05`.
    #[serde(rename = "type")]
    pub policy_type: String,
    /// The prefix's Gemma variant (informational: sizes come from the tensors).
    pub paligemma_variant: String,
    /// The action expert's Gemma variant (informational).
    pub action_expert_variant: String,
    /// The dtype LeRobot computes in (`float32` or `bfloat16`); Kairos computes in f32.
    pub dtype: String,
    /// Actions per chunk.
    pub chunk_size: usize,
    /// Padded state width (`state_proj` input, π0).
    pub max_state_dim: usize,
    /// Padded action width (noise, `action_in_proj` input, `action_out_proj` output).
    pub max_action_dim: usize,
    /// Euler steps.
    pub num_inference_steps: usize,
    /// Smallest period of the sinusoidal time embedding.
    pub min_period: f64,
    /// Largest period of the sinusoidal time embedding.
    pub max_period: f64,
    /// `(height, width)` every camera is resized (with centred padding) to; square.
    pub image_resolution: [usize; 2],
    /// Always-missing cameras LeRobot adds as `observation.images.empty_camera_<i>`.
    pub empty_cameras: usize,
    /// The tokenizer's maximum length (the preprocessor's tokenizer step has its own copy).
    pub tokenizer_max_length: usize,
    /// Input features in file order: the `VISUAL` ones give the camera order of the prefix.
    pub input_features: FeatureMap,
    /// Output features (`action` gives the real action width).
    pub output_features: FeatureMap,
    /// Normalisation mode per feature type (the processors' files carry the map applied).
    pub normalization_mapping: BTreeMap<String, String>,
    /// Whether actions are relative to the state (the processors' own steps say so too).
    pub use_relative_actions: bool,
    /// Real-time chunking settings, if any (not applied by this engine).
    pub rtc_config: Option<serde_json::Value>,
}

impl Default for PiConfig {
    fn default() -> Self {
        PiConfig {
            policy_type: "pi0".into(),
            paligemma_variant: "gemma_2b".into(),
            action_expert_variant: "gemma_300m".into(),
            dtype: "float32".into(),
            chunk_size: 50,
            max_state_dim: 32,
            max_action_dim: 32,
            num_inference_steps: 10,
            min_period: 4e-3,
            max_period: 4.0,
            image_resolution: [224, 224],
            empty_cameras: 0,
            tokenizer_max_length: 48,
            input_features: FeatureMap::default(),
            output_features: FeatureMap::default(),
            normalization_mapping: BTreeMap::new(),
            use_relative_actions: false,
            rtc_config: None,
        }
    }
}

impl PiConfig {
    /// The camera keys (`VISUAL` input features, `empty_camera_<i>` included) in LeRobot's
    /// order.
    pub fn image_keys(&self) -> Vec<String> {
        self.input_features
            .iter()
            .filter(|(_, f)| f.kind == "VISUAL")
            .map(|(k, _)| k.clone())
            .collect()
    }
}

/// SigLIP's heads in PaliGemma (so400m/14); the shapes cannot tell them.
pub const SIGLIP_HEADS: usize = 16;
/// SigLIP's LayerNorm epsilon in PaliGemma's vision config.
pub const SIGLIP_EPS: f64 = 1e-6;
/// Gemma's RMSNorm epsilon (`GemmaConfig.rms_norm_eps`, which LeRobot does not change).
pub const GEMMA_EPS: f64 = 1e-6;
/// Gemma's RoPE base (`rope_theta`).
pub const GEMMA_ROPE_THETA: f64 = 10_000.0;
/// Key/value heads of every Gemma variant openpi and LeRobot define.
pub const GEMMA_KV_HEADS: usize = 1;

/// The SigLIP tower's sizes.
#[derive(Clone, Debug, PartialEq)]
pub struct SiglipDims {
    /// Width (1152 for so400m).
    pub hidden: usize,
    /// Encoder layers (27).
    pub layers: usize,
    /// Attention heads (16).
    pub heads: usize,
    /// MLP width (4304).
    pub intermediate: usize,
    /// Patch side in pixels (14).
    pub patch: usize,
    /// Image side in pixels (224).
    pub image_size: usize,
    /// LayerNorm epsilon.
    pub eps: f64,
}

impl SiglipDims {
    /// Patches (= tokens) per camera.
    pub fn patches(&self) -> usize {
        (self.image_size / self.patch).pow(2)
    }
}

/// One Gemma stack's sizes (the prefix's or the expert's).
#[derive(Clone, Debug, PartialEq)]
pub struct GemmaDims {
    /// Width.
    pub width: usize,
    /// Decoder layers.
    pub depth: usize,
    /// GeGLU width.
    pub mlp: usize,
    /// Query heads.
    pub heads: usize,
    /// Key/value heads (1).
    pub kv_heads: usize,
    /// Head dimension.
    pub head_dim: usize,
    /// RMSNorm epsilon.
    pub eps: f64,
    /// RoPE base.
    pub rope_theta: f64,
}

impl GemmaDims {
    /// openpi's `gemma_2b` (the PaliGemma prefix).
    pub fn gemma_2b() -> Self {
        Self::variant(2048, 16_384)
    }

    /// openpi's `gemma_300m` (the action expert).
    pub fn gemma_300m() -> Self {
        Self::variant(1024, 4096)
    }

    fn variant(width: usize, mlp: usize) -> Self {
        GemmaDims {
            width,
            depth: 18,
            mlp,
            heads: 8,
            kv_heads: GEMMA_KV_HEADS,
            head_dim: 256,
            eps: GEMMA_EPS,
            rope_theta: GEMMA_ROPE_THETA,
        }
    }

    /// `heads * head_dim`: the width of the queries and of the attention output.
    pub fn q_width(&self) -> usize {
        self.heads * self.head_dim
    }

    /// `kv_heads * head_dim`: the width of the keys and of the values.
    pub fn kv_width(&self) -> usize {
        self.kv_heads * self.head_dim
    }
}

/// Everything the model's shapes depend on.
#[derive(Clone, Debug, PartialEq)]
pub struct PiDims {
    /// π0 or π0.5.
    pub family: PiFamily,
    /// The vision tower.
    pub vision: SiglipDims,
    /// The PaliGemma prefix.
    pub vlm: GemmaDims,
    /// Rows of the token embedding table.
    pub vocab: usize,
    /// The action expert.
    pub expert: GemmaDims,
    /// Actions per chunk.
    pub chunk: usize,
    /// Euler steps.
    pub steps: usize,
    /// Padded action width.
    pub action_pad: usize,
    /// Padded state width (π0's `state_proj` input).
    pub state_pad: usize,
    /// Time embedding periods.
    pub min_period: f64,
    /// See `min_period`.
    pub max_period: f64,
}

/// LeRobot's names of the model's parts (`PI0Policy.state_dict()`).
pub mod keys {
    /// The SigLIP tower.
    pub const VISION: &str =
        "model.paligemma_with_expert.paligemma.model.vision_tower.vision_model";
    /// PaliGemma's projector.
    pub const PROJECTOR: &str =
        "model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear";
    /// The prefix's Gemma.
    pub const VLM: &str = "model.paligemma_with_expert.paligemma.model.language_model";
    /// The action expert's Gemma.
    pub const EXPERT: &str = "model.paligemma_with_expert.gemma_expert.model";
}

/// A checkpoint read under LeRobot's key names (see [`resolve_key`]).
struct Shapes<'a> {
    ckpt: &'a Checkpoint,
    family: PiFamily,
}

impl Shapes<'_> {
    /// Layers `0..n` of a stack whose layer `i` has `{prefix}.layers.{i}.{probe}`.
    fn count_layers(&self, prefix: &str, probe: &str) -> usize {
        (0..)
            .take_while(|i| {
                resolve_key(
                    self.ckpt,
                    self.family,
                    &format!("{prefix}.layers.{i}.{probe}"),
                )
                .is_some()
            })
            .count()
    }

    fn of(&self, key: &str, rank: usize) -> Result<Vec<usize>, EngineError> {
        shape_of(self.ckpt, self.family, key, rank)
    }
}

fn shape_of(
    ckpt: &Checkpoint,
    family: PiFamily,
    key: &str,
    rank: usize,
) -> Result<Vec<usize>, EngineError> {
    let shape = resolve_key(ckpt, family, key)
        .and_then(|stored| ckpt.shape(&stored))
        .ok_or_else(|| EngineError::MissingTensor {
            key: key.to_owned(),
        })?;
    if shape.len() != rank || shape.contains(&0) {
        return Err(EngineError::Load {
            path: ckpt.path().to_owned(),
            reason: format!("tensor `{key}` has shape {shape:?}, expected {rank} non-zero dims"),
        });
    }
    Ok(shape.to_vec())
}

fn gemma_dims(shapes: &Shapes<'_>, prefix: &str) -> Result<GemmaDims, EngineError> {
    let ckpt = shapes.ckpt;
    let layer = format!("{prefix}.layers.0");
    let q = shapes.of(&format!("{layer}.self_attn.q_proj.weight"), 2)?;
    let k = shapes.of(&format!("{layer}.self_attn.k_proj.weight"), 2)?;
    let gate = shapes.of(&format!("{layer}.mlp.gate_proj.weight"), 2)?;
    let head_dim = k[0] / GEMMA_KV_HEADS;
    if !q[0].is_multiple_of(head_dim) {
        return Err(EngineError::Load {
            path: ckpt.path().to_owned(),
            reason: format!(
                "`{layer}.self_attn.q_proj.weight` has {} rows, not a multiple of the head \
                 dimension {head_dim} (k_proj's rows, one KV head)",
                q[0]
            ),
        });
    }
    Ok(GemmaDims {
        width: q[1],
        depth: shapes.count_layers(prefix, "self_attn.q_proj.weight"),
        mlp: gate[0],
        heads: q[0] / head_dim,
        kv_heads: GEMMA_KV_HEADS,
        head_dim,
        eps: GEMMA_EPS,
        rope_theta: GEMMA_ROPE_THETA,
    })
}

impl PiDims {
    /// Read the sizes from the checkpoint's tensors (see the module docs) and check that the
    /// two stacks fit each other as LeRobot's attention needs (same depth, same head dim).
    pub fn from_checkpoint(
        cfg: &PiConfig,
        family: PiFamily,
        ckpt: &Checkpoint,
    ) -> Result<Self, EngineError> {
        let bad = |reason: String| EngineError::Load {
            path: ckpt.path().to_owned(),
            reason,
        };
        let shapes = Shapes { ckpt, family };
        let v = keys::VISION;
        let conv = shapes.of(&format!("{v}.embeddings.patch_embedding.weight"), 4)?;
        let fc1 = shapes.of(&format!("{v}.encoder.layers.0.mlp.fc1.weight"), 2)?;
        let [image_h, image_w] = cfg.image_resolution;
        if image_h != image_w {
            return Err(bad(format!(
                "image_resolution {:?} is not square (PaliGemma needs square images)",
                cfg.image_resolution
            )));
        }
        let vision = SiglipDims {
            hidden: conv[0],
            layers: shapes.count_layers(&format!("{v}.encoder"), "self_attn.q_proj.weight"),
            heads: SIGLIP_HEADS,
            intermediate: fc1[0],
            patch: conv[2],
            image_size: image_h,
            eps: SIGLIP_EPS,
        };
        if conv[1] != 3 || conv[2] != conv[3] {
            return Err(bad(format!(
                "patch_embedding.weight has shape {conv:?}, expected [hidden, 3, p, p]"
            )));
        }
        if !vision.hidden.is_multiple_of(vision.heads) {
            return Err(bad(format!(
                "the vision width {} is not a multiple of SigLIP's {} heads",
                vision.hidden, vision.heads
            )));
        }
        if !image_h.is_multiple_of(vision.patch) {
            return Err(bad(format!(
                "image_resolution {image_h} is not a multiple of the patch size {}",
                vision.patch
            )));
        }
        let vlm = gemma_dims(&shapes, keys::VLM)?;
        let expert = gemma_dims(&shapes, keys::EXPERT)?;
        let embed = shapes.of(&format!("{}.embed_tokens.weight", keys::VLM), 2)?;
        if vlm.depth == 0 || expert.depth != vlm.depth {
            return Err(bad(format!(
                "the prefix has {} layers and the expert {}; LeRobot's expert reads the prefix's \
                 keys and values layer by layer, so they must be equal and non-zero",
                vlm.depth, expert.depth
            )));
        }
        if expert.head_dim != vlm.head_dim {
            return Err(bad(format!(
                "head dimension {} (prefix) != {} (expert)",
                vlm.head_dim, expert.head_dim
            )));
        }
        if !vlm.head_dim.is_multiple_of(2) {
            return Err(bad(format!(
                "head dimension {} is odd (RoPE)",
                vlm.head_dim
            )));
        }
        if !expert.width.is_multiple_of(2) {
            return Err(bad(format!(
                "expert width {} is odd (the time embedding is sin ; cos)",
                expert.width
            )));
        }
        if cfg.chunk_size == 0 || cfg.num_inference_steps == 0 || cfg.max_action_dim == 0 {
            return Err(bad(
                "chunk_size, num_inference_steps and max_action_dim must be positive".into(),
            ));
        }
        Ok(PiDims {
            family,
            vision,
            vocab: embed[0],
            vlm,
            expert,
            chunk: cfg.chunk_size,
            steps: cfg.num_inference_steps,
            action_pad: cfg.max_action_dim,
            state_pad: cfg.max_state_dim,
            min_period: cfg.min_period,
            max_period: cfg.max_period,
        })
    }

    /// Request `i`'s state as the expert takes it: π0's padded to `state_pad` (it needs one,
    /// of at most that many values), none for π0.5 (its state is in the prompt).
    pub fn expert_state(
        &self,
        i: usize,
        state: Option<&[f32]>,
    ) -> Result<Option<Vec<f32>>, EngineError> {
        match (self.family, state) {
            (PiFamily::Pi0, Some(s)) if s.len() <= self.state_pad => {
                let mut padded = s.to_vec();
                padded.resize(self.state_pad, 0.0);
                Ok(Some(padded))
            }
            (PiFamily::Pi0, Some(s)) => Err(EngineError::InvalidInput(format!(
                "request {i}: state has {} values, at most {}",
                s.len(),
                self.state_pad
            ))),
            (PiFamily::Pi0, None) => Err(EngineError::InvalidInput(format!(
                "request {i}: π0 needs the state"
            ))),
            (PiFamily::Pi05, _) => Ok(None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn variants_are_openpis() {
        let g = GemmaDims::gemma_2b();
        assert_eq!(
            (g.width, g.depth, g.mlp, g.q_width(), g.kv_width()),
            (2048, 18, 16_384, 2048, 256)
        );
        let e = GemmaDims::gemma_300m();
        assert_eq!((e.width, e.mlp, e.heads, e.head_dim), (1024, 4096, 8, 256));
    }

    #[test]
    fn the_family_is_the_type() {
        assert_eq!(PiFamily::from_type("pi0"), Some(PiFamily::Pi0));
        assert_eq!(PiFamily::from_type("pi05"), Some(PiFamily::Pi05));
        assert_eq!(PiFamily::from_type("pi0_fast"), None);
        assert_eq!(PiFamily::Pi05.policy_type(), "pi05");
    }
}
