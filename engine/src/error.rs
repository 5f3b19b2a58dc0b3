//! Errors of the model engine.

/// Everything that can go wrong while loading or running a model.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// A checkpoint lacks a tensor the model needs.
    #[error("checkpoint is missing tensor `{key}`")]
    MissingTensor {
        /// The checkpoint key, as LeRobot names it.
        key: String,
    },
    /// A checkpoint tensor has the wrong shape.
    #[error("tensor `{key}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        /// The checkpoint key.
        key: String,
        /// The shape the model needs.
        expected: Vec<usize>,
        /// The shape in the file.
        found: Vec<usize>,
    },
    /// A checkpoint tensor has a dtype the model cannot use.
    #[error("tensor `{key}` has dtype {found}, expected one of {expected}")]
    DtypeMismatch {
        /// The checkpoint key.
        key: String,
        /// Acceptable dtypes, human readable.
        expected: String,
        /// The dtype in the file.
        found: String,
    },
    /// The checkpoint or config file could not be read or parsed.
    #[error("cannot load {path}: {reason}")]
    Load {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// A request does not fit the model (wrong state length, undecodable image, ...).
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// A file a checkpoint needs does not exist.
    #[error("missing file {path}")]
    MissingFile {
        /// The file looked for.
        path: String,
    },
    /// A VLA checkpoint's task tokenizer was neither given nor found beside it.
    #[error(
        "missing file {beside}: the checkpoint needs its task tokenizer (SmolVLM2's \
         tokenizer.json for SmolVLA, PaliGemma's for π0 and π0.5); none was given \
         (`--tokenizer FILE`, or `tokenizer` in an [[engine]] table) and there is none beside \
         the checkpoint"
    )]
    NoTokenizer {
        /// Where it was looked for beside the checkpoint.
        beside: String,
    },
    /// A processor names a normalisation mode this engine does not implement.
    #[error("{file}: unknown normalisation mode `{mode}` for `{feature}`")]
    UnknownNormMode {
        /// The processor file.
        file: String,
        /// The feature type (`STATE`, ...) the mode is for.
        feature: String,
        /// The mode as written.
        mode: String,
    },
    /// A normaliser's stats file has stats for a feature, but not the one its mode needs.
    #[error("{file}: missing stat `{key}` needed by {mode} normalisation")]
    MissingStat {
        /// The stats file.
        file: String,
        /// The missing tensor, `<feature>.<stat>`.
        key: String,
        /// The mode that reads it.
        mode: String,
    },
    /// An observation names a camera the model does not have.
    #[error("unknown camera `{camera}`; the model's cameras are: {known}")]
    UnknownCamera {
        /// The camera as given.
        camera: String,
        /// The model's camera keys, comma separated.
        known: String,
    },
    /// A state vector of the wrong length.
    #[error("{field} has {found} values, the model expects {expected}")]
    StateLength {
        /// The field (`observation.state`).
        field: String,
        /// The model's state width.
        expected: usize,
        /// The length given.
        found: usize,
    },
    /// An error inside Candle.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// One field of a request the model cannot take. `field` is a path inside the request
/// (`state`, `images[1]`, `samples`), so the server can name the wire field it came from.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct InputError {
    /// Which field.
    pub field: String,
    /// What is wrong with it.
    pub reason: String,
}

impl From<InputError> for EngineError {
    fn from(error: InputError) -> EngineError {
        EngineError::InvalidInput(error.to_string())
    }
}
