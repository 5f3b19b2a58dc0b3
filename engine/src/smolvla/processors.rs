//! LeRobot's policy processors, read from a checkpoint's `policy_preprocessor.json` and
//! `policy_postprocessor.json` (LeRobot 0.6.1, `processor/pipeline.py`).
//!
//! A pipeline file lists its steps in order, each as `{"registry_name", "config",
//! "state_file"?}`; a step with state (the normalisers) names its safetensors file in
//! `state_file`, whose tensors are `<feature>.<stat>` (`observation.state.mean`, ...). The step
//! index inside that name differs between checkpoints, so the loader always follows the JSON.
//!
//! Steps understood here, with what they do at inference:
//! - `rename_observations_processor`: renames observation keys (`rename_map`);
//! - `to_batch_processor`, `device_processor`: shape/device bookkeeping, nothing to do on one
//!   host observation;
//! - `smolvla_new_line_processor`, `pi0_new_line_processor`: the task text gets a trailing
//!   `"\n"` if it has none;
//! - `pi05_prepare_state_tokenizer_processor_step`: π0.5's prompt with the discretised state
//!   ([`Preprocessor::state_prompt`]; the π checkpoint writes it);
//! - `relative_actions_processor` / `absolute_actions_processor`: actions relative to the raw
//!   state ([`RelativeActions`]);
//! - `tokenizer_processor`: max length, padding and truncation of the task tokens (see
//!   [`super::tokenize`]);
//! - `normalizer_processor` / `unnormalizer_processor`: [`Normalizer`].
//!
//! Any other step is refused by name: silently skipping a transform would change the actions.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::config::{Feature, FeatureMap, read_json};
use crate::EngineError;
use crate::weights::Checkpoint;

/// One step of a pipeline file, as LeRobot writes it.
#[derive(Clone, Debug, serde::Deserialize)]
struct StepEntry {
    registry_name: String,
    #[serde(default)]
    config: serde_json::Value,
    #[serde(default)]
    state_file: Option<String>,
}

#[derive(Clone, Debug, serde::Deserialize)]
struct PipelineFile {
    #[serde(default)]
    steps: Vec<StepEntry>,
}

/// A LeRobot normalisation mode (`NormalizationMode`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormMode {
    /// Pass through.
    Identity,
    /// `(x - mean) / (std + eps)`; inverse `x * std + mean`.
    MeanStd,
    /// `2 (x - min) / (max - min) - 1` (a zero range becomes `eps`).
    MinMax,
    /// Like `MinMax` with the 1st and 99th percentiles (`q01`, `q99`).
    Quantiles,
    /// Like `MinMax` with the 10th and 90th percentiles (`q10`, `q90`).
    Quantile10,
}

impl NormMode {
    /// Parse LeRobot's spelling; `None` for a mode this engine does not know.
    pub fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "IDENTITY" => NormMode::Identity,
            "MEAN_STD" => NormMode::MeanStd,
            "MIN_MAX" => NormMode::MinMax,
            "QUANTILES" => NormMode::Quantiles,
            "QUANTILE10" => NormMode::Quantile10,
            _ => return None,
        })
    }

    /// The two stats the mode reads, in the order `(shift, scale-or-upper)`.
    fn stat_names(self) -> Option<[&'static str; 2]> {
        match self {
            NormMode::Identity => None,
            NormMode::MeanStd => Some(["mean", "std"]),
            NormMode::MinMax => Some(["min", "max"]),
            NormMode::Quantiles => Some(["q01", "q99"]),
            NormMode::Quantile10 => Some(["q10", "q90"]),
        }
    }
}

/// How one feature is (un)normalised: its mode and the two stats that mode reads.
#[derive(Clone, Debug, PartialEq)]
struct FeatureNorm {
    mode: NormMode,
    /// `mean` / `min` / `q01` / `q10`.
    a: Vec<f32>,
    /// `std` / `max` / `q99` / `q90`.
    b: Vec<f32>,
}

/// LeRobot's `NormalizerProcessorStep` / `UnnormalizerProcessorStep`, with its stats.
///
/// Formulas are LeRobot 0.6.1's `_apply_transform`, in `f32` in the same operation order, so the
/// result is bit-identical to PyTorch's for elementwise ops. A feature whose key has no stats at
/// all passes through unchanged, as in LeRobot; the loader warns once, naming the key. A
/// feature with stats but without the ones its mode needs is an error (LeRobot raises too).
#[derive(Clone, Debug, PartialEq)]
pub struct Normalizer {
    eps: f32,
    features: FeatureMap,
    norms: BTreeMap<String, FeatureNorm>,
    /// Keys passed through for lack of stats (already warned about).
    unnormalised: Vec<String>,
}

impl Normalizer {
    /// Build from a step's `config` and its stats file. `file` names the pipeline JSON for errors.
    fn from_step(
        file: &Path,
        step: &StepEntry,
        stats: Option<&Checkpoint>,
    ) -> Result<Self, EngineError> {
        #[derive(serde::Deserialize)]
        struct Cfg {
            #[serde(default = "default_eps")]
            eps: f64,
            #[serde(default)]
            features: FeatureMap,
            #[serde(default)]
            norm_map: BTreeMap<String, String>,
            #[serde(default)]
            normalize_observation_keys: Option<BTreeSet<String>>,
        }
        fn default_eps() -> f64 {
            1e-8
        }
        let cfg: Cfg =
            serde_json::from_value(step.config.clone()).map_err(|e| EngineError::Load {
                path: file.display().to_string(),
                reason: format!("step `{}`: {e}", step.registry_name),
            })?;
        let mut modes = BTreeMap::new();
        for (kind, mode) in &cfg.norm_map {
            let parsed = NormMode::parse(mode).ok_or_else(|| EngineError::UnknownNormMode {
                file: file.display().to_string(),
                feature: kind.clone(),
                mode: mode.clone(),
            })?;
            modes.insert(kind.clone(), parsed);
        }
        let mut norms = BTreeMap::new();
        let mut unnormalised = Vec::new();
        for (key, feature) in cfg.features.iter() {
            if let Some(keys) = &cfg.normalize_observation_keys
                && feature.kind != "ACTION"
                && !keys.contains(key)
            {
                continue;
            }
            let mode = modes
                .get(&feature.kind)
                .copied()
                .unwrap_or(NormMode::Identity);
            let Some([sa, sb]) = mode.stat_names() else {
                continue;
            };
            let has_any = stats.is_some_and(|ck| {
                ck.keys()
                    .iter()
                    .any(|k| k.rsplit_once('.').is_some_and(|(f, _)| f == key))
            });
            let Some(ck) = stats.filter(|_| has_any) else {
                tracing::warn!(
                    feature = %key,
                    file = %file.display(),
                    "no normalisation stats for `{key}`: it passes through unchanged, as in LeRobot"
                );
                unnormalised.push(key.clone());
                continue;
            };
            let read = |stat: &str| -> Result<Vec<f32>, EngineError> {
                let name = format!("{key}.{stat}");
                let shape = ck.shape(&name).map(<[usize]>::to_vec).ok_or_else(|| {
                    EngineError::MissingStat {
                        file: ck.path().to_owned(),
                        key: name.clone(),
                        mode: format!("{mode:?}"),
                    }
                })?;
                let values = ck
                    .tensor(&name, &shape)
                    .map_err(|e| in_file(ck.path(), e))?;
                check_stat_len(ck.path(), &name, feature, values.len())?;
                Ok(values)
            };
            let (a, b) = (read(sa)?, read(sb)?);
            if a.len() != b.len() {
                return Err(EngineError::ShapeMismatch {
                    key: format!("{}: {key}.{sb}", ck.path()),
                    expected: vec![a.len()],
                    found: vec![b.len()],
                });
            }
            norms.insert(key.clone(), FeatureNorm { mode, a, b });
        }
        Ok(Normalizer {
            eps: cfg.eps as f32,
            features: cfg.features,
            norms,
            unnormalised,
        })
    }

    /// The features this step knows, in file order.
    pub fn features(&self) -> &FeatureMap {
        &self.features
    }

    /// The mode applied to `key` (`Identity` when it has none or no stats).
    pub fn mode(&self, key: &str) -> NormMode {
        self.norms
            .get(key)
            .map(|n| n.mode)
            .unwrap_or(NormMode::Identity)
    }

    /// Keys that pass through because the stats file has nothing for them.
    pub fn unnormalised(&self) -> &[String] {
        &self.unnormalised
    }

    /// Normalise `values` of feature `key` in place. `values` is the feature flattened
    /// row-major; stats broadcast over leading dims (an action chunk `[N][D]` with `[D]` stats)
    /// or, for `[C]`/`[C,1,1]` image stats, over each channel plane of a `[C][H][W]` image.
    pub fn normalize(&self, key: &str, values: &mut [f32]) -> Result<(), EngineError> {
        self.apply(key, values, false)
    }

    /// The inverse of [`Normalizer::normalize`].
    pub fn unnormalize(&self, key: &str, values: &mut [f32]) -> Result<(), EngineError> {
        self.apply(key, values, true)
    }

    /// The inverse transform of `key` as `y = scale * x + shift`, per element of the stats'
    /// width (every mode is affine): what maps a normalised initial noise and, with the scale
    /// alone, each Euler update into the robot's units so that `noise + sum(updates)` still
    /// equals the (unnormalised) actions. `None` when `key` passes through.
    pub fn inverse_affine(&self, key: &str) -> Option<(Vec<f32>, Vec<f32>)> {
        let n = self.norms.get(key)?;
        let eps = self.eps;
        let pairs = n.a.iter().zip(&n.b).map(|(&a, &b)| match n.mode {
            NormMode::Identity => (1.0, 0.0),
            NormMode::MeanStd => (b, a),
            NormMode::MinMax | NormMode::Quantiles | NormMode::Quantile10 => {
                let half = range(a, b, eps) / 2.0;
                (half, half + a)
            }
        });
        Some(pairs.unzip())
    }

    fn apply(&self, key: &str, values: &mut [f32], inverse: bool) -> Result<(), EngineError> {
        let Some(n) = self.norms.get(key) else {
            return Ok(());
        };
        let width = n.a.len();
        if width == 0 || !values.len().is_multiple_of(width) {
            return Err(EngineError::InvalidInput(format!(
                "{key}: {} values do not fit normalisation stats of {width}",
                values.len()
            )));
        }
        // Image stats are per channel over [C][H][W]: each stat value covers a plane.
        let is_plane = self
            .features
            .get(key)
            .is_some_and(|f| f.kind == "VISUAL" && f.shape.first() == Some(&width));
        let plane = if is_plane { values.len() / width } else { 1 };
        let eps = self.eps;
        for (i, x) in values.iter_mut().enumerate() {
            let c = if is_plane { i / plane } else { i % width };
            let (a, b) = (n.a[c], n.b[c]);
            *x = match (n.mode, inverse) {
                (NormMode::Identity, _) => *x,
                (NormMode::MeanStd, false) => (*x - a) / (b + eps),
                (NormMode::MeanStd, true) => *x * b + a,
                (NormMode::MinMax, false) => 2.0 * (*x - a) / range(a, b, eps) - 1.0,
                (NormMode::MinMax, true) => (*x + 1.0) / 2.0 * range(a, b, eps) + a,
                (NormMode::Quantiles | NormMode::Quantile10, false) => {
                    2.0 * (*x - a) / range(a, b, eps) - 1.0
                }
                (NormMode::Quantiles | NormMode::Quantile10, true) => {
                    (*x + 1.0) * range(a, b, eps) / 2.0 + a
                }
            };
        }
        Ok(())
    }
}

/// `error` with the stats file named in its key (a tensor error names only the key).
fn in_file(file: &str, error: EngineError) -> EngineError {
    match error {
        EngineError::MissingTensor { key } => EngineError::MissingTensor {
            key: format!("{file}: {key}"),
        },
        EngineError::ShapeMismatch {
            key,
            expected,
            found,
        } => EngineError::ShapeMismatch {
            key: format!("{file}: {key}"),
            expected,
            found,
        },
        EngineError::DtypeMismatch {
            key,
            expected,
            found,
        } => EngineError::DtypeMismatch {
            key: format!("{file}: {key}"),
            expected,
            found,
        },
        other => other,
    }
}

/// `hi - lo`, or `eps` where that is exactly zero (LeRobot's `torch.where(denom == 0, eps, ..)`).
fn range(lo: f32, hi: f32, eps: f32) -> f32 {
    let d = hi - lo;
    if d == 0.0 { eps } else { d }
}

fn check_stat_len(
    file: &str,
    name: &str,
    feature: &Feature,
    len: usize,
) -> Result<(), EngineError> {
    let total: usize = feature.shape.iter().product();
    let channels = feature.shape.first().copied().unwrap_or(0);
    let ok = len == total
        || (feature.kind == "VISUAL" && len == channels)
        || feature.shape.last() == Some(&len);
    if ok {
        Ok(())
    } else {
        Err(EngineError::ShapeMismatch {
            key: format!("{file}: {name}"),
            expected: feature.shape.clone(),
            found: vec![len],
        })
    }
}

/// Padding of the task tokens (`padding` of the tokenizer step).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TokenPadding {
    /// `"longest"`: as long as the (single) task needs, no padding.
    Longest,
    /// `"max_length"`: padded to `max_length`.
    MaxLength,
}

/// The tokenizer step's settings (LeRobot's `TokenizerProcessorStep` config).
#[derive(Clone, Debug, PartialEq)]
pub struct TokenizerStep {
    /// Most tokens kept (special tokens included).
    pub max_length: usize,
    /// Padding strategy.
    pub padding: TokenPadding,
    /// `true`: padding goes on the right (LeRobot SmolVLA's choice).
    pub pad_right: bool,
    /// Whether longer tasks are cut to `max_length`.
    pub truncation: bool,
    /// The hub tokenizer LeRobot would load (informational: nothing is downloaded).
    pub tokenizer_name: Option<String>,
}

impl TokenizerStep {
    fn from_step(file: &Path, step: &StepEntry) -> Result<Self, EngineError> {
        #[derive(serde::Deserialize)]
        struct Cfg {
            #[serde(default = "default_max")]
            max_length: usize,
            #[serde(default = "default_padding")]
            padding: String,
            #[serde(default = "default_side")]
            padding_side: String,
            #[serde(default = "default_true")]
            truncation: bool,
            #[serde(default)]
            tokenizer_name: Option<String>,
            #[serde(default = "default_task_key")]
            task_key: String,
        }
        fn default_max() -> usize {
            512
        }
        fn default_padding() -> String {
            "max_length".into()
        }
        fn default_side() -> String {
            "right".into()
        }
        fn default_true() -> bool {
            true
        }
        fn default_task_key() -> String {
            "task".into()
        }
        let bad = |field: &str, reason: String| EngineError::Load {
            path: file.display().to_string(),
            reason: format!("step `{}`, `{field}`: {reason}", step.registry_name),
        };
        let cfg: Cfg = serde_json::from_value(step.config.clone())
            .map_err(|e| bad("config", e.to_string()))?;
        let padding = match cfg.padding.as_str() {
            "longest" => TokenPadding::Longest,
            "max_length" => TokenPadding::MaxLength,
            other => {
                return Err(bad(
                    "padding",
                    format!("`{other}` is not supported (longest, max_length)"),
                ));
            }
        };
        let pad_right = match cfg.padding_side.as_str() {
            "right" => true,
            "left" => false,
            other => return Err(bad("padding_side", format!("`{other}`"))),
        };
        if cfg.task_key != "task" {
            return Err(bad(
                "task_key",
                format!("`{}`; only `task` is supported", cfg.task_key),
            ));
        }
        if cfg.max_length == 0 {
            return Err(bad("max_length", "must be at least 1".into()));
        }
        Ok(TokenizerStep {
            max_length: cfg.max_length,
            padding,
            pad_right,
            truncation: cfg.truncation,
            tokenizer_name: cfg.tokenizer_name,
        })
    }
}

/// LeRobot's `relative_actions_processor` settings: with `enabled`, the model's actions are
/// relative to the raw state, and the postprocessor's `absolute_actions_processor` adds the
/// state back (after unnormalising) to every action dim whose name matches none of
/// `exclude_joints` (all dims when there are no names).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RelativeActions {
    /// Whether actions are relative.
    pub enabled: bool,
    /// Joint names (substrings, case-insensitive) kept absolute.
    pub exclude_joints: Vec<String>,
    /// The action dims' names, if the dataset had them.
    pub action_names: Option<Vec<String>>,
}

impl RelativeActions {
    /// LeRobot's `_build_mask`: which of `action_dim` dims get the state added back.
    pub fn mask(&self, action_dim: usize) -> Vec<bool> {
        let tokens: Vec<String> = self
            .exclude_joints
            .iter()
            .filter(|j| !j.is_empty())
            .map(|j| j.to_lowercase())
            .collect();
        let (Some(names), false) = (&self.action_names, tokens.is_empty()) else {
            return vec![true; action_dim];
        };
        let mut mask: Vec<bool> = names
            .iter()
            .take(action_dim)
            .map(|n| {
                let n = n.to_lowercase();
                !tokens.iter().any(|t| *t == n || n.contains(t.as_str()))
            })
            .collect();
        mask.resize(action_dim, true);
        mask
    }
}

/// A checkpoint's `policy_preprocessor.json`, steps folded into what they do.
#[derive(Clone, Debug, PartialEq)]
pub struct Preprocessor {
    /// Observation key renames (old -> new).
    pub rename_map: BTreeMap<String, String>,
    /// Whether the task gets a trailing newline (`smolvla_new_line_processor`,
    /// `pi0_new_line_processor`).
    pub newline: bool,
    /// Whether the task becomes π0.5's prompt with the normalised state discretised into it
    /// (`pi05_prepare_state_tokenizer_processor_step`).
    pub state_prompt: bool,
    /// The `relative_actions_processor` step, if any.
    pub relative_actions: Option<RelativeActions>,
    /// The tokenizer step, if any.
    pub tokenizer: Option<TokenizerStep>,
    /// The normaliser, if any.
    pub normalizer: Option<Normalizer>,
}

/// A checkpoint's `policy_postprocessor.json`.
#[derive(Clone, Debug, PartialEq)]
pub struct Postprocessor {
    /// The unnormaliser, if any.
    pub unnormalizer: Option<Normalizer>,
    /// Whether an enabled `absolute_actions_processor` adds the raw state back to the actions.
    pub absolute_actions: bool,
}

/// Read a pipeline file and each step's stats file.
fn read_pipeline(path: &Path) -> Result<Vec<(StepEntry, Option<Checkpoint>)>, EngineError> {
    if !path.exists() {
        return Err(EngineError::MissingFile {
            path: path.display().to_string(),
        });
    }
    let file: PipelineFile = read_json(path)?;
    let dir: PathBuf = path.parent().map(Path::to_path_buf).unwrap_or_default();
    file.steps
        .into_iter()
        .map(|step| {
            let state = match &step.state_file {
                Some(name) => {
                    let p = dir.join(name);
                    if !p.exists() {
                        return Err(EngineError::MissingFile {
                            path: p.display().to_string(),
                        });
                    }
                    Some(Checkpoint::open(&p)?)
                }
                None => None,
            };
            Ok((step, state))
        })
        .collect()
}

fn unknown_step(path: &Path, step: &StepEntry) -> EngineError {
    EngineError::Load {
        path: path.display().to_string(),
        reason: format!(
            "processor step `{}` is not supported; refusing to skip it",
            step.registry_name
        ),
    }
}

impl Preprocessor {
    /// Load `policy_preprocessor.json` (and the stats files its steps name).
    pub fn load(path: &Path) -> Result<Self, EngineError> {
        let mut pre = Preprocessor {
            rename_map: BTreeMap::new(),
            newline: false,
            state_prompt: false,
            relative_actions: None,
            tokenizer: None,
            normalizer: None,
        };
        for (step, state) in read_pipeline(path)? {
            match step.registry_name.as_str() {
                "rename_observations_processor" => {
                    #[derive(serde::Deserialize)]
                    struct Cfg {
                        #[serde(default)]
                        rename_map: BTreeMap<String, String>,
                    }
                    let cfg: Cfg = serde_json::from_value(step.config.clone()).map_err(|e| {
                        EngineError::Load {
                            path: path.display().to_string(),
                            reason: format!("step `{}`: {e}", step.registry_name),
                        }
                    })?;
                    pre.rename_map.extend(cfg.rename_map);
                }
                "to_batch_processor" | "device_processor" => {}
                "smolvla_new_line_processor" | "pi0_new_line_processor" => pre.newline = true,
                "pi05_prepare_state_tokenizer_processor_step" => pre.state_prompt = true,
                "relative_actions_processor" => {
                    #[derive(serde::Deserialize)]
                    struct Cfg {
                        #[serde(default)]
                        enabled: bool,
                        #[serde(default)]
                        exclude_joints: Vec<String>,
                        #[serde(default)]
                        action_names: Option<Vec<String>>,
                    }
                    let cfg: Cfg = serde_json::from_value(step.config.clone()).map_err(|e| {
                        EngineError::Load {
                            path: path.display().to_string(),
                            reason: format!("step `{}`: {e}", step.registry_name),
                        }
                    })?;
                    pre.relative_actions = Some(RelativeActions {
                        enabled: cfg.enabled,
                        exclude_joints: cfg.exclude_joints,
                        action_names: cfg.action_names,
                    });
                }
                "tokenizer_processor" => {
                    pre.tokenizer = Some(TokenizerStep::from_step(path, &step)?);
                }
                "normalizer_processor" => {
                    pre.normalizer = Some(Normalizer::from_step(path, &step, state.as_ref())?);
                }
                _ => return Err(unknown_step(path, &step)),
            }
        }
        Ok(pre)
    }

    /// The key an observation key has after the rename step.
    pub fn rename<'a>(&'a self, key: &'a str) -> &'a str {
        self.rename_map.get(key).map_or(key, String::as_str)
    }

    /// The task text the tokenizer sees.
    pub fn task_text(&self, task: &str) -> String {
        if self.newline && !task.ends_with('\n') {
            format!("{task}\n")
        } else {
            task.to_owned()
        }
    }
}

impl Postprocessor {
    /// Load `policy_postprocessor.json` (and the stats files its steps name).
    pub fn load(path: &Path) -> Result<Self, EngineError> {
        let mut post = Postprocessor {
            unnormalizer: None,
            absolute_actions: false,
        };
        for (step, state) in read_pipeline(path)? {
            match step.registry_name.as_str() {
                "device_processor" => {}
                "absolute_actions_processor" => {
                    post.absolute_actions = step
                        .config
                        .get("enabled")
                        .and_then(serde_json::Value::as_bool)
                        .unwrap_or(false);
                }
                "unnormalizer_processor" => {
                    post.unnormalizer = Some(Normalizer::from_step(path, &step, state.as_ref())?);
                }
                _ => return Err(unknown_step(path, &step)),
            }
        }
        Ok(post)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn normalizer(mode: NormMode, a: Vec<f32>, b: Vec<f32>) -> Normalizer {
        let mut features = FeatureMap::default();
        features.insert(
            "x".into(),
            Feature {
                kind: "STATE".into(),
                shape: vec![a.len()],
            },
        );
        let mut norms = BTreeMap::new();
        norms.insert("x".to_owned(), FeatureNorm { mode, a, b });
        Normalizer {
            eps: 1e-8,
            features,
            norms,
            unnormalised: Vec::new(),
        }
    }

    #[test]
    fn formulas_match_lerobot() {
        let n = normalizer(NormMode::MeanStd, vec![1.0, -2.0], vec![2.0, 0.5]);
        let mut v = vec![3.0, -1.0, 1.0, -2.0];
        n.normalize("x", &mut v).unwrap();
        assert_eq!(v, vec![2.0 / (2.0 + 1e-8), 1.0 / (0.5 + 1e-8), 0.0, 0.0]);
        n.unnormalize("x", &mut v).unwrap();
        assert!((v[0] - 3.0).abs() < 1e-6 && (v[1] + 1.0).abs() < 1e-6);

        let n = normalizer(NormMode::MinMax, vec![0.0, 5.0], vec![4.0, 5.0]);
        let mut v = vec![1.0, 5.0];
        n.normalize("x", &mut v).unwrap();
        // Zero range: the denominator is eps, and min maps to -1.
        assert_eq!(v, vec![-0.5, -1.0]);
        n.unnormalize("x", &mut v).unwrap();
        assert_eq!(v, vec![1.0, 5.0]);

        let n = normalizer(NormMode::Quantiles, vec![-1.0], vec![3.0]);
        let mut v = vec![3.0, -1.0, 1.0];
        n.normalize("x", &mut v).unwrap();
        assert_eq!(v, vec![1.0, -1.0, 0.0]);
        n.unnormalize("x", &mut v).unwrap();
        assert_eq!(v, vec![3.0, -1.0, 1.0]);

        // No stats for a key: unchanged.
        let mut w = vec![7.0];
        n.normalize("other", &mut w).unwrap();
        assert_eq!(w, vec![7.0]);
        // A length that the stats cannot broadcast over is an error, not a panic.
        let mut bad = vec![1.0, 2.0, 3.0];
        let n2 = normalizer(NormMode::MeanStd, vec![0.0, 0.0], vec![1.0, 1.0]);
        assert!(n2.normalize("x", &mut bad).is_err());
    }

    #[test]
    fn relative_action_masks_follow_lerobot() {
        let all = RelativeActions::default();
        assert_eq!(all.mask(3), vec![true; 3]);
        let named = RelativeActions {
            enabled: true,
            exclude_joints: vec!["Gripper".into()],
            action_names: Some(vec!["shoulder".into(), "left_gripper".into()]),
        };
        // Names match as lower-case substrings; dims without a name stay relative.
        assert_eq!(named.mask(3), vec![true, false, true]);
    }

    #[test]
    fn modes_parse_lerobot_spellings() {
        assert_eq!(NormMode::parse("MEAN_STD"), Some(NormMode::MeanStd));
        assert_eq!(NormMode::parse("QUANTILES"), Some(NormMode::Quantiles));
        assert_eq!(NormMode::parse("mean_std"), None);
    }
}
