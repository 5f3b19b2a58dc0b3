//! The data that crosses the engine boundary, without the engine.
//!
//! The scheduler batches by an [`EngineProfile`], horizon policies read an [`ActionChunk`], and
//! the driver holds [`ActionRequest`]s until their batch runs. None of them needs a tensor, so
//! they live here, apart from Candle: `kairos-core` depends on this crate, never on
//! `kairos-engine`, and `kairos-engine` re-exports every type.

pub mod chunk;
pub mod guidance;
pub mod profile;
pub mod request;

pub use chunk::ActionChunk;
pub use guidance::{
    ActionSpace, Guidance, GuidanceMode, GuidanceSupport, ModelChunking, PrefixSchedule,
};
pub use profile::{DEFAULT_MIN_GAIN, EngineProfile, ProfilePoint, saturation_batch};
pub use request::{ActionRequest, ImageFormat, ImageInput};
