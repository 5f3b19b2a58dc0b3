//! Size limits on every field, and the checks that enforce them.
//!
//! A receiver checks a frame's length against [`Limits::max_frame`] before it reads the body, then
//! decodes the message and calls [`Validate::validate`]. Validation covers what the protocol itself
//! defines: sizes, counts, ranks, tensor byte lengths, the state's dtype and rank, finite numbers.
//! Whether an observation fits the served model (state length, image shapes) is the server's
//! check, made against its `ModelInfo`.

use std::collections::HashSet;

use serde::{Deserialize, Serialize};

use super::messages::{
    ChunkingSelection, ChunkingStrategy, EndTask, ErrorCode, ErrorReply, FetchObservation,
    FreshObservation, Hello, HorizonSelection, Image, ImagePayload, LastExecInfo, Observation,
    RemainingHint, Reply, Submit, TaskEnded, Tensor, Welcome,
};
use super::{DType, Message};

/// Size limits. Byte counts are bytes of the encoded field (UTF-8 for text).
///
/// The server sends the limits it enforces in `Welcome`; a client checks its requests against
/// them before sending, so it gets a local error instead of a round trip. Missing keys take the
/// default, so a newer peer may add limits without breaking an older one.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct Limits {
    /// Largest frame body, bytes (the 5-byte header not included).
    pub max_frame: u32,
    /// Largest image payload (encoded file or raw tensor data), bytes.
    pub max_image_bytes: u32,
    /// Most images per observation.
    pub max_images: u32,
    /// Largest instruction, bytes of UTF-8.
    pub max_instruction_bytes: u32,
    /// Longest joint state vector, elements.
    pub max_state_len: u32,
    /// Most horizon-policy parameters.
    pub max_params: u32,
    /// Most samples of the chunk per round.
    pub max_samples: u32,
    /// Highest tensor rank.
    pub max_tensor_rank: u32,
    /// Largest single tensor dimension.
    pub max_tensor_dim: u32,
    /// Longest name: camera, policy, parameter, client, server, robot and model names; bytes.
    pub max_name_bytes: u32,
    /// Longest auth token, bytes.
    pub max_token_bytes: u32,
    /// Longest human-readable error message, bytes.
    pub max_message_bytes: u32,
    /// Most rounds in a `TaskEnded` history.
    pub max_history: u32,
    /// Most pixels (`height * width`) of one camera image, raw or encoded. An encoded image is
    /// checked from its header, before the server decodes it, so a small file that declares a
    /// huge image (a decompression bomb) is refused without allocating its pixels.
    pub max_image_pixels: u32,
}

/// Highest round id a `Submit` may carry: 2^53 − 1. Round ids must increase, so a task whose
/// round reached `u64::MAX` could never send another round; the bound keeps every accepted id
/// followed by room for any realistic task (2^53 rounds at 1 kHz is 285 000 years), and it is
/// the largest integer every JSON and JavaScript consumer of traces represents exactly.
pub const MAX_ROUND: u64 = (1 << 53) - 1;

impl Default for Limits {
    /// Defaults sized for SmolVLA/pi0-class models: two or three cameras of up to 640×480 RGB
    /// sent raw (0.9 MB each as `u8`), a 32-dim state, a 50×32 chunk back. Images may have up to
    /// 16 times the pixels of the 512×512 input of SmolVLA's vision encoder (2048×2048).
    fn default() -> Limits {
        Limits {
            max_frame: 16 << 20,
            max_image_bytes: 4 << 20,
            max_images: 8,
            max_instruction_bytes: 4096,
            max_state_len: 1024,
            max_params: 32,
            max_samples: 16,
            max_tensor_rank: 4,
            max_tensor_dim: 8192,
            max_name_bytes: 128,
            max_token_bytes: 512,
            max_message_bytes: 4096,
            max_history: 4096,
            max_image_pixels: 16 * 512 * 512,
        }
    }
}

/// A field that breaks the protocol's rules. `field` is a path such as
/// `observation.images[1].payload.data`.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ValidationError {
    /// A size, count, rank or dimension is over its limit.
    #[error("{field} is {len}, over the limit of {max}")]
    TooLarge {
        /// Which field.
        field: String,
        /// Its size.
        len: u64,
        /// The limit.
        max: u64,
    },
    /// The observation is malformed (a tensor whose bytes do not match its shape, a state that is
    /// not 1-D `f32`, a duplicate camera).
    #[error("invalid observation: {field}: {reason}")]
    InvalidObservation {
        /// Which field.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Another field is malformed (a non-finite number, zero samples, an empty policy name).
    #[error("invalid request: {field}: {reason}")]
    InvalidRequest {
        /// Which field.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
}

impl ValidationError {
    /// The wire error code for this failure.
    pub fn code(&self) -> ErrorCode {
        match self {
            ValidationError::TooLarge { .. } => ErrorCode::TooLarge,
            ValidationError::InvalidObservation { .. } => ErrorCode::InvalidObservation,
            ValidationError::InvalidRequest { .. } => ErrorCode::InvalidRequest,
        }
    }
}

impl From<&ValidationError> for ErrorReply {
    fn from(error: &ValidationError) -> ErrorReply {
        ErrorReply::new(error.code(), error.to_string())
    }
}

/// Checks a decoded message against [`Limits`].
pub trait Validate {
    /// `Ok` if every field is within `limits` and well formed.
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError>;
}

pub(crate) fn check_size(
    field: impl FnOnce() -> String,
    len: usize,
    max: u32,
) -> Result<(), ValidationError> {
    if len as u64 > u64::from(max) {
        return Err(ValidationError::TooLarge {
            field: field(),
            len: len as u64,
            max: u64::from(max),
        });
    }
    Ok(())
}

pub(crate) fn invalid_request(
    field: impl Into<String>,
    reason: impl Into<String>,
) -> ValidationError {
    ValidationError::InvalidRequest {
        field: field.into(),
        reason: reason.into(),
    }
}

fn invalid_observation(field: impl Into<String>, reason: impl Into<String>) -> ValidationError {
    ValidationError::InvalidObservation {
        field: field.into(),
        reason: reason.into(),
    }
}

/// Rank and dimensions within limits.
fn check_shape(field: &str, shape: &[u32], limits: &Limits) -> Result<(), ValidationError> {
    check_size(
        || format!("{field}.shape (rank)"),
        shape.len(),
        limits.max_tensor_rank,
    )?;
    for (axis, dim) in shape.iter().enumerate() {
        check_size(
            || format!("{field}.shape[{axis}]"),
            *dim as usize,
            limits.max_tensor_dim,
        )?;
    }
    Ok(())
}

/// Rank and dimensions within limits, and `data` exactly `product(shape) × dtype.size()` bytes.
/// A byte-length mismatch is reported through `mismatch`, so each caller picks its error kind.
pub(crate) fn check_tensor(
    field: &str,
    tensor: &Tensor,
    limits: &Limits,
    mismatch: fn(String, String) -> ValidationError,
) -> Result<(), ValidationError> {
    check_shape(field, &tensor.shape, limits)?;
    tensor
        .check_len()
        .map_err(|error| mismatch(format!("{field}.data"), error.to_string()))?;
    Ok(())
}

/// What a raw image's shape and dtype must be, beyond a tensor's: `[height, width, channels]`,
/// `u8` or `f32`, at most `max_image_pixels` pixels.
fn check_image_shape(
    field: &str,
    shape: &[u32],
    dtype: DType,
    limits: &Limits,
) -> Result<(), ValidationError> {
    if shape.len() != 3 {
        return Err(invalid_observation(
            format!("{field}.shape"),
            format!(
                "a raw image is [height, width, channels], got rank {}",
                shape.len()
            ),
        ));
    }
    if !matches!(dtype, DType::U8 | DType::F32) {
        return Err(invalid_observation(
            format!("{field}.dtype"),
            "a raw image is u8 or f32",
        ));
    }
    let pixels = u64::from(shape[0]) * u64::from(shape[1]);
    if pixels > u64::from(limits.max_image_pixels) {
        return Err(ValidationError::TooLarge {
            field: format!("{field}.shape (pixels)"),
            len: pixels,
            max: u64::from(limits.max_image_pixels),
        });
    }
    Ok(())
}

/// Every check [`Validate`] makes of a raw image tensor (`field`) of `shape` and `dtype`, from
/// the shape alone: its byte size against `max_image_bytes`, rank and dimensions, the image
/// layout and pixel count. A reader that builds such a tensor from another layout (the server's
/// openpi endpoint transposes channel-first arrays) runs it before it copies a byte, so an
/// oversized image costs nothing to refuse.
pub fn check_raw_image(
    field: &str,
    shape: &[u32],
    dtype: DType,
    limits: &Limits,
) -> Result<(), ValidationError> {
    let bytes = shape
        .iter()
        .try_fold(dtype.size() as u64, |bytes, &dim| {
            bytes.checked_mul(u64::from(dim))
        })
        .unwrap_or(u64::MAX);
    if bytes > u64::from(limits.max_image_bytes) {
        return Err(ValidationError::TooLarge {
            field: format!("{field}.data"),
            len: bytes,
            max: u64::from(limits.max_image_bytes),
        });
    }
    check_shape(field, shape, limits)?;
    check_image_shape(field, shape, dtype, limits)
}

pub(crate) fn check_name(field: &str, name: &str, limits: &Limits) -> Result<(), ValidationError> {
    check_size(|| field.to_owned(), name.len(), limits.max_name_bytes)
}

fn check_image(field: &str, image: &Image, limits: &Limits) -> Result<(), ValidationError> {
    check_name(&format!("{field}.camera"), &image.camera, limits)?;
    match &image.payload {
        ImagePayload::Jpeg { data } | ImagePayload::Png { data } => {
            check_size(
                || format!("{field}.payload.data"),
                data.len(),
                limits.max_image_bytes,
            )?;
            if data.is_empty() {
                return Err(invalid_observation(
                    format!("{field}.payload.data"),
                    "empty image file",
                ));
            }
        }
        ImagePayload::Raw { tensor } => {
            let field = format!("{field}.payload.tensor");
            check_size(
                || format!("{field}.data"),
                tensor.data.len(),
                limits.max_image_bytes,
            )?;
            check_tensor(&field, tensor, limits, invalid_observation)?;
            check_image_shape(&field, &tensor.shape, tensor.dtype, limits)?;
        }
    }
    Ok(())
}

impl Validate for Observation {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_tensor(
            "observation.state",
            &self.state,
            limits,
            invalid_observation,
        )?;
        if self.state.dtype != DType::F32 || self.state.shape.len() != 1 {
            return Err(invalid_observation(
                "observation.state",
                format!(
                    "the state is a 1-D f32 vector, got {:?} with shape {:?}",
                    self.state.dtype, self.state.shape
                ),
            ));
        }
        check_size(
            || "observation.state.shape[0]".to_owned(),
            self.state.shape[0] as usize,
            limits.max_state_len,
        )?;
        check_size(
            || "observation.images (count)".to_owned(),
            self.images.len(),
            limits.max_images,
        )?;
        let mut cameras = HashSet::with_capacity(self.images.len());
        for (index, image) in self.images.iter().enumerate() {
            let field = format!("observation.images[{index}]");
            check_image(&field, image, limits)?;
            if !cameras.insert(image.camera.as_str()) {
                return Err(invalid_observation(
                    format!("{field}.camera"),
                    format!("camera {:?} appears twice", image.camera),
                ));
            }
        }
        check_size(
            || "observation.instruction".to_owned(),
            self.instruction.len(),
            limits.max_instruction_bytes,
        )?;
        Ok(())
    }
}

impl Validate for LastExecInfo {
    fn validate(&self, _limits: &Limits) -> Result<(), ValidationError> {
        if !(self.control_hz.is_finite() && self.control_hz > 0.0) {
            return Err(invalid_request(
                "last_exec.control_hz",
                format!("must be a positive finite number, got {}", self.control_hz),
            ));
        }
        Ok(())
    }
}

impl Validate for HorizonSelection {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        if self.policy.is_empty() {
            return Err(invalid_request("horizon.policy", "empty policy name"));
        }
        check_name("horizon.policy", &self.policy, limits)?;
        check_size(
            || "horizon.params (count)".to_owned(),
            self.params.len(),
            limits.max_params,
        )?;
        for (name, value) in &self.params {
            check_name(&format!("horizon.params[{name:?}] (name)"), name, limits)?;
            if !value.is_finite() {
                return Err(invalid_request(
                    format!("horizon.params[{name:?}]"),
                    format!("must be finite, got {value}"),
                ));
            }
        }
        if self.samples == 0 {
            return Err(invalid_request("horizon.samples", "must be at least 1"));
        }
        check_size(
            || "horizon.samples".to_owned(),
            self.samples as usize,
            limits.max_samples,
        )?;
        Ok(())
    }
}

impl Validate for ChunkingSelection {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        if let Some(weight) = self.max_guidance_weight
            && !(weight.is_finite() && weight > 0.0)
        {
            return Err(invalid_request(
                "chunking.max_guidance_weight",
                format!("must be a positive finite number, got {weight}"),
            ));
        }
        if self.execution_horizon == Some(0) {
            return Err(invalid_request(
                "chunking.execution_horizon",
                "must be at least 1",
            ));
        }
        let Some(forecast) = &self.forecast else {
            return Ok(());
        };
        if self.strategy != ChunkingStrategy::ArrivalState {
            return Err(invalid_request(
                "chunking.forecast",
                format!(
                    "a state forecast is for `arrival_state`, not `{}`",
                    self.strategy
                ),
            ));
        }
        check_tensor("chunking.forecast", forecast, limits, invalid_request)?;
        if forecast.dtype != DType::F32 || forecast.shape.len() != 2 || forecast.shape[0] == 0 {
            return Err(invalid_request(
                "chunking.forecast",
                format!(
                    "a forecast is f32 [M >= 1, state_dim], got {:?} with shape {:?}",
                    forecast.dtype, forecast.shape
                ),
            ));
        }
        check_size(
            || "chunking.forecast.shape[1]".to_owned(),
            forecast.shape[1] as usize,
            limits.max_state_len,
        )?;
        if let Some(at) = forecast
            .data
            .chunks_exact(4)
            .position(|b| !f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite())
        {
            return Err(invalid_request(
                format!("chunking.forecast[{at}]"),
                "not a finite number",
            ));
        }
        Ok(())
    }
}

impl Validate for RemainingHint {
    fn validate(&self, _limits: &Limits) -> Result<(), ValidationError> {
        if let Some(seconds) = self.seconds
            && !(seconds.is_finite() && seconds >= 0.0)
        {
            return Err(invalid_request(
                "remaining.seconds",
                format!("must be a non-negative finite number, got {seconds}"),
            ));
        }
        Ok(())
    }
}

impl Validate for Hello {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_size(
            || "token".to_owned(),
            self.token.len(),
            limits.max_token_bytes,
        )?;
        check_name("client", &self.client, limits)
    }
}

impl Validate for Welcome {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_name("server", &self.server, limits)?;
        check_name("robot", &self.robot, limits)?;
        check_name("model.name", &self.model.name, limits)
    }
}

impl Validate for Submit {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        if self.round > MAX_ROUND {
            return Err(invalid_request(
                "round",
                format!("{} is over the highest round id {MAX_ROUND}", self.round),
            ));
        }
        self.observation.validate(limits)?;
        if let Some(last_exec) = &self.last_exec {
            last_exec.validate(limits)?;
        }
        if let Some(hz) = self.control_hz
            && !(hz.is_finite() && hz > 0.0)
        {
            return Err(invalid_request(
                "control_hz",
                format!("must be a positive finite number, got {hz}"),
            ));
        }
        if let Some(horizon) = &self.horizon {
            horizon.validate(limits)?;
        }
        if let Some(remaining) = &self.remaining {
            remaining.validate(limits)?;
        }
        if let Some(chunking) = &self.chunking {
            chunking.validate(limits)?;
        }
        Ok(())
    }
}

impl Validate for FetchObservation {
    fn validate(&self, _limits: &Limits) -> Result<(), ValidationError> {
        Ok(())
    }
}

impl Validate for FreshObservation {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        self.observation.validate(limits)
    }
}

impl Validate for Reply {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_tensor("actions", &self.actions, limits, invalid_request)?;
        if self.actions.dtype != DType::F32 || self.actions.shape.len() != 2 {
            return Err(invalid_request(
                "actions",
                format!(
                    "actions are f32 [H, D], got {:?} with shape {:?}",
                    self.actions.dtype, self.actions.shape
                ),
            ));
        }
        if self.actions.shape[0] != self.horizon {
            return Err(invalid_request(
                "actions.shape[0]",
                format!(
                    "{} rows for horizon {}",
                    self.actions.shape[0], self.horizon
                ),
            ));
        }
        if self.horizon > self.chunk_len {
            return Err(invalid_request(
                "horizon",
                format!(
                    "horizon {} exceeds chunk length {}",
                    self.horizon, self.chunk_len
                ),
            ));
        }
        if let Some(chunking) = &self.chunking {
            check_name("chunking", chunking, limits)?;
        }
        check_name("policy", &self.policy, limits)
    }
}

impl Validate for EndTask {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        if let Some(last_exec) = &self.last_exec {
            last_exec.validate(limits)?;
        }
        Ok(())
    }
}

impl Validate for TaskEnded {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_size(
            || "history (count)".to_owned(),
            self.history.len(),
            limits.max_history,
        )
    }
}

impl Validate for ErrorReply {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        check_size(
            || "message".to_owned(),
            self.message.len(),
            limits.max_message_bytes,
        )
    }
}

impl Validate for Message {
    fn validate(&self, limits: &Limits) -> Result<(), ValidationError> {
        match self {
            Message::Hello(message) => message.validate(limits),
            Message::Welcome(message) => message.validate(limits),
            Message::Submit(message) => message.validate(limits),
            Message::FetchObservation(message) => message.validate(limits),
            Message::FreshObservation(message) => message.validate(limits),
            Message::Reply(message) => message.validate(limits),
            Message::EndTask(message) => message.validate(limits),
            Message::TaskEnded(message) => message.validate(limits),
            Message::Error(message) => message.validate(limits),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{Image, ImagePayload, Observation, Tensor};

    /// An observation with one raw image of `shape` and `dtype` (zeros).
    fn with_image(shape: &[u32], dtype: DType) -> Observation {
        let len = shape.iter().map(|&d| d as usize).product::<usize>() * dtype.size();
        Observation {
            captured_at_us: 0,
            state: Tensor::from_f32(vec![1], &[0.0]).unwrap(),
            images: vec![Image {
                camera: "cam".into(),
                payload: ImagePayload::Raw {
                    tensor: Tensor {
                        dtype,
                        shape: shape.to_vec(),
                        data: vec![0; len],
                    },
                },
            }],
            instruction: String::new(),
        }
    }

    #[test]
    fn the_raw_image_check_from_the_shape_agrees_with_validation() {
        let limits = Limits {
            max_image_bytes: 4096,
            max_image_pixels: 600,
            max_tensor_dim: 100,
            ..Limits::default()
        };
        let shapes: [&[u32]; 9] = [
            &[16, 16, 3],
            &[20, 20, 3],
            &[30, 30, 1],
            &[24, 25, 1],
            &[101, 1, 1],
            &[8, 8],
            &[4, 4, 3, 1],
            &[0, 4, 3],
            &[1, 1, 5000],
        ];
        for shape in shapes {
            for dtype in [DType::U8, DType::F32, DType::F16] {
                let from_shape = check_raw_image(
                    "observation.images[0].payload.tensor",
                    shape,
                    dtype,
                    &limits,
                );
                let validated = with_image(shape, dtype).validate(&limits);
                assert_eq!(
                    from_shape.is_ok(),
                    validated.is_ok(),
                    "{shape:?} {dtype:?}: {from_shape:?} vs {validated:?}"
                );
                if let (Err(a), Err(b)) = (&from_shape, &validated) {
                    assert_eq!(a.code(), b.code(), "{shape:?} {dtype:?}");
                }
            }
        }
        // A shape whose byte size overflows is refused, not wrapped.
        assert!(matches!(
            check_raw_image("x", &[u32::MAX, u32::MAX, u32::MAX], DType::F32, &limits),
            Err(ValidationError::TooLarge { len: u64::MAX, .. })
        ));
    }
}
