//! `kairos bench chunking`: parses its arguments, runs [`kairos_bench::chunking_bench`] with a
//! progress bar, and writes `results.csv`, `summary.md` and the plot (and `live.csv` with
//! `--live`).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use kairos_bench::chunking_bench::episode::Execution;
use kairos_bench::chunking_bench::live::{LivePlan, LiveReport, run_live};
use kairos_bench::chunking_bench::report::{
    cost_table, jump_table, results_csv, success_table, verdict,
};
use kairos_bench::chunking_bench::{BenchPlan, DELAYS, TaskPlan, cells, cost, run_bench};
use kairos_bench::horizon_bench::env::TASKS;
use kairos_bench::horizon_bench::live::{remove_scratch, scratch_data_dir};
use kairos_bench::horizon_bench::model::FlowPolicy;
use kairos_bench::plot::{ParetoSeries, SuccessPanel, success_panels};
use kairos_core::chunking::ChunkingDefaults;
use kairos_sdk::robot::Alignment;

use super::bench_horizon::task_model_dir;

/// `kairos bench chunking`
#[derive(Args, Debug, Clone)]
pub struct ChunkingArgs {
    /// A smaller run for first looks: delays 0, 2 and 4, 30 episodes.
    #[arg(long)]
    pub quick: bool,
    /// Output directory for results.csv, summary.md and success.png/.svg.
    #[arg(long, short = 'o', default_value = "kairos-chunking")]
    pub out: PathBuf,
    /// Tasks to run (repeatable; default: uniform, contact and reactive), each with its
    /// committed model (workloads/horizon*/model).
    #[arg(long = "task", value_parser = clap::builder::PossibleValuesParser::new(TASKS))]
    pub tasks: Vec<String>,
    /// Delays D in control steps (repeatable; default 0, 1, 2, 3, 4, 8).
    #[arg(long = "delay")]
    pub delays: Vec<u32>,
    /// Executions to compare (repeatable; default all: sync and every strategy).
    #[arg(long = "execution", value_parser = parse_execution)]
    pub executions: Vec<Execution>,
    /// Episodes per cell (default 200, or 30 with --quick). The same seeds in every cell.
    #[arg(long)]
    pub episodes: Option<usize>,
    /// Seed of the first episode.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads (default: available cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Chunks timed per guidance mode for the cost table (0: skip it).
    #[arg(long, default_value_t = 300)]
    pub cost_rounds: usize,
    /// Skip the plot.
    #[arg(long)]
    pub no_plots: bool,
    /// Also run the live comparison: a server on loopback QUIC loaded by --live-robots robots
    /// that run in real time; the server predicts each round's d.
    #[arg(long)]
    pub live: bool,
    /// --live: the task.
    #[arg(long, default_value = "reactive", value_parser = clap::builder::PossibleValuesParser::new(TASKS))]
    pub live_task: String,
    /// --live: robots connected at once.
    #[arg(long, default_value_t = 12)]
    pub live_robots: usize,
    /// --live: control ticks per second.
    #[arg(long, default_value_t = 100.0)]
    pub live_hz: f32,
    /// --live: steps between requests.
    #[arg(long, default_value_t = 4)]
    pub live_period: u32,
    /// --live: episodes per (execution, alignment).
    #[arg(long, default_value_t = 40)]
    pub live_episodes: usize,
    /// --live: the least time of one forward pass of the served model, ms (the bench policy
    /// itself takes well under one; a VLA on a GPU tens).
    #[arg(long, default_value_t = 20)]
    pub live_forward_ms: u64,
}

fn parse_execution(name: &str) -> Result<Execution, String> {
    Execution::parse(name).ok_or_else(|| {
        let names: Vec<&str> = Execution::all().iter().map(|e| e.name()).collect();
        format!("`{name}` is not one of {}", names.join(", "))
    })
}

fn pct(x: f64) -> String {
    format!("{:.1}", 100.0 * x)
}

/// Runs `kairos bench chunking`.
pub fn run(a: ChunkingArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let tasks: Vec<String> = if a.tasks.is_empty() {
        TASKS.iter().map(|t| t.to_string()).collect()
    } else {
        a.tasks.clone()
    };
    let delays: Vec<u32> = if !a.delays.is_empty() {
        a.delays.clone()
    } else if a.quick {
        vec![0, 2, 4]
    } else {
        DELAYS.to_vec()
    };
    let executions = if a.executions.is_empty() {
        Execution::all()
    } else {
        a.executions.clone()
    };
    let episodes = a.episodes.unwrap_or(if a.quick { 30 } else { 200 });
    if episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let threads = a
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
        .max(1);
    let mut models = Vec::with_capacity(tasks.len());
    for task in &tasks {
        let dir = PathBuf::from(task_model_dir(task));
        let (model, saved) = FlowPolicy::load(&dir).with_context(|| {
            format!(
                "loading the {task} policy from {} (train it with `kairos bench horizon --task {task} --train`)",
                dir.display()
            )
        })?;
        if saved.train.env.task_name() != task {
            bail!(
                "{} was trained on the {} task, not {task}",
                dir.display(),
                saved.train.env.task_name()
            );
        }
        models.push((task.clone(), dir, model, saved));
    }
    let defaults = ChunkingDefaults::default();
    let plan = BenchPlan {
        tasks: models
            .iter()
            .map(|(task, _, model, saved)| TaskPlan {
                env: saved.train.env.clone(),
                model,
                cells: cells(task, &delays, model.config().chunk_len, &executions),
            })
            .collect(),
        episodes,
        seed: a.seed,
        threads,
        defaults,
    };
    let total: usize = plan.tasks.iter().map(|t| t.cells.len()).sum::<usize>() * episodes;
    let bar = progress(total as u64, "episodes");
    let results = run_bench(&plan, &|| bar.inc(1))?;
    bar.finish_and_clear();
    let costs = match models.first() {
        Some((_, _, model, saved)) if a.cost_rounds > 0 => {
            cost(model, &saved.train.env, a.cost_rounds)?
        }
        _ => Vec::new(),
    };

    let live = if a.live {
        let dir = PathBuf::from(task_model_dir(&a.live_task));
        let (_, saved) = FlowPolicy::load(&dir)
            .with_context(|| format!("loading the --live-task policy from {}", dir.display()))?;
        let live_plan = LivePlan {
            model_dir: dir,
            data_dir: scratch_data_dir(),
            env: saved.train.env.clone(),
            executions: executions.clone(),
            alignments: vec![Alignment::Executed, Alignment::ServerStart],
            episodes: a.live_episodes,
            seed: a.seed,
            robots: a.live_robots,
            control_hz: a.live_hz,
            period: a.live_period,
            forward: std::time::Duration::from_millis(a.live_forward_ms),
        };
        let bar = progress(
            (live_plan.executions.len() * live_plan.alignments.len() * a.live_episodes) as u64,
            "live episodes",
        );
        let run = run_live(&live_plan, &|| bar.inc(1));
        bar.finish_and_clear();
        remove_scratch(&live_plan.data_dir);
        Some((live_plan, run?))
    } else {
        None
    };

    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    std::fs::write(a.out.join("results.csv"), results_csv(&results))
        .context("writing results.csv")?;
    let mut summary = format!(
        "# Chunk switching under delay, in closed loop\n\nGenerated by `kairos bench chunking{}` ({episodes} episodes per cell, seeds {}..{}, the same in every cell; {threads} threads). A delay of D control steps between an observation's capture and its chunk's arrival, during which the robot keeps executing; a request every max(2, D) steps and every max(N/4, D) = max(4, D) steps (N = 16). Success with a 95% Wilson interval. `sync`: the robot stands still while each chunk is generated. The strategies are the server's (`kairos_core::chunking`), with the exact d; `arrival_state` gets the robot's own forecast (its episode without future randomness, stepped through the committed actions); `rtc` and `rtc_vjp`: the server's defaults (LeRobot 0.6.1's: linear schedule, max guidance weight 10, execution horizon 10); `rtc_zeros`: `rtc` guiding the committed actions only (schedule `zeros`); `rtc_exp4`: `rtc` with schedule `exp` over an execution horizon of 4 (LeRobot's 10 of 50 at this chunk of 16).\n\n",
        if a.quick { " --quick" } else { "" },
        a.seed,
        a.seed + episodes as u64 - 1,
    );
    for (task, dir, model, saved) in &models {
        let n = model.config().chunk_len;
        let _ = write!(
            summary,
            "## {task}\n\nModel `{}` ({} demonstration pairs, final loss {:.4}).\n\nRe-planning every max(2, D):\n\n{}\nRe-planning every max(N/4, D):\n\n{}\nAt D = 2 (every 2 steps): the jump of the velocity command at chunk switches and within chunks, chunks per episode, sampling time per chunk:\n\n{}\n",
            dir.display(),
            saved.pairs,
            saved.final_loss,
            success_table(&results, task, &delays, n, false),
            success_table(&results, task, &delays, n, true),
            jump_table(&results, task, 2, n),
        );
        let _ = writeln!(summary, "Verdict:\n");
        summary.push_str(&verdict(
            &results,
            task,
            Execution::Async(defaults.strategy),
            &delays,
            n,
        ));
        summary.push('\n');
    }
    if !costs.is_empty() {
        let _ = write!(
            summary,
            "## Cost of sampling\n\nOne chunk of the {} policy, median of {} alternating rounds on one thread (`chunking_bench::cost`):\n\n{}\n",
            models[0].0,
            a.cost_rounds,
            cost_table(&costs)
        );
    }
    if let Some((plan, report)) = &live {
        let csv = live_csv(report);
        std::fs::write(a.out.join("live.csv"), &csv).context("writing live.csv")?;
        summary.push_str(&live_summary(plan, report));
    }
    std::fs::write(a.out.join("summary.md"), &summary).context("writing summary.md")?;
    if !a.no_plots {
        let labels: Vec<String> = executions.iter().map(|e| e.name().to_string()).collect();
        let panels: Vec<SuccessPanel<'_>> = models
            .iter()
            .map(|(task, _, model, _)| SuccessPanel {
                title: format!("{task}: success vs delay (re-plan every max(2, D))"),
                series: executions
                    .iter()
                    .zip(&labels)
                    .map(|(e, label)| ParetoSeries {
                        label,
                        points: results
                            .iter()
                            .filter(|r| {
                                r.cell.task == *task
                                    && r.cell.execution == *e
                                    && r.cell.period
                                        == kairos_bench::chunking_bench::periods(
                                            r.cell.delay,
                                            model.config().chunk_len,
                                        )[0]
                            })
                            .map(|r| {
                                let (lo, hi) = r.ci();
                                (f64::from(r.cell.delay), r.success_rate(), lo, hi)
                            })
                            .collect(),
                    })
                    .collect(),
            })
            .collect();
        success_panels(&a.out, "success", "delay D (control steps)", &panels)?;
    }
    println!("{summary}");
    println!(
        "{} cells x {episodes} episodes on {threads} thread(s) in {:.1} s. Outputs in {}",
        results.len(),
        started.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

fn progress(len: u64, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{{elapsed_precise}} [{{bar:40}}] {{pos}}/{{len}} {what}, eta {{eta}}"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar
}

fn alignment_name(a: Alignment) -> &'static str {
    match a {
        Alignment::Executed => "executed",
        Alignment::ServerStart => "server_start",
    }
}

/// `live.csv`: one row per (execution, alignment).
fn live_csv(report: &LiveReport) -> String {
    let mut s = String::from(
        "execution,alignment,episodes,successes,success_rate,switch_jump,within_jump,rounds,mean_actual_d,mean_abs_error,mean_error,exact,diverged\n",
    );
    for r in &report.results {
        let rounds = r.rounds.max(1) as f64;
        let _ = writeln!(
            s,
            "{},{},{},{},{:.4},{:.4},{:.4},{},{:.3},{:.3},{:.3},{:.4},{}",
            r.execution.name(),
            alignment_name(r.alignment),
            r.episodes,
            r.successes,
            r.success_rate(),
            r.outcome.switch_jump / f64::from(r.outcome.switches.max(1)),
            r.outcome.within_jump / f64::from(r.outcome.within.max(1)),
            r.rounds,
            r.actual_sum as f64 / rounds,
            r.abs_error_sum as f64 / rounds,
            r.error_sum as f64 / rounds,
            r.exact as f64 / rounds,
            r.diverged
        );
    }
    s
}

fn live_summary(plan: &LivePlan, report: &LiveReport) -> String {
    let mut s = format!(
        "## Live: a loaded server predicts d\n\nTask `{}`, {} robots connected at once to a server on loopback QUIC with one engine instance whose forward pass takes at least {} ms (`chunking_bench::live::SlowForward`; profiled at start, batches as the scheduler forms them), {} Hz control in real time, a request every {} steps, {} episodes per row (seeds {}..{}). The robots report each round's actual d in their next Last Exec Info; the robot-side columns compare it with the reply's predicted `delay` over rounds whose chunk replaced one still executing.\n\n| execution | alignment | success | switch jump | within jump | mean actual d | mean \\|error\\| | mean error | exact | diverged |\n|---|---|---|---|---|---|---|---|---|---|\n",
        plan.env.task_name(),
        plan.robots,
        plan.forward.as_millis(),
        plan.control_hz,
        plan.period,
        plan.episodes,
        plan.seed,
        plan.seed + plan.episodes as u64 - 1,
    );
    for r in &report.results {
        let rounds = r.rounds.max(1) as f64;
        let _ = writeln!(
            s,
            "| {} | {} | {}% | {:.3} | {:.3} | {:.2} | {:.2} | {:+.2} | {}% | {} |",
            r.execution.name(),
            alignment_name(r.alignment),
            pct(r.success_rate()),
            r.outcome.switch_jump / f64::from(r.outcome.switches.max(1)),
            r.outcome.within_jump / f64::from(r.outcome.within.max(1)),
            r.actual_sum as f64 / rounds,
            r.abs_error_sum as f64 / rounds,
            r.error_sum as f64 / rounds,
            pct(r.exact as f64 / rounds),
            r.diverged,
        );
    }
    let e = &report.server.delay_error;
    let _ = write!(
        s,
        "\nThe server's own record (`kairos_delay_prediction_error_steps`): {} rounds scored, mean error {:+.2} steps; predicted d over {} answered rounds: mean {:.2}.\n\n",
        e.count(),
        e.sum() / e.count().max(1) as f64,
        report.server.delay_predicted.count(),
        report.server.delay_predicted.sum() / report.server.delay_predicted.count().max(1) as f64,
    );
    s
}
