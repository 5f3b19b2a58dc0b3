//! Round latency over an impaired link: the real client and a real QUIC/TLS responder with a
//! userspace impairment proxy between them (loss, delay, jitter that reorders), comparing quinn's
//! default transport with the tuned one (`docs/PROTOCOL.md` § Transport).
//!
//! The workload follows FIELD-NOTES: 8 robots, 100 KB observation up, 1.4 KB chunk back
//! (50 × 7 f32), 3 requests per second each. Each (link, transport) cell runs twice, in
//! alternating order, so load from other processes on the machine biases no configuration.
//!
//! `cargo bench -p kairos-sdk --bench lossy_link --profile dev [-- ROUNDS]`

#![allow(clippy::unwrap_used, missing_docs)]

#[path = "../tests/it/support/mod.rs"]
mod support;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use kairos_sdk::client::{Client, ClientConfig, NoRefetch, RoundRequest};
use kairos_sdk::protocol::{Image, ImagePayload, Tensor};
use kairos_sdk::transport::{Congestion, TransportTuning};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use support::{Behavior, Responder, observation};
use tokio::net::UdpSocket;
use tokio::time::Instant;

const ROBOTS: usize = 8;
const PERIOD: Duration = Duration::from_millis(333);

#[derive(Clone, Copy, Debug)]
struct Link {
    name: &'static str,
    delay: Duration,
    jitter: Duration,
    loss: f64,
}

/// Forwards datagrams between clients and `server`, each direction delayed by
/// `delay ± jitter` (uniform, per packet, so packets reorder) and dropped with probability
/// `loss`.
async fn start_proxy(server: SocketAddr, link: Link, seed: u64) -> SocketAddr {
    let front = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
    let addr = front.local_addr().unwrap();
    let rng = Arc::new(Mutex::new(StdRng::seed_from_u64(seed)));
    tokio::spawn(async move {
        let mut upstreams: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
        let mut buf = vec![0u8; 65536];
        while let Ok((len, client)) = front.recv_from(&mut buf).await {
            let upstream = match upstreams.get(&client) {
                Some(upstream) => upstream.clone(),
                None => {
                    let upstream = Arc::new(UdpSocket::bind("127.0.0.1:0").await.unwrap());
                    upstream.connect(server).await.unwrap();
                    upstreams.insert(client, upstream.clone());
                    let (front, upstream_rx, rng) = (front.clone(), upstream.clone(), rng.clone());
                    tokio::spawn(async move {
                        let mut buf = vec![0u8; 65536];
                        while let Ok(len) = upstream_rx.recv(&mut buf).await {
                            let front = front.clone();
                            impair(&rng, link, buf[..len].to_vec(), move |packet| async move {
                                let _ = front.send_to(&packet, client).await;
                            });
                        }
                    });
                    upstream
                }
            };
            impair(&rng, link, buf[..len].to_vec(), move |packet| async move {
                let _ = upstream.send(&packet).await;
            });
        }
    });
    addr
}

fn impair<F, Fut>(rng: &Mutex<StdRng>, link: Link, packet: Vec<u8>, send: F)
where
    F: FnOnce(Vec<u8>) -> Fut + Send + 'static,
    Fut: std::future::Future<Output = ()> + Send,
{
    let (drop, offset) = {
        let mut rng = rng.lock().unwrap();
        (
            rng.random::<f64>() < link.loss,
            rng.random_range(-1.0..=1.0f64),
        )
    };
    if drop {
        return;
    }
    let delay = link.delay.as_secs_f64() + offset * link.jitter.as_secs_f64();
    let delay = Duration::try_from_secs_f64(delay.max(0.0)).unwrap_or(Duration::ZERO);
    let deadline = Instant::now() + delay;
    tokio::spawn(async move {
        tokio::time::sleep_until(deadline).await;
        send(packet).await;
    });
}

/// Round latencies (µs) of `ROBOTS` robots doing `rounds` rounds each, and the rounds that failed.
async fn measure(
    link: Link,
    tuning: &TransportTuning,
    rounds: usize,
    seed: u64,
) -> (Vec<u64>, usize) {
    let responder = Responder::start(Behavior {
        horizon: 50,
        chunk_len: 50,
        action_dim: 7,
        generation: Duration::ZERO,
        tuning: tuning.clone(),
        ..Behavior::default()
    });
    let proxy = start_proxy(responder.addr, link, seed).await;
    let mut robots = tokio::task::JoinSet::new();
    for robot in 0..ROBOTS {
        let mut config = ClientConfig::pinned(proxy, responder.fingerprint, "secret");
        config.transport = tuning.clone();
        config.connect_timeout = Duration::from_secs(10);
        robots.spawn(async move {
            let client = Client::connect(config).await.unwrap();
            let mut task = client.task(robot as u64);
            let mut latencies = Vec::with_capacity(rounds);
            let mut failures = 0;
            // Spread the robots over the period, as independent robots would be.
            let start = Instant::now() + PERIOD * robot as u32 / ROBOTS as u32;
            for round in 0..rounds {
                tokio::time::sleep_until(start + PERIOD * round as u32).await;
                let mut obs = observation(client.now_us());
                obs.images = vec![Image {
                    camera: "front".to_owned(),
                    payload: ImagePayload::Raw {
                        tensor: Tensor::from_u8(vec![100, 334, 3], vec![round as u8; 100_200])
                            .unwrap(),
                    },
                }];
                match task.submit(RoundRequest::new(obs), &mut NoRefetch).await {
                    Ok(reply) => latencies.push(reply.received_at_us - reply.sent_at_us),
                    Err(_) => failures += 1,
                }
            }
            client.close().await;
            (latencies, failures)
        });
    }
    let mut all = Vec::new();
    let mut failures = 0;
    while let Some(result) = robots.join_next().await {
        let (latencies, failed) = result.unwrap();
        all.extend(latencies);
        failures += failed;
    }
    drop(responder);
    (all, failures)
}

/// The `p`-quantile of ascending latencies in µs, in ms: the project's one percentile
/// definition (`kairos_core::stats::quantile`, linear interpolation).
fn percentile(sorted: &[u64], p: f64) -> f64 {
    let ms: Vec<f64> = sorted.iter().map(|&us| us as f64 / 1000.0).collect();
    kairos_core::stats::quantile(&ms, p)
}

#[tokio::main]
async fn main() {
    let rounds: usize = std::env::args()
        .skip(1)
        .find_map(|arg| arg.parse().ok())
        .unwrap_or(40);
    let links = [
        Link {
            name: "2.5 ms, 1% loss",
            delay: Duration::from_micros(1250),
            jitter: Duration::ZERO,
            loss: 0.01,
        },
        Link {
            name: "2.5 ms, 5% loss",
            delay: Duration::from_micros(1250),
            jitter: Duration::ZERO,
            loss: 0.05,
        },
        Link {
            name: "20 ± 10 ms jitter, 2% loss",
            delay: Duration::from_millis(10),
            jitter: Duration::from_millis(5),
            loss: 0.02,
        },
    ];
    let cubic_tuned = TransportTuning {
        congestion: Congestion::Cubic,
        ..TransportTuning::default()
    };
    let configs = [
        ("quinn defaults", TransportTuning::quinn_defaults()),
        ("tuned, CUBIC", cubic_tuned),
        ("tuned (BBR)", TransportTuning::default()),
    ];
    println!(
        "{ROBOTS} robots × {rounds} rounds × 2 runs per cell, 100 KB up / 1.4 KB down, 3 req/s per robot; RTT = 2 × one-way delay"
    );
    println!("| link | transport | p50 ms | p99 ms | max ms | rounds | failed |");
    println!("|---|---|---|---|---|---|---|");
    for (l, link) in links.iter().enumerate() {
        let mut results: Vec<(Vec<u64>, usize)> = vec![(Vec::new(), 0); configs.len()];
        for run in 0..2 {
            let order: Vec<usize> = if run == 0 {
                (0..configs.len()).collect()
            } else {
                (0..configs.len()).rev().collect()
            };
            for c in order {
                let seed = (l * 100 + c * 10 + run) as u64;
                let (latencies, failed) = measure(*link, &configs[c].1, rounds, seed).await;
                results[c].0.extend(latencies);
                results[c].1 += failed;
            }
        }
        for (c, (mut latencies, failed)) in results.into_iter().enumerate() {
            latencies.sort_unstable();
            println!(
                "| {} | {} | {:.1} | {:.1} | {:.1} | {} | {} |",
                link.name,
                configs[c].0,
                percentile(&latencies, 0.50),
                percentile(&latencies, 0.99),
                percentile(&latencies, 1.0),
                latencies.len(),
                failed
            );
        }
    }
}
