//! A LeRobot π0 / π0.5 checkpoint directory and the processors around the model, as LeRobot
//! 0.6.1's `make_pi0_pre_post_processors` / `make_pi05_pre_post_processors` and the policies'
//! `_preprocess_images` run them:
//!
//! ```text
//! my_pi05/
//!   config.json                 PI05Config (type "pi05") or PI0Config (type "pi0")
//!   model.safetensors           the weights (read by the model)
//!   policy_preprocessor.json    rename, batch, relative actions, normalizer, state prompt
//!                               (π0.5) or newline (π0), tokenizer, device
//!   policy_postprocessor.json   unnormalizer, absolute actions, device
//!   policy_*_step_<i>_*.safetensors   the stats the normalisers name
//!   tokenizer.json              optional: PaliGemma's tokenizer, if not given explicitly
//! ```
//!
//! The pipeline files, stats, tokenizer and normalisation are the SmolVLA checkpoint's
//! ([`crate::smolvla::processors`], [`crate::smolvla::tokenize`]); what differs is here:
//! - images are resized with **centred** zero padding and clamped to `[0, 1]`
//!   (`resize_with_pad_torch`), and not resized at all when already at `image_resolution`;
//! - every missing camera (the `empty_camera_<i>` features included) becomes an all `-1`
//!   image with a false mask, after the present ones;
//! - π0.5's prompt carries the normalised state in 256 bins ([`state_prompt`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::config::{PiConfig, PiFamily};
use crate::image_features::ImageLimits;
use crate::smolvla::checkpoint::{
    ACTION_KEY, IMAGE_PREFIX, Observation, STATE_KEY, camera_aliases, resolve_camera,
    tokenizer_path,
};
use crate::smolvla::config::read_json;
use crate::smolvla::images::{PreparedImage, empty_camera, interpolate_bilinear, to_chw_unit};
use crate::smolvla::processors::{Postprocessor, Preprocessor};
use crate::smolvla::tokenize::{TaskTokenizer, TaskTokens};
use crate::{EngineError, ImageInput};

/// An observation after the preprocessor and `_preprocess_images`: what the prefix reads.
#[derive(Clone, Debug, PartialEq)]
pub struct PiPrepared {
    /// One slot per camera key, present cameras first in config order, then the missing ones.
    pub images: Vec<PreparedImage>,
    /// Task (π0.5: prompt) tokens and mask.
    pub tokens: TaskTokens,
    /// The normalised state (π0's state token reads it).
    pub state: Vec<f32>,
    /// The raw state (relative actions add it back).
    pub raw_state: Vec<f32>,
}

/// π0.5's prompt (`Pi05PrepareStateTokenizerProcessorStep`): the task cleaned as Python's
/// `task.strip().replace("_", " ").replace("\n", " ")`, and each normalised state value as its
/// bin `np.digitize(x, np.linspace(-1, 1, 257)[:-1]) - 1` (from -1 below -1 to 255 at 1 and
/// above): `"Task: {task}, State: {b0 b1 ..};\nAction: "`.
pub fn state_prompt(task: &str, normalized_state: &[f32]) -> String {
    let cleaned = task.trim_matches(is_python_space).replace(['_', '\n'], " ");
    let bins: Vec<String> = normalized_state
        .iter()
        .map(|&x| state_bin(x).to_string())
        .collect();
    format!("Task: {cleaned}, State: {};\nAction: ", bins.join(" "))
}

/// The bin of one normalised value: how many of the 256 edges `-1 + k/128` (exact in f64,
/// as numpy's `linspace` makes them) are `<= x`, minus one.
fn state_bin(x: f32) -> i32 {
    let x = f64::from(x);
    let below = (0..256)
        .filter(|&k| -1.0 + f64::from(k) / 128.0 <= x)
        .count();
    below as i32 - 1
}

/// Python's `str.isspace` (what `strip()` removes): Unicode whitespace plus the four ASCII
/// separators `\x1c..\x1f`, which Rust's `char::is_whitespace` leaves out.
fn is_python_space(c: char) -> bool {
    c.is_whitespace() || ('\u{1c}'..='\u{1f}').contains(&c)
}

/// LeRobot's `resize_with_pad_torch` for one `[3][h][w]` image in `[0, 1]`: bilinear resize
/// keeping the aspect ratio (ratio `max(w / W, h / H)`, sizes truncated), clamp to `[0, 1]`,
/// then zero padding split evenly, the odd pixel at the bottom / right.
pub fn resize_with_centered_pad(chw: &[f32], h: usize, w: usize, out: usize) -> Vec<f32> {
    let ratio = f64::max(w as f64 / out as f64, h as f64 / out as f64);
    let rh = ((h as f64 / ratio) as usize).clamp(1, out);
    let rw = ((w as f64 / ratio) as usize).clamp(1, out);
    let resized = interpolate_bilinear(chw, 3, h, w, rh, rw);
    let (top, left) = ((out - rh) / 2, (out - rw) / 2);
    let mut padded = vec![0.0f32; 3 * out * out];
    for ch in 0..3 {
        for y in 0..rh {
            let src = &resized[(ch * rh + y) * rw..(ch * rh + y + 1) * rw];
            let at = (ch * out + top + y) * out + left;
            for (d, &v) in padded[at..at + rw].iter_mut().zip(src) {
                *d = v.clamp(0.0, 1.0);
            }
        }
    }
    padded
}

/// A π checkpoint's config and processors, loaded once.
#[derive(Debug)]
pub struct PiCheckpoint {
    dir: PathBuf,
    family: PiFamily,
    config: PiConfig,
    pre: Preprocessor,
    post: Postprocessor,
    tokenizer: TaskTokenizer,
    limits: ImageLimits,
}

impl PiCheckpoint {
    /// Load `config.json`, both processor files and their stats, and the tokenizer
    /// (`tokenizer`, or `tokenizer.json` in `dir`).
    pub fn open(dir: &Path, tokenizer: Option<&Path>) -> Result<Self, EngineError> {
        let config_path = dir.join("config.json");
        if !config_path.exists() {
            return Err(EngineError::MissingFile {
                path: config_path.display().to_string(),
            });
        }
        let config: PiConfig = read_json(&config_path)?;
        let family = PiFamily::from_type(&config.policy_type).ok_or_else(|| EngineError::Load {
            path: config_path.display().to_string(),
            reason: format!(
                "policy type is `{}`, expected `pi0` or `pi05`",
                config.policy_type
            ),
        })?;
        let pre_path = dir.join("policy_preprocessor.json");
        let pre = Preprocessor::load(&pre_path)?;
        let post = Postprocessor::load(&dir.join("policy_postprocessor.json"))?;
        let step = pre.tokenizer.clone().ok_or_else(|| EngineError::Load {
            path: pre_path.display().to_string(),
            reason: "no `tokenizer_processor` step".into(),
        })?;
        if pre.state_prompt && family != PiFamily::Pi05 {
            return Err(EngineError::Load {
                path: pre_path.display().to_string(),
                reason: "π0.5's state prompt step in a π0 pipeline".into(),
            });
        }
        let tokenizer = TaskTokenizer::load(&tokenizer_path(dir, tokenizer)?, step)?;
        if config.image_keys().is_empty() {
            return Err(EngineError::Load {
                path: config_path.display().to_string(),
                reason: "input_features has no VISUAL feature (a camera)".into(),
            });
        }
        if config.input_features.get(STATE_KEY).is_none() {
            return Err(EngineError::Load {
                path: config_path.display().to_string(),
                reason: format!("input_features has no `{STATE_KEY}`"),
            });
        }
        Ok(PiCheckpoint {
            dir: dir.to_path_buf(),
            family,
            config,
            pre,
            post,
            tokenizer,
            limits: ImageLimits::default(),
        })
    }

    /// The checkpoint directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// π0 or π0.5.
    pub fn family(&self) -> PiFamily {
        self.family
    }

    /// The policy config.
    pub fn config(&self) -> &PiConfig {
        &self.config
    }

    /// The postprocessor.
    pub fn postprocessor(&self) -> &Postprocessor {
        &self.post
    }

    /// The real state width.
    pub fn state_dim(&self) -> usize {
        self.config
            .input_features
            .get(STATE_KEY)
            .and_then(|f| f.shape.first().copied())
            .unwrap_or(0)
    }

    /// The real action width.
    pub fn action_dim(&self) -> usize {
        self.config
            .output_features
            .get(ACTION_KEY)
            .and_then(|f| f.shape.first().copied())
            .unwrap_or(self.config.max_action_dim)
    }

    /// The cameras a robot sends, in order (without LeRobot's `empty_camera_<i>` placeholders).
    pub fn camera_keys(&self) -> Vec<String> {
        let placeholders: Vec<String> = (0..self.config.empty_cameras)
            .map(|i| format!("{IMAGE_PREFIX}empty_camera_{i}"))
            .collect();
        self.config
            .image_keys()
            .into_iter()
            .filter(|k| !placeholders.contains(k))
            .collect()
    }

    /// Other names a robot may give a camera -> its key.
    pub fn camera_aliases(&self) -> BTreeMap<String, String> {
        camera_aliases(&self.config.image_keys(), &self.camera_keys(), &self.pre)
    }

    /// The synthetic observation of `kairos predict` with no inputs: a mid-grey image for every
    /// camera at its configured shape, a zero state, the task "pick up the cube".
    pub fn synthetic_observation(&self) -> Observation {
        let side = self.config.image_resolution[0];
        let images = self
            .camera_keys()
            .into_iter()
            .map(|key| {
                let (h, w) = match self
                    .config
                    .input_features
                    .get(&key)
                    .map(|f| f.shape.as_slice())
                {
                    Some([_, h, w]) if *h > 0 && *w > 0 => (*h, *w),
                    _ => (side, side),
                };
                let image = ImageInput::RawF32 {
                    height: h,
                    width: w,
                    channels: 3,
                    data: vec![0.5; h * w * 3],
                };
                (key, image)
            })
            .collect();
        Observation {
            images,
            state: vec![0.0; self.state_dim()],
            task: "pick up the cube".into(),
        }
    }

    /// The preprocessor and `_preprocess_images` for one observation.
    pub fn prepare(&self, obs: &Observation) -> Result<PiPrepared, EngineError> {
        let keys = self.config.image_keys();
        let mut present: BTreeMap<String, &ImageInput> = BTreeMap::new();
        for (name, image) in &obs.images {
            let key = resolve_camera(&keys, &self.pre, name)?;
            if present.insert(key.clone(), image).is_some() {
                return Err(EngineError::InvalidInput(format!(
                    "camera `{key}` given twice"
                )));
            }
        }
        if present.is_empty() {
            return Err(EngineError::InvalidInput(format!(
                "no camera image; the model reads {}",
                self.camera_keys().join(", ")
            )));
        }
        let state_dim = self.state_dim();
        if obs.state.len() != state_dim {
            return Err(EngineError::StateLength {
                field: STATE_KEY.into(),
                expected: state_dim,
                found: obs.state.len(),
            });
        }
        if let Some(i) = obs.state.iter().position(|v| !v.is_finite()) {
            return Err(EngineError::InvalidInput(format!(
                "{STATE_KEY}[{i}] is not finite"
            )));
        }
        let normalizer = self.pre.normalizer.as_ref();
        let mut state = obs.state.clone();
        if let Some(n) = normalizer {
            n.normalize(STATE_KEY, &mut state)?;
        }
        let text = if self.pre.state_prompt {
            state_prompt(&obs.task, &state)
        } else {
            self.pre.task_text(&obs.task)
        };
        let tokens = self.tokenizer.encode(&text)?;

        let side = self.config.image_resolution[0];
        let mut images = Vec::with_capacity(keys.len());
        for key in &keys {
            let Some(image) = present.get(key) else {
                continue;
            };
            let (mut chw, h, w) = to_chw_unit(image, &self.limits, key)?;
            if let Some(n) = normalizer {
                n.normalize(key, &mut chw)?;
            }
            let mut pixels = if (h, w) == (side, side) {
                chw
            } else {
                resize_with_centered_pad(&chw, h, w, side)
            };
            for v in &mut pixels {
                *v = *v * 2.0 - 1.0;
            }
            images.push(PreparedImage {
                pixels,
                height: side,
                width: side,
                present: true,
            });
        }
        let missing = keys.len() - images.len();
        let blank = empty_camera(&images[0]);
        images.extend(std::iter::repeat_n(blank, missing));
        Ok(PiPrepared {
            images,
            tokens,
            state,
            raw_state: obs.state.clone(),
        })
    }

    /// The output side for one chunk: `actions` `[chunk][width]` (`width` the padded
    /// `max_action_dim` or the action dim) cut to the action dim, unnormalised, and, with
    /// relative actions, the raw state added back. Returns `[chunk][action_dim]`.
    pub fn finish_actions(
        &self,
        actions: &[f32],
        width: usize,
        raw_state: &[f32],
    ) -> Result<Vec<Vec<f32>>, EngineError> {
        let dim = self.action_dim();
        if width < dim || width == 0 || !actions.len().is_multiple_of(width) {
            return Err(EngineError::InvalidInput(format!(
                "actions of {} values are not rows of {width} >= action dim {dim}",
                actions.len()
            )));
        }
        let mut cut: Vec<f32> = actions
            .chunks_exact(width)
            .flat_map(|row| row[..dim].iter().copied())
            .collect();
        if let Some(n) = &self.post.unnormalizer {
            n.unnormalize(ACTION_KEY, &mut cut)?;
        }
        if let Some(offset) = self.absolute_offset(raw_state)? {
            for row in cut.chunks_exact_mut(dim) {
                for (a, o) in row.iter_mut().zip(&offset) {
                    *a += o;
                }
            }
        }
        Ok(cut.chunks_exact(dim).map(<[f32]>::to_vec).collect())
    }

    /// What `absolute_actions_processor` adds to every action: the raw state on the masked
    /// dims (`to_absolute_actions`), or `None` when actions are absolute.
    pub fn absolute_offset(&self, raw_state: &[f32]) -> Result<Option<Vec<f32>>, EngineError> {
        let relative = self.pre.relative_actions.as_ref().filter(|r| r.enabled);
        let (Some(relative), true) = (relative, self.post.absolute_actions) else {
            return Ok(None);
        };
        let dim = self.action_dim();
        if raw_state.len() < dim {
            return Err(EngineError::InvalidInput(format!(
                "relative actions need a state at least as wide as the action ({} < {dim})",
                raw_state.len()
            )));
        }
        let mask = relative.mask(dim);
        Ok(Some(
            mask.iter()
                .zip(raw_state)
                .map(|(&m, &s)| if m { s } else { 0.0 })
                .collect(),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_bins_follow_numpy_digitize() {
        assert_eq!(state_bin(-1.0), 0);
        assert_eq!(state_bin(-1.0001), -1);
        assert_eq!(state_bin(1.0), 255);
        assert_eq!(state_bin(7.5), 255);
        assert_eq!(state_bin(0.0), 128);
        // An edge belongs to the bin it opens; just below it, the one before.
        assert_eq!(state_bin(-1.0 + 1.0 / 128.0), 1);
        assert_eq!(
            state_bin(f32::from_bits((-1.0f32 + 1.0 / 128.0).to_bits() + 1)),
            0
        );
    }

    #[test]
    fn prompts_are_lerobots() {
        assert_eq!(
            state_prompt("  pick_up the\ncube\u{1f}", &[0.0, -2.0, 1.0]),
            "Task: pick up the cube, State: 128 -1 255;\nAction: "
        );
    }

    #[test]
    fn centered_padding_splits_evenly() {
        // 2 x 4 -> 4 x 4: rows 1..3 hold the (unchanged-width) image, rows 0 and 3 are zero.
        let chw: Vec<f32> = (0..24).map(|i| (i % 8) as f32 / 8.0).collect();
        let out = resize_with_centered_pad(&chw, 2, 4, 4);
        assert_eq!(&out[0..4], &[0.0; 4]);
        assert_eq!(&out[4..8], &chw[0..4]);
        assert_eq!(&out[12..16], &[0.0; 4]);
    }
}
