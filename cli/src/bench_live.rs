//! `kairos bench live`: parses its arguments, runs [`kairos_bench::live_replay`] with progress bars,
//! and writes and prints the side-by-side of live and simulated latency.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use kairos_sdk::tls::Fingerprint;

use kairos_bench::live_replay::{
    Comparison, LiveEvent, SimNetworkMode, Target, compare, comparison_table, live_job, load,
    relative_diff, run_live, scale_traces, simulate_scaled, start_replay_server, variant,
};
use kairos_bench::sim::experiment::{Job, JobResult, Report, Variant};
use kairos_bench::workload::Workload;

/// `kairos bench live`
#[derive(Args, Debug, Clone)]
pub struct LiveArgs {
    /// Workload file (TOML): engines (the replay engine's latency profile), trace generator,
    /// default arrival rate.
    #[arg(long, short = 'w', default_value = "workloads/libero-smolvla.toml")]
    pub workload: PathBuf,
    /// Replay this trace file instead of generating traces from the workload.
    #[arg(long)]
    pub traces: Option<PathBuf>,
    /// Systems to run, comma-separated keys of the online experiment: fifo, autellix, kairos,
    /// kairos-static, fifo-dynamic, autellix-dynamic, srw, srw-hint.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "fifo,autellix,kairos,srw"
    )]
    pub variants: Vec<String>,
    /// Poisson arrival rate, tasks per second of the recording (default: the workload's middle
    /// rate, a moderate load).
    #[arg(long)]
    pub rate: Option<f64>,
    /// Tasks per run.
    #[arg(long, default_value_t = 40, value_parser = clap::value_parser!(u64).range(1..=4096))]
    pub tasks: u64,
    /// Seed of arrivals and task picks (the simulator draws the same schedule from it).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Seed of the trace generator.
    #[arg(long, default_value_t = 42)]
    pub trace_seed: u64,
    /// Run this many times faster than the recording (control rates and arrival rates x k,
    /// latencies / k, for both the live run and its simulation; reported times are scaled
    /// back).
    #[arg(long, default_value_t = 4.0)]
    pub time_scale: f64,
    /// Output directory for summary.md, live.csv, sim.csv and plots.
    #[arg(long, short = 'o', default_value = "kairos-live")]
    pub out: PathBuf,
    /// Skip the plots.
    #[arg(long)]
    pub no_plots: bool,
    /// Replay against this running replay server instead of starting one (see `--serve`);
    /// it runs one system, the first of `--variants`, which must match the server's policy.
    #[arg(long, requires_all = ["pin", "token"])]
    pub server: Option<SocketAddr>,
    /// The remote server's certificate pin, `sha256:<64 hex>`.
    #[arg(long)]
    pub pin: Option<Fingerprint>,
    /// A robot token of the remote server.
    #[arg(long)]
    pub token: Option<String>,
    /// How the simulation models the robot link: `measured` (the live run's network + client
    /// overhead per round) or `free`.
    #[arg(long, default_value = "measured", value_name = "measured|free")]
    pub sim_network: SimNetworkMode,
    /// Only simulate the runs (what the live runs would be compared with), printing the table.
    #[arg(long, conflicts_with_all = ["server", "serve"])]
    pub sim_only: bool,
    /// Only serve: start the replay server for this workload on ADDR with the scheduler of the
    /// first of `--variants`, print how to connect, and wait for Ctrl-C.
    #[arg(long, conflicts_with = "server")]
    pub serve: Option<SocketAddr>,
    /// Users' plugins to run beside the built-in systems, as in `kairos bench sim`.
    #[command(flatten)]
    pub plugins: super::bench::UserPluginArgs,
}

/// Runs `kairos bench live`.
pub fn run(args: LiveArgs) -> anyhow::Result<()> {
    let k = args.time_scale;
    if !(k.is_finite() && k > 0.0) {
        bail!("--time-scale must be a positive number");
    }
    // Users' plugins, loaded and registered exactly as `kairos bench sim` does it; the server
    // of every live run and its simulation resolve policies in the same registries.
    let user = args.plugins.load()?;
    let (w, set) = load(
        &args.workload,
        args.traces.as_deref(),
        args.trace_seed,
        &user,
    )?;
    let rate = match args.rate {
        Some(r) if r.is_finite() && r > 0.0 => r,
        Some(r) => bail!("--rate must be a positive number, got {r}"),
        None => w.experiments.rates[w.experiments.rates.len() / 2],
    };
    let mut variants = args
        .variants
        .iter()
        .map(|key| variant(key.trim()))
        .collect::<anyhow::Result<Vec<_>>>()?;
    variants.extend(user.variants(args.plugins.plugin_refetch));
    // A run's job, with the users' plugins registered.
    let job_for = |v: &Variant, rate: f64, tasks: usize, seed: u64, k: f64| {
        let mut job = live_job(&w, v, rate, tasks, seed, k);
        job.config.policies = user.policies.clone();
        job
    };
    let first = variants.first().context("--variants is empty")?;
    let tasks = usize::try_from(args.tasks).context("--tasks")?;
    let scaled = scale_traces(&set, k);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;

    if let Some(listen) = args.serve {
        let job = job_for(first, rate, tasks, args.seed, k);
        let data_dir = args.out.join("server-data");
        return runtime.block_on(async {
            let server = start_replay_server(&job, &scaled, listen, &data_dir).await?;
            let token = server
                .token
                .clone()
                .context("the replay server generated no robot token")?;
            println!(
                "trace-replay server for `{}` ({} scheduler, time scale {k}) on {}",
                w.name,
                first.label,
                server.addr()
            );
            println!(
                "connect with: kairos bench live -w {} --variants {} --time-scale {k} --server {} --pin {} --token {token}",
                args.workload.display(),
                first.key,
                server.addr(),
                server.pin
            );
            tokio::signal::ctrl_c().await.context("waiting for Ctrl-C")?;
            server.shutdown().await;
            anyhow::Ok(())
        });
    }

    let runs: Vec<Variant> = match args.server {
        Some(_) => vec![first.clone()],
        None => variants,
    };
    println!(
        "live replay of `{}`: {} tasks at {rate} tasks/s (seed {}), time scale {k}, systems: {}",
        w.name,
        tasks,
        args.seed,
        runs.iter()
            .map(|v| v.label.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    );
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut rows = Vec::new();
    for v in &runs {
        let job = job_for(v, rate, tasks, args.seed, k);
        if args.sim_only {
            let sim = simulate_scaled(&job, &scaled, k)?;
            println!(
                "{:<24} sim P25 {:.2} s, avg {:.2} s, P95 {:.2} s, {:.1} rounds/task, batch {:.2}, queue {:.0} ms, re-fetched {:.0}%",
                v.label,
                sim.summary.p25,
                sim.summary.mean,
                sim.summary.p95,
                sim.rounds_per_task,
                sim.mean_batch,
                sim.mean_queue_s * 1e3,
                sim.refetch_share * 100.0
            );
            continue;
        }
        let target = match (args.server, args.pin, &args.token) {
            (Some(addr), Some(pin), Some(token)) => Target::Remote {
                addr,
                pin,
                token: token.clone(),
            },
            _ => Target::InProcess(args.out.join("server-data")),
        };
        let bar = ProgressBar::new(tasks as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} {prefix:<24} [{elapsed_precise}] {bar:30} {pos}/{len} tasks, {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(v.label.clone());
        bar.set_message("connecting");
        bar.enable_steady_tick(Duration::from_millis(200));
        let rounds = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let (events_bar, events_rounds) = (bar.clone(), Arc::clone(&rounds));
        let outcome = runtime.block_on(run_live(&job, &scaled, &target, move |event| {
            use std::sync::atomic::Ordering;
            match event {
                LiveEvent::Connected => events_bar.set_message("running"),
                LiveEvent::Round => {
                    let n = events_rounds.fetch_add(1, Ordering::Relaxed) + 1;
                    events_bar.set_message(format!("{n} rounds"));
                }
                LiveEvent::TaskDone => events_bar.inc(1),
            }
        }))?;
        bar.finish_and_clear();
        let row = compare(job, &outcome, &scaled, k, args.sim_network)?;
        println!(
            "{:<24} live avg {:.2} s, sim avg {:.2} s ({:+.1}%), {:.1} s wall",
            v.label,
            row.live.summary.mean,
            row.sim.summary.mean,
            relative_diff(row.live.summary.mean, row.sim.summary.mean) * 100.0,
            row.measured.wall.as_secs_f64()
        );
        rows.push(row);
    }
    if args.sim_only {
        return Ok(());
    }
    write_outputs(&args, &w, rate, k, &rows)
}

fn write_outputs(
    args: &LiveArgs,
    w: &Workload,
    rate: f64,
    k: f64,
    rows: &[Comparison],
) -> anyhow::Result<()> {
    let workloads = [w.clone()];
    let jobs: Vec<Job> = rows.iter().map(|c| c.job.clone()).collect();
    let live: Vec<JobResult> = rows.iter().map(|c| c.live.clone()).collect();
    let sim: Vec<JobResult> = rows.iter().map(|c| c.sim.clone()).collect();
    let live_report = Report {
        workloads: &workloads,
        jobs: &jobs,
        results: &live,
    };
    let sim_report = Report {
        workloads: &workloads,
        jobs: &jobs,
        results: &sim,
    };
    let wall: f64 = rows.iter().map(|c| c.measured.wall.as_secs_f64()).sum();
    let network = match args.sim_network {
        SimNetworkMode::Measured => format!(
            "the robot round trip set to the live run's measured network + client overhead per round ({})",
            rows.iter()
                .map(|c| format!("{:.2} ms", c.sim_rtt.as_secs_f64() * 1e3))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        SimNetworkMode::Free => "a free network (zero round trip)".to_string(),
    };
    let mut summary = format!(
        "# Live replay vs simulation\n\nGenerated by `kairos bench live -w {}` ({} tasks at {rate} tasks/s, seed {}, trace seed {}, time scale {k}); {wall:.1} s of live runs. Times are in the recording's seconds (wall-clock x {k}) except the last three columns, which are wall-clock.\n\nLive: robots replay the traces over QUIC on loopback against the real server, whose engine is the trace-replay engine (the profiled latency of `{}`, the recorded chunks). Sim: the same schedule and inputs in virtual time, with {network}. Each cell is live (sim).\n\n",
        args.workload.display(),
        args.tasks,
        args.seed,
        args.trace_seed,
        w.engines.edge.device,
    );
    summary.push_str(&comparison_table(rows));
    summary.push_str("\n## Live, as `kairos bench sim` reports it\n");
    summary.push_str(&live_report.peak_table());
    std::fs::write(args.out.join("summary.md"), &summary)
        .with_context(|| format!("writing {}", args.out.join("summary.md").display()))?;
    std::fs::write(args.out.join("live.csv"), live_report.csv())
        .with_context(|| format!("writing {}", args.out.join("live.csv").display()))?;
    std::fs::write(args.out.join("sim.csv"), sim_report.csv())
        .with_context(|| format!("writing {}", args.out.join("sim.csv").display()))?;
    if !args.no_plots {
        kairos_bench::plot::all(&live_report, &args.out)?;
    }
    println!("\n{summary}");
    println!("Outputs in {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: LiveArgs,
    }

    fn parse(extra: &[&str]) -> Result<LiveArgs, clap::Error> {
        Cli::try_parse_from(std::iter::once("live").chain(extra.iter().copied())).map(|c| c.args)
    }

    #[test]
    fn arguments_parse_and_remote_runs_need_a_pin_and_token() {
        let args = parse(&["--variants", "fifo,kairos", "--tasks", "12"]).unwrap();
        assert_eq!(args.variants, ["fifo", "kairos"]);
        assert_eq!(args.sim_network, SimNetworkMode::Measured);
        assert!(parse(&["--server", "127.0.0.1:4433"]).is_err());
        assert!(parse(&["--tasks", "0"]).is_err());
        assert!(parse(&["--serve", "127.0.0.1:1", "--server", "127.0.0.1:2"]).is_err());
        assert!(variant("kairos").is_ok());
        let unknown = variant("lottery").unwrap_err().to_string();
        assert!(unknown.contains("fifo"), "{unknown}");
    }
}
