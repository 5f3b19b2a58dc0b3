//! `kairos robot`: a fleet of simulated robots against a Kairos server.
//!
//! Each robot is its own QUIC connection and runs one task with the SDK's [`RobotRunner`]:
//! actions execute at the control frequency in real time, the next request goes out at the
//! trigger, chunks are aligned on arrival. At the end it prints task and round latency
//! percentiles and the server's timing breakdown.
//!
//! Against a local `kairos serve`, no flag is needed: the pin and the token of `--robot-name` come
//! from the server's data directory ([`DataDir`]).
//!
//! `run` is synchronous: it builds its own multi-threaded tokio runtime. The robots run through
//! [`kairos_bench::fleet`], like `kairos demo` and `kairos bench live`.

use std::collections::BTreeMap;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{Context, bail};
use indicatif::{ProgressBar, ProgressStyle};
use kairos_sdk::client::{Client, ClientConfig};
use kairos_sdk::protocol::{HorizonSelection, Submit, encode_body};
use kairos_sdk::robot::{
    Robot, RobotRunner, RunnerConfig, RunnerEvent, SimulatedRobot, TaskSummary,
};
use kairos_sdk::tls::{Fingerprint, ServerTrust};
use kairos_sdk::trace::{HorizonSetting, RecordSetup, RunnerTraceRecorder};
use tokio::time::Instant;

use kairos_bench::fleet;
use kairos_core::stats::{Summary, summarize_u64};
use kairos_server::data_dir::DataDir;

/// Run N simulated robots against a server and report per-task latency.
#[derive(clap::Args, Debug, Clone)]
pub struct RobotArgs {
    /// Server UDP address.
    #[arg(long, default_value = "127.0.0.1:4433")]
    pub server: SocketAddr,
    /// TLS server name (any name works with a pinned certificate).
    #[arg(long, default_value = "kairos")]
    pub server_name: String,
    /// Data directory of a local `kairos serve`, read for the certificate pin and the robot's
    /// token when `--pin` or `--token` is not given.
    #[arg(long, default_value = kairos_sdk::data_dir::DEFAULT_DATA_DIR)]
    pub data_dir: PathBuf,
    /// Pinned server certificate, `sha256:<64 hex>`.
    #[arg(long, conflicts_with = "ca_file")]
    pub pin: Option<Fingerprint>,
    /// Verify the server against the CA certificates in this PEM file instead of a pin.
    #[arg(long)]
    pub ca_file: Option<PathBuf>,
    /// The robots' token (default: `--robot-name`'s entry in the data directory's tokens file).
    #[arg(long)]
    pub token: Option<String>,
    /// Robot whose token is read from the data directory.
    #[arg(long, default_value = "default")]
    pub robot_name: String,
    /// Number of simulated robots, each with its own connection and task.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub robots: u32,
    /// Task length, in rounds.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..))]
    pub rounds: u64,
    /// Control frequency, actions per second.
    #[arg(long, default_value_t = 30.0, value_parser = parse_positive)]
    pub control_hz: f32,
    /// Executed fraction of a chunk at which the next request is sent (0 = at once, 1 = when
    /// the chunk runs out).
    #[arg(long, default_value_t = 0.5, value_parser = parse_fraction)]
    pub trigger: f32,
    /// Horizon policy, e.g. `threshold` or `static` (default: the server's).
    #[arg(long)]
    pub horizon: Option<String>,
    /// Horizon policy parameter, `NAME=VALUE`; repeatable (e.g. `--param t=0.4 --param h_min=8`).
    #[arg(long = "param", value_parser = super::parse_finite_param, requires = "horizon")]
    pub params: Vec<(String, f64)>,
    /// Chunk samples the horizon policy gets.
    #[arg(long, default_value_t = 1, requires = "horizon")]
    pub samples: u32,
    /// Cameras per robot (capped at the model's maximum).
    #[arg(long, default_value_t = 1)]
    pub cameras: u32,
    /// Camera image size, `HEIGHTxWIDTH`, sent raw as RGB u8.
    #[arg(long, default_value = "64x64", value_parser = parse_size)]
    pub image: (u32, u32),
    /// Answer the server's observation re-fetches with the observation already sent.
    #[arg(long)]
    pub no_refetch: bool,
    /// Delay between robot starts, ms.
    #[arg(long, default_value_t = 0)]
    pub stagger_ms: u64,
    /// Record every task as a trace (docs/TRACES.md) into this file.
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Setting label of the recorded tasks (default: `static` for the static policy,
    /// `dynamic` for any other, `default` when the server's default policy is used).
    #[arg(long, requires = "record")]
    pub record_setting: Option<String>,
}

fn parse_positive(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(value) if value.is_finite() && value > 0.0 => Ok(value),
        _ => Err(format!("expected a positive number, got {text:?}")),
    }
}

fn parse_fraction(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(value) if (0.0..=1.0).contains(&value) => Ok(value),
        _ => Err(format!("expected a number in [0, 1], got {text:?}")),
    }
}

fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let parse = || {
        let (height, width) = text.split_once(['x', 'X'])?;
        Some((height.trim().parse().ok()?, width.trim().parse().ok()?))
    };
    parse().ok_or_else(|| format!("expected HEIGHTxWIDTH, e.g. 224x224, got {text:?}"))
}

/// The trust decision: `--pin`, `--ca-file`, or the data directory's fingerprint.
fn resolve_trust(args: &RobotArgs) -> anyhow::Result<ServerTrust> {
    if let Some(pin) = args.pin {
        return Ok(ServerTrust::Pinned(pin));
    }
    if let Some(path) = &args.ca_file {
        return Ok(ServerTrust::ca_file(path)?);
    }
    let pin = DataDir::new(&args.data_dir)
        .read_pin()
        .context("no --pin given; pass the fingerprint `kairos serve` printed")?;
    Ok(ServerTrust::Pinned(pin))
}

/// The token: `--token`, or `--robot-name`'s entry in the data directory's tokens file.
fn resolve_token(args: &RobotArgs) -> anyhow::Result<String> {
    if let Some(token) = &args.token {
        return Ok(token.clone());
    }
    DataDir::new(&args.data_dir)
        .token(&args.robot_name)
        .context("no --token given; pass the robot's token")
}

/// Runs the fleet and prints the report. Builds its own tokio runtime.
pub fn run(args: RobotArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let outcome = runtime.block_on(run_fleet(&args))?;
    print!("{}", report(&args, &outcome.summaries));
    println!(
        "{}",
        fleet::RoundAccount::of(&outcome.summaries, u64::from(args.robots), args.rounds)
    );
    if !outcome.errors.is_empty() {
        eprintln!("{} of {} robots failed:", outcome.errors.len(), args.robots);
        for error in &outcome.errors {
            eprintln!("  {error:#}");
        }
        if outcome.summaries.is_empty() {
            bail!("every robot failed");
        }
    }
    Ok(())
}

/// Bytes of one observation as the simulated robots send it: a whole `Submit` frame, whose other
/// fields are a few dozen bytes.
async fn observation_frame_bytes(
    state_dim: usize,
    cameras: usize,
    height: u32,
    width: u32,
) -> anyhow::Result<u32> {
    let observation = SimulatedRobot::new(state_dim, cameras, height, width)
        .get_obs(0)
        .await?;
    let submit = Submit {
        task: 0,
        round: 0,
        sent_at_us: 0,
        observation,
        last_exec: None,
        horizon: None,
        remaining: None,
        attempt: 0,
        control_hz: None,
        seed: None,
        chunking: None,
    };
    let bytes = encode_body(&submit, u32::MAX)?.len();
    Ok(u32::try_from(bytes).unwrap_or(u32::MAX))
}

type Recorder = Mutex<RunnerTraceRecorder<std::io::BufWriter<std::fs::File>>>;

/// Feeds `event` to the trace recorder, if recording.
fn record(recorder: Option<&Recorder>, event: &RunnerEvent) -> Result<(), String> {
    let Some(recorder) = recorder else {
        return Ok(());
    };
    match recorder.lock() {
        Ok(mut recorder) => recorder.on_event(event).map_err(|error| error.to_string()),
        Err(_) => Err("the trace recorder panicked".to_owned()),
    }
}

/// Prints a line above the progress bar (or plainly when the bar is hidden, e.g. not a TTY).
fn note(progress: &ProgressBar, line: String) {
    progress.suspend(|| eprintln!("{line}"));
}

/// What the trace records about every task of this run.
fn record_setup(args: &RobotArgs, obs_bytes: u32) -> RecordSetup {
    let policy = args.horizon.clone().unwrap_or_else(|| "default".to_owned());
    let setting = args.record_setting.clone().unwrap_or_else(|| {
        match args.horizon.as_deref() {
            None => "default",
            Some("static") => "static",
            Some(_) => "dynamic",
        }
        .to_owned()
    });
    RecordSetup {
        setting,
        horizon: HorizonSetting {
            policy,
            params: args.params.iter().cloned().collect(),
        },
        control_hz: args.control_hz,
        obs_bytes,
    }
}

struct FleetOutcome {
    summaries: Vec<TaskSummary>,
    errors: Vec<anyhow::Error>,
}

async fn run_fleet(args: &RobotArgs) -> anyhow::Result<FleetOutcome> {
    let trust = resolve_trust(args)?;
    let token = resolve_token(args)?;
    let mut config = ClientConfig::new(args.server, trust, token);
    config.server_name = args.server_name.clone();
    // Fail fast on a wrong address, pin or token before starting the whole fleet.
    let probe = Client::connect(config.clone())
        .await
        .with_context(|| format!("cannot connect to {}", args.server))?;
    let welcome = probe
        .welcome()
        .await
        .context("connected but got no Welcome")?;
    probe.close().await;
    eprintln!(
        "{} at {}: model {} (chunk {}, action dim {}, state dim {}), robot {:?}",
        welcome.server,
        args.server,
        welcome.model.name,
        welcome.model.chunk_len,
        welcome.model.action_dim,
        welcome.model.state_dim,
        welcome.robot,
    );

    let progress = ProgressBar::new(u64::from(args.robots) * args.rounds);
    progress.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} rounds ({per_sec}) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    progress.enable_steady_tick(Duration::from_millis(200));
    let runner = RobotRunner::new(RunnerConfig {
        control_hz: args.control_hz,
        trigger: args.trigger,
        rounds: args.rounds,
        horizon: args.horizon.as_ref().map(|policy| HorizonSelection {
            policy: policy.clone(),
            params: args.params.iter().cloned().collect::<BTreeMap<_, _>>(),
            samples: args.samples,
        }),
        refetch: !args.no_refetch,
        ..RunnerConfig::default()
    });
    let cameras = args.cameras.min(welcome.model.max_images) as usize;
    let state_dim = welcome.model.state_dim as usize;
    // A model that matches images by name gets its own camera names.
    let camera_names = welcome.model.cameras.clone();
    let (height, width) = args.image;
    let recorder = match &args.record {
        Some(path) => {
            let obs_bytes = observation_frame_bytes(state_dim, cameras, height, width).await?;
            let file = std::fs::File::create(path)
                .with_context(|| format!("cannot create {}", path.display()))?;
            let recorder = RunnerTraceRecorder::new(
                std::io::BufWriter::new(file),
                record_setup(args, obs_bytes),
            )
            .with_context(|| format!("cannot write {}", path.display()))?;
            Some(Arc::new(Mutex::new(recorder)))
        }
        None => None,
    };

    let starts: Vec<Duration> = (0..u64::from(args.robots))
        .map(|index| Duration::from_millis(args.stagger_ms.saturating_mul(index)))
        .collect();
    let outcomes = fleet::run_from(Instant::now(), &starts, |index| {
        let (config, runner, progress) = (config.clone(), runner.clone(), progress.clone());
        let recorder = recorder.clone();
        let camera_names = camera_names.clone();
        async move {
            // Each robot connects at its start, so a large fleet does not handshake all at once.
            let client = Client::connect(config)
                .await
                .with_context(|| format!("robot {index}: cannot connect"))?;
            let mut robot = SimulatedRobot::new(state_dim, cameras, height, width)
                .with_camera_names(&camera_names);
            let task = client.task(rand::random());
            let summary = runner
                .run(&mut robot, task, |event| {
                    if let Err(error) = record(recorder.as_deref(), event) {
                        note(
                            &progress,
                            format!("robot {index}: trace not recorded: {error}"),
                        );
                    }
                    match event {
                        RunnerEvent::ReplyReceived { .. } => progress.inc(1),
                        RunnerEvent::RoundFailed {
                            round,
                            error,
                            retrying,
                            ..
                        } => {
                            let what = if *retrying { "retrying" } else { "giving up" };
                            note(
                                &progress,
                                format!("robot {index}: round {round} failed ({what}): {error}"),
                            );
                        }
                        _ => {}
                    }
                })
                .await
                .with_context(|| format!("robot {index}"))?;
            client.close().await;
            anyhow::Ok(summary)
        }
    })
    .await;
    let mut outcome = FleetOutcome {
        summaries: Vec::new(),
        errors: Vec::new(),
    };
    for robot in outcomes {
        match robot {
            Ok(Ok(summary)) => outcome.summaries.push(summary),
            Ok(Err(error)) => outcome.errors.push(error),
            Err(error) => outcome.errors.push(error.into()),
        }
    }
    progress.finish_and_clear();
    if let (Some(recorder), Some(path)) = (recorder, &args.record) {
        let recorder = Arc::try_unwrap(recorder)
            .map_err(|_| anyhow::anyhow!("a robot still holds the trace recorder"))?
            .into_inner()
            .map_err(|_| anyhow::anyhow!("the trace recorder panicked"))?;
        let tasks = recorder.tasks_written();
        let mut writer = recorder
            .finish()
            .with_context(|| format!("cannot write {}", path.display()))?;
        writer
            .flush()
            .with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!("recorded {tasks} task(s) to {}", path.display());
    }
    outcome
        .summaries
        .sort_by_key(|summary| summary.started_at_us);
    Ok(outcome)
}

fn ms(us: f64) -> String {
    if us >= 10_000_000.0 {
        format!("{:.1} s", us / 1e6)
    } else if us >= 1_000_000.0 {
        format!("{:.2} s", us / 1e6)
    } else {
        format!("{:.1} ms", us / 1e3)
    }
}

/// Milliseconds with microsecond resolution, for sub-millisecond latencies.
fn ms3(us: f64) -> String {
    format!("{:.3} ms", us / 1e3)
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, count) = values.fold((0.0, 0usize), |(sum, count), v| (sum + v, count + 1));
    if count == 0 { 0.0 } else { sum / count as f64 }
}

/// The end-of-run report: task and round latency percentiles, the server's timing breakdown,
/// and one line per task.
fn report(args: &RobotArgs, summaries: &[TaskSummary]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{} robot(s), {} rounds per task, {} Hz, trigger {}",
        args.robots, args.rounds, args.control_hz, args.trigger
    );
    let rounds: Vec<_> = summaries.iter().flat_map(|s| &s.rounds).collect();
    let tasks: Vec<u64> = summaries.iter().map(TaskSummary::latency_us).collect();
    let round_latencies: Vec<u64> = rounds.iter().map(|r| r.latency_us()).collect();
    let line = |name: &str, stats: Option<Summary>| match stats {
        Some(p) => format!(
            "{name:<15} p50 {:>9}  p95 {:>9}  avg {:>9}  max {:>9}\n",
            ms(p.p50),
            ms(p.p95),
            ms(p.mean),
            ms(p.max)
        ),
        None => format!("{name:<15} no data\n"),
    };
    out.push_str("task latency = first request to last action; round latency = request to reply\n");
    out.push_str(&line("task latency", summarize_u64(&tasks)));
    out.push_str(&line("round latency", summarize_u64(&round_latencies)));
    let tail = |name: &str, values: Vec<u64>| match summarize_u64(&values) {
        Some(p) => format!(
            "{name:<15} p50 {:>9}  p99 {:>9}  max {:>9}\n",
            ms3(p.p50),
            ms3(p.p99),
            ms3(p.max)
        ),
        None => format!("{name:<15} no data\n"),
    };
    out.push_str(
        "server-added = reply timing total - inference; network + client = round latency - server total\n",
    );
    out.push_str(&tail(
        "server-added",
        rounds
            .iter()
            .map(|r| r.timing.total_us.saturating_sub(r.timing.inference_us))
            .collect(),
    ));
    out.push_str(&tail(
        "network+client",
        rounds
            .iter()
            .map(|r| r.latency_us().saturating_sub(r.timing.total_us))
            .collect(),
    ));
    if !rounds.is_empty() {
        let server_total = mean(rounds.iter().map(|r| r.timing.total_us as f64));
        let _ = writeln!(
            out,
            "server timing per round (avg): queue {}, re-fetch {}, inference {}, server total {}, network + client {}, batch {:.2}",
            ms(mean(rounds.iter().map(|r| r.timing.queue_us as f64))),
            ms(mean(rounds.iter().map(|r| r.timing.refetch_us as f64))),
            ms(mean(rounds.iter().map(|r| r.timing.inference_us as f64))),
            ms(server_total),
            ms((mean(round_latencies.iter().map(|&l| l as f64)) - server_total).max(0.0)),
            mean(rounds.iter().map(|r| f64::from(r.timing.batch_size))),
        );
        let _ = writeln!(
            out,
            "chunks (avg per round): horizon H {:.1} of N {:.1}, discarded on arrival {:.1}, executed {:.1}, resent {:.2}, re-fetched {:.2}",
            mean(rounds.iter().map(|r| f64::from(r.horizon))),
            mean(rounds.iter().map(|r| f64::from(r.chunk_len))),
            mean(rounds.iter().map(|r| f64::from(r.discarded))),
            mean(rounds.iter().map(|r| f64::from(r.executed))),
            mean(
                rounds
                    .iter()
                    .map(|r| f64::from(r.attempts.saturating_sub(1)))
            ),
            mean(rounds.iter().map(|r| f64::from(r.refetches))),
        );
    }
    let unended: Vec<&TaskSummary> = summaries.iter().filter(|s| s.end_error.is_some()).collect();
    if let Some(first) = unended.first() {
        let _ = writeln!(
            out,
            "tasks not ended on the server: {} (task {:016x}: {})",
            unended.len(),
            first.task,
            first.end_error.as_deref().unwrap_or_default()
        );
    }
    let _ = writeln!(
        out,
        "{:<18} {:>6} {:>10} {:>10} {:>10} {:>10} {:>8} {:>6}",
        "task", "rounds", "latency", "round p50", "round p95", "idle", "actions", "failed"
    );
    for summary in summaries {
        let latencies: Vec<u64> = summary.rounds.iter().map(|r| r.latency_us()).collect();
        let stats = summarize_u64(&latencies);
        let _ = writeln!(
            out,
            "{:<18} {:>6} {:>10} {:>10} {:>10} {:>10} {:>8} {:>6}",
            format!("{:016x}", summary.task),
            summary.rounds.len(),
            ms(summary.latency_us() as f64),
            stats.map_or("-".to_owned(), |p| ms(p.p50)),
            stats.map_or("-".to_owned(), |p| ms(p.p95)),
            ms(summary.idle_us as f64),
            summary.actions_executed,
            summary.failed_rounds,
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use kairos_sdk::protocol::Timing;
    use kairos_sdk::robot::RoundRecord;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: RobotArgs,
    }

    fn parse(extra: &[&str]) -> Result<RobotArgs, clap::Error> {
        Cli::try_parse_from(std::iter::once("robot").chain(extra.iter().copied()))
            .map(|cli| cli.args)
    }

    #[test]
    fn arguments_parse_and_bad_ones_are_refused() {
        let args = parse(&[
            "--robots",
            "4",
            "--horizon",
            "threshold",
            "--param",
            "t=0.4",
            "--param",
            "h_min=8",
            "--image",
            "224x224",
            "--trigger",
            "1",
        ])
        .unwrap();
        assert_eq!(args.robots, 4);
        assert_eq!(
            args.params,
            [("t".to_owned(), 0.4), ("h_min".to_owned(), 8.0)]
        );
        assert_eq!(args.image, (224, 224));
        assert_eq!(args.trigger, 1.0);
        for bad in [
            &["--trigger", "1.5"][..],
            &["--control-hz", "0"],
            &["--robots", "0"],
            &["--image", "224"],
            &["--param", "t=0.4"],
            &["--horizon", "static", "--param", "h"],
            &["--pin", "sha256:1234"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?} should be refused");
        }
    }

    #[test]
    fn pin_and_token_come_from_the_data_dir() {
        let dir = tempfile::tempdir().unwrap();
        let pin = Fingerprint([7; 32]);
        let data_dir = DataDir::new(dir.path());
        data_dir.write_fingerprint(&pin.to_string()).unwrap();
        std::fs::write(
            data_dir.tokens(),
            "[[robot]]\nname = \"default\"\ntoken = \"kairos_abc\"\n\n[[robot]]\nname = \"arm2\"\ntoken = \"kairos_def\"\n",
        )
        .unwrap();
        let data_dir = dir.path().to_str().unwrap();
        let args = parse(&["--data-dir", data_dir, "--robot-name", "arm2"]).unwrap();
        assert!(matches!(resolve_trust(&args).unwrap(), ServerTrust::Pinned(p) if p == pin));
        assert_eq!(resolve_token(&args).unwrap(), "kairos_def");
        let flags = parse(&[
            "--data-dir",
            data_dir,
            "--token",
            "t",
            "--pin",
            &Fingerprint([1; 32]).to_string(),
        ])
        .unwrap();
        assert_eq!(resolve_token(&flags).unwrap(), "t");
        assert!(
            matches!(resolve_trust(&flags).unwrap(), ServerTrust::Pinned(p) if p == Fingerprint([1; 32]))
        );
        let missing = parse(&["--data-dir", data_dir, "--robot-name", "nobody"]).unwrap();
        let error = format!("{:#}", resolve_token(&missing).unwrap_err());
        assert!(error.contains("nobody"), "{error}");
        let empty = tempfile::tempdir().unwrap();
        let nothing = parse(&["--data-dir", empty.path().to_str().unwrap()]).unwrap();
        let error = format!("{:#}", resolve_trust(&nothing).unwrap_err());
        assert!(error.contains("fingerprint.txt"), "{error}");
    }

    #[tokio::test]
    async fn recording_setup_follows_the_horizon_flags() {
        let args = parse(&[
            "--record",
            "t.jsonl",
            "--horizon",
            "static",
            "--param",
            "h=10",
            "--control-hz",
            "50",
        ])
        .unwrap();
        let setup = record_setup(&args, 123);
        assert_eq!(setup.setting, "static");
        assert_eq!(setup.horizon.policy, "static");
        assert_eq!(
            setup.horizon.params,
            BTreeMap::from([("h".to_owned(), 10.0)])
        );
        assert_eq!((setup.control_hz, setup.obs_bytes), (50.0, 123));
        let threshold = parse(&["--record", "t", "--horizon", "threshold"]).unwrap();
        assert_eq!(record_setup(&threshold, 0).setting, "dynamic");
        let labelled = parse(&["--record", "t", "--record-setting", "h8"]).unwrap();
        assert_eq!(record_setup(&labelled, 0).setting, "h8");
        assert!(parse(&["--record-setting", "x"]).is_err(), "needs --record");
        // 2 cameras of 8×8×3 raw bytes plus a 4-float state, and the frame around them.
        let bytes = observation_frame_bytes(4, 2, 8, 8).await.unwrap();
        assert!((2 * 192 + 16..2 * 192 + 400).contains(&bytes), "{bytes}");
    }

    #[test]
    fn report_shows_latencies_and_the_timing_breakdown() {
        let record = |round: u64, latency_ms: u64| RoundRecord {
            round,
            sent_at_us: 0,
            received_at_us: latency_ms * 1000,
            attempts: 1,
            refetches: 0,
            horizon: 10,
            chunk_len: 50,
            discarded: 2,
            executed: 8,
            policy: "threshold".to_owned(),
            timing: Timing {
                queue_us: 30_000,
                refetch_us: 0,
                inference_us: 50_000,
                total_us: 80_000,
                batch_size: 2,
            },
        };
        let summary = TaskSummary {
            task: 0xabc,
            rounds: vec![record(0, 100), record(1, 120)],
            started_at_us: 0,
            finished_at_us: 2_500_000,
            actions_executed: 16,
            idle_us: 100_000,
            failed_rounds: 0,
            server_record: None,
            end_error: None,
        };
        let args = parse(&[]).unwrap();
        let unended = TaskSummary {
            task: 0xdef,
            end_error: Some("server error unknown_task: task 3567 is not open".into()),
            ..summary.clone()
        };
        let text = report(&args, &[summary.clone(), unended]);
        assert!(
            text.contains(
                "tasks not ended on the server: 1 (task 0000000000000def: server error unknown_task"
            ),
            "{text}"
        );
        let text = report(&args, &[summary]);
        assert!(!text.contains("not ended"), "{text}");
        // The project's one percentile (kairos_core::stats): 100 and 120 ms have a median of 110.
        assert!(text.contains("round latency   p50  110.0 ms"), "{text}");
        assert!(text.contains("queue 30.0 ms"), "{text}");
        assert!(text.contains("network + client 30.0 ms"), "{text}");
        // total 80 ms - inference 50 ms; round latency 100/120 ms - total 80 ms.
        assert!(
            text.contains("server-added    p50 30.000 ms  p99 30.000 ms"),
            "{text}"
        );
        assert!(
            text.contains("network+client  p50 30.000 ms  p99 39.800 ms"),
            "{text}"
        );
        assert!(text.contains("0000000000000abc"), "{text}");
        assert!(text.contains("2.50 s"), "{text}");
    }
}
