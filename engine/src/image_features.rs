//! Camera images to the fixed-size feature vectors the flow head reads.
//!
//! Every [`ImageInput`] (JPEG, PNG, raw `u8` or raw `f32` pixels) becomes an RGB image with
//! values in `[0, 1]` (grey is replicated to three channels, alpha is dropped), which is then
//! average-pooled over a fixed `grid x grid` partition and mapped to `[-1, 1]`
//! (`2 * mean - 1`, SigLIP's input range). The result, `[grid][grid][3]` row-major, does not
//! depend on the image size, so cameras of any resolution feed the same model.
//!
//! Cell `(i, j)` covers rows `[floor(i H / g), floor((i+1) H / g))` and the analogous columns,
//! widened to at least one pixel when the image is smaller than the grid.

use image::ImageDecoder;

use crate::{EngineError, ImageFormat, ImageInput};

/// Largest accepted image side, to bound decoding work on untrusted input.
pub const MAX_SIDE: usize = 8192;

/// Most pixels of one image the engine decodes at all: 64 times the 512 x 512 input of SmolVLA's
/// vision encoder (4096 x 4096, 48 MiB as RGB). A server sets a lower cap per deployment (the
/// protocol's `max_image_pixels`, checked before a round is queued); this one bounds direct
/// callers of the engine. An 8192 x 8192 decompression bomb is refused from its header.
pub const MAX_PIXELS: usize = 64 * 512 * 512;

/// Bounds on the images a request may carry. They are checked against the image's header (or a
/// raw image's shape) before a single pixel is decoded or allocated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageLimits {
    /// Longest side, pixels.
    pub max_side: usize,
    /// Most pixels (`height * width`).
    pub max_pixels: usize,
}

impl Default for ImageLimits {
    fn default() -> Self {
        ImageLimits {
            max_side: MAX_SIDE,
            max_pixels: MAX_PIXELS,
        }
    }
}

/// An image's size as its header or shape declares it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageSize {
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
}

impl ImageLimits {
    fn check(&self, size: ImageSize) -> Result<(), String> {
        let ImageSize { height, width } = size;
        if height == 0 || width == 0 {
            return Err(format!("image is {height}x{width}; an image has pixels"));
        }
        if height > self.max_side || width > self.max_side {
            return Err(format!(
                "image is {height}x{width}; sides must be at most {}",
                self.max_side
            ));
        }
        if height.saturating_mul(width) > self.max_pixels {
            return Err(format!(
                "image is {height}x{width} = {} pixels, over the limit of {}",
                height.saturating_mul(width),
                self.max_pixels
            ));
        }
        Ok(())
    }
}

/// Checks everything about `image` that the engine would refuse, without decoding pixels: an
/// encoded file's header (format, declared size) and a raw image's shape, length and values.
/// Returns the declared size. The error is the reason, for the caller to attach to a field.
pub fn check_image(image: &ImageInput, limits: &ImageLimits) -> Result<ImageSize, String> {
    match image {
        ImageInput::Encoded { format, bytes } => {
            let decoder = header(*format, bytes, limits)?;
            Ok(decoder_size(&decoder))
        }
        ImageInput::RawU8 {
            height,
            width,
            channels,
            data,
        } => check_raw(*height, *width, *channels, data.len(), limits),
        ImageInput::RawF32 {
            height,
            width,
            channels,
            data,
        } => {
            let size = check_raw(*height, *width, *channels, data.len(), limits)?;
            if let Some(at) = data.iter().position(|v| !v.is_finite()) {
                return Err(format!(
                    "image contains a non-finite value ({} at index {at})",
                    data[at]
                ));
            }
            Ok(size)
        }
    }
}

/// Decodes an encoded image to 8-bit RGB, `[height][width][3]`, after checking its header
/// against `limits`: a file that declares too many pixels is refused before any pixel buffer
/// is allocated. Raw images are returned unchanged (after [`check_image`]).
pub fn decode(image: &ImageInput, limits: &ImageLimits) -> Result<ImageInput, String> {
    let ImageInput::Encoded { format, bytes } = image else {
        check_image(image, limits)?;
        return Ok(image.clone());
    };
    let decoder = header(*format, bytes, limits)?;
    let ImageSize { height, width } = decoder_size(&decoder);
    let decoded = image::DynamicImage::from_decoder(decoder)
        .map_err(|e| format!("cannot decode {format:?} image: {e}"))?;
    let rgb = decoded.into_rgb8();
    Ok(ImageInput::RawU8 {
        height,
        width,
        channels: 3,
        data: rgb.into_raw(),
    })
}

/// A decoder that has read only the file's header, with the declared size within `limits` and
/// the decoder's own allocation limit set to what that size needs.
fn header<'a>(
    format: ImageFormat,
    bytes: &'a [u8],
    limits: &ImageLimits,
) -> Result<impl ImageDecoder + 'a, String> {
    let fmt = match format {
        ImageFormat::Jpeg => image::ImageFormat::Jpeg,
        ImageFormat::Png => image::ImageFormat::Png,
    };
    let reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), fmt);
    let mut decoder = reader
        .into_decoder()
        .map_err(|e| format!("not a readable {format:?} file: {e}"))?;
    limits.check(decoder_size(&decoder))?;
    // The declared size is within the limits; hold the decoder to what that size needs (16-bit
    // RGBA is the widest output of the two codecs), so a lying header cannot make it allocate
    // more.
    let mut decoder_limits = image::Limits::default();
    decoder_limits.max_alloc = Some(limits.max_pixels as u64 * 8);
    decoder
        .set_limits(decoder_limits)
        .map_err(|e| format!("cannot decode {format:?} image: {e}"))?;
    Ok(decoder)
}

fn decoder_size(decoder: &impl ImageDecoder) -> ImageSize {
    let (width, height) = decoder.dimensions();
    ImageSize {
        height: height as usize,
        width: width as usize,
    }
}

/// Pool `image` to `grid x grid x 3` features in `[-1, 1]`, within the default [`ImageLimits`].
pub fn pooled_features(image: &ImageInput, grid: usize) -> Result<Vec<f32>, EngineError> {
    if grid == 0 {
        return Err(EngineError::InvalidInput(
            "image grid must be at least 1".into(),
        ));
    }
    let limits = ImageLimits::default();
    let invalid = |reason: String| EngineError::InvalidInput(reason);
    let decoded;
    let image = match image {
        ImageInput::Encoded { .. } => {
            decoded = decode(image, &limits).map_err(invalid)?;
            &decoded
        }
        raw => {
            check_image(raw, &limits).map_err(invalid)?;
            raw
        }
    };
    match image {
        ImageInput::RawU8 {
            height,
            width,
            channels,
            data,
        } => {
            let values: Vec<f32> = data.iter().map(|&v| f32::from(v) / 255.0).collect();
            Ok(pool(&values, *height, *width, *channels, grid))
        }
        ImageInput::RawF32 {
            height,
            width,
            channels,
            data,
        } => Ok(pool(data, *height, *width, *channels, grid)),
        ImageInput::Encoded { .. } => Err(EngineError::InvalidInput(
            "an image was still encoded after decoding".into(),
        )),
    }
}

fn check_raw(
    height: usize,
    width: usize,
    channels: usize,
    len: usize,
    limits: &ImageLimits,
) -> Result<ImageSize, String> {
    if !matches!(channels, 1 | 3 | 4) {
        return Err(format!(
            "image has {channels} channels; 1, 3 or 4 supported"
        ));
    }
    let size = ImageSize { height, width };
    limits.check(size)?;
    if len != height * width * channels {
        return Err(format!(
            "image data has {len} values, {height}x{width}x{channels} needs {}",
            height * width * channels
        ));
    }
    Ok(size)
}

/// Average-pool `[h][w][c]` pixels (c = 1, 3 or 4) to `[grid][grid][3]`, mapped to `[-1, 1]`.
fn pool(pixels: &[f32], h: usize, w: usize, c: usize, grid: usize) -> Vec<f32> {
    let bounds = |i: usize, side: usize| {
        let start = (i * side / grid).min(side - 1);
        let end = ((i + 1) * side / grid).max(start + 1).min(side);
        (start, end)
    };
    let mut out = Vec::with_capacity(grid * grid * 3);
    for gi in 0..grid {
        let (r0, r1) = bounds(gi, h);
        for gj in 0..grid {
            let (c0, c1) = bounds(gj, w);
            let mut sum = [0.0f64; 3];
            for r in r0..r1 {
                for col in c0..c1 {
                    let px = &pixels[(r * w + col) * c..(r * w + col) * c + c];
                    let rgb = if c == 1 {
                        [px[0]; 3]
                    } else {
                        [px[0], px[1], px[2]]
                    };
                    for (s, v) in sum.iter_mut().zip(rgb) {
                        *s += f64::from(v);
                    }
                }
            }
            let n = ((r1 - r0) * (c1 - c0)) as f64;
            out.extend(sum.iter().map(|s| (2.0 * s / n - 1.0) as f32));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4x6 RGB image: left half red, right half blue, bottom row green.
    fn quadrants() -> Vec<u8> {
        let mut data = Vec::new();
        for r in 0..4 {
            for c in 0..6 {
                let px = if r == 3 {
                    [0, 255, 0]
                } else if c < 3 {
                    [255, 0, 0]
                } else {
                    [0, 0, 255]
                };
                data.extend_from_slice(&px);
            }
        }
        data
    }

    fn encode(format: image::ImageFormat) -> Vec<u8> {
        let img = image::RgbImage::from_raw(6, 4, quadrants()).unwrap();
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, format).unwrap();
        bytes.into_inner()
    }

    #[test]
    fn raw_u8_pools_cells() {
        let img = ImageInput::RawU8 {
            height: 4,
            width: 6,
            channels: 3,
            data: quadrants(),
        };
        let f = pooled_features(&img, 2).unwrap();
        // Cell (0,0): rows 0-1, cols 0-2: pure red.
        assert_eq!(&f[0..3], &[1.0, -1.0, -1.0]);
        // Cell (1,1): rows 2-3, cols 3-5: half blue, half green.
        assert_eq!(&f[9..12], &[-1.0, 0.0, 0.0]);
        assert_eq!(pooled_features(&img, 1).unwrap().len(), 3);
    }

    #[test]
    fn png_decodes_to_the_same_features_as_raw() {
        let raw = pooled_features(
            &ImageInput::RawU8 {
                height: 4,
                width: 6,
                channels: 3,
                data: quadrants(),
            },
            2,
        )
        .unwrap();
        let png = pooled_features(
            &ImageInput::Encoded {
                format: ImageFormat::Png,
                bytes: encode(image::ImageFormat::Png),
            },
            2,
        )
        .unwrap();
        assert_eq!(raw, png);
    }

    #[test]
    fn jpeg_decodes_close_to_raw() {
        let raw = pooled_features(
            &ImageInput::RawU8 {
                height: 4,
                width: 6,
                channels: 3,
                data: quadrants(),
            },
            2,
        )
        .unwrap();
        let jpg = pooled_features(
            &ImageInput::Encoded {
                format: ImageFormat::Jpeg,
                bytes: encode(image::ImageFormat::Jpeg),
            },
            2,
        )
        .unwrap();
        // Lossy, chroma-subsampled: close, not equal.
        assert!(
            raw.iter().zip(&jpg).all(|(a, b)| (a - b).abs() < 0.35),
            "{raw:?} vs {jpg:?}"
        );
        assert_ne!(raw, jpg);
    }

    #[test]
    fn grey_f32_and_alpha_inputs() {
        let grey = ImageInput::RawF32 {
            height: 2,
            width: 2,
            channels: 1,
            data: vec![0.0, 1.0, 0.5, 0.5],
        };
        assert_eq!(pooled_features(&grey, 1).unwrap(), vec![0.0, 0.0, 0.0]);
        let rgba = ImageInput::RawU8 {
            height: 1,
            width: 1,
            channels: 4,
            data: vec![255, 0, 255, 7],
        };
        assert_eq!(pooled_features(&rgba, 3).unwrap().len(), 27);
        assert_eq!(&pooled_features(&rgba, 3).unwrap()[..3], &[1.0, -1.0, 1.0]);
    }

    #[test]
    fn sizes_are_checked_from_the_header_before_decoding() {
        let png = ImageInput::Encoded {
            format: ImageFormat::Png,
            bytes: encode(image::ImageFormat::Png),
        };
        let roomy = ImageLimits::default();
        assert_eq!(
            check_image(&png, &roomy),
            Ok(ImageSize {
                height: 4,
                width: 6
            })
        );
        // 24 pixels against a cap of 23: refused by the header alone, before any pixel buffer
        // exists, with the same answer from the check and the decoder.
        let tight = ImageLimits {
            max_side: 8,
            max_pixels: 23,
        };
        let refusal = check_image(&png, &tight).unwrap_err();
        assert!(
            refusal.contains("4x6 = 24 pixels, over the limit of 23"),
            "{refusal}"
        );
        assert_eq!(decode(&png, &tight).unwrap_err(), refusal);
        let narrow = ImageLimits {
            max_side: 5,
            max_pixels: 100,
        };
        assert!(
            check_image(&png, &narrow)
                .unwrap_err()
                .contains("at most 5")
        );
        // Decoding within the limits gives the raw pixels.
        assert_eq!(
            decode(&png, &roomy).unwrap(),
            ImageInput::RawU8 {
                height: 4,
                width: 6,
                channels: 3,
                data: quadrants()
            }
        );
    }

    #[test]
    fn a_file_that_is_not_what_it_claims_is_refused_by_the_check() {
        let mislabelled = ImageInput::Encoded {
            format: ImageFormat::Jpeg,
            bytes: encode(image::ImageFormat::Png),
        };
        let refusal = check_image(&mislabelled, &ImageLimits::default()).unwrap_err();
        assert!(refusal.contains("not a readable Jpeg file"), "{refusal}");
        let empty = ImageInput::RawU8 {
            height: 0,
            width: 3,
            channels: 3,
            data: Vec::new(),
        };
        assert!(check_image(&empty, &ImageLimits::default()).is_err());
    }

    #[test]
    fn bad_images_are_clear_errors() {
        let short = ImageInput::RawU8 {
            height: 4,
            width: 6,
            channels: 3,
            data: vec![0; 10],
        };
        assert!(
            pooled_features(&short, 2)
                .unwrap_err()
                .to_string()
                .contains("4x6x3 needs 72")
        );
        let channels = ImageInput::RawU8 {
            height: 1,
            width: 1,
            channels: 2,
            data: vec![0; 2],
        };
        assert!(pooled_features(&channels, 2).is_err());
        let garbage = ImageInput::Encoded {
            format: ImageFormat::Jpeg,
            bytes: vec![1, 2, 3],
        };
        assert!(
            pooled_features(&garbage, 2)
                .unwrap_err()
                .to_string()
                .contains("not a readable Jpeg file")
        );
        let nan = ImageInput::RawF32 {
            height: 1,
            width: 1,
            channels: 1,
            data: vec![f32::NAN],
        };
        assert!(pooled_features(&nan, 2).is_err());
    }
}
