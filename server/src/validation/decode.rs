//! Image decoding before the queue, on a bounded pool.
//!
//! A checked observation's JPEG and PNG images are decoded to pixels off the async runtime, off
//! the engine threads, and before the round is queued, so a file whose body is corrupt (its
//! header passed [`Validator::submit`](super::Validator::submit)) fails its own round with
//! `invalid_observation` and engines never decode. Waiting rounds queue on the pool's semaphore
//! (no thread each); a permit's holder runs on tokio's blocking pool.

use std::sync::Arc;

use kairos_core::error::RoundError;
use kairos_core::round::{ValidObservation, ValidSubmit};
use kairos_engine::ImageInput;
use kairos_engine::image_features::{self, ImageLimits};
use tokio::sync::Semaphore;

use super::{RequestError, observation_error};

/// Decodes observations' images, at most `slots` at once. One per server
/// ([`ServerContext`](crate::transport::ServerContext)); cheap to clone.
#[derive(Clone, Debug)]
pub struct DecodePool {
    slots: Arc<Semaphore>,
    limits: ImageLimits,
}

impl DecodePool {
    /// A pool decoding at most `slots` observations at once (at least one), each image within
    /// `limits`.
    pub fn new(slots: usize, limits: ImageLimits) -> DecodePool {
        DecodePool {
            slots: Arc::new(Semaphore::new(slots.max(1))),
            limits,
        }
    }

    /// A pool sized to this machine's cores, at most 4: a capped image decodes in tens of
    /// milliseconds, and the engines need the rest.
    pub fn for_this_machine(limits: ImageLimits) -> DecodePool {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        DecodePool::new(cores.clamp(1, 4), limits)
    }

    /// `observation` with its encoded images decoded to pixels (unchanged when it has none).
    pub async fn decode(
        &self,
        mut observation: ValidObservation,
    ) -> Result<ValidObservation, RequestError> {
        if !observation
            .request
            .images
            .iter()
            .any(|i| matches!(i, ImageInput::Encoded { .. }))
        {
            return Ok(observation);
        }
        let limits = self.limits;
        let images = std::mem::take(&mut observation.request.images);
        let _slot = self
            .slots
            .acquire()
            .await
            .map_err(|_| RequestError::Round(RoundError::ShuttingDown))?;
        let decoded = tokio::task::spawn_blocking(move || decode_images(&images, &limits))
            .await
            .map_err(|e| RequestError::internal(format!("image decoding failed: {e}")))??;
        observation.request.images = decoded;
        Ok(observation)
    }

    /// [`DecodePool::decode`] for a round request.
    pub async fn decode_submit(
        &self,
        mut submit: ValidSubmit,
    ) -> Result<ValidSubmit, RequestError> {
        submit.observation = self.decode(submit.observation).await?;
        Ok(submit)
    }
}

/// Decodes an observation's JPEG and PNG images to pixels (raw ones are checked and kept), each
/// within `limits` from its header before any pixel is allocated. Blocking: the server calls it
/// through a [`DecodePool`]; the fuzz targets call it directly.
pub fn decode_images(
    images: &[ImageInput],
    limits: &ImageLimits,
) -> Result<Vec<ImageInput>, RequestError> {
    images
        .iter()
        .enumerate()
        .map(|(i, image)| {
            image_features::decode(image, limits)
                .map_err(|reason| observation_error(format!("observation.images[{i}]"), reason))
        })
        .collect()
}
