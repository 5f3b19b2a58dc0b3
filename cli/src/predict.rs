//! `kairos predict`: one action chunk from a LeRobot SmolVLA, π0 or π0.5 checkpoint directory,
//! printed as JSON (the family is `config.json`'s `type`).
//!
//! ```text
//! kairos predict --model ./my_smolvla --tokenizer ./tokenizer.json \
//!     --image camera1=front.png --state 0.1,0.2,... --task "pick up the cube"
//! ```
//!
//! With no inputs the observation is synthetic: a mid-grey image for every camera the config
//! names, a zero state, the task "pick up the cube". The processors and the models live in
//! `kairos_engine::smolvla` ([`SmolVlaPipeline`]) and `kairos_engine::pi` ([`PiPipeline`]); this
//! command only assembles the observation and prints
//! `{"actions": [[..]..], "chunk": C, "action_dim": D, "timing_ms": {..}, "paths": {..}}`, where
//! `paths` names the path each stage ran on (`{"vision": "candle:cuda:0", "prefix": ..,
//! "expert": ..}`, or `"fast:avx512-bf16"` and the like).

use std::path::PathBuf;

use anyhow::Context;
use kairos_engine::pi::{PiFamily, PiPipeline};
use kairos_engine::smolvla::SmolVlaPipeline;
use kairos_engine::smolvla::checkpoint::Observation;
use kairos_engine::smolvla::images::image_file;
use kairos_engine::smolvla::pipeline::{Prediction, StageTimes};
use kairos_engine::{DeviceKind, EngineOptions, Kernels, Precision, StagePaths, profile};

/// Arguments of `kairos predict`.
#[derive(clap::Args, Debug, Clone)]
pub struct PredictArgs {
    /// A LeRobot SmolVLA, π0 or π0.5 checkpoint directory (what `save_pretrained` writes).
    #[arg(long)]
    pub model: PathBuf,
    /// The task tokenizer (`tokenizer.json`) [default: `tokenizer.json` in the model directory].
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// A camera image, `name=file.png` (PNG or JPEG); `name` is the camera's key or the part after
    /// `observation.images.`. Repeat per camera; cameras not given count as missing.
    #[arg(long = "image", value_name = "NAME=FILE")]
    pub images: Vec<String>,
    /// The robot state, comma separated (unnormalised).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub state: Option<Vec<f32>>,
    /// The instruction.
    #[arg(long)]
    pub task: Option<String>,
    /// A whole observation as JSON: `{"task", "state", "images": {name: path or raw}}`;
    /// `--image`, `--state` and `--task` override its parts.
    #[arg(long)]
    pub json_in: Option<PathBuf>,
    /// Seed of the initial noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Device: `cpu`, `cuda` or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Kernels: `auto`, `fast`, `portable` or `candle`.
    #[arg(long, default_value = "auto")]
    pub kernels: String,
    /// CPU threads for the engine (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Weight GEMMs in `f32` (exact) or `bf16` (AVX512_BF16; falls back to f32 elsewhere).
    #[arg(long, default_value = "f32")]
    pub precision: String,
    /// Replay SmolVLA's Euler loop as a CUDA graph, one per batch shape (CUDA only; the first
    /// batch of a shape runs uncaptured and captures it).
    #[arg(long)]
    pub cuda_graphs: bool,
    /// Predict this many copies of the observation in one batch (as a server batches robots),
    /// copy `i` with noise seed `seed + i`; `actions` is copy 0's chunk, `batch_actions` all.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub batch: u32,
    /// Run the prediction this many times after one untimed warm-up (a benchmark:
    /// `engine/tools/bench_smolvla_full.py`); `timing_ms` is the last run's, `runs_ms` every
    /// run's total, `cpu_ms_per_run` the process CPU time per run. 0: no warm-up, one run.
    #[arg(long, default_value_t = 0)]
    pub repeat: u32,
}

/// What `kairos predict` prints.
#[derive(serde::Serialize)]
struct Output {
    actions: Vec<Vec<f32>>,
    chunk: usize,
    action_dim: usize,
    timing_ms: StageTimes,
    /// The path each stage ran on.
    paths: StagePaths,
    /// With `--batch N > 1`: every copy's chunk.
    #[serde(skip_serializing_if = "Option::is_none")]
    batch_actions: Option<Vec<Vec<Vec<f32>>>>,
    /// With `--repeat`: the batch size, each run's total, CPU per run, peak RSS.
    #[serde(skip_serializing_if = "Option::is_none", flatten)]
    bench: Option<Bench>,
}

/// `--repeat`'s measurements.
#[derive(serde::Serialize)]
struct Bench {
    batch: u32,
    runs_ms: Vec<f64>,
    cpu_ms_per_run: f64,
    peak_rss_mb: f64,
}

/// A whole policy of either family.
enum Policy {
    SmolVla(Box<SmolVlaPipeline>),
    Pi(Box<PiPipeline>),
}

impl Policy {
    /// The family `config.json`'s `type` names.
    fn load(
        dir: &std::path::Path,
        tokenizer: Option<&std::path::Path>,
        options: &EngineOptions,
    ) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(dir.join("config.json"))
            .with_context(|| format!("reading {}", dir.join("config.json").display()))?;
        #[derive(serde::Deserialize)]
        struct Probe {
            #[serde(rename = "type", default)]
            policy_type: String,
        }
        let probe: Probe = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", dir.join("config.json").display()))?;
        Ok(if PiFamily::from_type(&probe.policy_type).is_some() {
            Policy::Pi(Box::new(PiPipeline::load(dir, tokenizer, options)?))
        } else {
            Policy::SmolVla(Box::new(SmolVlaPipeline::load(dir, tokenizer, options)?))
        })
    }

    fn synthetic_observation(&self) -> Observation {
        match self {
            Policy::SmolVla(p) => p.checkpoint().synthetic_observation(),
            Policy::Pi(p) => p.checkpoint().synthetic_observation(),
        }
    }

    fn predict(
        &self,
        observations: &[Observation],
        seeds: &[u64],
    ) -> Result<(Vec<Prediction>, StageTimes), kairos_engine::EngineError> {
        match self {
            Policy::SmolVla(p) => p.predict(observations, seeds),
            Policy::Pi(p) => p.predict(observations, seeds),
        }
    }

    /// The path each stage runs on.
    fn paths(&self) -> StagePaths {
        match self {
            Policy::SmolVla(p) => p.paths(),
            Policy::Pi(p) => p.paths(),
        }
    }

    fn action_dim(&self) -> usize {
        match self {
            Policy::SmolVla(p) => p.action_dim(),
            Policy::Pi(p) => p.action_dim(),
        }
    }
}

/// Run `kairos predict`.
pub fn run(args: PredictArgs) -> anyhow::Result<()> {
    // Warnings (a bf16 fallback, a feature without stats) go to stderr; stdout stays JSON.
    super::init_logging("warn");
    let options = EngineOptions {
        device: args.device.parse::<DeviceKind>().context("--device")?,
        kernels: args.kernels.parse::<Kernels>().context("--kernels")?,
        threads: args.threads,
        precision: args.precision.parse::<Precision>().context("--precision")?,
        cuda_graphs: args.cuda_graphs,
    };
    let pipeline = Policy::load(&args.model, args.tokenizer.as_deref(), &options)
        .with_context(|| format!("loading {}", args.model.display()))?;
    let mut obs = match &args.json_in {
        Some(path) => Observation::from_json_file(path)?,
        None => pipeline.synthetic_observation(),
    };
    if !args.images.is_empty() {
        obs.images.clear();
        for spec in &args.images {
            let (name, file) = spec
                .split_once('=')
                .with_context(|| format!("--image `{spec}` is not name=file"))?;
            let image = image_file(std::path::Path::new(file))?;
            obs.images.insert(name.to_owned(), image);
        }
    }
    if let Some(state) = args.state {
        obs.state = state;
    }
    if let Some(task) = args.task {
        obs.task = task;
    }
    let batch = args.batch as usize;
    let observations = vec![obs; batch];
    let seeds: Vec<u64> = (0..args.batch)
        .map(|i| args.seed.wrapping_add(u64::from(i)))
        .collect();
    let mut bench = None;
    if args.repeat > 0 {
        pipeline.predict(&observations, &seeds)?;
        let cpu0 = profile::process_cpu_ms();
        let mut runs_ms = Vec::new();
        for _ in 1..args.repeat {
            runs_ms.push(pipeline.predict(&observations, &seeds)?.1.total);
        }
        bench = Some((cpu0, runs_ms));
    }
    let (predictions, timing) = pipeline.predict(&observations, &seeds)?;
    let bench = bench.map(|(cpu0, mut runs_ms)| {
        runs_ms.push(timing.total);
        Bench {
            batch: args.batch,
            cpu_ms_per_run: (profile::process_cpu_ms() - cpu0) / runs_ms.len() as f64,
            runs_ms,
            peak_rss_mb: profile::peak_rss_mb(),
        }
    });
    let mut chunks: Vec<Vec<Vec<f32>>> = predictions.into_iter().map(|p| p.actions).collect();
    let batch_actions = (batch > 1).then(|| chunks.clone());
    let actions = chunks.drain(..).next().context("no prediction")?;
    let out = Output {
        chunk: actions.len(),
        action_dim: pipeline.action_dim(),
        actions,
        timing_ms: timing,
        paths: pipeline.paths(),
        batch_actions,
        bench,
    };
    println!("{}", serde_json::to_string(&out)?);
    Ok(())
}
