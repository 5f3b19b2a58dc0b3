//! openpi observation dicts → the protocol's [`Observation`], through the configured key map.
//!
//! Only the mapping happens here; every check against the served model (state length, image
//! count, image sizes, finite numbers) is the [`Validator`](crate::validation::Validator)'s, the
//! same one QUIC rounds go through. The size checks that the mapping's own copies depend on run
//! first, from the arrays' shapes, against the same [`Limits`] (the protocol's
//! [`check_raw_image`] and `max_state_len`, `max_images`): a request that would be refused costs
//! no copy, no conversion and no transpose.

use kairos_sdk::protocol::{
    DType as WireDType, Image, ImagePayload, Limits, Observation, Tensor, ValidationError,
    check_raw_image,
};

use super::msgpack::{NdArray, Value, number_count, numbers};
use crate::config::OpenpiConfig;
use crate::validation::RequestError;

fn field_error(field: &str, reason: impl std::fmt::Display) -> RequestError {
    RequestError::Observation {
        field: field.to_string(),
        reason: reason.to_string(),
    }
}

fn too_large(field: String, len: usize, max: u32) -> RequestError {
    RequestError::Protocol(ValidationError::TooLarge {
        field,
        len: len as u64,
        max: u64::from(max),
    })
}

/// Builds the observation of one openpi request `dict`, captured at `captured_at_us`, within
/// `limits`.
///
/// - `state`: the arrays under `config.state`, in order, flattened and concatenated to `f32`;
///   every key must be present.
/// - `images`: the arrays under `config.cameras` that are present, in that order, as raw
///   `[height, width, channels]` images (`uint8` stays `u8`, any other numeric dtype becomes
///   `f32`); a `[channels, height, width]` array (channels 1 or 3, openpi's ALOHA layout) is
///   transposed.
/// - `instruction`: the text under `config.prompt`, empty when absent.
///
/// Other keys are ignored. The state's length, the number of images and each image's size (as
/// it will be sent on, after conversion) are checked against `limits` before anything is copied.
pub fn observation(
    dict: &Value<'_>,
    config: &OpenpiConfig,
    captured_at_us: u64,
    limits: &Limits,
) -> Result<Observation, RequestError> {
    if !matches!(dict, Value::Map(_)) {
        return Err(RequestError::Invalid {
            field: "observation".into(),
            reason: format!("expected a msgpack map (a dict), got a {}", dict.kind()),
        });
    }
    let mut state_len = 0usize;
    for key in &config.state {
        let value = dict
            .get(key)
            .ok_or_else(|| field_error(key, "missing (the key map's `state`)"))?;
        state_len = state_len.saturating_add(number_count(value).map_err(|e| field_error(key, e))?);
    }
    if state_len > limits.max_state_len as usize {
        return Err(too_large(
            "observation.state".into(),
            state_len,
            limits.max_state_len,
        ));
    }
    let mut state = Vec::with_capacity(state_len);
    for key in &config.state {
        if let Some(value) = dict.get(key) {
            state.extend(numbers(value).map_err(|e| field_error(key, e))?);
        }
    }
    let state = Tensor::from_f32(vec![u32::try_from(state.len()).unwrap_or(u32::MAX)], &state)
        .map_err(|e| field_error("state", e))?;
    let present: Vec<(&String, &Value<'_>)> = config
        .cameras
        .iter()
        .filter_map(|key| dict.get(key).map(|value| (key, value)))
        .collect();
    if present.len() > limits.max_images as usize {
        return Err(too_large(
            "observation.images (count)".into(),
            present.len(),
            limits.max_images,
        ));
    }
    // Every image is checked before the first is copied.
    let mut layouts = Vec::with_capacity(present.len());
    for &(key, value) in &present {
        let array = NdArray::from_value(value).map_err(|e| field_error(key, e))?;
        let layout = ImageLayout::of(&array).map_err(|e| field_error(key, e))?;
        check_raw_image(key, &layout.wire_shape(), layout.dtype, limits)?;
        layouts.push((key, array, layout));
    }
    let images = layouts
        .into_iter()
        .map(|(key, array, layout)| Image {
            camera: key.clone(),
            payload: ImagePayload::Raw {
                tensor: layout.tensor(&array),
            },
        })
        .collect();
    let instruction = match dict.get(&config.prompt) {
        None | Some(Value::Nil) => String::new(),
        Some(value) => {
            let text = prompt_text(value)
                .ok_or_else(|| field_error(&config.prompt, "expected a string"))?;
            if text.len() > limits.max_instruction_bytes as usize {
                return Err(too_large(
                    "observation.instruction".into(),
                    text.len(),
                    limits.max_instruction_bytes,
                ));
            }
            text.to_string()
        }
    };
    Ok(Observation {
        captured_at_us,
        state,
        images,
        instruction,
    })
}

/// A prompt: a string, UTF-8 bytes, or a numpy string scalar (`np.str_`).
fn prompt_text<'a>(value: &Value<'a>) -> Option<&'a str> {
    if value.get("__npgeneric__").is_some() {
        return value.get("data").and_then(Value::as_text);
    }
    value.as_text()
}

/// How an image array becomes a raw `[height, width, channels]` tensor, decided from its shape
/// and dtype alone.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct ImageLayout {
    height: usize,
    width: usize,
    channels: usize,
    /// The source is `[channels, height, width]`.
    channels_first: bool,
    /// The tensor's dtype: `u8` for `uint8` sources, `f32` for any other numeric dtype.
    dtype: WireDType,
}

impl ImageLayout {
    fn of(array: &NdArray<'_>) -> Result<ImageLayout, String> {
        let &[a, b, c] = array.shape.as_slice() else {
            return Err(format!(
                "an image is [height, width, channels] (or [channels, height, width]), got shape {:?}",
                array.shape
            ));
        };
        // [C, H, W] with few channels first and many last.
        let channels_first = matches!(a, 1 | 3) && !matches!(c, 1 | 3 | 4);
        let (height, width, channels) = if channels_first { (b, c, a) } else { (a, b, c) };
        let dtype = if array.dtype.kind == 'u' && array.dtype.size == 1 {
            WireDType::U8
        } else {
            WireDType::F32
        };
        Ok(ImageLayout {
            height,
            width,
            channels,
            channels_first,
            dtype,
        })
    }

    /// The tensor's shape as the wire carries it (a side beyond `u32` saturates, which the
    /// limits refuse).
    fn wire_shape(&self) -> [u32; 3] {
        [self.height, self.width, self.channels].map(|d| u32::try_from(d).unwrap_or(u32::MAX))
    }

    /// The tensor, copied (and transposed, for a channel-first source) in one pass. Only called
    /// after the shape passed the limits, so its size is bounded.
    fn tensor(&self, array: &NdArray<'_>) -> Tensor {
        let (height, width, channels) = (self.height, self.width, self.channels);
        let plane = height * width;
        // The source index of output position `i` ([H, W, C] order).
        let source = |i: usize| {
            if self.channels_first {
                (i % channels) * plane + i / channels
            } else {
                i
            }
        };
        let len = plane * channels;
        let data = match self.dtype {
            WireDType::U8 if !self.channels_first => array.data.to_vec(),
            WireDType::U8 => (0..len).map(|i| array.data[source(i)]).collect(),
            _ => {
                let size = array.dtype.size;
                let mut data = Vec::with_capacity(len * 4);
                for i in 0..len {
                    let at = source(i) * size;
                    let value = array.dtype.read(&array.data[at..at + size]) as f32;
                    data.extend_from_slice(&value.to_le_bytes());
                }
                data
            }
        };
        Tensor {
            dtype: self.dtype,
            shape: self.wire_shape().to_vec(),
            data,
        }
    }
}

/// The key map's `cameras` are the model's cameras in order. For a model that matches images
/// by name (`model_cameras` not empty), each image is renamed from its openpi key to the model
/// camera at that key's position, so a missing key leaves its own camera missing rather than
/// shifting the others; an image whose key has no model camera keeps its key, which the
/// validator then refuses by name.
pub fn name_cameras(
    observation: &mut Observation,
    config: &OpenpiConfig,
    model_cameras: &[String],
) {
    if model_cameras.is_empty() {
        return;
    }
    for image in &mut observation.images {
        let position = config.cameras.iter().position(|k| *k == image.camera);
        if let Some(name) = position.and_then(|i| model_cameras.get(i)) {
            image.camera.clone_from(name);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::openpi::msgpack::{Writer, decode};

    fn libero_like(state: &[f32], image: (&[usize], &[u8])) -> Vec<u8> {
        let mut w = Writer::new();
        w.map(4);
        w.str("observation/state")
            .ndarray_f32(&[state.len()], state);
        w.str("observation/image")
            .ndarray_raw(image.0, "|u1", image.1);
        w.str("prompt").str("pick up the cup");
        w.str("extra").uint(1);
        w.finish()
    }

    #[test]
    fn maps_the_default_keys_to_state_images_and_instruction() {
        let pixels: Vec<u8> = (0..2 * 2 * 3).collect();
        let frame = libero_like(&[0.5, -1.0], (&[2, 2, 3], &pixels));
        let config = OpenpiConfig::default();
        let obs = observation(
            &decode(&frame, 1000).unwrap(),
            &config,
            7,
            &Limits::default(),
        )
        .unwrap();
        assert_eq!(obs.captured_at_us, 7);
        assert_eq!(obs.state.to_f32().unwrap(), [0.5, -1.0]);
        assert_eq!(obs.instruction, "pick up the cup");
        assert_eq!(obs.images.len(), 1, "the absent wrist camera is skipped");
        assert_eq!(obs.images[0].camera, "observation/image");
        match &obs.images[0].payload {
            ImagePayload::Raw { tensor } => {
                assert_eq!(tensor.shape, [2, 2, 3]);
                assert_eq!(tensor.dtype, WireDType::U8);
                assert_eq!(tensor.data, pixels);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn images_take_the_model_camera_names_by_key_position() {
        let pixels: Vec<u8> = (0..2 * 2 * 3).collect();
        let frame = libero_like(&[0.5, -1.0], (&[2, 2, 3], &pixels));
        let config = OpenpiConfig {
            cameras: vec!["observation/wrist_image".into(), "observation/image".into()],
            ..OpenpiConfig::default()
        };
        let mut obs = observation(
            &decode(&frame, 1000).unwrap(),
            &config,
            7,
            &Limits::default(),
        )
        .unwrap();
        let unnamed = obs.clone();
        name_cameras(&mut obs, &config, &[]);
        assert_eq!(obs, unnamed, "a positional model keeps the keys");
        // The only image is the second key's: it is the model's second camera, not its first.
        name_cameras(&mut obs, &config, &["top".into(), "side".into()]);
        assert_eq!(obs.images.len(), 1);
        assert_eq!(obs.images[0].camera, "side");
    }

    #[test]
    fn channel_first_images_are_transposed() {
        // [C=3, H=1, W=2]: channel planes [0 1], [10 11], [20 21].
        let frame = libero_like(&[0.0], (&[3, 1, 2], &[0, 1, 10, 11, 20, 21]));
        let obs = observation(
            &decode(&frame, 1000).unwrap(),
            &OpenpiConfig::default(),
            0,
            &Limits::default(),
        )
        .unwrap();
        let ImagePayload::Raw { tensor } = &obs.images[0].payload else {
            panic!("raw image expected")
        };
        assert_eq!(tensor.shape, [1, 2, 3]);
        assert_eq!(tensor.data, [0, 10, 20, 1, 11, 21]);
    }

    #[test]
    fn several_state_keys_concatenate_and_missing_ones_are_named() {
        let mut w = Writer::new();
        w.map(2);
        w.str("joints").ndarray_f32(&[3], &[1.0, 2.0, 3.0]);
        w.str("gripper").float(0.5);
        let frame = w.finish();
        let config = OpenpiConfig {
            state: vec!["joints".into(), "gripper".into()],
            ..OpenpiConfig::default()
        };
        let dict = decode(&frame, 100).unwrap();
        let obs = observation(&dict, &config, 0, &Limits::default()).unwrap();
        assert_eq!(obs.state.to_f32().unwrap(), [1.0, 2.0, 3.0, 0.5]);
        assert_eq!(obs.instruction, "");
        let missing =
            observation(&dict, &OpenpiConfig::default(), 0, &Limits::default()).unwrap_err();
        assert!(
            missing.to_string().contains("observation/state: missing"),
            "{missing}"
        );
    }

    #[test]
    fn wrong_shapes_and_types_are_refused_with_the_key() {
        let frame = libero_like(&[0.0], (&[4, 3], &[0; 12]));
        let error = observation(
            &decode(&frame, 100).unwrap(),
            &OpenpiConfig::default(),
            0,
            &Limits::default(),
        )
        .unwrap_err();
        assert!(
            error.to_string().contains("observation/image") && error.to_string().contains("[4, 3]"),
            "{error}"
        );
        let error = observation(
            &Value::UInt(3),
            &OpenpiConfig::default(),
            0,
            &Limits::default(),
        )
        .unwrap_err();
        assert!(
            error.to_string().contains("expected a msgpack map"),
            "{error}"
        );
    }
}
