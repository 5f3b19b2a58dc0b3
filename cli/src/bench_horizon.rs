//! `kairos bench horizon`: parses its arguments, runs [`kairos_bench::horizon_bench`] with a progress
//! bar, and writes `pareto.csv`, `summary.md` and the plot; `--train` trains the policy instead.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use kairos_bench::horizon_bench::env::{EnvConfig, TASKS};
use kairos_bench::horizon_bench::live::{
    LiveSetup, remove_scratch, run_live_bench, scratch_data_dir,
};
use kairos_bench::horizon_bench::model::{FlowPolicy, TrainConfig, train};
use kairos_bench::horizon_bench::signals;
use kairos_bench::horizon_bench::{
    BenchPlan, PolicyPoint, action_manager, builtin_points, contact_points, episodes_csv,
    markdown_table, pareto_csv, run_bench,
};
use kairos_bench::plot::{ParetoSeries, pareto};
use kairos_bench::sim::plugins::{PluginRole, load_user_plugins, plugin_cache_dir};

/// `kairos bench horizon`
#[derive(Args, Debug, Clone)]
pub struct HorizonArgs {
    /// A smaller run for CI and first looks (fewer policies and episodes).
    #[arg(long)]
    pub quick: bool,
    /// Output directory for pareto.csv, summary.md and pareto.png/.svg.
    #[arg(long, short = 'o', default_value = "kairos-horizon")]
    pub out: PathBuf,
    /// The task: `uniform` (disturbances at any step, the default), `contact` (disturbances
    /// only at contact: `horizon_bench::env`'s contact variant) or `reactive` (a fast goal, no
    /// pushes). Picks the default --model and what --train trains on; a model trained on
    /// another task is refused.
    #[arg(long, default_value = "uniform", value_parser = clap::builder::PossibleValuesParser::new(TASKS))]
    pub task: String,
    /// The trained policy (config.json + model.safetensors); default: the task's committed
    /// model, workloads/horizon/model, workloads/horizon-contact/model or
    /// workloads/horizon-reactive/model.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Episodes per policy (default 200, or 40 with --quick). The same seeds for every policy.
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Seed of the first episode.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads (default: available cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Run these policies instead of the built-in grid: `name` or `name:k=v,k=v` (a native
    /// policy, e.g. `steady:delta=0.3,margin=1`; `samples=S` draws S samples per request).
    /// Repeatable; plugins given with --horizon-plugin are still added.
    #[arg(long = "policy", value_name = "SPEC", value_parser = PolicyPoint::parse)]
    pub policies: Vec<PolicyPoint>,
    /// A horizon-policy plugin (`.wasm` component) to evaluate beside the built-ins. Repeatable.
    #[arg(long = "horizon-plugin", value_name = "F.wasm")]
    pub horizon_plugins: Vec<PathBuf>,
    /// A parameter handed to every plugin, `name=value` (repeatable).
    #[arg(long = "param", value_parser = super::parse_param)]
    pub params: Vec<(String, f64)>,
    /// Samples per request for the plugins (a multi-sample plugin needs 2 or more).
    #[arg(long, default_value_t = 1)]
    pub plugin_samples: usize,
    /// Precompiled plugin code cache (default: the user's cache directory).
    #[arg(long, value_name = "DIR")]
    pub plugin_cache: Option<PathBuf>,
    /// Also record, over this many episodes at static H = 2, what the horizon signals
    /// correlate with (`horizon_bench::signals`), into summary.md. 0: skip.
    #[arg(long, default_value_t = 0, value_name = "EPISODES")]
    pub signals: usize,
    /// Also run the ground-truth oracles (`horizon_bench::signals::oracle_episode`, with and
    /// without foresight of the episode's future: upper bounds no serving-time policy can
    /// reach) at this error bound. Repeatable.
    #[arg(long = "oracle", value_name = "MAX_ERROR")]
    pub oracles: Vec<f64>,
    /// Skip the plot.
    #[arg(long)]
    pub no_plots: bool,
    /// Serve the policy over loopback QUIC instead of calling it in-process: a real server in
    /// this process (model `horizon-flow:--model`, the plugins in its registries) and one robot
    /// connection per thread, each round carrying the in-process run's sampler seed, so the
    /// episodes match the in-process ones (`horizon_bench::live`). Oracles and --signals still
    /// run in-process.
    #[arg(long, conflicts_with = "train")]
    pub live: bool,
    /// Train the policy on fresh demonstrations and write it to --model, instead of running.
    #[arg(long)]
    pub train: bool,
    /// With --train: optimiser steps (default: the committed model's).
    #[arg(long, requires = "train")]
    pub iterations: Option<usize>,
    /// With --train: demonstration episodes.
    #[arg(long, requires = "train")]
    pub demos: Option<usize>,
    /// With --train: seed of demonstrations, initialisation and batches.
    #[arg(long, requires = "train")]
    pub train_seed: Option<u64>,
}

/// Runs `kairos bench horizon`.
pub fn run(a: HorizonArgs) -> anyhow::Result<()> {
    if a.train {
        return run_train(&a);
    }
    let started = Instant::now();
    let model_dir = model_dir(&a);
    let (model, saved) = FlowPolicy::load(&model_dir).with_context(|| {
        format!(
            "loading the policy from {} (train one with --train)",
            model_dir.display()
        )
    })?;
    if saved.train.env.task_name() != a.task {
        bail!(
            "{} was trained on the {} task, not {} (pass --task {})",
            model_dir.display(),
            saved.train.env.task_name(),
            a.task,
            saved.train.env.task_name()
        );
    }
    let cache = plugin_cache_dir(a.plugin_cache.clone());
    let user = load_user_plugins(
        &[],
        &a.horizon_plugins,
        &a.params.iter().cloned().collect(),
        &cache,
    )?;
    let manager = action_manager(user.policies.horizon.clone())?;
    let mut points = if a.policies.is_empty() {
        let mut points = builtin_points(a.quick);
        if saved.train.env.contact.is_some() {
            points.extend(contact_points(a.quick));
        }
        points
    } else {
        a.policies.clone()
    };
    for p in user
        .plugins
        .iter()
        .filter(|p| p.role == PluginRole::Horizon)
    {
        points.push(PolicyPoint {
            family: p.label.clone(),
            name: p.name.clone(),
            params: p.params.clone(),
            samples: a.plugin_samples.max(1),
        });
    }
    let episodes = a.episodes.unwrap_or(if a.quick { 40 } else { 200 });
    if episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let threads = a
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
        .max(1);
    let plan = BenchPlan {
        points,
        episodes,
        seed: a.seed,
        env: saved.train.env.clone(),
        threads,
    };
    let bar = ProgressBar::new((plan.points.len() * episodes) as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} episodes, eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    let (mut results, fallbacks) = if a.live {
        let setup = LiveSetup {
            model_dir: model_dir.clone(),
            data_dir: scratch_data_dir(),
            policies: user.policies.clone(),
        };
        let run = run_live_bench(&setup, &plan, &|| bar.inc(1));
        remove_scratch(&setup.data_dir);
        run?
    } else {
        let results = run_bench(&model, &manager, &plan, &|| bar.inc(1))?;
        (results, manager.fallback_count() as usize)
    };
    bar.finish_and_clear();
    let policy_rows = results.len();
    for foresight in [true, false] {
        for &bound in &a.oracles {
            results.push(signals::oracle_point(
                &model,
                &plan.env,
                (a.seed, episodes, threads),
                bound,
                foresight,
            )?);
        }
    }

    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let csv = pareto_csv(&results);
    std::fs::write(a.out.join("pareto.csv"), &csv).context("writing pareto.csv")?;
    std::fs::write(
        a.out.join("episodes.csv"),
        episodes_csv(&results[..policy_rows], a.seed),
    )
    .context("writing episodes.csv")?;
    let mut summary = format!(
        "# Horizon policies in closed loop\n\nGenerated by `kairos bench horizon{}{}{}` ({} episodes per policy, seeds {}..{}, model `{}`: {} demonstration pairs, final training loss {:.4}, {} fallback decisions). Success with a 95% Wilson interval; mean executed H = actions executed per chunk.\n\nMode: {}.\n\n",
        if a.task == "uniform" {
            String::new()
        } else {
            format!(" --task {}", a.task)
        },
        if a.quick { " --quick" } else { "" },
        if a.live { " --live" } else { "" },
        episodes,
        a.seed,
        a.seed + episodes as u64 - 1,
        model_dir.display(),
        saved.pairs,
        saved.final_loss,
        fallbacks,
        if a.live {
            "live (the policy served over loopback QUIC by a server in this process, one robot connection per thread; oracles and signals in-process)"
        } else {
            "in-process (policy and horizon code called directly)"
        },
    );
    summary.push_str(&markdown_table(&results));
    if a.signals > 0 {
        let records = signals::collect(&model, &plan.env, a.seed, a.signals, 2)?;
        let _ = write!(
            summary,
            "\n## What the signals correlate with\n\nEvery action of every chunk of {} episodes at static H = 2 (seeds {}..{}), rolled out open loop to the chunk's end; error = distance to the nearer of the expert's two modes at the state reached (`horizon_bench::signals`). ",
            a.signals,
            a.seed,
            a.seed + a.signals as u64 - 1
        );
        summary.push_str(&signals::correlation_table(&records));
    }
    std::fs::write(a.out.join("summary.md"), &summary).context("writing summary.md")?;
    if !a.no_plots {
        let mut families: Vec<ParetoSeries<'_>> = Vec::new();
        for r in &results {
            let (lo, hi) = r.ci();
            let point = (r.mean_horizon, r.success_rate(), lo, hi);
            match families.iter_mut().find(|f| f.label == r.point.family) {
                Some(f) => f.points.push(point),
                None => families.push(ParetoSeries {
                    label: &r.point.family,
                    points: vec![point],
                }),
            }
        }
        pareto(
            &a.out,
            "pareto",
            "closed-loop success vs mean executed horizon",
            &families,
        )?;
    }
    println!("{summary}");
    println!(
        "{} policies x {episodes} episodes on {threads} thread(s) in {:.1} s. Outputs in {}",
        plan.points.len(),
        started.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

fn run_train(a: &HorizonArgs) -> anyhow::Result<()> {
    let defaults = TrainConfig {
        env: EnvConfig::for_task(&a.task).context("unknown task")?,
        ..TrainConfig::default()
    };
    let cfg = TrainConfig {
        iterations: a.iterations.unwrap_or(defaults.iterations),
        demos: a.demos.unwrap_or(defaults.demos),
        seed: a.train_seed.unwrap_or(defaults.seed),
        ..defaults
    };
    let started = Instant::now();
    let bar = ProgressBar::new(cfg.iterations as u64);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} steps, {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let (policy, saved) = train(&cfg, &mut |it, loss| {
        if it % 20 == 0 {
            bar.set_message(format!("loss {loss:.4}"));
        }
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    let model_dir = model_dir(a);
    policy.save(&model_dir, &saved)?;
    println!(
        "trained on {} demonstration pairs ({} episodes), {} steps in {:.1} s, final loss {:.4}; wrote {}",
        saved.pairs,
        cfg.demos,
        cfg.iterations,
        started.elapsed().as_secs_f64(),
        saved.final_loss,
        model_dir.display()
    );
    Ok(())
}

/// `--model`, or the task's committed model.
fn model_dir(a: &HorizonArgs) -> PathBuf {
    a.model
        .clone()
        .unwrap_or_else(|| PathBuf::from(task_model_dir(&a.task)))
}

/// The committed model of task `task`.
pub fn task_model_dir(task: &str) -> &'static str {
    match task {
        "contact" => "workloads/horizon-contact/model",
        "reactive" => "workloads/horizon-reactive/model",
        _ => "workloads/horizon/model",
    }
}
