//! Kairos model engine: flow-matching action heads in Candle.
//!
//! Every model here generates an action chunk of `N` actions of dimension `D` by `K` Euler steps
//! of a learned velocity field, and returns, besides the chunk, the per-step updates
//! `U[k] = dt_k * v_k` that the horizon policy reads (paper §3.1). `noise + Σ_k U[k]` equals the
//! chunk. A request may ask for `S` samples of the same observation; they share the observation
//! encoding and run along the batch dimension.
//!
//! The server talks to models only through [`ActionModel`]; it never sees tensors.

pub mod builtin;
pub mod candle_ops;
mod candle_vjp;
pub mod error;
pub mod flow_head;
pub mod guidance;
pub mod image_features;
pub mod kernels;
pub mod model;
pub mod options;
pub mod pi;
pub mod prefix_encoder;
pub mod profile;
pub mod sampler;
pub mod smolvla;
pub mod weights;

pub use builtin::{default_model, load_model, load_model_with, resolve_model, resolve_model_with};
pub use error::{EngineError, InputError};
pub use image_features::ImageLimits;
pub use kairos_engine_types::ActionChunk;
pub use kairos_engine_types::{ActionRequest, ImageFormat, ImageInput};
pub use kairos_engine_types::{
    ActionSpace, Guidance, GuidanceMode, GuidanceSupport, ModelChunking, PrefixSchedule,
};
pub use kairos_engine_types::{EngineProfile, ProfilePoint};
pub use kernels::Precision;
pub use model::{ActionModel, MAX_SAMPLES, ModelSpec, StagePaths, generate_isolated};
pub use options::{DeviceKind, EngineOptions, Kernels};
