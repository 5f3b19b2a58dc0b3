//! SmolVLA, as LeRobot 0.6.1 has it (`policies/smolvla/`): a VLM that turns images, the task
//! and the state into a prefix key/value cache, and an action expert that denoises a chunk of
//! actions against it.
//!
//! - [`vlm`]: SmolVLM's SigLIP vision tower and connector, and its SmolLM2 text layers over the
//!   prefix ([`SmolVlaVlm`] -> [`PrefixKv`]).
//! - [`expert`]: the action expert and its Euler loop ([`SmolVlaExpert`]: [`PrefixKv`] ->
//!   actions), on the engine's CPU kernels or in Candle.
//! - Shared by both: the checkpoint's configs ([`config`]), its `Linear` and Llama-layer weights
//!   ([`linear`], [`llama_layer`]; on a Candle device through `candle_weights`), and the prefix
//!   cache between them ([`prefix`]).
//! - The policy around them: the processors ([`processors`], [`tokenize`], [`images`],
//!   [`checkpoint`]), the whole pipeline ([`pipeline`]), and the expert served with a stand-in
//!   prefix ([`serving`]).
//! - A seeded random checkpoint folder of any SmolVLA shape, `smolvla_base`'s included
//!   ([`random_checkpoint`]).

mod candle_weights;
pub mod checkpoint;
pub mod config;
pub mod expert;
pub mod images;
pub mod linear;
pub mod llama_layer;
pub mod pipeline;
pub mod prefix;
pub mod processors;
pub mod random_checkpoint;
pub mod serving;
pub mod tokenize;
pub mod vlm;

pub use checkpoint::{Observation, PreparedObservation, SmolVlaCheckpoint};
pub use config::{ExpertDims, LayerKind, SmolVlaConfig, VlmConfig, VlmTextConfig, VlmVisionConfig};
pub use expert::{CudaGraphStats, ExpertInput, ExpertSample, ExpertWeights, SmolVlaExpert};
pub use pipeline::SmolVlaPipeline;
pub use prefix::PrefixKv;
pub use vlm::vision::{VisionImage, VisionOutput};
pub use vlm::weights::VlmWeights;
pub use vlm::{PrefixEmbeddings, SmolVlaVlm, VlmObservation};
