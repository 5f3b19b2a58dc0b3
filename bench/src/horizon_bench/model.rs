//! The policy: a small flow-matching model in Candle that maps an observation to a chunk of
//! `N` actions, sampled with the engine's own flow-matching sampler
//! ([`kairos_engine::sampler`]: seeded noise, LeRobot's Euler schedule from `t = 1` to `t = 0`,
//! per-step updates `U`), so its chunks carry the same `[S][K][N][D]` updates the served models'
//! do and every horizon policy reads them as it would in `serve`.
//!
//! The velocity field is an MLP on `[observation, x_t, time features]` (SiLU). Training is
//! conditional flow matching on demonstrations of the scripted [`Expert`]: `x_t = t·ε + (1−t)·a`,
//! target `ε − a`, mean squared error, AdamW ([`train`]).

use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Linear, Module, Optimizer, VarBuilder, VarMap, linear};
use kairos_engine::sampler::{
    RowLayout, Schedule, VelocityField, gaussian_noise, integrate_guided, row_guides,
};
use kairos_engine::{ActionChunk, Guidance};
use rand::{Rng, SeedableRng, rngs::StdRng};
use rand_distr::StandardNormal;

use super::env::{ACTION_DIM, Env, EnvConfig, Expert, OBS_DIM};

/// Weights file name inside a model directory.
pub const WEIGHTS: &str = "model.safetensors";
/// Configuration file name inside a model directory.
pub const CONFIG: &str = "config.json";

/// Why a model could not be built, trained, saved or loaded.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// Candle failed.
    #[error("candle: {0}")]
    Candle(#[from] candle_core::Error),
    /// The engine's sampler failed.
    #[error("sampler: {0}")]
    Sampler(#[from] kairos_engine::EngineError),
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The configuration file is not valid.
    #[error("{path}: {source}")]
    Config {
        /// The file.
        path: String,
        /// Why.
        source: serde_json::Error,
    },
}

/// The network's shape and sampling.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ModelConfig {
    /// Actions per chunk `N`.
    pub chunk_len: usize,
    /// Hidden width.
    pub hidden: usize,
    /// Hidden layers.
    pub depth: usize,
    /// Euler steps `K`.
    pub steps: usize,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            chunk_len: 16,
            hidden: 128,
            depth: 2,
            steps: 10,
        }
    }
}

/// How a model was (or is to be) trained: everything needed to reproduce it.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainConfig {
    /// The network.
    pub model: ModelConfig,
    /// The task the demonstrations come from.
    pub env: EnvConfig,
    /// Demonstration episodes.
    pub demos: usize,
    /// Optimiser steps.
    pub iterations: usize,
    /// Batch size.
    pub batch: usize,
    /// AdamW learning rate.
    pub lr: f64,
    /// Seed of demonstrations, initialisation order, batches and noise.
    pub seed: u64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            model: ModelConfig::default(),
            env: EnvConfig::default(),
            demos: 3000,
            iterations: 30000,
            batch: 128,
            lr: 2e-3,
            seed: 1,
        }
    }
}

/// What a model directory's `config.json` holds.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SavedConfig {
    /// How it was trained.
    pub train: TrainConfig,
    /// Demonstration pairs trained on.
    pub pairs: usize,
    /// Mean loss over the last 100 iterations.
    pub final_loss: f64,
    /// Kairos version that trained it.
    pub kairos_version: String,
}

const TIME_FREQS: [f32; 4] = [1.0, 2.0, 4.0, 8.0];
const TIME_DIM: usize = 1 + 2 * TIME_FREQS.len();

/// The flow-matching policy.
pub struct FlowPolicy {
    varmap: VarMap,
    layers: Vec<Linear>,
    cfg: ModelConfig,
    device: Device,
}

impl std::fmt::Debug for FlowPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FlowPolicy")
            .field("cfg", &self.cfg)
            .finish()
    }
}

impl FlowPolicy {
    /// A freshly initialised network (Candle's default initialisation).
    pub fn new(cfg: ModelConfig) -> Result<FlowPolicy, ModelError> {
        let device = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
        let len = cfg.chunk_len * ACTION_DIM;
        let mut layers = Vec::with_capacity(cfg.depth + 1);
        let mut width = OBS_DIM + len + TIME_DIM;
        for i in 0..cfg.depth {
            layers.push(linear(width, cfg.hidden, vb.pp(format!("l{i}")))?);
            width = cfg.hidden;
        }
        layers.push(linear(width, len, vb.pp("out"))?);
        Ok(FlowPolicy {
            varmap,
            layers,
            cfg,
            device,
        })
    }

    /// Loads `dir/config.json` and `dir/model.safetensors`.
    pub fn load(dir: &Path) -> Result<(FlowPolicy, SavedConfig), ModelError> {
        let path = dir.join(CONFIG);
        let text = std::fs::read_to_string(&path).map_err(|source| ModelError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let saved: SavedConfig =
            serde_json::from_str(&text).map_err(|source| ModelError::Config {
                path: path.display().to_string(),
                source,
            })?;
        let mut policy = FlowPolicy::new(saved.train.model.clone())?;
        policy.varmap.load(dir.join(WEIGHTS))?;
        Ok((policy, saved))
    }

    /// Writes `dir/config.json` and `dir/model.safetensors`.
    pub fn save(&self, dir: &Path, saved: &SavedConfig) -> Result<(), ModelError> {
        let io = |path: &Path| {
            let path = path.display().to_string();
            move |source| ModelError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        self.varmap.save(dir.join(WEIGHTS))?;
        let path = dir.join(CONFIG);
        let text = serde_json::to_string_pretty(saved).map_err(|source| ModelError::Config {
            path: path.display().to_string(),
            source,
        })?;
        std::fs::write(&path, text + "\n").map_err(io(&path))?;
        Ok(())
    }

    /// The network's shape.
    pub fn config(&self) -> &ModelConfig {
        &self.cfg
    }

    fn time_features(&self, t: &[f32]) -> candle_core::Result<Tensor> {
        let mut f = Vec::with_capacity(t.len() * TIME_DIM);
        for &ti in t {
            f.push(ti);
            for w in TIME_FREQS {
                let a = std::f32::consts::TAU * w * ti;
                f.push(a.sin());
                f.push(a.cos());
            }
        }
        Tensor::from_vec(f, (t.len(), TIME_DIM), &self.device)
    }

    /// The velocity field at `x` (`[B][N·D]`) and times `t` (`[B]`) for observations `obs`
    /// (`[B][OBS_DIM]`).
    fn velocity(&self, obs: &Tensor, x: &Tensor, t: &[f32]) -> candle_core::Result<Tensor> {
        let mut h = Tensor::cat(&[obs, x, &self.time_features(t)?], 1)?;
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            h = layer.forward(&h)?;
            if i < last {
                h = h.silu()?;
            }
        }
        Ok(h)
    }

    /// `samples` chunks for `obs`, drawn in one batch with the engine's sampler from the noise
    /// of `seed` (sample `s` gets `gaussian_noise(seed, s, ..)`, as in the engine).
    ///
    /// Runs on a one-thread rayon pool of the calling thread's own ([`on_own_pool`]): Candle
    /// splits every matmul over the global rayon pool, and for this network's few-row matmuls
    /// waking the pool's workers costs far more than the arithmetic (9× the bench's wall time
    /// on a loaded 2-core machine, docs/BENCHMARKS.md). The split is the same, so the chunk is
    /// the same bit for bit.
    pub fn sample(
        &self,
        obs: &[f32; OBS_DIM],
        samples: usize,
        seed: u64,
    ) -> Result<ActionChunk, ModelError> {
        self.sample_guided(obs, samples, seed, None)
    }

    /// [`FlowPolicy::sample`] with `guidance` toward the actions the robot committed to
    /// (`kairos_engine::guidance`: LeRobot's real-time chunking, the paper's with a true
    /// vector–Jacobian product through this network by Candle's autograd, or a hard prefix).
    /// The actions are in the network's own space (the task's commands), so the prefix needs
    /// no mapping. `None` gives exactly [`FlowPolicy::sample`]'s chunk.
    pub fn sample_guided(
        &self,
        obs: &[f32; OBS_DIM],
        samples: usize,
        seed: u64,
        guidance: Option<&Guidance>,
    ) -> Result<ActionChunk, ModelError> {
        on_own_pool(|| self.sample_here(obs, samples, seed, guidance))
    }

    fn sample_here(
        &self,
        obs: &[f32; OBS_DIM],
        samples: usize,
        seed: u64,
        guidance: Option<&Guidance>,
    ) -> Result<ActionChunk, ModelError> {
        let (n, k) = (self.cfg.chunk_len, self.cfg.steps);
        let len = n * ACTION_DIM;
        let rows = samples.max(1);
        let mut x: Vec<f32> = (0..rows)
            .flat_map(|s| gaussian_noise(seed, s, len))
            .collect();
        let noise = x.clone();
        let mut updates = vec![0.0f32; rows * k * len];
        let obs_rows = Tensor::from_vec(
            (0..rows)
                .flat_map(|_| obs.iter().copied())
                .collect::<Vec<f32>>(),
            (rows, OBS_DIM),
            &self.device,
        )?;
        let layout = RowLayout {
            samples: vec![rows],
            steps: k,
            chunk_len: n,
            full_dim: ACTION_DIM,
            action_dim: ACTION_DIM,
        };
        let guides = match guidance {
            Some(g) => {
                let request = guided_request(g);
                row_guides(std::slice::from_ref(&request), &layout, &noise, &|_| {})?
            }
            None => vec![None; rows],
        };
        let mut field = PolicyField {
            policy: self,
            obs: obs_rows,
            rows,
            len,
        };
        integrate_guided(
            Schedule { steps: k },
            rows,
            len,
            &mut x,
            &mut updates,
            &guides,
            None,
            &mut field,
        )?;
        layout.chunks(&noise, &x, &updates).pop().ok_or_else(|| {
            ModelError::Sampler(kairos_engine::EngineError::InvalidInput(
                "the sampler returned no chunk".into(),
            ))
        })
    }
}

/// A request that carries only `guidance` (what [`row_guides`] reads of it).
fn guided_request(guidance: &Guidance) -> kairos_engine::ActionRequest {
    kairos_engine::ActionRequest {
        state: Vec::new(),
        images: Vec::new(),
        cameras: Vec::new(),
        instruction: String::new(),
        samples: 1,
        seed: 0,
        guidance: Some(guidance.clone()),
    }
}

/// The network's velocity field over a batch of rows of one observation, with Candle's
/// autograd for the vector–Jacobian product `rtc_vjp` needs.
struct PolicyField<'a> {
    policy: &'a FlowPolicy,
    obs: Tensor,
    rows: usize,
    len: usize,
}

fn engine_error(e: candle_core::Error) -> kairos_engine::EngineError {
    kairos_engine::EngineError::InvalidInput(format!("candle: {e}"))
}

impl VelocityField for PolicyField<'_> {
    fn velocity(
        &mut self,
        _k: usize,
        t: f32,
        x: &[f32],
        v: &mut [f32],
    ) -> Result<(), kairos_engine::EngineError> {
        let device = &self.policy.device;
        let xt = Tensor::from_slice(x, (self.rows, self.len), device).map_err(engine_error)?;
        let out = self
            .policy
            .velocity(&self.obs, &xt, &vec![t; self.rows])
            .and_then(|o| o.flatten_all()?.to_vec1::<f32>())
            .map_err(engine_error)?;
        v.copy_from_slice(&out);
        Ok(())
    }

    fn velocity_vjp(
        &mut self,
        _k: usize,
        t: f32,
        x: &[f32],
        v: &mut [f32],
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
        pullback: &mut [f32],
    ) -> Result<(), kairos_engine::EngineError> {
        let device = &self.policy.device;
        let shape = (self.rows, self.len);
        let xt = Var::from_tensor(&Tensor::from_slice(x, shape, device).map_err(engine_error)?)
            .map_err(engine_error)?;
        let out = self
            .policy
            .velocity(&self.obs, xt.as_tensor(), &vec![t; self.rows])
            .map_err(engine_error)?;
        let values = out
            .flatten_all()
            .and_then(|o| o.to_vec1::<f32>())
            .map_err(engine_error)?;
        v.copy_from_slice(&values);
        // One backward pass of <v(x), c> gives J_v(x)^T c at x.
        let c = Tensor::from_vec(cotangent(v), shape, device).map_err(engine_error)?;
        let grads = (out * c)
            .and_then(|p| p.sum_all())
            .and_then(|l| l.backward())
            .map_err(engine_error)?;
        let g = grads.get(xt.as_tensor()).ok_or_else(|| {
            kairos_engine::EngineError::InvalidInput("no gradient reached the sample".into())
        })?;
        let g = g
            .flatten_all()
            .and_then(|g| g.to_vec1::<f32>())
            .map_err(engine_error)?;
        pullback.copy_from_slice(&g);
        Ok(())
    }
}

thread_local! {
    /// This thread's one-thread rayon pool (`None` if it could not be started: then the global
    /// pool is used).
    static OWN_POOL: Option<rayon::ThreadPool> =
        rayon::ThreadPoolBuilder::new().num_threads(1).build().ok();
}

/// Runs `f` inside the calling thread's one-thread rayon pool, so that the parallel loops inside
/// it (Candle's matmuls) never wake the global pool.
fn on_own_pool<T: Send>(f: impl FnOnce() -> T + Send) -> T {
    OWN_POOL.with(|pool| match pool {
        Some(pool) => pool.install(f),
        None => f(),
    })
}

/// Demonstrations: `(observation, the next N expert actions)` pairs from `cfg.demos` episodes
/// of the expert, the chunk padded past the episode's end with its last action.
pub fn demonstrations(cfg: &TrainConfig) -> (Vec<f32>, Vec<f32>) {
    let n = cfg.model.chunk_len;
    let (mut obs, mut chunks) = (Vec::new(), Vec::new());
    for episode in 0..cfg.demos as u64 {
        let seed = demo_seed(cfg.seed, episode);
        let mut env = Env::new(cfg.env.clone(), seed);
        let mut expert = Expert::new(seed ^ 0xE);
        let (mut seen, mut acts) = (Vec::new(), Vec::new());
        while !env.done() {
            let o = env.observe();
            let a = expert.act(&o, env.config());
            env.step(&a);
            seen.push(o);
            acts.push(a);
        }
        for (t, o) in seen.iter().enumerate() {
            obs.extend_from_slice(o);
            for i in 0..n {
                chunks.extend_from_slice(&acts[(t + i).min(acts.len() - 1)]);
            }
        }
    }
    (obs, chunks)
}

/// Seeds of demonstration episodes: far from the evaluation seeds (`0..episodes`).
fn demo_seed(seed: u64, episode: u64) -> u64 {
    (seed << 40) ^ (1 << 39) ^ episode
}

/// Trains a fresh model on demonstrations, calling `progress(iteration, loss)` after each
/// optimiser step. Deterministic for a given configuration (one thread of Candle's CPU
/// backend per process is not required: the matmuls are reproducible on one machine).
pub fn train(
    cfg: &TrainConfig,
    progress: &mut dyn FnMut(usize, f64),
) -> Result<(FlowPolicy, SavedConfig), ModelError> {
    let policy = FlowPolicy::new(cfg.model.clone())?;
    let (obs, chunks) = demonstrations(cfg);
    let len = cfg.model.chunk_len * ACTION_DIM;
    let pairs = obs.len() / OBS_DIM;
    let mut opt = candle_nn::AdamW::new(
        policy.varmap.all_vars(),
        candle_nn::ParamsAdamW {
            lr: cfg.lr,
            weight_decay: 0.0,
            ..Default::default()
        },
    )?;
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    let b = cfg.batch.max(1);
    let mut recent = std::collections::VecDeque::with_capacity(100);
    for it in 0..cfg.iterations {
        let (mut o, mut xt, mut target, mut t) = (
            Vec::with_capacity(b * OBS_DIM),
            Vec::with_capacity(b * len),
            Vec::with_capacity(b * len),
            Vec::with_capacity(b),
        );
        for _ in 0..b {
            let i = rng.random_range(0..pairs.max(1));
            o.extend_from_slice(&obs[i * OBS_DIM..(i + 1) * OBS_DIM]);
            let ti: f32 = rng.random();
            t.push(ti);
            for &a in &chunks[i * len..(i + 1) * len] {
                let eps: f32 = rng.sample(StandardNormal);
                xt.push(ti * eps + (1.0 - ti) * a);
                target.push(eps - a);
            }
        }
        let o = Tensor::from_vec(o, (b, OBS_DIM), &policy.device)?;
        let xt = Tensor::from_vec(xt, (b, len), &policy.device)?;
        let target = Tensor::from_vec(target, (b, len), &policy.device)?;
        let v = policy.velocity(&o, &xt, &t)?;
        let loss = (v - target)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        let loss = f64::from(loss.to_scalar::<f32>()?);
        if recent.len() == 100 {
            recent.pop_front();
        }
        recent.push_back(loss);
        progress(it, loss);
    }
    let final_loss = recent.iter().sum::<f64>() / recent.len().max(1) as f64;
    let saved = SavedConfig {
        train: cfg.clone(),
        pairs,
        final_loss,
        kairos_version: env!("CARGO_PKG_VERSION").to_string(),
    };
    Ok((policy, saved))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny() -> TrainConfig {
        TrainConfig {
            model: ModelConfig {
                chunk_len: 16,
                hidden: 32,
                depth: 2,
                steps: 4,
            },
            demos: 20,
            iterations: 30,
            batch: 32,
            ..TrainConfig::default()
        }
    }

    fn guidance(mode: kairos_engine::GuidanceMode, prefix: Vec<f32>, delay: usize) -> Guidance {
        Guidance {
            mode,
            prefix,
            delay,
            execution_horizon: 8,
            schedule: kairos_engine::PrefixSchedule::Linear,
            max_guidance_weight: 10.0,
        }
    }

    /// The pullback `rtc_vjp` takes from Candle's autograd is the network's Jacobian applied
    /// to the cotangent: central differences of `<v(x), c>` agree with it.
    #[test]
    fn the_vector_jacobian_product_matches_finite_differences() {
        let policy = FlowPolicy::new(ModelConfig {
            chunk_len: 4,
            hidden: 16,
            depth: 2,
            steps: 3,
        })
        .unwrap();
        let obs = Env::new(EnvConfig::default(), 3).observe();
        let len = 4 * ACTION_DIM;
        let obs_rows = Tensor::from_vec(obs.to_vec(), (1, OBS_DIM), &policy.device).unwrap();
        let mut field = PolicyField {
            policy: &policy,
            obs: obs_rows,
            rows: 1,
            len,
        };
        let x: Vec<f32> = gaussian_noise(5, 0, len);
        let c: Vec<f32> = gaussian_noise(6, 0, len);
        let (mut v, mut pullback) = (vec![0.0; len], vec![0.0; len]);
        field
            .velocity_vjp(0, 0.6, &x, &mut v, &mut |_| c.clone(), &mut pullback)
            .unwrap();
        let mut plain = vec![0.0; len];
        field.velocity(0, 0.6, &x, &mut plain).unwrap();
        assert_eq!(
            v, plain,
            "the velocity is the same with or without the graph"
        );
        let dot = |field: &mut PolicyField<'_>, x: &[f32]| {
            let mut v = vec![0.0; len];
            field.velocity(0, 0.6, x, &mut v).unwrap();
            v.iter()
                .zip(&c)
                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                .sum::<f64>()
        };
        let h = 1e-2f32;
        for i in 0..len {
            let (mut up, mut down) = (x.clone(), x.clone());
            up[i] += h;
            down[i] -= h;
            let numeric = (dot(&mut field, &up) - dot(&mut field, &down)) / f64::from(2.0 * h);
            let analytic = f64::from(pullback[i]);
            assert!(
                (numeric - analytic).abs() < 2e-2 * (1.0 + analytic.abs()),
                "{i}: numeric {numeric}, autograd {analytic}"
            );
        }
    }

    /// Guidance pulls the chunk's committed actions toward the previous chunk (a hard prefix
    /// lands on them exactly), and no guidance is plain sampling.
    #[test]
    fn guided_chunks_start_on_the_committed_actions() {
        use kairos_engine::GuidanceMode;
        let policy = FlowPolicy::new(ModelConfig {
            hidden: 16,
            steps: 5,
            ..ModelConfig::default()
        })
        .unwrap();
        let obs = Env::new(EnvConfig::default(), 4).observe();
        let plain = policy.sample(&obs, 1, 9).unwrap();
        assert_eq!(policy.sample_guided(&obs, 1, 9, None).unwrap(), plain);
        let prefix: Vec<f32> = (0..6 * ACTION_DIM).map(|i| 0.5 - 0.05 * i as f32).collect();
        let distance = |chunk: &ActionChunk, actions: usize| {
            chunk.actions[..actions * ACTION_DIM]
                .iter()
                .zip(&prefix)
                .map(|(a, p)| (a - p).abs())
                .sum::<f32>()
        };
        let inpaint = policy
            .sample_guided(
                &obs,
                1,
                9,
                Some(&guidance(GuidanceMode::Inpaint, prefix.clone(), 3)),
            )
            .unwrap();
        assert_eq!(
            &inpaint.actions[..3 * ACTION_DIM],
            &prefix[..3 * ACTION_DIM]
        );
        for mode in [GuidanceMode::Rtc, GuidanceMode::RtcVjp] {
            let guided = policy
                .sample_guided(&obs, 1, 9, Some(&guidance(mode, prefix.clone(), 3)))
                .unwrap();
            assert!(
                distance(&guided, 3) < 0.5 * distance(&plain, 3),
                "{mode:?}: {} vs {}",
                distance(&guided, 3),
                distance(&plain, 3)
            );
            assert_ne!(guided.actions, plain.actions);
        }
    }

    #[test]
    fn training_lowers_the_loss_and_a_saved_model_samples_the_same_chunks() {
        let mut losses = Vec::new();
        let (policy, saved) = train(&tiny(), &mut |_, l| losses.push(l)).unwrap();
        assert_eq!(losses.len(), 30);
        let first = losses[..5].iter().sum::<f64>() / 5.0;
        let last = losses[25..].iter().sum::<f64>() / 5.0;
        assert!(last < first, "loss {first} -> {last}");
        let dir = tempfile::tempdir().unwrap();
        policy.save(dir.path(), &saved).unwrap();
        let (loaded, again) = FlowPolicy::load(dir.path()).unwrap();
        // The loss is a JSON number: serde_json's default float parser may differ from the
        // written value in the last bit, so it is compared within a bound.
        assert_eq!(
            (&again.train, again.pairs, &again.kairos_version),
            (&saved.train, saved.pairs, &saved.kairos_version)
        );
        assert!((again.final_loss - saved.final_loss).abs() <= 1e-12 * saved.final_loss.abs());
        let obs = Env::new(EnvConfig::default(), 5).observe();
        let a = policy.sample(&obs, 2, 9).unwrap();
        let b = loaded.sample(&obs, 2, 9).unwrap();
        assert_eq!(a.actions, b.actions);
        assert_eq!(
            (a.samples, a.steps, a.chunk_len, a.action_dim),
            (2, 4, 16, ACTION_DIM)
        );
        // The updates sum to the chunk from the noise, as the engine's sampler promises.
        for i in 0..16 * ACTION_DIM {
            let mut x = a.noise[i];
            for k in 0..4 {
                x += a.updates[k * 16 * ACTION_DIM + i];
            }
            assert_eq!(x, a.actions[i]);
        }
        // Other noise, other chunk.
        assert_ne!(
            policy.sample(&obs, 1, 10).unwrap().actions[..48],
            a.actions[..48]
        );
    }
}
