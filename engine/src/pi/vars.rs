//! Named access to a π checkpoint's tensors on a Candle device, in the shape of Candle's
//! `VarBuilder` (`vars.pp("layers").pp(i).get(shape, "weight")`) so each model struct's fields
//! follow the checkpoint's keys, with the engine's errors (the missing or mis-shaped key, named).
//!
//! Keys are LeRobot 0.6.1's (`PI0Policy.state_dict()`). As LeRobot's `from_pretrained` does
//! (`_fix_pytorch_state_dict_keys`, then the `model.` prefix), a key is also found without its
//! `model.` prefix (openpi's converted files), π0's `action_time_mlp_*` also as `time_mlp_*`
//! and π0.5's `time_mlp_*` also as `action_time_mlp_*`, and the prefix's token embedding also
//! as PaliGemma's tied `lm_head`.

use candle_core::{Device, Tensor};

use super::config::PiFamily;
use crate::EngineError;
use crate::smolvla::linear::LinearWeights;
use crate::weights::{Checkpoint, StoredTensor};

/// The embedding key and the tied head LeRobot copies into it when the embedding is absent.
const EMBED: &str =
    "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight";
const TIED_HEAD: &str = "model.paligemma_with_expert.paligemma.lm_head.weight";

/// The name under which `key` (a LeRobot key) is stored in `ckpt`, if it is.
pub fn resolve_key(ckpt: &Checkpoint, family: PiFamily, key: &str) -> Option<String> {
    let mut candidates = vec![key.to_owned()];
    let bare = key.strip_prefix("model.");
    if let Some(bare) = bare {
        candidates.push(bare.to_owned());
        let renamed = match family {
            PiFamily::Pi0 => bare
                .strip_prefix("action_time_mlp_")
                .map(|r| format!("time_mlp_{r}")),
            PiFamily::Pi05 => bare
                .strip_prefix("time_mlp_")
                .map(|r| format!("action_time_mlp_{r}")),
        };
        if let Some(r) = renamed {
            candidates.push(format!("model.{r}"));
            candidates.push(r);
        }
    }
    if key == EMBED {
        candidates.push(TIED_HEAD.to_owned());
        candidates.push(TIED_HEAD.trim_start_matches("model.").to_owned());
    }
    candidates.into_iter().find(|k| ckpt.contains(k))
}

/// A position in the checkpoint's key tree, on one device.
#[derive(Clone)]
pub struct Vars<'a> {
    ckpt: &'a Checkpoint,
    family: PiFamily,
    device: Device,
    prefix: String,
}

impl<'a> Vars<'a> {
    /// The root of `ckpt`'s keys.
    pub fn new(ckpt: &'a Checkpoint, family: PiFamily, device: &Device) -> Self {
        Vars {
            ckpt,
            family,
            device: device.clone(),
            prefix: String::new(),
        }
    }

    /// The child `name` (`a.b` joins with a dot).
    pub fn pp(&self, name: impl std::fmt::Display) -> Self {
        let prefix = if self.prefix.is_empty() {
            name.to_string()
        } else {
            format!("{}.{name}", self.prefix)
        };
        Vars {
            prefix,
            ..self.clone()
        }
    }

    /// The full key of `name` here.
    pub fn key(&self, name: &str) -> String {
        if self.prefix.is_empty() {
            name.to_owned()
        } else {
            format!("{}.{name}", self.prefix)
        }
    }

    /// Whether `name` is stored here (under any of its accepted names).
    pub fn contains(&self, name: &str) -> bool {
        resolve_key(self.ckpt, self.family, &self.key(name)).is_some()
    }

    /// The device tensors go to.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// `name` as f32 on the device, checked to have `shape`. Errors name LeRobot's key.
    pub fn get(&self, shape: &[usize], name: &str) -> Result<Tensor, EngineError> {
        Ok(Tensor::from_vec(
            self.values(shape, name)?,
            shape,
            &self.device,
        )?)
    }

    /// `name` as f32 values on the host, checked to have `shape`.
    pub fn values(&self, shape: &[usize], name: &str) -> Result<Vec<f32>, EngineError> {
        let key = self.key(name);
        let stored = resolve_key(self.ckpt, self.family, &key)
            .ok_or_else(|| EngineError::MissingTensor { key: key.clone() })?;
        self.ckpt.tensor(&stored, shape)
    }

    /// `name` as the checkpoint stores it (bf16 bits stay bf16), checked to have `shape`.
    pub fn stored(&self, shape: &[usize], name: &str) -> Result<StoredTensor, EngineError> {
        let key = self.key(name);
        let stored = resolve_key(self.ckpt, self.family, &key)
            .ok_or_else(|| EngineError::MissingTensor { key: key.clone() })?;
        self.ckpt.tensor_stored(&stored, shape)
    }

    /// The `nn.Linear` here for the fast kernels: `weight` `[out][in]` as stored and, with
    /// `bias`, `bias` `[out]` widened to f32.
    pub fn linear_weights(
        &self,
        out: usize,
        inp: usize,
        bias: bool,
    ) -> Result<LinearWeights<StoredTensor>, EngineError> {
        Ok(LinearWeights {
            weight: self.stored(&[out, inp], "weight")?,
            bias: bias.then(|| self.values(&[out], "bias")).transpose()?,
            out_dim: out,
            in_dim: inp,
        })
    }
}
