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

use crate::{EngineError, ImageFormat, ImageInput};

/// Largest accepted image side, to bound decoding work on untrusted input.
pub const MAX_SIDE: usize = 8192;

/// Pool `image` to `grid x grid x 3` features in `[-1, 1]`.
pub fn pooled_features(image: &ImageInput, grid: usize) -> Result<Vec<f32>, EngineError> {
    if grid == 0 {
        return Err(EngineError::InvalidInput(
            "image grid must be at least 1".into(),
        ));
    }
    match image {
        ImageInput::Encoded { format, bytes } => {
            let fmt = match format {
                ImageFormat::Jpeg => image::ImageFormat::Jpeg,
                ImageFormat::Png => image::ImageFormat::Png,
            };
            let mut reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), fmt);
            let mut limits = image::Limits::default();
            limits.max_image_width = Some(MAX_SIDE as u32);
            limits.max_image_height = Some(MAX_SIDE as u32);
            reader.limits(limits);
            let decoded = reader.decode().map_err(|e| {
                EngineError::InvalidInput(format!("cannot decode {format:?} image: {e}"))
            })?;
            let rgb = decoded.to_rgb32f();
            let (w, h) = (rgb.width() as usize, rgb.height() as usize);
            Ok(pool(rgb.as_raw(), h, w, 3, grid))
        }
        ImageInput::RawU8 {
            height,
            width,
            channels,
            data,
        } => {
            check_raw(*height, *width, *channels, data.len())?;
            let values: Vec<f32> = data.iter().map(|&v| f32::from(v) / 255.0).collect();
            Ok(pool(&values, *height, *width, *channels, grid))
        }
        ImageInput::RawF32 {
            height,
            width,
            channels,
            data,
        } => {
            check_raw(*height, *width, *channels, data.len())?;
            if data.iter().any(|v| !v.is_finite()) {
                return Err(EngineError::InvalidInput(
                    "image contains a non-finite value".into(),
                ));
            }
            Ok(pool(data, *height, *width, *channels, grid))
        }
    }
}

fn check_raw(height: usize, width: usize, channels: usize, len: usize) -> Result<(), EngineError> {
    if !matches!(channels, 1 | 3 | 4) {
        return Err(EngineError::InvalidInput(format!(
            "image has {channels} channels; 1, 3 or 4 supported"
        )));
    }
    if height == 0 || width == 0 || height > MAX_SIDE || width > MAX_SIDE {
        return Err(EngineError::InvalidInput(format!(
            "image is {height}x{width}; sides must be 1..={MAX_SIDE}"
        )));
    }
    if len != height * width * channels {
        return Err(EngineError::InvalidInput(format!(
            "image data has {len} values, {height}x{width}x{channels} needs {}",
            height * width * channels
        )));
    }
    Ok(())
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
                .contains("cannot decode")
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
