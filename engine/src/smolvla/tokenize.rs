//! The task tokenizer: a Hugging Face `tokenizer.json` read with the `tokenizers` crate (no
//! network, no onig), driven by the preprocessor's tokenizer step as LeRobot's
//! `TokenizerProcessorStep` drives `transformers`:
//! `tokenizer(task, max_length, truncation, padding, padding_side)`, special tokens added.
//!
//! LeRobot does not ship the tokenizer in the checkpoint (it loads SmolVLM2's from the hub), so
//! the caller passes the file, or the checkpoint directory has a `tokenizer.json` beside it.
//!
//! Padding is per observation. With `"longest"` (SmolVLA's default) LeRobot pads a batch to its
//! longest task; padded tokens are masked out of every attention, so one observation's actions
//! do not depend on that, and Kairos tokenizes each observation alone.

use std::path::{Path, PathBuf};

use tokenizers::{Tokenizer, TruncationDirection, TruncationParams, TruncationStrategy};

use super::processors::{TokenPadding, TokenizerStep};
use crate::EngineError;

/// Token ids and the attention mask of one task (`false`: padding).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TaskTokens {
    /// Token ids.
    pub ids: Vec<u32>,
    /// `true` for real tokens.
    pub mask: Vec<bool>,
}

/// A tokenizer configured like the checkpoint's tokenizer step.
pub struct TaskTokenizer {
    tokenizer: Tokenizer,
    step: TokenizerStep,
    pad_id: Option<u32>,
    path: PathBuf,
}

impl std::fmt::Debug for TaskTokenizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TaskTokenizer")
            .field("path", &self.path)
            .field("step", &self.step)
            .field("pad_id", &self.pad_id)
            .finish()
    }
}

impl TaskTokenizer {
    /// Load `tokenizer.json` at `path` for `step`. The pad token, needed only for
    /// `max_length` padding, comes from the file's own padding settings or, as in
    /// `transformers`, from a `tokenizer_config.json` beside it (`pad_token`).
    pub fn load(path: &Path, step: TokenizerStep) -> Result<Self, EngineError> {
        if !path.exists() {
            return Err(EngineError::MissingFile {
                path: path.display().to_string(),
            });
        }
        let load_err = |reason: String| EngineError::Load {
            path: path.display().to_string(),
            reason,
        };
        let mut tokenizer = Tokenizer::from_file(path).map_err(|e| load_err(e.to_string()))?;
        let mut pad_id = tokenizer.get_padding().map(|p| p.pad_id);
        if pad_id.is_none() {
            pad_id = pad_from_config(path, &tokenizer)?;
        }
        if step.padding == TokenPadding::MaxLength && pad_id.is_none() {
            return Err(load_err(
                "the tokenizer step pads to max_length but the tokenizer has no pad token \
                 (neither in tokenizer.json nor as `pad_token` in tokenizer_config.json)"
                    .into(),
            ));
        }
        // transformers sets its own truncation and padding on the backend for every call.
        tokenizer.with_padding(None);
        let truncation = step.truncation.then_some(TruncationParams {
            direction: TruncationDirection::Right,
            max_length: step.max_length,
            strategy: TruncationStrategy::LongestFirst,
            stride: 0,
        });
        tokenizer
            .with_truncation(truncation)
            .map_err(|e| load_err(format!("truncation to {}: {e}", step.max_length)))?;
        Ok(TaskTokenizer {
            tokenizer,
            step,
            pad_id,
            path: path.to_path_buf(),
        })
    }

    /// The step settings in use.
    pub fn step(&self) -> &TokenizerStep {
        &self.step
    }

    /// The tokenizer file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Tokenize `text` exactly (the newline step is the caller's: see
    /// [`super::processors::Preprocessor::task_text`]).
    pub fn encode(&self, text: &str) -> Result<TaskTokens, EngineError> {
        let enc = self
            .tokenizer
            .encode(text, true)
            .map_err(|e| EngineError::InvalidInput(format!("task: cannot tokenize: {e}")))?;
        let mut ids = enc.get_ids().to_vec();
        let mut mask: Vec<bool> = enc.get_attention_mask().iter().map(|&m| m != 0).collect();
        if self.step.padding == TokenPadding::MaxLength && ids.len() < self.step.max_length {
            // Checked at load: max_length padding has a pad id.
            let pad = self.pad_id.unwrap_or(0);
            let n = self.step.max_length - ids.len();
            if self.step.pad_right {
                ids.extend(std::iter::repeat_n(pad, n));
                mask.extend(std::iter::repeat_n(false, n));
            } else {
                ids.splice(0..0, std::iter::repeat_n(pad, n));
                mask.splice(0..0, std::iter::repeat_n(false, n));
            }
        }
        if ids.is_empty() {
            return Err(EngineError::InvalidInput(
                "task: tokenizes to no tokens".into(),
            ));
        }
        Ok(TaskTokens { ids, mask })
    }
}

/// `pad_token` of a `tokenizer_config.json` beside `path`, as an id.
fn pad_from_config(path: &Path, tokenizer: &Tokenizer) -> Result<Option<u32>, EngineError> {
    let cfg_path = path.with_file_name("tokenizer_config.json");
    if !cfg_path.exists() {
        return Ok(None);
    }
    let cfg: serde_json::Value = super::config::read_json(&cfg_path)?;
    let token = match cfg.get("pad_token") {
        Some(serde_json::Value::String(s)) => s.clone(),
        Some(serde_json::Value::Object(o)) => match o.get("content") {
            Some(serde_json::Value::String(s)) => s.clone(),
            _ => return Ok(None),
        },
        _ => return Ok(None),
    };
    tokenizer
        .token_to_id(&token)
        .map(Some)
        .ok_or_else(|| EngineError::Load {
            path: cfg_path.display().to_string(),
            reason: format!("pad_token `{token}` is not in the vocabulary"),
        })
}
