//! What a model is asked: one observation per request.

/// Encodings the engine can decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// JPEG bytes.
    Jpeg,
    /// PNG bytes.
    Png,
}

/// One camera image of an observation.
#[derive(Clone, Debug, PartialEq)]
pub enum ImageInput {
    /// Compressed bytes, decoded on the engine thread.
    Encoded {
        /// The codec.
        format: ImageFormat,
        /// The file bytes.
        bytes: Vec<u8>,
    },
    /// Raw 8-bit pixels, `[height][width][channels]`.
    RawU8 {
        /// Rows.
        height: usize,
        /// Columns.
        width: usize,
        /// 1 (grey), 3 (RGB) or 4 (RGBA).
        channels: usize,
        /// `height * width * channels` bytes.
        data: Vec<u8>,
    },
    /// Raw float pixels in `[0, 1]`, `[height][width][channels]`.
    RawF32 {
        /// Rows.
        height: usize,
        /// Columns.
        width: usize,
        /// 1, 3 or 4.
        channels: usize,
        /// `height * width * channels` values.
        data: Vec<f32>,
    },
}

/// One observation to generate a chunk for.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionRequest {
    /// Robot state vector, `ModelSpec::state_dim` long.
    pub state: Vec<f32>,
    /// Camera images, at most `ModelSpec::max_images`.
    pub images: Vec<ImageInput>,
    /// What the robot calls each image's camera, parallel to `images`, or empty: the images
    /// are then the model's cameras in order. A model with [`ModelSpec::cameras`] matches
    /// named images to its cameras by name; other models ignore the names.
    pub cameras: Vec<String>,
    /// The task instruction (models without a language backbone may ignore it).
    pub instruction: String,
    /// Samples `S` to draw for this observation (1 = the usual single chunk).
    pub samples: usize,
    /// Seed of the initial noise, so a retried round reproduces its chunk.
    pub seed: u64,
    /// Guidance toward the actions the robot committed to while this request is in flight
    /// (real-time chunking, inpainting); `None`: plain sampling. It applies to this request's
    /// rows only: the other requests of the batch get what they would get alone.
    pub guidance: Option<crate::Guidance>,
}
