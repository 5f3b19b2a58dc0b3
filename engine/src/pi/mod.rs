//! π0 and π0.5 (Physical Intelligence's flow-matching VLAs), as LeRobot 0.6.1 has them
//! (`policies/pi0/`, `policies/pi05/`, `policies/pi_gemma.py`, ports of openpi's PyTorch code).
//!
//! - [`config`]: `config.json`, the family (`type`), and the sizes read from the tensors.
//! - [`checkpoint`]: the processors (shared with SmolVLA's, plus π's image padding and π0.5's
//!   state prompt); [`pipeline`]: the whole policy behind `ActionModel` ([`PiPipeline`]).
//! - [`model`]: the network on Candle ops ([`PiModel`]): SigLIP + projector ([`vision`]), the
//!   PaliGemma prefix and the Gemma action expert ([`gemma`]), built from [`layers`].
//!
//! - [`fast`]: the same network on the engine's fast CPU kernels ([`FastPiModel`]), in f32 or
//!   with bf16 weight GEMMs.
//!
//! [`PiModel`] runs on any Candle device (the CPU; CUDA with the `cuda` feature);
//! [`FastPiModel`] is the CPU default (`--kernels auto|fast|portable`).

pub mod checkpoint;
pub mod config;
pub mod fast;
pub mod gemma;
pub mod layers;
pub mod model;
pub mod pipeline;
pub mod vars;
pub mod vision;

pub use checkpoint::{PiCheckpoint, PiPrepared};
pub use config::{GemmaDims, PiConfig, PiDims, PiFamily, SiglipDims};
pub use fast::{FastPiModel, FastPrefix, FastSampleInput};
pub use gemma::PrefixCache;
pub use model::{PiModel, PiObservation, SampleInput};
pub use pipeline::PiPipeline;
pub use vision::VisionOutput;
