//! A Python observation dict → the protocol's [`Observation`].
//!
//! Accepted keys (LeRobot's flat names as aliases):
//! - `state` / `observation.state`: 1-D float32 (float64 is converted);
//! - `images`: a dict camera → image, and/or `observation.images.<camera>` keys; an image is a
//!   `[height, width, channels]` uint8 or float32 array (raw pixels) or JPEG/PNG file bytes;
//! - `instruction` / `task` / `prompt`: the task instruction.
//!
//! Numpy arrays are read in place (a contiguous float32 state or uint8 image is copied once, into
//! the message); anything else raises `InvalidObservation` naming the field.

use kairos_sdk::protocol::{Image, ImagePayload, Observation, Tensor};
use numpy::{PyReadonlyArray1, PyReadonlyArray3, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyString};

use crate::errors::InvalidObservation;

const STATE_KEYS: [&str; 2] = ["state", "observation.state"];
const INSTRUCTION_KEYS: [&str; 3] = ["instruction", "task", "prompt"];
const IMAGE_PREFIX: &str = "observation.images.";

/// `field` is a Python subscript path, e.g. `["images"]["front"]`.
fn invalid(field: &str, reason: impl std::fmt::Display) -> PyErr {
    InvalidObservation::new_err(format!("observation{field}: {reason}"))
}

fn path(key: &str) -> String {
    format!("[{key:?}]")
}

/// What a value is, for error messages: `float64 array of shape (6,)`, `list`, ...
fn describe(value: &Bound<'_, PyAny>) -> String {
    if let Ok(array) = value.cast::<PyUntypedArray>() {
        let dtype = array
            .dtype()
            .str()
            .map_or_else(|_| "?".to_owned(), |s| s.to_string());
        return format!("a {dtype} array of shape {:?}", array.shape());
    }
    value
        .get_type()
        .name()
        .map_or_else(|_| "an object".to_owned(), |n| format!("a {n}"))
}

fn state(field: &str, value: &Bound<'_, PyAny>) -> PyResult<Tensor> {
    let values: Vec<f32>;
    let tensor = if let Ok(array) = value.extract::<PyReadonlyArray1<'_, f32>>() {
        let len = array.len();
        match array.as_slice() {
            Ok(slice) => Tensor::from_f32(vec![dim(field, len)?], slice),
            Err(_) => {
                values = array.as_array().to_vec();
                Tensor::from_f32(vec![dim(field, len)?], &values)
            }
        }
    } else if let Ok(array) = value.extract::<PyReadonlyArray1<'_, f64>>() {
        values = array.as_array().iter().map(|&v| v as f32).collect();
        Tensor::from_f32(vec![dim(field, values.len())?], &values)
    } else {
        return Err(invalid(
            field,
            format!(
                "expected a 1-D float32 numpy array, got {}",
                describe(value)
            ),
        ));
    };
    tensor.map_err(|e| invalid(field, e))
}

fn dim(field: &str, len: usize) -> PyResult<u32> {
    u32::try_from(len).map_err(|_| invalid(field, format!("{len} elements is too many")))
}

fn image(field: &str, camera: String, value: &Bound<'_, PyAny>) -> PyResult<Image> {
    let payload = if let Ok(bytes) = value.cast::<PyBytes>() {
        let data = bytes.as_bytes();
        if data.starts_with(&[0xFF, 0xD8, 0xFF]) {
            ImagePayload::Jpeg {
                data: data.to_vec(),
            }
        } else if data.starts_with(b"\x89PNG\r\n\x1a\n") {
            ImagePayload::Png {
                data: data.to_vec(),
            }
        } else {
            return Err(invalid(
                field,
                "bytes that are neither a JPEG nor a PNG file",
            ));
        }
    } else if let Ok(array) = value.extract::<PyReadonlyArray3<'_, u8>>() {
        let shape = shape(field, array.shape())?;
        let data = match array.as_slice() {
            Ok(slice) => slice.to_vec(),
            Err(_) => array.as_array().iter().copied().collect(),
        };
        ImagePayload::Raw {
            tensor: Tensor::from_u8(shape, data).map_err(|e| invalid(field, e))?,
        }
    } else if let Ok(array) = value.extract::<PyReadonlyArray3<'_, f32>>() {
        let shape = shape(field, array.shape())?;
        let tensor = match array.as_slice() {
            Ok(slice) => Tensor::from_f32(shape, slice),
            Err(_) => {
                Tensor::from_f32(shape, &array.as_array().iter().copied().collect::<Vec<_>>())
            }
        };
        ImagePayload::Raw {
            tensor: tensor.map_err(|e| invalid(field, e))?,
        }
    } else {
        return Err(invalid(
            field,
            format!(
                "expected a [height, width, channels] uint8 or float32 array, or JPEG/PNG bytes; got {}",
                describe(value)
            ),
        ));
    };
    Ok(Image { camera, payload })
}

fn shape(field: &str, dims: &[usize]) -> PyResult<Vec<u32>> {
    dims.iter().map(|&d| dim(field, d)).collect()
}

/// Reads `value` as an observation captured at `captured_at_us` (client clock).
pub fn from_python(value: &Bound<'_, PyAny>, captured_at_us: u64) -> PyResult<Observation> {
    let dict = value.cast::<PyDict>().map_err(|_| {
        InvalidObservation::new_err(format!(
            "observation: expected a dict with a \"state\" array, got {}",
            describe(value)
        ))
    })?;
    let mut state_tensor = None;
    let mut instruction = String::new();
    let mut images = Vec::new();
    for (key, item) in dict.iter() {
        let Ok(key) = key.cast::<PyString>().map(|k| k.to_string()) else {
            return Err(InvalidObservation::new_err(format!(
                "observation: keys are strings, got {}",
                describe(&key)
            )));
        };
        let field = path(&key);
        if STATE_KEYS.contains(&key.as_str()) {
            state_tensor = Some(state(&field, &item)?);
        } else if INSTRUCTION_KEYS.contains(&key.as_str()) {
            instruction = item
                .extract::<String>()
                .map_err(|_| invalid(&field, format!("expected a str, got {}", describe(&item))))?;
        } else if key == "images" {
            let cameras = item.cast::<PyDict>().map_err(|_| {
                invalid(
                    &field,
                    format!("expected a dict camera → image, got {}", describe(&item)),
                )
            })?;
            for (camera, image_value) in cameras.iter() {
                let camera: String = camera.extract().map_err(|_| {
                    invalid(
                        &field,
                        format!("camera names are str, got {}", describe(&camera)),
                    )
                })?;
                let field = format!("{field}{}", path(&camera));
                images.push(image(&field, camera, &image_value)?);
            }
        } else if let Some(camera) = key.strip_prefix(IMAGE_PREFIX) {
            images.push(image(&field, camera.to_owned(), &item)?);
        } else {
            return Err(invalid(
                &field,
                "unknown key (expected state, images, instruction, or LeRobot's \
                 observation.state / observation.images.<camera> / task)",
            ));
        }
    }
    let Some(state) = state_tensor else {
        return Err(InvalidObservation::new_err(
            "observation[\"state\"]: missing (a 1-D float32 array of the robot's joint state)",
        ));
    };
    Ok(Observation {
        captured_at_us,
        state,
        images,
        instruction,
    })
}
