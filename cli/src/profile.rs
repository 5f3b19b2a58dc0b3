//! `kairos profile`: measure a model's latency-versus-batch-size profile on this machine and
//! write the engine profile file the scheduler batches by (paper §3.2).
//!
//! ```text
//! kairos profile --model builtin:flow-head-small --batches 1,2,4,8,16,32 --iterations 5
//! ```
//!
//! The measuring and the saturation rule live in `kairos_engine::profile`; this command adds the
//! progress bar and the file.

use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use kairos_engine::profile::{DEFAULT_MIN_GAIN, MeasureEvent, MeasureOptions, measure};
use kairos_engine::{DeviceKind, EngineOptions, Kernels, Precision, builtin};

/// Arguments of `kairos profile`.
#[derive(clap::Args, Debug, Clone)]
pub struct ProfileArgs {
    /// Model: `builtin:flow-head-small`, `builtin:smolvla-random`, or a checkpoint directory.
    #[arg(long, default_value = builtin::DEFAULT_MODEL)]
    pub model: String,
    /// The task tokenizer of a whole SmolVLA checkpoint [default: `tokenizer.json` beside it].
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// Batch sizes to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16,32")]
    pub batches: Vec<u32>,
    /// Timed generations per batch size, after one warm-up; the median is kept.
    #[arg(long, default_value_t = 5)]
    pub iterations: usize,
    /// Device: `cpu`, `cuda` or `cuda:N` (CUDA needs a build with the `cuda` feature).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Kernels: `auto`, `fast`, `portable` or `candle`.
    #[arg(long, default_value = "auto")]
    pub kernels: String,
    /// CPU threads for the engine (0: one per core).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// The weight GEMMs' number format: `f32` (exact) or `bf16` (AVX512_BF16; falls back to
    /// f32 with a warning elsewhere). Profile with the precision you serve with.
    #[arg(long, default_value = "f32")]
    pub precision: String,
    /// Replay SmolVLA's Euler loop as a CUDA graph, one per batch shape (CUDA only; the first
    /// batch of a shape runs uncaptured and captures it).
    #[arg(long)]
    pub cuda_graphs: bool,
    /// A batch is worth forming only if it raises throughput by more than this fraction.
    #[arg(long, default_value_t = DEFAULT_MIN_GAIN)]
    pub min_gain: f64,
    /// Output file [default: profiles/<model>.json].
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Run `kairos profile`.
pub fn run(args: ProfileArgs) -> anyhow::Result<()> {
    let device: DeviceKind = args.device.parse().context("--device")?;
    let kernels: Kernels = args.kernels.parse().context("--kernels")?;
    let options = EngineOptions {
        device,
        kernels,
        threads: args.threads,
        precision: args.precision.parse::<Precision>().context("--precision")?,
        cuda_graphs: args.cuda_graphs,
    };
    anyhow::ensure!(
        !args.batches.is_empty() && !args.batches.contains(&0),
        "--batches must be positive"
    );
    anyhow::ensure!(args.iterations > 0, "--iterations must be at least 1");
    let out = args.out.clone().unwrap_or_else(|| {
        PathBuf::from("profiles").join(format!("{}.json", builtin::model_slug(&args.model)))
    });

    let model = kairos_bench::horizon_bench::served::schemes()
        .resolve(&args.model, args.tokenizer.as_deref(), &options)
        .with_context(|| format!("loading model `{}`", args.model))?;
    let device_desc = match device {
        DeviceKind::Cpu => format!("{} ({})", cpu_name(), options.describe()?),
        DeviceKind::Cuda(_) => options.describe()?,
    };
    let measure_options = MeasureOptions {
        batches: args.batches.clone(),
        iterations: args.iterations,
        device: device_desc.clone(),
        min_gain: args.min_gain,
    };

    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} runs  {msg}",
        )
        .context("progress bar template")?,
    );
    if let Some(paths) = model.paths() {
        println!("{}: {paths}", model.spec().name);
    }
    bar.set_message(format!("{} on {device_desc}", model.spec().name));
    let profile = measure(model.as_ref(), &measure_options, |event| match event {
        MeasureEvent::Started { runs } => bar.set_length(runs as u64),
        MeasureEvent::Run { batch, latency } => {
            bar.set_message(format!(
                "batch {batch}: {:.1} ms",
                latency.as_secs_f64() * 1e3
            ));
            bar.inc(1);
        }
        MeasureEvent::Point(p) => bar.println(format!(
            "  batch {:>4}: {:>9.1} ms  ({:.1} req/s)",
            p.batch,
            p.latency_ms,
            1e3 * f64::from(p.batch) / p.latency_ms
        )),
    })
    .context("measuring the profile")?;
    bar.finish_and_clear();

    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let json = serde_json::to_string_pretty(&profile).context("serialising the profile")?;
    std::fs::write(&out, json + "\n").with_context(|| format!("writing {}", out.display()))?;
    println!(
        "{}: saturation batch {} -> {}",
        profile.model,
        profile.max_batch,
        out.display()
    );
    Ok(())
}

/// The CPU model from /proc/cpuinfo (Linux), for the profile's device field.
fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|n| n.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use kairos_engine::EngineProfile;

    #[test]
    fn writes_a_profile_the_scheduler_can_read() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("nested/flow.json");
        run(ProfileArgs {
            model: builtin::DEFAULT_MODEL.into(),
            tokenizer: None,
            batches: vec![2, 1],
            iterations: 1,
            device: "cpu".into(),
            kernels: "fast".into(),
            threads: 2,
            precision: "f32".into(),
            cuda_graphs: false,
            min_gain: 0.05,
            out: Some(out.clone()),
        })
        .unwrap();
        let profile: EngineProfile =
            serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        assert_eq!(profile.model, "flow-head-small");
        assert_eq!(
            profile.points.iter().map(|p| p.batch).collect::<Vec<_>>(),
            vec![1, 2]
        );
        assert!(profile.points.iter().all(|p| p.latency_ms > 0.0));
        assert!([1, 2].contains(&profile.max_batch));
        assert!(profile.device.contains("threads"));
    }

    /// A whole SmolVLA checkpoint is profiled with its task tokenizer, from `--tokenizer` or
    /// beside it; with neither, the error names both.
    #[test]
    fn a_smolvla_checkpoint_is_profiled_with_its_tokenizer() {
        let fixture = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../engine/tests/fixtures/smolvla_tiny");
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("my_smolvla");
        std::fs::create_dir(&model).unwrap();
        for entry in std::fs::read_dir(&fixture).unwrap() {
            let path = entry.unwrap().path();
            if path.is_file() && path.file_name().is_some_and(|n| n != "tokenizer.json") {
                std::fs::copy(&path, model.join(path.file_name().unwrap())).unwrap();
            }
        }
        let out = dir.path().join("smolvla.json");
        let args = ProfileArgs {
            model: model.display().to_string(),
            tokenizer: None,
            batches: vec![1],
            iterations: 1,
            device: "cpu".into(),
            kernels: "auto".into(),
            threads: 1,
            precision: "f32".into(),
            cuda_graphs: false,
            min_gain: 0.05,
            out: Some(out.clone()),
        };
        let error = format!("{:#}", run(args.clone()).unwrap_err());
        assert!(
            error.contains(&model.join("tokenizer.json").display().to_string())
                && error.contains("--tokenizer"),
            "{error}"
        );
        run(ProfileArgs {
            tokenizer: Some(fixture.join("tokenizer.json")),
            ..args.clone()
        })
        .unwrap();
        let profile: EngineProfile =
            serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        assert_eq!(profile.model, "smolvla");
        // `--precision bf16` profiles the bf16 weight GEMMs (f32 with a warning on a CPU
        // without AVX512_BF16); an unknown format is an error that names the flag.
        run(ProfileArgs {
            tokenizer: Some(fixture.join("tokenizer.json")),
            precision: "bf16".into(),
            ..args.clone()
        })
        .unwrap();
        let bad = run(ProfileArgs {
            tokenizer: Some(fixture.join("tokenizer.json")),
            precision: "fp8".into(),
            ..args.clone()
        })
        .unwrap_err();
        assert!(format!("{bad:#}").contains("--precision"), "{bad:#}");
        // A model that reads no text refuses a tokenizer rather than ignore it.
        let builtin = run(ProfileArgs {
            model: builtin::DEFAULT_MODEL.into(),
            tokenizer: Some(fixture.join("tokenizer.json")),
            ..args
        })
        .unwrap_err();
        assert!(
            format!("{builtin:#}").contains("reads no text"),
            "{builtin:#}"
        );
    }

    #[test]
    fn bad_arguments_are_errors() {
        let args = ProfileArgs {
            model: "builtin:nope".into(),
            tokenizer: None,
            batches: vec![1],
            iterations: 1,
            device: "cpu".into(),
            kernels: "auto".into(),
            threads: 1,
            precision: "f32".into(),
            cuda_graphs: false,
            min_gain: 0.05,
            out: None,
        };
        assert!(
            run(args.clone())
                .unwrap_err()
                .to_string()
                .contains("builtin:nope")
        );
        assert!(
            run(ProfileArgs {
                device: "tpu".into(),
                ..args.clone()
            })
            .is_err()
        );
        assert!(
            run(ProfileArgs {
                batches: vec![0],
                model: builtin::DEFAULT_MODEL.into(),
                ..args
            })
            .is_err()
        );
    }
}
