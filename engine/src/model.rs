//! The interface between the server and every model.

use std::collections::BTreeMap;

use crate::error::InputError;
use crate::image_features::{ImageLimits, check_image};
use crate::{ActionChunk, ActionRequest, EngineError, ModelChunking};

/// What a model produces and consumes; the server validates requests against it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelSpec {
    /// A short model name, e.g. `flow-head-small` or `smolvla-expert`.
    pub name: String,
    /// Actions per chunk `N`.
    pub chunk_len: usize,
    /// Dimension of one action `D` as returned to the robot.
    pub action_dim: usize,
    /// Length of the robot state vector the model expects.
    pub state_dim: usize,
    /// Number of flow-matching steps `K`.
    pub steps: usize,
    /// Most camera images one observation may carry.
    pub max_images: usize,
    /// The model's cameras in its order, when it matches a request's images to them by name
    /// ([`ActionRequest::cameras`]); empty: images are matched by position.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<String>,
    /// Other names a robot may give a camera (`top` for `observation.images.top`, a rename-map
    /// source, ...) -> the camera in [`ModelSpec::cameras`] it means.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub camera_aliases: BTreeMap<String, String>,
}

/// Most samples one request may ask for.
pub const MAX_SAMPLES: usize = 64;

impl ModelSpec {
    /// Checks one request against this spec: state length, finite state values, image count,
    /// `1 <= samples <= MAX_SAMPLES`, and every image within `images` (from its header or shape,
    /// see [`check_image`]). This is everything the model would refuse, so a request that passes
    /// fails in `generate` only through a model bug.
    pub fn check_request(
        &self,
        request: &ActionRequest,
        images: &ImageLimits,
    ) -> Result<(), InputError> {
        let fail = |field: String, reason: String| Err(InputError { field, reason });
        if request.state.len() != self.state_dim {
            return fail(
                "state".into(),
                format!(
                    "{} values, model `{}` needs {}",
                    request.state.len(),
                    self.name,
                    self.state_dim
                ),
            );
        }
        if let Some(at) = request.state.iter().position(|v| !v.is_finite()) {
            return fail(
                format!("state[{at}]"),
                format!("{} is not a finite number", request.state[at]),
            );
        }
        if request.images.len() > self.max_images {
            return fail(
                "images".into(),
                format!(
                    "{} images, model `{}` takes at most {}",
                    request.images.len(),
                    self.name,
                    self.max_images
                ),
            );
        }
        for (i, image) in request.images.iter().enumerate() {
            if let Err(reason) = check_image(image, images) {
                return fail(format!("images[{i}]"), reason);
            }
        }
        if !request.cameras.is_empty() {
            if request.cameras.len() != request.images.len() {
                return fail(
                    "images".into(),
                    format!(
                        "{} camera names for {} images",
                        request.cameras.len(),
                        request.images.len()
                    ),
                );
            }
            if !self.cameras.is_empty() {
                let mut seen: Vec<&str> = Vec::with_capacity(request.cameras.len());
                for (i, name) in request.cameras.iter().enumerate() {
                    let Some(camera) = self.camera(name) else {
                        return fail(
                            format!("images[{i}].camera"),
                            format!(
                                "model `{}` has no camera `{name}`; its cameras are {}",
                                self.name,
                                self.cameras.join(", ")
                            ),
                        );
                    };
                    if seen.contains(&camera) {
                        return fail(
                            format!("images[{i}].camera"),
                            format!(
                                "`{name}` is camera `{camera}`, which another image already is"
                            ),
                        );
                    }
                    seen.push(camera);
                }
            }
        }
        if let Some(guidance) = &request.guidance {
            let rows = guidance.prefix_rows(self.action_dim);
            if rows * self.action_dim != guidance.prefix.len() || rows > self.chunk_len {
                return fail(
                    "guidance.prefix".into(),
                    format!(
                        "{} values are not at most {} whole actions of {}",
                        guidance.prefix.len(),
                        self.chunk_len,
                        self.action_dim
                    ),
                );
            }
            if let Some(at) = guidance.prefix.iter().position(|v| !v.is_finite()) {
                return fail(
                    format!("guidance.prefix[{at}]"),
                    "not a finite number".into(),
                );
            }
            if guidance.delay > self.chunk_len {
                return fail(
                    "guidance.delay".into(),
                    format!("{} is past the chunk of {}", guidance.delay, self.chunk_len),
                );
            }
            if !(guidance.max_guidance_weight.is_finite() && guidance.max_guidance_weight > 0.0) {
                return fail(
                    "guidance.max_guidance_weight".into(),
                    format!("{} is not a positive number", guidance.max_guidance_weight),
                );
            }
        }
        if request.samples == 0 || request.samples > MAX_SAMPLES {
            return fail(
                "samples".into(),
                format!("{}, must be 1..={MAX_SAMPLES}", request.samples),
            );
        }
        Ok(())
    }

    /// The model camera a robot's camera `name` means: `name` itself if it is one of
    /// [`ModelSpec::cameras`], else its alias. `None` when the model has no such camera (or
    /// matches images by position).
    pub fn camera(&self, name: &str) -> Option<&str> {
        if let Some(own) = self.cameras.iter().find(|c| *c == name) {
            return Some(own);
        }
        self.camera_aliases
            .get(name)
            .map(String::as_str)
            .filter(|c| self.cameras.iter().any(|own| own == c))
    }

    /// Checks every request of `batch` with [`ModelSpec::check_request`] and the default
    /// [`ImageLimits`]. Errors name the request's index.
    pub fn validate(&self, batch: &[ActionRequest]) -> Result<(), EngineError> {
        let images = ImageLimits::default();
        for (i, request) in batch.iter().enumerate() {
            self.check_request(request, &images)
                .map_err(|e| EngineError::InvalidInput(format!("request {i}: {e}")))?;
        }
        Ok(())
    }
}

/// Runs `batch` so that a request that fails fails alone.
///
/// Requests that `check` refuses get its error and are left out; the rest run as one batch
/// through `run`. If that batch fails as a whole, each of its requests runs alone, so a failure
/// the check did not foresee (a model bug, a panic that `run` turns into an error) stays with
/// the request that causes it. [`ActionModel::generate`] gives each request the chunk it would
/// get alone, so the requests that succeed get exactly the chunks of a clean batch.
///
/// `run` answering `Ok` with a chunk count other than its batch's is an error built by
/// `wrong_count(chunks, requests)`. Returns one result per request, in order.
pub fn generate_isolated<E>(
    batch: &[ActionRequest],
    check: impl Fn(&ActionRequest) -> Result<(), E>,
    mut run: impl FnMut(&[ActionRequest]) -> Result<Vec<ActionChunk>, E>,
    wrong_count: impl Fn(usize, usize) -> E,
) -> Vec<Result<ActionChunk, E>> {
    let mut run = |requests: &[ActionRequest]| {
        run(requests).and_then(|chunks| {
            if chunks.len() == requests.len() {
                Ok(chunks)
            } else {
                Err(wrong_count(chunks.len(), requests.len()))
            }
        })
    };
    let mut results: Vec<Option<Result<ActionChunk, E>>> = batch
        .iter()
        .map(|request| check(request).err().map(Err))
        .collect();
    let good: Vec<usize> = (0..batch.len()).filter(|&i| results[i].is_none()).collect();
    let batched = match good.len() {
        0 => Ok(Vec::new()),
        n if n == batch.len() => run(batch),
        // Only on the failure path: a copy without the refused requests.
        _ => run(&good.iter().map(|&i| batch[i].clone()).collect::<Vec<_>>()),
    };
    match batched {
        Ok(chunks) => {
            for (&i, chunk) in good.iter().zip(chunks) {
                results[i] = Some(Ok(chunk));
            }
        }
        Err(error) if good.len() == 1 => results[good[0]] = Some(Err(error)),
        Err(_) => {
            for &i in &good {
                let alone = run(std::slice::from_ref(&batch[i]))
                    .map(|chunks| chunks.into_iter().next())
                    .transpose()
                    .unwrap_or_else(|| Err(wrong_count(0, 1)));
                results[i] = Some(alone);
            }
        }
    }
    results.into_iter().flatten().collect()
}

/// A loaded model that turns a batch of observations into action chunks.
///
/// Implementations run the whole batch in one forward pass per step where the architecture
/// allows it, and must give each request the same result it would get alone (same seed, same
/// chunk). `generate` is blocking and CPU/GPU-heavy: callers run it on a dedicated thread.
pub trait ActionModel: Send + Sync {
    /// The shapes this model works with.
    fn spec(&self) -> &ModelSpec;

    /// Generate one [`ActionChunk`] per request, in request order.
    fn generate(&self, batch: &[ActionRequest]) -> Result<Vec<ActionChunk>, EngineError>;

    /// What the server's chunking strategies may do with this model: the guidance
    /// ([`ActionRequest::guidance`]) its sampler applies on its backend, and what its actions
    /// are. The default is neither: such a model refuses a request with guidance, and the
    /// server refuses the strategies that need it before the round is queued.
    fn chunking(&self) -> ModelChunking {
        ModelChunking::default()
    }

    /// The path each stage runs on, for a model made of a vision tower, a prefix and an
    /// expert (`None`: the model does not say).
    fn paths(&self) -> Option<StagePaths> {
        None
    }
}

/// The path each stage of the policy runs on (what `kairos predict` prints as `paths`):
/// `fast:<isa>` for the engine's CPU kernels (`fast:avx512-bf16`, `fast:avx2-fma`, ...) or
/// `candle:<device>` for Candle ops (`candle:cpu`, `candle:cuda:0`, `-bf16` in bf16).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct StagePaths {
    /// The vision tower and connector.
    pub vision: String,
    /// The SmolLM2 prefix layers.
    pub prefix: String,
    /// The action expert and its Euler loop.
    pub expert: String,
}

impl StagePaths {
    /// Every stage on one path (a model that runs on one backend).
    pub fn all(path: &str) -> Self {
        StagePaths {
            vision: path.to_owned(),
            prefix: path.to_owned(),
            expert: path.to_owned(),
        }
    }
}

impl std::fmt::Display for StagePaths {
    /// `vision <path>, prefix <path>, expert <path>`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "vision {}, prefix {}, expert {}",
            self.vision, self.prefix, self.expert
        )
    }
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use super::*;
    use crate::ImageInput;
    use crate::flow_head::{FlowHead, FlowHeadConfig};
    use crate::{EngineOptions, InputError};

    fn head() -> FlowHead {
        // The default head, cut to one layer and a short chunk (test time).
        let config = FlowHeadConfig {
            layers: 1,
            self_attn_every_n_layers: 1,
            chunk_size: 8,
            num_steps: 3,
            ..Default::default()
        };
        let options = EngineOptions {
            threads: 1,
            ..Default::default()
        };
        FlowHead::random(config, 3, &options).unwrap()
    }

    fn request(k: f32, seed: u64) -> ActionRequest {
        ActionRequest {
            cameras: Vec::new(),
            state: (0..8).map(|i| (i as f32 * 0.4 + k).sin()).collect(),
            images: vec![ImageInput::RawU8 {
                height: 4,
                width: 4,
                channels: 3,
                data: (0..48)
                    .map(|i| (i as u8).wrapping_mul(seed as u8 + 1))
                    .collect(),
            }],
            instruction: "pick".into(),
            samples: 1,
            seed,
            guidance: None,
        }
    }

    fn nan_state() -> ActionRequest {
        let mut bad = request(9.0, 4);
        bad.state[2] = f32::NAN;
        bad
    }

    #[test]
    fn one_bad_request_fails_alone_and_the_rest_get_the_chunks_of_a_clean_batch() {
        let model = head();
        let good = [request(0.0, 1), request(1.0, 2), request(2.0, 3)];
        let clean = model.generate(&good).unwrap();
        // Today's whole-batch answer: one bad request fails everyone.
        let mut batch = good.to_vec();
        batch.insert(1, nan_state());
        let whole = model.generate(&batch).unwrap_err().to_string();
        assert!(whole.contains("request 1: state[2]"), "{whole}");

        let wrong_count = |chunks: usize, requests: usize| {
            EngineError::InvalidInput(format!("{chunks} chunks for {requests} requests"))
        };
        // Unforeseen by a check: the batch fails, then each request runs alone.
        let runs = Cell::new(0);
        let results = generate_isolated(
            &batch,
            |_| Ok(()),
            |b| {
                runs.set(runs.get() + 1);
                model.generate(b)
            },
            wrong_count,
        );
        assert_eq!(runs.get(), 1 + 4);
        assert!(
            results[1]
                .as_ref()
                .unwrap_err()
                .to_string()
                .contains("state[2]")
        );
        let rest: Vec<&ActionChunk> = [0, 2, 3]
            .iter()
            .map(|&i| results[i].as_ref().unwrap())
            .collect();
        assert_eq!(rest, clean.iter().collect::<Vec<_>>(), "bit-identical");

        // Refused by the spec's check: the other three run as one batch.
        let runs = Cell::new(0);
        let images = ImageLimits::default();
        let results = generate_isolated(
            &batch,
            |r| {
                model
                    .spec()
                    .check_request(r, &images)
                    .map_err(EngineError::from)
            },
            |b| {
                runs.set(runs.get() + 1);
                model.generate(b)
            },
            wrong_count,
        );
        assert_eq!(runs.get(), 1);
        assert!(results[1].is_err());
        let rest: Vec<&ActionChunk> = [0, 2, 3]
            .iter()
            .map(|&i| results[i].as_ref().unwrap())
            .collect();
        assert_eq!(rest, clean.iter().collect::<Vec<_>>());
    }

    #[test]
    fn a_runner_that_miscounts_is_an_error_not_a_panic() {
        let results = generate_isolated(
            &[request(0.0, 1), request(1.0, 2)],
            |_| Ok::<(), String>(()),
            |_| Ok(Vec::new()),
            |chunks, requests| format!("{chunks} for {requests}"),
        );
        assert_eq!(
            results,
            vec![Err("0 for 1".to_owned()), Err("0 for 1".to_owned())]
        );
    }

    #[test]
    fn check_request_names_each_field() {
        let spec = head().spec().clone();
        let images = ImageLimits::default();
        let field = |r: ActionRequest| spec.check_request(&r, &images).unwrap_err().field;
        assert_eq!(field(nan_state()), "state[2]");
        let mut r = request(0.0, 1);
        r.state.pop();
        assert_eq!(field(r), "state");
        let mut r = request(0.0, 1);
        r.images = vec![r.images[0].clone(); 3];
        assert_eq!(field(r), "images");
        let mut r = request(0.0, 1);
        r.images[0] = ImageInput::RawF32 {
            height: 0,
            width: 2,
            channels: 1,
            data: Vec::new(),
        };
        assert_eq!(field(r), "images[0]");
        let mut r = request(0.0, 1);
        r.samples = MAX_SAMPLES + 1;
        assert_eq!(field(r), "samples");
        let r = request(0.0, 1);
        assert_eq!(spec.check_request(&r, &images), Ok::<(), InputError>(()));
    }
}
