//! The `kairos` command line: one module per subcommand, each with a `clap::Args` struct and a
//! `run` function that calls the library (`demo`, `live_replay`, `fleet`, `sim`, ...) and prints.
//! Nothing here is reused by other code: tests and other subcommands import the library modules.
//! `main.rs` only parses and dispatches.
pub mod bench;
pub mod bench_horizon;
pub mod bench_live;
pub mod demo;
pub mod plugin;
pub mod predict;
pub mod profile;
pub mod robot;
pub mod serve;
pub mod worker;

/// A policy parameter on the command line, `name=value` with a numeric value (`inf` is one).
pub(crate) fn parse_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = text
        .split_once('=')
        .ok_or_else(|| format!("`{text}` is not key=value"))?;
    let name = name.trim();
    if name.is_empty() {
        return Err(format!("`{text}` has an empty name"));
    }
    let value: f64 = value
        .trim()
        .parse()
        .map_err(|_| format!("{name}: `{value}` is not a number"))?;
    Ok((name.to_owned(), value))
}

/// [`parse_param`], with a finite value.
pub(crate) fn parse_finite_param(text: &str) -> Result<(String, f64), String> {
    let (name, value) = parse_param(text)?;
    if !value.is_finite() {
        return Err(format!("{name}: `{text}` must have a finite value"));
    }
    Ok((name, value))
}

/// Logs to stderr (stdout stays free for a command's output), at `RUST_LOG`'s filter or else
/// `default_filter`. A second call is a no-op, so tests may run several commands in one process.
pub(crate) fn init_logging(default_filter: &str) {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter)),
        )
        .with_writer(std::io::stderr)
        .try_init();
}
