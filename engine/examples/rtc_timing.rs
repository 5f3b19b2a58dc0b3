//! Time what real-time chunking adds to a whole SmolVLA policy: one request through
//! `ActionModel::generate` (preprocessing, vision tower, VLM prefix, expert, postprocessing)
//! plainly, with `rtc` guidance, with `inpaint` and (on the Candle path, the one that serves it)
//! with `rtc_vjp`, in an order rotating run by run, on a
//! checkpoint directory (e.g. the smolvla_base-shaped one `engine/tools/bench_smolvla_full.py
//! --write-checkpoint` writes).
//!
//! `cargo run --release -p kairos-engine --example rtc_timing -- --model DIR [--iters 5]
//! [--threads 2] [--kernels fast|candle] [--delay 3]`
//!
//! The guidance: the committed actions are a previous chunk of the model's (its own plain
//! output, from action 2 on: the robot executed 2 before the capture), `d = --delay`, LeRobot's
//! defaults (linear schedule, execution horizon 10, max guidance weight 10). Prints one JSON
//! line per mode: `{"mode":..,"median_ms":..,"min_ms":..,"median_cpu_ms":..,"runs":[..]}`,
//! then one with the medians' ratios to plain sampling (`rtc_vjp_over_plain` on the Candle
//! path) and the guidance's own work per chunk (`RowGuide::prepare` and its ten velocity
//! corrections, timed alone: on a shared machine the whole-chunk medians move by more than
//! that). The ratios are given in wall time and in the process's CPU time, which other
//! processes' load moves far less: with `--threads 1` it is the chunk's own work.

use std::time::Instant;

use kairos_engine::guidance::RowGuide;
use kairos_engine::smolvla::SmolVlaPipeline;
use kairos_engine::{
    ActionModel, ActionRequest, EngineOptions, Guidance, GuidanceMode, Kernels, PrefixSchedule,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut model = None;
    let mut iters = 5usize;
    let mut threads = 0usize;
    let mut kernels = Kernels::Fast;
    let mut delay = 3usize;
    let mut args = std::env::args().skip(1);
    while let Some(flag) = args.next() {
        if flag == "--help" || flag == "-h" {
            println!(
                "Times a whole SmolVLA policy's chunk plainly, with rtc, with inpaint and, on \
                 the Candle path, with rtc_vjp.\n\n\
                 Usage: rtc_timing --model DIR [--iters 5] [--threads 2] \
                 [--kernels fast|candle] [--delay 3]"
            );
            return Ok(());
        }
        let value = args.next().ok_or_else(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--model" => model = Some(std::path::PathBuf::from(value)),
            "--iters" => iters = value.parse()?,
            "--threads" => threads = value.parse()?,
            "--delay" => delay = value.parse()?,
            "--kernels" => {
                kernels = match value.as_str() {
                    "fast" => Kernels::Fast,
                    "candle" => Kernels::Candle,
                    other => return Err(format!("--kernels {other}: fast or candle").into()),
                }
            }
            other => return Err(format!("unknown flag {other}").into()),
        }
    }
    let model = model.ok_or("--model DIR is required")?;
    let options = EngineOptions {
        kernels,
        threads,
        ..Default::default()
    };
    let pipeline = SmolVlaPipeline::load(&model, None, &options)?;
    let obs = pipeline.checkpoint().synthetic_observation();
    let request = |guidance: Option<Guidance>| ActionRequest {
        cameras: obs.images.keys().cloned().collect(),
        images: obs.images.values().cloned().collect(),
        state: obs.state.clone(),
        instruction: obs.task.clone(),
        samples: 1,
        seed: 1,
        guidance,
    };
    // Warm-up, and the previous chunk the guided runs follow.
    let previous = pipeline.generate(&[request(None)])?.remove(0);
    let dim = previous.action_dim;
    let guidance = |mode| Guidance {
        mode,
        prefix: previous.actions[2 * dim..].to_vec(),
        delay,
        execution_horizon: 10,
        schedule: PrefixSchedule::Linear,
        max_guidance_weight: 10.0,
    };
    let mut modes: Vec<(&str, Option<Guidance>)> = vec![
        ("plain", None),
        ("rtc", Some(guidance(GuidanceMode::Rtc))),
        ("inpaint", Some(guidance(GuidanceMode::Inpaint))),
    ];
    if kernels == Kernels::Candle {
        modes.push(("rtc_vjp", Some(guidance(GuidanceMode::RtcVjp))));
    }
    let mut runs = vec![Vec::new(); modes.len()];
    let mut cpu = vec![Vec::new(); modes.len()];
    for i in 0..iters {
        // The order rotates run by run, so that no mode always follows another.
        for j in 0..modes.len() {
            let m = (i + j) % modes.len();
            let batch = [request(modes[m].1.clone())];
            let (started, cpu_started) = (Instant::now(), process_cpu_ms());
            pipeline.generate(&batch)?;
            runs[m].push(started.elapsed().as_secs_f64() * 1e3);
            cpu[m].push(process_cpu_ms() - cpu_started);
        }
    }
    let median = |v: &[f64]| {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        s[s.len() / 2]
    };
    let medians: Vec<f64> = runs.iter().map(|r| median(r)).collect();
    let cpu_medians: Vec<f64> = cpu.iter().map(|r| median(r)).collect();
    for (((name, _), times), cpu_median) in modes.iter().zip(&runs).zip(&cpu_medians) {
        let min = times.iter().copied().fold(f64::INFINITY, f64::min);
        let runs: Vec<String> = times.iter().map(|t| format!("{t:.1}")).collect();
        println!(
            "{{\"mode\":\"{name}\",\"median_ms\":{:.1},\"min_ms\":{min:.1},\"median_cpu_ms\":{cpu_median:.1},\"runs\":[{}]}}",
            median(times),
            runs.join(",")
        );
    }
    // The guidance's own work for one chunk, timed alone.
    let d = pipeline.expert().dims().clone();
    let len = d.chunk * d.action_pad;
    let noise = kairos_engine::sampler::gaussian_noise(1, 0, len);
    let (mut x, mut v) = (noise.clone(), vec![0.5f32; len]);
    let reps = 200;
    let started = Instant::now();
    for _ in 0..reps {
        let guide = RowGuide::prepare(
            &guidance(GuidanceMode::Rtc),
            d.chunk,
            d.action_dim,
            d.action_pad,
            &noise,
            &|_| {},
        )?;
        for k in 0..d.steps {
            let t = 1.0 - k as f64 / d.steps as f64;
            guide.guide(t, t as f32, &x, &mut v, None);
            x.iter_mut().zip(&v).for_each(|(xi, vi)| *xi -= vi * 1e-3);
        }
    }
    let guidance_us = started.elapsed().as_secs_f64() * 1e6 / reps as f64;
    let vjp = medians
        .get(3)
        .map(|m| format!("\"rtc_vjp_over_plain\":{:.4},", m / medians[0]))
        .unwrap_or_default();
    println!(
        "{{\"rtc_over_plain\":{:.4},\"inpaint_over_plain\":{:.4},\"rtc_cpu_over_plain\":{:.4},\"inpaint_cpu_over_plain\":{:.4},{vjp}\"rtc_guidance_us_per_chunk\":{guidance_us:.1},\"description\":\"{}\"}}",
        medians[1] / medians[0],
        medians[2] / medians[0],
        cpu_medians[1] / cpu_medians[0],
        cpu_medians[2] / cpu_medians[0],
        pipeline.expert().description()
    );
    Ok(())
}

/// The CPU time this process has used so far (every thread, user and system), in ms.
fn process_cpu_ms() -> f64 {
    // SAFETY: `getrusage` only writes the `rusage` it is given, which is a plain C struct that
    // all-zero bytes initialise validly.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `usage` is a valid, writable `rusage`; `RUSAGE_SELF` is a valid `who`.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
        return f64::NAN;
    }
    let ms = |t: libc::timeval| t.tv_sec as f64 * 1e3 + t.tv_usec as f64 / 1e3;
    ms(usage.ru_utime) + ms(usage.ru_stime)
}
