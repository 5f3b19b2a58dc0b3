//! Camera images the way LeRobot 0.6.1's SmolVLA prepares them (`prepare_images` and
//! `policies/common/vla_utils.resize_with_pad`), in `f32` like LeRobot:
//!
//! 1. decode (JPEG/PNG, sizes checked from the header, [`crate::image_features::decode`]) and
//!    scale `u8` to `[0, 1]` (`v / 255`), as `[3][H][W]` (grey replicated, alpha dropped);
//! 2. resize without distortion to the configured size: ratio `max(W / w, H / h)`, new size
//!    `int(H / ratio) x int(W / ratio)`, PyTorch's bilinear `F.interpolate` with
//!    `align_corners=False` and no antialias; then pad with `0` on the **left and top**;
//! 3. `x * 2 - 1` (SigLIP's range).
//!
//! A missing camera becomes an all-`-1` image with a false mask, for at most `empty_cameras`
//! missing cameras (LeRobot drops the rest).

use crate::image_features::{ImageLimits, decode};
use crate::{EngineError, ImageInput};

/// Read a PNG or JPEG file (recognised by its first bytes) as an encoded [`ImageInput`];
/// decoding, with its size checks, happens in [`to_chw_unit`].
pub fn image_file(path: &std::path::Path) -> Result<ImageInput, EngineError> {
    let bytes = std::fs::read(path).map_err(|e| EngineError::Load {
        path: path.display().to_string(),
        reason: e.to_string(),
    })?;
    let format = if bytes.starts_with(&[0x89, b'P', b'N', b'G']) {
        crate::ImageFormat::Png
    } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        crate::ImageFormat::Jpeg
    } else {
        return Err(EngineError::Load {
            path: path.display().to_string(),
            reason: "not a PNG or JPEG file".into(),
        });
    };
    Ok(ImageInput::Encoded { format, bytes })
}

/// One camera after preprocessing: `[3][height][width]` values in `[-1, 1]`.
#[derive(Clone, Debug, PartialEq)]
pub struct PreparedImage {
    /// Pixels, channel planes of `height * width`.
    pub pixels: Vec<f32>,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// `false` for an empty camera (LeRobot's image mask): its tokens are padding.
    pub present: bool,
}

/// An image as `[3][H][W]` `f32` in `[0, 1]` (LeRobot's observation layout), after decoding
/// within `limits`. `field` names the image in errors.
pub fn to_chw_unit(
    image: &ImageInput,
    limits: &ImageLimits,
    field: &str,
) -> Result<(Vec<f32>, usize, usize), EngineError> {
    let bad = |reason: String| EngineError::InvalidInput(format!("{field}: {reason}"));
    let decoded = decode(image, limits).map_err(bad)?;
    let (h, w, c, values): (usize, usize, usize, Vec<f32>) = match decoded {
        ImageInput::RawU8 {
            height,
            width,
            channels,
            data,
        } => (
            height,
            width,
            channels,
            data.iter().map(|&v| f32::from(v) / 255.0).collect(),
        ),
        ImageInput::RawF32 {
            height,
            width,
            channels,
            data,
        } => (height, width, channels, data),
        ImageInput::Encoded { .. } => {
            return Err(bad("image was still encoded after decoding".into()));
        }
    };
    let plane = h * w;
    let mut chw = vec![0.0f32; 3 * plane];
    for p in 0..plane {
        for ch in 0..3 {
            // Grey: every channel reads channel 0; RGBA: alpha is never read.
            let src = if c == 1 { 0 } else { ch };
            chw[ch * plane + p] = values[p * c + src];
        }
    }
    Ok((chw, h, w))
}

/// LeRobot's `resize_with_pad(img, height, width, pad_value)` for one `[c][h][w]` image:
/// bilinear resize keeping the aspect ratio, then `pad_value` on the left and top.
pub fn resize_with_pad(
    chw: &[f32],
    c: usize,
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
    pad_value: f32,
) -> Vec<f32> {
    if h == out_h && w == out_w {
        return chw.to_vec();
    }
    // Python: ratio = max(w / W, h / H) in float64; int() truncates.
    let ratio = f64::max(w as f64 / out_w as f64, h as f64 / out_h as f64);
    let rh = ((h as f64 / ratio) as usize).max(1);
    let rw = ((w as f64 / ratio) as usize).max(1);
    let resized = interpolate_bilinear(chw, c, h, w, rh, rw);
    let pad_h = out_h.saturating_sub(rh);
    let pad_w = out_w.saturating_sub(rw);
    let mut out = vec![pad_value; c * out_h * out_w];
    for ch in 0..c {
        for y in 0..rh.min(out_h) {
            let src = &resized[(ch * rh + y) * rw..(ch * rh + y) * rw + rw.min(out_w)];
            let at = (ch * out_h + pad_h + y) * out_w + pad_w;
            out[at..at + src.len()].copy_from_slice(src);
        }
    }
    out
}

/// Source indices and weights of one output axis, as PyTorch's `compute_indices_weights_linear`
/// (`align_corners=False`): `src = max(0, (in/out) * (i + 0.5) - 0.5)` in `f32`,
/// `i0 = min(floor(src), in - 1)`, `i1 = i0 + (i0 < in - 1)`, `l1 = clamp(src - i0, 0, 1)`.
fn axis_weights(input: usize, output: usize) -> Vec<(usize, usize, f32, f32)> {
    let scale = input as f32 / output as f32;
    (0..output)
        .map(|i| {
            if input == output {
                return (i, i, 1.0, 0.0);
            }
            let src = (scale * (i as f32 + 0.5) - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(input - 1);
            let l1 = (src - i0 as f32).clamp(0.0, 1.0);
            let i1 = if i0 < input - 1 { i0 + 1 } else { i0 };
            (i0, i1, 1.0 - l1, l1)
        })
        .collect()
}

/// `F.interpolate(mode="bilinear", align_corners=False)` without antialias, summed in the
/// order of PyTorch's generic CPU kernel: `(x00 w0 + x01 w1) h0 + (x10 w0 + x11 w1) h1`.
pub fn interpolate_bilinear(
    chw: &[f32],
    c: usize,
    h: usize,
    w: usize,
    out_h: usize,
    out_w: usize,
) -> Vec<f32> {
    let ys = axis_weights(h, out_h);
    let xs = axis_weights(w, out_w);
    let mut out = Vec::with_capacity(c * out_h * out_w);
    for ch in 0..c {
        let plane = &chw[ch * h * w..(ch + 1) * h * w];
        for &(y0, y1, h0, h1) in &ys {
            let r0 = &plane[y0 * w..y0 * w + w];
            let r1 = &plane[y1 * w..y1 * w + w];
            for &(x0, x1, w0, w1) in &xs {
                let t0 = r0[x0] * w0 + r0[x1] * w1;
                let t1 = r1[x0] * w0 + r1[x1] * w1;
                out.push(t0 * h0 + t1 * h1);
            }
        }
    }
    out
}

/// Steps 2 and 3 for one camera already in `[0, 1]`: resize with padding to `size`
/// (`(height, width)`, or the image's own size for `None`), then `x * 2 - 1`.
pub fn prepare_unit_image(
    chw: &[f32],
    h: usize,
    w: usize,
    size: Option<(usize, usize)>,
) -> PreparedImage {
    let (out_h, out_w) = size.unwrap_or((h, w));
    let mut pixels = resize_with_pad(chw, 3, h, w, out_h, out_w, 0.0);
    for v in &mut pixels {
        *v = *v * 2.0 - 1.0;
    }
    PreparedImage {
        pixels,
        height: out_h,
        width: out_w,
        present: true,
    }
}

/// The stand-in for a missing camera: `-1` everywhere, mask false, shaped like `like`.
pub fn empty_camera(like: &PreparedImage) -> PreparedImage {
    PreparedImage {
        pixels: vec![-1.0; like.pixels.len()],
        height: like.height,
        width: like.width,
        present: false,
    }
}

/// The worst-case absolute difference between this module's prepared pixels and PyTorch's
/// (any kernel, thread count or ISA) for an input whose longer side is `side` pixels, with
/// `u = 2^-24`:
/// - every output is a convex combination of four inputs in `[0, 1]`, computed with four
///   products and three sums, each rounded by at most `u` (values are at most 1): `7u`;
/// - the source coordinate `scale * (i + 0.5) - 0.5` (below `side`) may be rounded once more or
///   once less (a fused multiply-add in PyTorch's compiled kernel), moving a bilinear weight by
///   up to `ulp(side) <= 2u side`, and the output by that much per axis: `4u side`;
/// - `x * 2 - 1` doubles both and rounds once more.
pub fn prepared_pixel_bound(side: usize) -> f32 {
    let u = f32::EPSILON / 2.0;
    2.0 * (7.0 * u + 4.0 * u * (side as f32).max(1.0)) + u
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_weights_follow_pytorch() {
        // 4 -> 2: src = 2 * (i + 0.5) - 0.5 = 0.5, 2.5.
        assert_eq!(axis_weights(4, 2), vec![(0, 1, 0.5, 0.5), (2, 3, 0.5, 0.5)]);
        // 2 -> 4 (upsampling): src = 0.5 * (i + 0.5) - 0.5 = -0.25 -> 0, 0.25, 0.75, 1.25.
        let up = axis_weights(2, 4);
        assert_eq!(up[0], (0, 1, 1.0, 0.0));
        assert_eq!(up[1], (0, 1, 0.75, 0.25));
        // The last source row has no successor: i1 == i0.
        assert_eq!(up[3].0, 1);
        assert_eq!(up[3].1, 1);
    }

    #[test]
    fn pads_left_and_top() {
        // A 2x4 white image into 4x4: ratio 1, resized 2x4, two rows of padding on top.
        let img = vec![1.0f32; 3 * 2 * 4];
        let p = prepare_unit_image(&img, 2, 4, Some((4, 4)));
        let plane = &p.pixels[..16];
        assert_eq!(&plane[..8], &[-1.0; 8]);
        assert_eq!(&plane[8..], &[1.0; 8]);
        // A 4x2 image into 4x4: padding on the left.
        let img = vec![1.0f32; 3 * 4 * 2];
        let p = prepare_unit_image(&img, 4, 2, Some((4, 4)));
        for row in p.pixels[..16].chunks(4) {
            assert_eq!(row, &[-1.0, -1.0, 1.0, 1.0]);
        }
    }

    #[test]
    fn grey_and_rgba_become_three_channels() {
        let grey = ImageInput::RawU8 {
            height: 1,
            width: 2,
            channels: 1,
            data: vec![0, 255],
        };
        let (chw, h, w) = to_chw_unit(&grey, &ImageLimits::default(), "cam").unwrap();
        assert_eq!((h, w), (1, 2));
        assert_eq!(chw, vec![0.0, 1.0, 0.0, 1.0, 0.0, 1.0]);
        let rgba = ImageInput::RawU8 {
            height: 1,
            width: 1,
            channels: 4,
            data: vec![255, 0, 51, 7],
        };
        let (chw, _, _) = to_chw_unit(&rgba, &ImageLimits::default(), "cam").unwrap();
        assert_eq!(chw, vec![1.0, 0.0, 0.2]);
        let broken = ImageInput::RawU8 {
            height: 2,
            width: 2,
            channels: 3,
            data: vec![0; 5],
        };
        let err = to_chw_unit(&broken, &ImageLimits::default(), "observation.images.top")
            .unwrap_err()
            .to_string();
        assert!(err.contains("observation.images.top"), "{err}");
    }
}
