//! A LeRobot SmolVLA checkpoint directory (what `save_pretrained` writes) and the processors
//! around the model: observation in, [`PreparedObservation`] for the VLM; normalised actions in,
//! robot actions out.
//!
//! ```text
//! my_smolvla/
//!   config.json                   SmolVLAConfig
//!   model.safetensors             the weights (read by the model, not here)
//!   policy_preprocessor.json      rename, batch, newline, tokenizer, device, normalizer
//!   policy_postprocessor.json     unnormalizer, device
//!   policy_*_step_<i>_*.safetensors   the stats the normalisers name in `state_file`
//!   tokenizer.json                optional: the task tokenizer, if not given explicitly
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::config::{SmolVlaConfig, read_json};
use super::images::{PreparedImage, empty_camera, prepare_unit_image, to_chw_unit};
use super::processors::{Postprocessor, Preprocessor};
use super::tokenize::{TaskTokenizer, TaskTokens};
use crate::image_features::ImageLimits;
use crate::{EngineError, ImageInput};

/// LeRobot's state key.
pub const STATE_KEY: &str = "observation.state";
/// LeRobot's action key.
pub const ACTION_KEY: &str = "action";
/// Prefix of LeRobot's camera keys.
pub const IMAGE_PREFIX: &str = "observation.images.";

/// One robot observation, keyed as the robot (or dataset) names things; the preprocessor's
/// rename map is applied to these keys.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Observation {
    /// Camera key (`observation.images.top`, or just `top`) -> image.
    pub images: BTreeMap<String, ImageInput>,
    /// The raw (unnormalised) state.
    pub state: Vec<f32>,
    /// The instruction.
    pub task: String,
}

/// An image in an observation file: a path (relative to the file) or raw `u8` pixels.
#[derive(serde::Deserialize)]
#[serde(untagged)]
enum ImageSpec {
    Path(PathBuf),
    Raw {
        height: usize,
        width: usize,
        #[serde(default = "three")]
        channels: usize,
        /// `[height][width][channels]` bytes.
        data: Vec<u8>,
    },
}

fn three() -> usize {
    3
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ObservationFile {
    #[serde(default)]
    images: BTreeMap<String, ImageSpec>,
    #[serde(default)]
    state: Vec<f32>,
    #[serde(default)]
    task: String,
}

impl Observation {
    /// Read an observation file (`kairos predict --json-in`):
    /// `{"task": "...", "state": [..], "images": {"top": "front.png",
    /// "wrist": {"height": H, "width": W, "channels": 3, "data": [..]}}}`. Image paths are
    /// relative to the file.
    pub fn from_json_file(path: &Path) -> Result<Self, EngineError> {
        let file: ObservationFile = read_json(path)?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let images = file
            .images
            .into_iter()
            .map(|(key, spec)| {
                let image = match spec {
                    ImageSpec::Path(p) => super::images::image_file(&base.join(p))?,
                    ImageSpec::Raw {
                        height,
                        width,
                        channels,
                        data,
                    } => ImageInput::RawU8 {
                        height,
                        width,
                        channels,
                        data,
                    },
                };
                Ok((key, image))
            })
            .collect::<Result<_, EngineError>>()?;
        Ok(Observation {
            images,
            state: file.state,
            task: file.task,
        })
    }
}

/// An observation after LeRobot's preprocessor and `prepare_images`/`prepare_state`: what the
/// VLM prefix is computed from. Batching several of these never changes any one of them.
#[derive(Clone, Debug, PartialEq)]
pub struct PreparedObservation {
    /// Cameras in the model's order, then the empty cameras.
    pub images: Vec<PreparedImage>,
    /// Task tokens and mask.
    pub tokens: TaskTokens,
    /// The normalised state, `state_dim` long (the prefix pads it to `max_state_dim`).
    pub state: Vec<f32>,
}

/// The task tokenizer of the checkpoint in `dir`: `explicit` (`--tokenizer FILE`) when given,
/// else `tokenizer.json` beside the checkpoint (LeRobot loads it from the SmolVLM2 hub repo;
/// Kairos downloads nothing). Errors name the file looked for, and both places when the
/// tokenizer was not given and is not beside the checkpoint.
pub fn tokenizer_path(dir: &Path, explicit: Option<&Path>) -> Result<PathBuf, EngineError> {
    match explicit {
        Some(path) if path.is_file() => Ok(path.to_path_buf()),
        Some(path) => Err(EngineError::MissingFile {
            path: format!("{} (the tokenizer given)", path.display()),
        }),
        None => {
            let beside = dir.join(TOKENIZER_FILE);
            if beside.is_file() {
                Ok(beside)
            } else {
                Err(EngineError::NoTokenizer {
                    beside: beside.display().to_string(),
                })
            }
        }
    }
}

/// The tokenizer's file name beside a checkpoint.
pub const TOKENIZER_FILE: &str = "tokenizer.json";

/// The model's key (one of `image_keys`) for a camera named by the user: the key itself, a key
/// the preprocessor's rename map gives it, or the same for `observation.images.<name>`.
pub fn resolve_camera(
    image_keys: &[String],
    pre: &Preprocessor,
    name: &str,
) -> Result<String, EngineError> {
    let renamed = pre.rename(name);
    if image_keys.iter().any(|k| k == renamed) {
        return Ok(renamed.to_owned());
    }
    let long = format!("{IMAGE_PREFIX}{name}");
    let renamed = pre.rename(&long);
    if image_keys.iter().any(|k| k == renamed) {
        return Ok(renamed.to_owned());
    }
    Err(EngineError::UnknownCamera {
        camera: name.to_owned(),
        known: image_keys.join(", "),
    })
}

/// Every other name [`resolve_camera`] accepts for one of `camera_keys` (the part after
/// `observation.images.`, rename-map sources and their short forms) -> that key: the server's
/// [`ModelSpec::camera_aliases`](crate::ModelSpec::camera_aliases), so it can refuse an unknown
/// camera before a batch.
pub fn camera_aliases(
    image_keys: &[String],
    camera_keys: &[String],
    pre: &Preprocessor,
) -> BTreeMap<String, String> {
    let short = |k: &str| k.strip_prefix(IMAGE_PREFIX).map(str::to_owned);
    let candidates = camera_keys
        .iter()
        .cloned()
        .chain(pre.rename_map.keys().cloned())
        .flat_map(|k| [short(&k), Some(k)])
        .flatten();
    candidates
        .filter_map(|name| {
            let key = resolve_camera(image_keys, pre, &name).ok()?;
            (key != name && camera_keys.contains(&key)).then_some((name, key))
        })
        .collect()
}

/// A checkpoint's config and processors, loaded once.
#[derive(Debug)]
pub struct SmolVlaCheckpoint {
    dir: PathBuf,
    config: SmolVlaConfig,
    pre: Preprocessor,
    post: Postprocessor,
    tokenizer: TaskTokenizer,
    limits: ImageLimits,
}

impl SmolVlaCheckpoint {
    /// Load `config.json`, both processor files and their stats, and the tokenizer (`tokenizer`,
    /// or `tokenizer.json` in `dir`).
    pub fn open(dir: &Path, tokenizer: Option<&Path>) -> Result<Self, EngineError> {
        let config_path = dir.join("config.json");
        if !config_path.exists() {
            return Err(EngineError::MissingFile {
                path: config_path.display().to_string(),
            });
        }
        let config: SmolVlaConfig = read_json(&config_path)?;
        if config.policy_type != "smolvla" {
            return Err(EngineError::Load {
                path: config_path.display().to_string(),
                reason: format!(
                    "policy type is `{}`, expected `smolvla`",
                    config.policy_type
                ),
            });
        }
        let pre = Preprocessor::load(&dir.join("policy_preprocessor.json"))?;
        let post = Postprocessor::load(&dir.join("policy_postprocessor.json"))?;
        // π's steps are read by the same loader; a SmolVLA pipeline has none of them.
        let relative = pre.relative_actions.as_ref().is_some_and(|r| r.enabled);
        if pre.state_prompt || relative || post.absolute_actions {
            return Err(EngineError::Load {
                path: dir.join("policy_preprocessor.json").display().to_string(),
                reason: "a π0.5 state prompt or relative actions in a SmolVLA pipeline".into(),
            });
        }
        let step = pre.tokenizer.clone().ok_or_else(|| EngineError::Load {
            path: dir.join("policy_preprocessor.json").display().to_string(),
            reason: "no `tokenizer_processor` step".into(),
        })?;
        let tokenizer = TaskTokenizer::load(&tokenizer_path(dir, tokenizer)?, step)?;
        if config.image_keys().is_empty() {
            return Err(EngineError::Load {
                path: config_path.display().to_string(),
                reason: "input_features has no VISUAL feature (a camera)".into(),
            });
        }
        Ok(SmolVlaCheckpoint {
            dir: dir.to_path_buf(),
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

    /// The policy config.
    pub fn config(&self) -> &SmolVlaConfig {
        &self.config
    }

    /// The preprocessor.
    pub fn preprocessor(&self) -> &Preprocessor {
        &self.pre
    }

    /// The postprocessor.
    pub fn postprocessor(&self) -> &Postprocessor {
        &self.post
    }

    /// The tokenizer.
    pub fn tokenizer(&self) -> &TaskTokenizer {
        &self.tokenizer
    }

    /// Use other image bounds (a server's per-deployment cap).
    pub fn set_image_limits(&mut self, limits: ImageLimits) {
        self.limits = limits;
    }

    /// The real state width (`observation.state`'s shape).
    pub fn state_dim(&self) -> usize {
        self.config
            .input_features
            .get(STATE_KEY)
            .and_then(|f| f.shape.first().copied())
            .unwrap_or(0)
    }

    /// The real action width (`action`'s shape).
    pub fn action_dim(&self) -> usize {
        self.config
            .output_features
            .get(ACTION_KEY)
            .and_then(|f| f.shape.first().copied())
            .unwrap_or(self.config.max_action_dim)
    }

    /// The cameras the model reads, in order, excluding the `empty_camera_<i>` placeholders
    /// LeRobot itself adds to the config for `empty_cameras`.
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

    /// The image size `(height, width)` the cameras are resized to (`None`: own size).
    pub fn image_size(&self) -> Option<(usize, usize)> {
        self.config.resize_imgs_with_padding.map(|[w, h]| (h, w))
    }

    /// The model's key for a camera named by the user: the key itself, a renamed key, or the
    /// suffix after `observation.images.` (see [`resolve_camera`]).
    pub fn resolve_camera(&self, name: &str) -> Result<String, EngineError> {
        resolve_camera(&self.config.image_keys(), &self.pre, name)
    }

    /// Every other name [`SmolVlaCheckpoint::resolve_camera`] accepts for one of
    /// [`SmolVlaCheckpoint::camera_keys`] (see [`camera_aliases`]).
    pub fn camera_aliases(&self) -> BTreeMap<String, String> {
        camera_aliases(&self.config.image_keys(), &self.camera_keys(), &self.pre)
    }

    /// The synthetic observation of `kairos predict` with no inputs: a mid-grey (`0.5`) image
    /// for every camera at its configured shape, a zero state, the task "pick up the cube".
    pub fn synthetic_observation(&self) -> Observation {
        let images = self
            .camera_keys()
            .into_iter()
            .map(|key| {
                let shape = self
                    .config
                    .input_features
                    .get(&key)
                    .map(|f| f.shape.clone())
                    .unwrap_or_default();
                let (h, w) = match shape.as_slice() {
                    [_, h, w] if *h > 0 && *w > 0 => (*h, *w),
                    _ => self.image_size().unwrap_or((224, 224)),
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

    /// Run the preprocessor and LeRobot's `prepare_images`: rename, tokenize the task (with its
    /// newline), normalise the state (and any image feature with stats), resize and scale the
    /// images, add empty cameras.
    pub fn prepare(&self, obs: &Observation) -> Result<PreparedObservation, EngineError> {
        let keys = self.config.image_keys();
        let mut present: BTreeMap<String, &ImageInput> = BTreeMap::new();
        for (name, image) in &obs.images {
            let key = self.resolve_camera(name)?;
            if present.insert(key.clone(), image).is_some() {
                return Err(EngineError::InvalidInput(format!(
                    "camera `{key}` given twice"
                )));
            }
        }
        if present.is_empty() {
            return Err(EngineError::InvalidInput(format!(
                "no camera image; the model reads {}",
                keys.join(", ")
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
        let mut state = obs.state.clone();
        let normalizer = self.pre.normalizer.as_ref();
        if let Some(n) = normalizer {
            n.normalize(STATE_KEY, &mut state)?;
        }
        let text = self.pre.task_text(&obs.task);
        let tokens = self.tokenizer.encode(&text)?;

        let size = self.image_size();
        let mut images = Vec::new();
        let mut missing = 0;
        for key in &keys {
            let Some(image) = present.get(key) else {
                missing += 1;
                continue;
            };
            let (mut chw, h, w) = to_chw_unit(image, &self.limits, key)?;
            if let Some(n) = normalizer {
                n.normalize(key, &mut chw)?;
            }
            images.push(prepare_unit_image(&chw, h, w, size));
        }
        let last = images.last().cloned();
        if let Some(last) = last {
            for _ in 0..missing.min(self.config.empty_cameras) {
                images.push(empty_camera(&last));
            }
        }
        Ok(PreparedObservation {
            images,
            tokens,
            state,
        })
    }

    /// LeRobot's output side for one chunk: `actions` is the model's `[chunk][width]` output
    /// (`width` the padded `max_action_dim` or already the action dim); cut every action to the
    /// action dim, then unnormalise. Returns `[chunk][action_dim]`.
    pub fn finish_actions(
        &self,
        actions: &[f32],
        width: usize,
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
        Ok(cut.chunks_exact(dim).map(<[f32]>::to_vec).collect())
    }
}
