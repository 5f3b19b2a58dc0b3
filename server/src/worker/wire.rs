//! The one set of conversions between the engine's types and their worker-protocol wire forms,
//! used by both ends: the scheduler (`registration`, `remote`) and `kairos worker` (`client`).

use kairos_engine::{
    ActionChunk, ActionRequest, EngineProfile, Guidance, GuidanceMode, ImageFormat, ImageInput,
    ModelSpec, PrefixSchedule, ProfilePoint,
};
use kairos_sdk::protocol::worker::{
    ProfilePointWire, ProfileWire, WorkChunk, WorkGuidance, WorkRequest,
};
use kairos_sdk::protocol::{
    ChunkingStrategy, DType, Image, ImagePayload, Limits, ModelInfo,
    PrefixSchedule as WirePrefixSchedule, Tensor, Validate,
};

fn usize_u32(value: usize) -> u32 {
    u32::try_from(value).unwrap_or(u32::MAX)
}

/// A model request in its wire form (a request without camera names names its images
/// `camera0`, `camera1`, ... by position).
pub fn request_to_wire(request: &ActionRequest) -> Result<WorkRequest, String> {
    let state = Tensor::from_f32(vec![usize_u32(request.state.len())], &request.state)
        .map_err(|e| e.to_string())?;
    let images = request
        .images
        .iter()
        .enumerate()
        .map(|(i, image)| {
            let payload = match image {
                ImageInput::Encoded {
                    format: ImageFormat::Jpeg,
                    bytes,
                } => ImagePayload::Jpeg {
                    data: bytes.clone(),
                },
                ImageInput::Encoded {
                    format: ImageFormat::Png,
                    bytes,
                } => ImagePayload::Png {
                    data: bytes.clone(),
                },
                ImageInput::RawU8 {
                    height,
                    width,
                    channels,
                    data,
                } => ImagePayload::Raw {
                    tensor: Tensor::from_u8(
                        vec![usize_u32(*height), usize_u32(*width), usize_u32(*channels)],
                        data.clone(),
                    )
                    .map_err(|e| e.to_string())?,
                },
                ImageInput::RawF32 {
                    height,
                    width,
                    channels,
                    data,
                } => ImagePayload::Raw {
                    tensor: Tensor::from_f32(
                        vec![usize_u32(*height), usize_u32(*width), usize_u32(*channels)],
                        data,
                    )
                    .map_err(|e| e.to_string())?,
                },
            };
            Ok(Image {
                camera: request
                    .cameras
                    .get(i)
                    .cloned()
                    .unwrap_or_else(|| format!("camera{i}")),
                payload,
            })
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok(WorkRequest {
        state,
        images,
        instruction: request.instruction.clone(),
        samples: usize_u32(request.samples),
        seed: request.seed,
        guidance: request
            .guidance
            .as_ref()
            .map(guidance_to_wire)
            .transpose()?,
    })
}

fn guidance_to_wire(guidance: &Guidance) -> Result<WorkGuidance, String> {
    Ok(WorkGuidance {
        mode: match guidance.mode {
            GuidanceMode::Rtc => ChunkingStrategy::Rtc,
            GuidanceMode::RtcVjp => ChunkingStrategy::RtcVjp,
            GuidanceMode::Inpaint => ChunkingStrategy::Inpaint,
        },
        prefix: Tensor::from_f32(vec![usize_u32(guidance.prefix.len())], &guidance.prefix)
            .map_err(|e| e.to_string())?,
        delay: usize_u32(guidance.delay),
        execution_horizon: usize_u32(guidance.execution_horizon),
        schedule: match guidance.schedule {
            PrefixSchedule::Zeros => WirePrefixSchedule::Zeros,
            PrefixSchedule::Ones => WirePrefixSchedule::Ones,
            PrefixSchedule::Linear => WirePrefixSchedule::Linear,
            PrefixSchedule::Exp => WirePrefixSchedule::Exp,
        },
        max_guidance_weight: guidance.max_guidance_weight,
    })
}

fn guidance_from_wire(guidance: WorkGuidance) -> Result<Guidance, String> {
    let mode = match guidance.mode {
        ChunkingStrategy::Rtc => GuidanceMode::Rtc,
        ChunkingStrategy::RtcVjp => GuidanceMode::RtcVjp,
        ChunkingStrategy::Inpaint => GuidanceMode::Inpaint,
        other => return Err(format!("`{other}` is not a guidance mode")),
    };
    if guidance.prefix.shape.len() != 1 {
        return Err(format!(
            "a guidance prefix is flat [rows × action_dim], got shape {:?}",
            guidance.prefix.shape
        ));
    }
    Ok(Guidance {
        mode,
        prefix: guidance.prefix.to_f32().map_err(|e| e.to_string())?,
        delay: guidance.delay as usize,
        execution_horizon: guidance.execution_horizon as usize,
        schedule: kairos_core::chunking::engine_schedule(guidance.schedule),
        max_guidance_weight: guidance.max_guidance_weight,
    })
}

/// A wire request as a model request (the worker's side). Shapes are checked; the model's own
/// `check_request` still refuses what it cannot serve, one request at a time.
pub fn request_from_wire(request: WorkRequest) -> Result<ActionRequest, String> {
    let state = request.state.to_f32().map_err(|e| e.to_string())?;
    let cameras = request.images.iter().map(|i| i.camera.clone()).collect();
    let images = request
        .images
        .into_iter()
        .map(|image| match image.payload {
            ImagePayload::Jpeg { data } => Ok(ImageInput::Encoded {
                format: ImageFormat::Jpeg,
                bytes: data,
            }),
            ImagePayload::Png { data } => Ok(ImageInput::Encoded {
                format: ImageFormat::Png,
                bytes: data,
            }),
            ImagePayload::Raw { tensor } => {
                tensor.check_len().map_err(|e| e.to_string())?;
                let [height, width, channels] = tensor.shape[..] else {
                    return Err(format!("raw image of shape {:?}", tensor.shape));
                };
                let (height, width, channels) =
                    (height as usize, width as usize, channels as usize);
                match tensor.dtype {
                    DType::U8 => Ok(ImageInput::RawU8 {
                        height,
                        width,
                        channels,
                        data: tensor.data,
                    }),
                    _ => Ok(ImageInput::RawF32 {
                        height,
                        width,
                        channels,
                        data: tensor.to_f32().map_err(|e| e.to_string())?,
                    }),
                }
            }
        })
        .collect::<Result<Vec<_>, String>>()?;
    Ok(ActionRequest {
        cameras,
        state,
        images,
        instruction: request.instruction,
        samples: request.samples as usize,
        seed: request.seed,
        guidance: request.guidance.map(guidance_from_wire).transpose()?,
    })
}

/// A generated chunk in its wire form.
pub fn chunk_to_wire(chunk: &ActionChunk) -> Result<WorkChunk, String> {
    let (s, k, n, d) = (
        usize_u32(chunk.samples),
        usize_u32(chunk.steps),
        usize_u32(chunk.chunk_len),
        usize_u32(chunk.action_dim),
    );
    let tensor = |shape: Vec<u32>, values: &[f32]| {
        Tensor::from_f32(shape, values).map_err(|e| e.to_string())
    };
    Ok(WorkChunk {
        actions: tensor(vec![s, n, d], &chunk.actions)?,
        updates: tensor(vec![s, k, n, d], &chunk.updates)?,
        noise: tensor(vec![s, n, d], &chunk.noise)?,
    })
}

/// A wire chunk as the engine's, for a request of `samples` samples of a `spec` model. Refused
/// unless every tensor is `f32` of exactly the shape the model and the request give
/// (`actions` and `noise` `[S, N, D]`, `updates` `[S, K, N, D]`) and every value is finite:
/// a worker's numbers reach the horizon policy and the robot.
pub fn chunk_from_wire(
    spec: &ModelSpec,
    samples: usize,
    chunk: &WorkChunk,
) -> Result<ActionChunk, String> {
    let dims = |dims: &[usize]| dims.iter().map(|&d| usize_u32(d)).collect::<Vec<u32>>();
    let (s, k, n, d) = (samples, spec.steps, spec.chunk_len, spec.action_dim);
    let values = |name: &str, t: &Tensor, shape: Vec<u32>| {
        if t.dtype != DType::F32 {
            return Err(format!(
                "{name}: {:?} tensor where f32 is expected",
                t.dtype
            ));
        }
        if t.shape != shape {
            return Err(format!("{name}: shape {:?}, expected {shape:?}", t.shape));
        }
        let values = t.to_f32().map_err(|e| format!("{name}: {e}"))?;
        match values.iter().position(|v| !v.is_finite()) {
            Some(at) => Err(format!(
                "{name}[{at}] is {}, not a finite number",
                values[at]
            )),
            None => Ok(values),
        }
    };
    Ok(ActionChunk {
        samples,
        steps: k,
        chunk_len: n,
        action_dim: d,
        actions: values("actions", &chunk.actions, dims(&[s, n, d]))?,
        updates: values("updates", &chunk.updates, dims(&[s, k, n, d]))?,
        noise: values("noise", &chunk.noise, dims(&[s, n, d]))?,
    })
}

/// A profile in its wire form.
pub fn profile_to_wire(profile: &EngineProfile) -> ProfileWire {
    ProfileWire {
        model: profile.model.clone(),
        device: profile.device.clone(),
        points: profile
            .points
            .iter()
            .map(|p| ProfilePointWire {
                batch: p.batch,
                latency_ms: p.latency_ms,
            })
            .collect(),
        max_batch: profile.max_batch,
    }
}

/// A wire profile as the engine's, its points sorted by batch; refused unless it follows the
/// protocol's rules (at least one point, batches and latencies finite, positive and bounded:
/// `ProfileWire`'s [`Validate`]).
pub fn profile_from_wire(profile: ProfileWire) -> Result<EngineProfile, String> {
    profile
        .validate(&Limits::default())
        .map_err(|e| e.to_string())?;
    let mut points: Vec<ProfilePoint> = profile
        .points
        .iter()
        .map(|p| ProfilePoint {
            batch: p.batch,
            latency_ms: p.latency_ms,
        })
        .collect();
    points.sort_by_key(|p| p.batch);
    Ok(EngineProfile {
        model: profile.model,
        device: profile.device,
        points,
        max_batch: profile.max_batch,
    })
}

/// A model's shapes as the wire's `ModelInfo`.
pub fn model_info(spec: &ModelSpec) -> ModelInfo {
    ModelInfo {
        name: spec.name.clone(),
        chunk_len: usize_u32(spec.chunk_len),
        action_dim: usize_u32(spec.action_dim),
        state_dim: usize_u32(spec.state_dim),
        steps: usize_u32(spec.steps),
        max_images: usize_u32(spec.max_images),
        cameras: spec.cameras.clone(),
    }
}

/// The wire's `ModelInfo` as a model spec.
pub fn model_spec(info: &ModelInfo) -> ModelSpec {
    ModelSpec {
        cameras: info.cameras.clone(),
        camera_aliases: Default::default(),
        name: info.name.clone(),
        chunk_len: info.chunk_len as usize,
        action_dim: info.action_dim as usize,
        state_dim: info.state_dim as usize,
        steps: info.steps as usize,
        max_images: info.max_images as usize,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pool::test_model::LinearFlow;

    #[test]
    fn profiles_and_specs_round_trip_and_empty_profiles_are_refused() {
        let profile = EngineProfile {
            model: "m".into(),
            device: "cpu".into(),
            points: vec![
                ProfilePoint {
                    batch: 1,
                    latency_ms: 2.0,
                },
                ProfilePoint {
                    batch: 4,
                    latency_ms: 5.0,
                },
            ],
            max_batch: 4,
        };
        assert_eq!(
            profile_from_wire(profile_to_wire(&profile)).unwrap(),
            profile
        );
        let mut empty = profile_to_wire(&profile);
        empty.points.clear();
        assert!(profile_from_wire(empty).is_err());
        let spec = LinearFlow::new().spec;
        assert_eq!(model_spec(&model_info(&spec)), spec);
    }
}
