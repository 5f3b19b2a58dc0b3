//! The models Kairos can run without further code: built-ins and checkpoints on disk.
//!
//! | `--model` | what |
//! |---|---|
//! | `builtin:flow-head-small` (default) | [`FlowHead`] with [`FlowHeadConfig::default`] and seeded random weights |
//! | `builtin:smolvla-random` | the full-size SmolVLA expert (`lerobot/smolvla_base` shapes) with seeded random weights, fed by the labelled stand-in prefix ([`SmolVlaStandIn`]) |
//! | a directory (or its `config.json`) | a checkpoint: `"type": "kairos_flow_head"`, LeRobot's `"type": "smolvla"`, `"pi0"` or `"pi05"` |
//!
//! A LeRobot SmolVLA directory with its processors (`policy_preprocessor.json`) is served as the
//! whole policy ([`SmolVlaPipeline`]: VLM, expert, processors), with the task tokenizer given
//! (`--tokenizer`) or beside it (`tokenizer.json`), and an error naming both places when there
//! is neither; one with only `config.json` and weights gets the expert with the stand-in prefix.
//! A LeRobot π0 or π0.5 directory is served as the whole policy ([`PiPipeline`]), with
//! PaliGemma's tokenizer given or beside it. The family is the config's `type`, never a file
//! name.

use std::path::{Path, PathBuf};

use crate::flow_head::{FLOW_HEAD_TYPE, FlowHead, FlowHeadConfig};
use crate::pi::PiPipeline;
use crate::smolvla::config::{ExpertDims, read_json};
use crate::smolvla::serving::SmolVlaStandIn;
use crate::smolvla::{ExpertWeights, SmolVlaExpert, SmolVlaPipeline};
use crate::{ActionModel, EngineError, EngineOptions};

/// Seed of the built-in models' random weights.
pub const DEFAULT_SEED: u64 = 0x4B41_4952_4F53;
/// The preprocessor file that marks a whole LeRobot SmolVLA checkpoint.
const PREPROCESSOR_FILE: &str = "policy_preprocessor.json";
/// Name of the default model.
pub const DEFAULT_MODEL: &str = "builtin:flow-head-small";

/// The default model: the small flow head with seeded random weights.
pub fn default_model(options: &EngineOptions) -> Result<Box<dyn ActionModel>, EngineError> {
    Ok(Box::new(FlowHead::random(
        FlowHeadConfig::default(),
        DEFAULT_SEED,
        options,
    )?))
}

/// Load a checkpoint directory (or its `config.json`) with default options.
pub fn load_model(path: &Path) -> Result<Box<dyn ActionModel>, EngineError> {
    load_model_with(path, &EngineOptions::default())
}

/// Load a checkpoint directory (or its `config.json`), dispatching on the config's `type`.
pub fn load_model_with(
    path: &Path,
    options: &EngineOptions,
) -> Result<Box<dyn ActionModel>, EngineError> {
    load_checkpoint(path, None, options)
}

/// [`load_model_with`], with the task tokenizer of a whole SmolVLA checkpoint (`None`: the
/// `tokenizer.json` beside it; see [`tokenizer_path`]).
fn load_checkpoint(
    path: &Path,
    tokenizer: Option<&Path>,
    options: &EngineOptions,
) -> Result<Box<dyn ActionModel>, EngineError> {
    let dir: PathBuf = if path.is_file() {
        path.parent().map(Path::to_path_buf).unwrap_or_default()
    } else {
        path.to_path_buf()
    };
    #[derive(serde::Deserialize)]
    struct Probe {
        #[serde(rename = "type")]
        model_type: Option<String>,
        #[serde(default)]
        input_features: std::collections::BTreeMap<String, crate::smolvla::config::Feature>,
    }
    let probe: Probe = read_json(&dir.join("config.json"))?;
    match probe.model_type.as_deref() {
        _ if tokenizer.is_some() && !dir.join(PREPROCESSOR_FILE).exists() => {
            Err(EngineError::Load {
                path: dir.display().to_string(),
                reason: format!(
                    "a tokenizer was given, but this is not a whole SmolVLA checkpoint \
                     (no {PREPROCESSOR_FILE}): nothing would read it"
                ),
            })
        }
        Some(FLOW_HEAD_TYPE) => Ok(Box::new(FlowHead::load(&dir, options)?)),
        // π0 / π0.5: always the whole policy (processors, PaliGemma prefix, expert).
        Some("pi0" | "pi05") => Ok(Box::new(PiPipeline::load(&dir, tokenizer, options)?)),
        // A whole LeRobot checkpoint (with its processors): the real policy, which needs the
        // task tokenizer, given or beside it.
        Some("smolvla") if dir.join(PREPROCESSOR_FILE).exists() => {
            Ok(Box::new(SmolVlaPipeline::load(&dir, tokenizer, options)?))
        }
        // Only the config and the weights: the expert behind the labelled stand-in prefix.
        Some("smolvla") => {
            let cameras = probe
                .input_features
                .values()
                .filter(|f| f.kind == "VISUAL")
                .count();
            Ok(Box::new(SmolVlaStandIn::load(
                &dir,
                options,
                if cameras == 0 { 2 } else { cameras },
            )?))
        }
        other => Err(EngineError::Load {
            path: dir.join("config.json").display().to_string(),
            reason: format!(
                "unknown model type {other:?}; expected `{FLOW_HEAD_TYPE}`, `smolvla`, `pi0` or \
                 `pi05`"
            ),
        }),
    }
}

/// Resolve a `--model` argument: a built-in name or a checkpoint path.
pub fn resolve_model(
    name: &str,
    options: &EngineOptions,
) -> Result<Box<dyn ActionModel>, EngineError> {
    resolve_model_with(name, None, options)
}

/// [`resolve_model`] with a `--tokenizer` argument: the task tokenizer of a whole SmolVLA, π0
/// or π0.5 checkpoint (`None`: the `tokenizer.json` beside it). Any other model refuses a tokenizer
/// rather than ignore it.
pub fn resolve_model_with(
    name: &str,
    tokenizer: Option<&Path>,
    options: &EngineOptions,
) -> Result<Box<dyn ActionModel>, EngineError> {
    if let Some(file) = tokenizer
        && name.starts_with("builtin")
    {
        return Err(EngineError::InvalidInput(format!(
            "a tokenizer ({}) was given, but `{name}` reads no text",
            file.display()
        )));
    }
    match name {
        "builtin" | DEFAULT_MODEL => default_model(options),
        "builtin:smolvla-random" => {
            let dims = ExpertDims::smolvla_base();
            let expert =
                SmolVlaExpert::from_weights(&ExpertWeights::random(&dims, DEFAULT_SEED), options)?;
            Ok(Box::new(SmolVlaStandIn::new(expert, 2)))
        }
        other if other.starts_with("builtin:") => Err(EngineError::InvalidInput(format!(
            "unknown built-in model `{other}` (builtin:flow-head-small, builtin:smolvla-random)"
        ))),
        path => load_checkpoint(Path::new(path), tokenizer, options),
    }
}

/// A short file-system-safe name for a `--model` argument (e.g. for `profiles/<model>.json`).
pub fn model_slug(name: &str) -> String {
    let base = name.strip_prefix("builtin:").unwrap_or_else(|| {
        let p = Path::new(name);
        let p = if p.file_name().is_some_and(|f| f == "config.json") {
            p.parent().unwrap_or(p)
        } else {
            p
        };
        p.file_name().and_then(|f| f.to_str()).unwrap_or(name)
    });
    base.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}
