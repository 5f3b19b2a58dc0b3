//! The SmolVLA action expert, as LeRobot 0.6.1 has it (`policies/smolvla/`).
//!
//! The expert is a 16-layer Llama-style transformer (hidden 720, GQA 15/5 heads of 64, RMSNorm,
//! SwiGLU) over the 50 action tokens. Even layers self-attend over `[VLM prefix K/V of that layer
//! ; their own K/V]` (causal among actions); odd layers project the cached prefix K/V with their
//! own `k_proj`/`v_proj` and cross-attend to the prefix only. Action tokens are
//! `action_time_mlp_out(silu(action_time_mlp_in([action_in_proj(x_t) ; sincos(t)])))`, and
//! `action_out_proj` of the final norm is the velocity. The sampler is LeRobot's Euler loop.
//!
//! Input: the VLM's prefix KV cache ([`PrefixKv`]), which [`super::SmolVlaVlm`] computes from
//! images, tokens and the state token. `state_proj` is loaded and exposed
//! ([`SmolVlaExpert::embed_state`]) because in SmolVLA the state is the last prefix token the
//! VLM encodes.
//!
//! Two backends run it: the engine's CPU kernels (`cpu`), and plain Candle tensor ops for any
//! Candle device (`candle_backend`). Its weights are in [`weights`]. Both apply the shared
//! sampler's guidance ([`crate::guidance`]); `rtc_vjp`, which pulls the guidance error back
//! through the velocity network, only the Candle one, with Candle's autograd.

pub mod weights;

mod candle_backend;
mod cpu;
#[cfg(feature = "cuda")]
mod cuda_graph;

use std::path::Path;

pub use weights::ExpertWeights;

use super::config::{self, ExpertDims, SmolVlaConfig, VlmConfig};
use super::prefix::PrefixKv;
use crate::candle_vjp::VJP_PATH;
use crate::guidance::RowGuide;
use crate::options::{EngineOptions, Target};
use crate::sampler::{RowLayout, gaussian_noise};
use crate::weights::Checkpoint;
use crate::{ActionChunk, ActionRequest, EngineError, Guidance, GuidanceSupport};

/// Where the expert runs: the engine's CPU kernels on a pool of threads, or Candle.
enum Backend {
    Fast {
        model: Box<cpu::CpuExpert>,
        pool: crate::kernels::Pool,
    },
    Candle(Box<candle_backend::CandleExpert>),
}

/// A loaded SmolVLA action expert.
pub struct SmolVlaExpert {
    dims: ExpertDims,
    backend: Backend,
    description: String,
    path: String,
}

impl std::fmt::Debug for SmolVlaExpert {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SmolVlaExpert")
            .field("dims", &self.dims)
            .field("backend", &self.description)
            .finish()
    }
}

/// What the CUDA graphs of an expert's Euler loop have done (one graph per batch shape: rows and
/// padded prefix length).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CudaGraphStats {
    /// Shapes whose loop is captured as a graph and replayed (each thread that samples captures
    /// its own).
    pub captured: usize,
    /// Shapes whose capture or replay failed once, which run uncaptured from then on.
    pub uncaptured: usize,
    /// Calls served by replaying a graph (a shape's first call runs uncaptured).
    pub replays: u64,
}

/// The result of one request: `S` samples, each `[chunk][action_pad]` wide (LeRobot's padded
/// action width; the robot's actions are the first `action_dim` values of each action).
#[derive(Clone, Debug, PartialEq)]
pub struct ExpertSample {
    /// Samples.
    pub samples: usize,
    /// Initial noise, `[S][N][action_pad]`.
    pub noise: Vec<f32>,
    /// Final actions, `[S][N][action_pad]`.
    pub actions: Vec<f32>,
    /// Velocity of every Euler step, `[S][K][N][action_pad]`.
    pub velocities: Vec<f32>,
    /// Updates `dt * v`, `[S][K][N][action_pad]`.
    pub updates: Vec<f32>,
}

/// The flat buffers of one sampling call, the rows of every request one after another: `noise`
/// and `actions` `[row][len]`, `velocities` and `updates` `[row][step][len]`. Every flow
/// expert (SmolVLA's, π's) samples all rows at once and cuts them per request with
/// [`SampledRows::split`].
pub(crate) struct SampledRows<'a> {
    pub noise: &'a [f32],
    pub actions: &'a [f32],
    pub velocities: &'a [f32],
    pub updates: &'a [f32],
    /// Values per row (`chunk * action_pad`).
    pub len: usize,
    /// Euler steps.
    pub steps: usize,
}

impl SampledRows<'_> {
    /// One [`ExpertSample`] per request, request `i` taking the next `samples[i]` rows.
    pub(crate) fn split(&self, samples: impl IntoIterator<Item = usize>) -> Vec<ExpertSample> {
        let (len, per_step) = (self.len, self.steps * self.len);
        let mut row = 0;
        samples
            .into_iter()
            .map(|s| {
                let out = ExpertSample {
                    samples: s,
                    noise: self.noise[row * len..(row + s) * len].to_vec(),
                    actions: self.actions[row * len..(row + s) * len].to_vec(),
                    velocities: self.velocities[row * per_step..(row + s) * per_step].to_vec(),
                    updates: self.updates[row * per_step..(row + s) * per_step].to_vec(),
                };
                row += s;
                out
            })
            .collect()
    }
}

/// One request to the expert: a prefix and the noise of each sample (`[N][action_pad]` each).
#[derive(Clone, Copy, Debug)]
pub struct ExpertInput<'a> {
    /// The observation's VLM prefix.
    pub prefix: &'a PrefixKv,
    /// One initial noise per sample; samples share the prefix work.
    pub noise: &'a [Vec<f32>],
}

impl SmolVlaExpert {
    /// Load from a LeRobot SmolVLA checkpoint directory: `config.json`, `model.safetensors`
    /// (LeRobot's parameter names; VLM tensors are ignored), and, for a VLM other than
    /// SmolVLM2-500M, the VLM's own `vlm_config.json`.
    pub fn load(dir: &Path, options: &EngineOptions) -> Result<Self, EngineError> {
        let cfg: SmolVlaConfig = config::read_json(&dir.join("config.json"))?;
        let text = VlmConfig::for_checkpoint(dir, &cfg)?.text_config;
        let dims = ExpertDims::resolve(&cfg, &text)?;
        let ckpt = Checkpoint::open(&dir.join("model.safetensors"))?;
        let weights = ExpertWeights::load(&ckpt, &dims)?;
        Self::from_weights(&weights, options)
    }

    /// Build from weights already in memory.
    pub fn from_weights(
        weights: &ExpertWeights,
        options: &EngineOptions,
    ) -> Result<Self, EngineError> {
        let target = options.target()?;
        let description = target.describe();
        let path = target.path(options.precision);
        let backend = match target {
            Target::Fast(pool) => Backend::Fast {
                model: Box::new(cpu::CpuExpert::new(
                    weights,
                    options.precision.resolve(pool.isa()),
                )),
                pool,
            },
            Target::Candle(device) => Backend::Candle(Box::new(candle_backend::CandleExpert::new(
                weights,
                &device,
                options.precision,
                options.cuda_graphs,
            )?)),
        };
        // The Euler loop replays a graph: `kairos predict` reports it with the path.
        let path = if options.cuda_graphs {
            format!("{path}+graphs")
        } else {
            path
        };
        Ok(SmolVlaExpert {
            dims: weights.dims.clone(),
            backend,
            description,
            path,
        })
    }

    /// The path it runs on, e.g. `fast:avx2-fma` or `candle:cuda:0-bf16`.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// What the Euler loop's CUDA graphs have done so far ([`EngineOptions::cuda_graphs`]);
    /// `None` when it runs without graphs.
    pub fn cuda_graph_stats(&self) -> Option<CudaGraphStats> {
        match &self.backend {
            Backend::Candle(model) => model.graph_stats(),
            Backend::Fast { .. } => None,
        }
    }

    /// Shapes.
    pub fn dims(&self) -> &ExpertDims {
        &self.dims
    }

    /// Where and how it runs, e.g. `cpu, fast kernels Avx2Fma, 2 threads`.
    pub fn description(&self) -> &str {
        &self.description
    }

    /// `state_proj` of each state (zero-padded to `max_state_dim`): the state token the VLM
    /// appends to the prefix.
    pub fn embed_state(&self, states: &[Vec<f32>]) -> Result<Vec<Vec<f32>>, EngineError> {
        let pad = self.dims.state_pad;
        let mut flat = vec![0.0f32; states.len() * pad];
        for (i, s) in states.iter().enumerate() {
            if s.len() > pad {
                return Err(EngineError::InvalidInput(format!(
                    "state has {} values, at most {pad}",
                    s.len()
                )));
            }
            flat[i * pad..i * pad + s.len()].copy_from_slice(s);
        }
        let out = match &self.backend {
            Backend::Fast { model, pool } => model.embed_state(pool, &flat, states.len()),
            Backend::Candle(model) => model.embed_state(&flat, states.len())?,
        };
        Ok(out
            .chunks_exact(self.dims.vlm_hidden)
            .map(<[f32]>::to_vec)
            .collect())
    }

    /// The guidance its sampler applies: `rtc` and `inpaint` on both backends (per-row work in
    /// the shared sampler); `rtc_vjp` on the Candle path only, which takes the vector–Jacobian
    /// product with Candle's autograd (the fast kernels have no backward pass).
    pub fn guidance_support(&self) -> GuidanceSupport {
        match self.backend {
            Backend::Fast { .. } => GuidanceSupport::PREFIX,
            Backend::Candle(_) => GuidanceSupport::ALL,
        }
    }

    /// Run the sampler for a batch of requests in one forward pass per step.
    pub fn sample(&self, inputs: &[ExpertInput<'_>]) -> Result<Vec<ExpertSample>, EngineError> {
        self.sample_guided(inputs, &[])
    }

    /// [`SmolVlaExpert::sample`] with a [`RowGuide`] per row (rows are `[input][sample]`; an
    /// empty `guides` is plain sampling for every row). The velocities recorded are those each
    /// step used: the guided ones on guided rows.
    pub fn sample_guided(
        &self,
        inputs: &[ExpertInput<'_>],
        guides: &[Option<RowGuide>],
    ) -> Result<Vec<ExpertSample>, EngineError> {
        let d = &self.dims;
        let len = d.chunk * d.action_pad;
        let mut row_prefix = Vec::new();
        let mut x = Vec::new();
        for (i, input) in inputs.iter().enumerate() {
            if input.noise.is_empty() {
                return Err(EngineError::InvalidInput(
                    "a request needs at least one sample".into(),
                ));
            }
            if input.prefix.keys(0).len() != input.prefix.len() * d.kv_width()
                || input.prefix.is_empty()
            {
                return Err(EngineError::InvalidInput(
                    "prefix does not match this expert".into(),
                ));
            }
            for noise in input.noise {
                if noise.len() != len {
                    return Err(EngineError::InvalidInput(format!(
                        "noise has {} values, expected {len}",
                        noise.len()
                    )));
                }
                x.extend_from_slice(noise);
                row_prefix.push(i);
            }
        }
        let rows = row_prefix.len();
        if rows == 0 {
            return Ok(Vec::new());
        }
        let guides = crate::guidance::guides_per_row(guides, rows)?;
        let guides = &guides[..];
        let prefixes: Vec<&PrefixKv> = inputs.iter().map(|i| i.prefix).collect();
        let noise = x.clone();
        let mut velocities = vec![0.0f32; rows * d.steps * len];
        let mut updates = vec![0.0f32; rows * d.steps * len];
        match &self.backend {
            Backend::Fast { model, pool } => model.sample(
                pool,
                &prefixes,
                &row_prefix,
                &mut x,
                &mut velocities,
                &mut updates,
                guides,
            )?,
            Backend::Candle(model) => model.sample(
                &prefixes,
                &row_prefix,
                &mut x,
                &mut velocities,
                &mut updates,
                guides,
            )?,
        }
        let rows = SampledRows {
            noise: &noise,
            actions: &x,
            velocities: &velocities,
            updates: &updates,
            len,
            steps: d.steps,
        };
        Ok(rows.split(inputs.iter().map(|input| input.noise.len())))
    }

    /// Serve a validated batch of requests: embed every state, build each request's prefix with
    /// `prefix(request, state_token)`, and generate with each request's samples, seed and
    /// guidance (`to_model` maps one robot action into the model's normalised action space). The
    /// serving models differ only in how they build the prefix.
    pub fn generate_requests(
        &self,
        batch: &[ActionRequest],
        prefix: impl Fn(&ActionRequest, &[f32]) -> Result<PrefixKv, EngineError>,
        to_model: &dyn Fn(&mut [f32]),
    ) -> Result<Vec<ActionChunk>, EngineError> {
        let states: Vec<Vec<f32>> = batch.iter().map(|r| r.state.clone()).collect();
        let state_tokens = self.embed_state(&states)?;
        let prefixes = batch
            .iter()
            .zip(&state_tokens)
            .map(|(r, s)| prefix(r, s))
            .collect::<Result<Vec<_>, _>>()?;
        let requests: Vec<(&PrefixKv, usize, u64)> = prefixes
            .iter()
            .zip(batch)
            .map(|(p, r)| (p, r.samples, r.seed))
            .collect();
        let guidance: Vec<Option<&Guidance>> = batch.iter().map(|r| r.guidance.as_ref()).collect();
        self.generate_guided(&requests, &guidance, to_model)
    }

    /// Generate one [`ActionChunk`] per `(prefix, samples, seed)`, cut to the robot's action dim,
    /// with noise from [`gaussian_noise`].
    pub fn generate(
        &self,
        requests: &[(&PrefixKv, usize, u64)],
    ) -> Result<Vec<ActionChunk>, EngineError> {
        self.generate_guided(requests, &vec![None; requests.len()], &|_| {})
    }

    /// [`SmolVlaExpert::generate`] with each request's guidance (`None`: plain sampling);
    /// `to_model` maps one robot action into the model's normalised action space.
    pub fn generate_guided(
        &self,
        requests: &[(&PrefixKv, usize, u64)],
        guidance: &[Option<&Guidance>],
        to_model: &dyn Fn(&mut [f32]),
    ) -> Result<Vec<ActionChunk>, EngineError> {
        let d = &self.dims;
        let len = d.chunk * d.action_pad;
        if guidance.len() != requests.len() {
            return Err(EngineError::InvalidInput(format!(
                "{} guidances for {} requests",
                guidance.len(),
                requests.len()
            )));
        }
        if let Some(mode) = guidance
            .iter()
            .flatten()
            .map(|g| g.mode)
            .find(|&mode| !self.guidance_support().supports(mode))
        {
            return Err(EngineError::InvalidInput(format!(
                "guidance `{}`: SmolVLA's expert has no backward pass on {} (rtc and inpaint \
                 work); {VJP_PATH}",
                mode.as_str(),
                self.description
            )));
        }
        let noises: Vec<Vec<Vec<f32>>> = requests
            .iter()
            .map(|&(_, s, seed)| (0..s).map(|i| gaussian_noise(seed, i, len)).collect())
            .collect();
        let inputs: Vec<ExpertInput<'_>> = requests
            .iter()
            .zip(&noises)
            .map(|(&(prefix, _, _), noise)| ExpertInput { prefix, noise })
            .collect();
        let layout = RowLayout {
            samples: requests.iter().map(|r| r.1).collect(),
            steps: d.steps,
            chunk_len: d.chunk,
            full_dim: d.action_pad,
            action_dim: d.action_dim,
        };
        let mut guides = Vec::new();
        if guidance.iter().any(Option::is_some) {
            for (g, noise) in guidance.iter().zip(&noises) {
                for sample_noise in noise {
                    guides.push(
                        g.map(|g| {
                            RowGuide::prepare(
                                g,
                                d.chunk,
                                d.action_dim,
                                d.action_pad,
                                sample_noise,
                                to_model,
                            )
                        })
                        .transpose()?,
                    );
                }
            }
        }
        let out = self.sample_guided(&inputs, &guides)?;
        let cat = |f: fn(&ExpertSample) -> &Vec<f32>| -> Vec<f32> {
            out.iter().flat_map(|o| f(o).iter().copied()).collect()
        };
        Ok(layout.chunks(
            &cat(|o| &o.noise),
            &cat(|o| &o.actions),
            &cat(|o| &o.updates),
        ))
    }
}
