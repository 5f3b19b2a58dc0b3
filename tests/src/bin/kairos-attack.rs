//! The attackers of the mixed soak (`scripts/soak.sh --mixed`), together in one process
//! (`kairos_tests::attacks`): a slowloris on the QUIC robot listener, on the openpi listener and
//! on the metrics listener, and one robot token that opens every connection it can and holds
//! them. Runs until SIGINT/SIGTERM or `--seconds`; prints each attack's counts every 30 s and
//! at the end.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use kairos_sdk::tls::ServerTrust;
use kairos_server::data_dir::DataDir;
use kairos_tests::attacks::{
    AttackCounters, connection_hog, slowloris_quic, slowloris_tcp, until_stopped,
};
use tokio::task::JoinSet;

/// Attack a Kairos server's listeners.
#[derive(Parser, Debug)]
#[command(name = "kairos-attack", version)]
struct Args {
    /// The QUIC robot listener.
    #[arg(long)]
    server: SocketAddr,
    /// The server's data directory, for its certificate pin (public: robots pin it).
    #[arg(long)]
    data_dir: PathBuf,
    /// The openpi listener (no attack on it without).
    #[arg(long)]
    openpi: Option<SocketAddr>,
    /// The metrics listener (no attack on it without).
    #[arg(long)]
    metrics: Option<SocketAddr>,
    /// A robot token for the connection hog (no hog without).
    #[arg(long)]
    hog_token: Option<String>,
    /// Slowloris connections held on the QUIC listener (0: none).
    #[arg(long, default_value_t = 64)]
    quic_slots: usize,
    /// Slowloris connections held on each TCP listener.
    #[arg(long, default_value_t = 64)]
    tcp_slots: usize,
    /// Attack from this address of the host (e.g. 127.0.0.2 on loopback), so that the server's
    /// per-address guards see the attacker apart from clients on the default address.
    #[arg(long)]
    source_ip: Option<IpAddr>,
    /// Stop after this long (default: at SIGINT/SIGTERM).
    #[arg(long)]
    seconds: Option<u64>,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let pin = DataDir::new(&args.data_dir)
        .read_pin()
        .context("reading the server's pin")?;
    let trust = ServerTrust::Pinned(pin);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let mut attacks: Vec<(&str, Arc<AttackCounters>)> = Vec::new();
    runtime.block_on(async {
        let mut set = JoinSet::new();
        if args.quic_slots > 0 {
            let counters = AttackCounters::shared();
            attacks.push(("slowloris quic", counters.clone()));
            set.spawn(slowloris_quic(
                args.server,
                trust.clone(),
                args.quic_slots,
                counters,
                args.source_ip,
            ));
        }
        for (name, target) in [
            ("slowloris openpi", args.openpi),
            ("slowloris metrics", args.metrics),
        ] {
            if let Some(target) = target {
                let counters = AttackCounters::shared();
                attacks.push((name, counters.clone()));
                set.spawn(async move {
                    slowloris_tcp(target, args.tcp_slots, counters, args.source_ip).await;
                    Ok(())
                });
            }
        }
        if let Some(token) = args.hog_token.clone() {
            let counters = AttackCounters::shared();
            attacks.push(("connection hog", counters.clone()));
            set.spawn(connection_hog(
                args.server,
                trust.clone(),
                token,
                counters,
                args.source_ip,
            ));
        }
        let report = async {
            let mut ticker = tokio::time::interval(Duration::from_secs(30));
            ticker.tick().await;
            loop {
                ticker.tick().await;
                for (name, counters) in &attacks {
                    println!("{name}: {}", counters.summary());
                }
            }
        };
        tokio::select! {
            Some(Ok(Err(error))) = set.join_next() => eprintln!("an attack failed: {error:#}"),
            () = until_stopped(args.seconds) => {}
            () = report => {}
        }
        set.abort_all();
    });
    for (name, counters) in &attacks {
        println!("{name}: {}", counters.summary());
    }
    Ok(())
}
