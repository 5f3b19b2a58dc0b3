//! A userspace UDP impairment proxy on loopback, owned by the test that starts it.
//!
//! The kernel here has no `netem`, so lossy links are emulated between client and server:
//! clients send to [`Proxy::addr`]; each client address gets its own upstream socket towards the
//! server, so a client that rebinds to a new port appears to the server as a new address (what a
//! NAT rebinding or Wi-Fi roam looks like) and QUIC connection migration is exercised. Each
//! direction has its own [`Impairment`]: loss, a base delay, jitter (a uniform extra delay per
//! packet, so packets overtake each other: reordering) and duplication. Decisions come from
//! seeded RNGs, one per direction. It listens on loopback ([`Proxy::start`]) or on any local
//! address ([`Proxy::start_on`]: the host side of a network namespace's veth pair, for a delay
//! relay in front of a "far" worker). The proxy is bounded (at most `max_queued` packets in flight
//! per direction; beyond that packets are dropped and counted) and stops itself when dropped or
//! after `idle_timeout` without a packet.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::JoinSet;

/// What happens to packets in one direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Impairment {
    /// Probability that a packet is dropped.
    pub loss: f64,
    /// Delay every packet gets.
    pub delay: Duration,
    /// Extra delay, uniform in `[0, jitter]`, drawn per packet: later packets can overtake.
    pub jitter: Duration,
    /// Probability that a packet is delivered twice (with independent delays).
    pub duplicate: f64,
}

impl Impairment {
    /// A perfect link.
    pub const NONE: Impairment = Impairment {
        loss: 0.0,
        delay: Duration::ZERO,
        jitter: Duration::ZERO,
        duplicate: 0.0,
    };
}

/// The proxy's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProxyConfig {
    /// Client → server.
    pub to_server: Impairment,
    /// Server → client.
    pub to_client: Impairment,
    /// Seed of the per-direction RNGs.
    pub seed: u64,
    /// Packets in flight per direction before new ones are dropped.
    pub max_queued: usize,
    /// The proxy stops after this long without a packet.
    pub idle_timeout: Duration,
}

impl ProxyConfig {
    /// The same impairment both ways.
    pub fn symmetric(impairment: Impairment, seed: u64) -> ProxyConfig {
        ProxyConfig {
            to_server: impairment,
            to_client: impairment,
            seed,
            max_queued: 4096,
            idle_timeout: Duration::from_secs(60),
        }
    }
}

/// Packet counts of one direction.
#[derive(Debug, Default)]
pub struct DirectionStats {
    /// Packets received from the sender.
    pub received: AtomicU64,
    /// Dropped on purpose (loss).
    pub lost: AtomicU64,
    /// Extra copies scheduled.
    pub duplicated: AtomicU64,
    /// Dropped because `max_queued` was reached.
    pub overflow: AtomicU64,
    /// Delivered after a packet sent later (reordered).
    pub reordered: AtomicU64,
    /// Sent on.
    pub delivered: AtomicU64,
}

/// Counts of both directions, plus flows.
#[derive(Debug, Default)]
pub struct ProxyStats {
    /// Client → server.
    pub to_server: DirectionStats,
    /// Server → client.
    pub to_client: DirectionStats,
    /// Distinct client addresses seen (a rebind adds one).
    pub flows: AtomicU64,
    /// Those addresses, in the order first seen.
    pub clients: Mutex<Vec<SocketAddr>>,
}

/// A running proxy. Dropping it stops it.
pub struct Proxy {
    addr: SocketAddr,
    stats: Arc<ProxyStats>,
    tasks: JoinSet<()>,
}

impl Proxy {
    /// Starts a proxy on `127.0.0.1:0` in front of `server`.
    pub async fn start(server: SocketAddr, config: ProxyConfig) -> std::io::Result<Proxy> {
        Proxy::start_on(SocketAddr::from(([127, 0, 0, 1], 0)), server, config).await
    }

    /// Starts a proxy listening on `bind` (e.g. the host side of a [`crate::netns::NetNs`]'s
    /// veth pair, so clients inside the namespace reach `server` only through it) in front of
    /// `server`.
    pub async fn start_on(
        bind: SocketAddr,
        server: SocketAddr,
        config: ProxyConfig,
    ) -> std::io::Result<Proxy> {
        let front = Arc::new(UdpSocket::bind(bind).await?);
        let addr = front.local_addr()?;
        let stats = Arc::new(ProxyStats::default());
        let mut tasks = JoinSet::new();
        let (to_server_tx, to_server_rx) = mpsc::channel(config.max_queued.max(1));
        let (to_client_tx, to_client_rx) = mpsc::channel(config.max_queued.max(1));
        tasks.spawn(deliver(to_server_rx, stats.clone(), Direction::ToServer));
        tasks.spawn(deliver(to_client_rx, stats.clone(), Direction::ToClient));
        let shared = Arc::new(Shared {
            config,
            stats: stats.clone(),
            to_server_rng: Mutex::new(StdRng::seed_from_u64(config.seed)),
            to_client_rng: Mutex::new(StdRng::seed_from_u64(config.seed ^ 0x9e37_79b9_7f4a_7c15)),
            last_packet: Mutex::new(Instant::now()),
            seq: AtomicU64::new(0),
        });
        tasks.spawn(front_loop(
            front,
            server,
            shared,
            to_server_tx,
            to_client_tx,
        ));
        Ok(Proxy { addr, stats, tasks })
    }

    /// Where clients send.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Packet counts so far.
    pub fn stats(&self) -> &ProxyStats {
        &self.stats
    }

    /// Stops the proxy now.
    pub fn stop(&mut self) {
        self.tasks.abort_all();
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.tasks.abort_all();
    }
}

#[derive(Clone, Copy)]
enum Direction {
    ToServer,
    ToClient,
}

struct Shared {
    config: ProxyConfig,
    stats: Arc<ProxyStats>,
    to_server_rng: Mutex<StdRng>,
    to_client_rng: Mutex<StdRng>,
    last_packet: Mutex<Instant>,
    seq: AtomicU64,
}

impl Shared {
    fn direction(&self, d: Direction) -> (&Impairment, &Mutex<StdRng>, &DirectionStats) {
        match d {
            Direction::ToServer => (
                &self.config.to_server,
                &self.to_server_rng,
                &self.stats.to_server,
            ),
            Direction::ToClient => (
                &self.config.to_client,
                &self.to_client_rng,
                &self.stats.to_client,
            ),
        }
    }

    /// Decides the fate of one packet and queues its copies.
    fn impair(
        &self,
        direction: Direction,
        data: &[u8],
        socket: &Arc<UdpSocket>,
        dest: SocketAddr,
        queue: &mpsc::Sender<Delivery>,
    ) {
        if let Ok(mut last) = self.last_packet.lock() {
            *last = Instant::now();
        }
        let (impairment, rng, stats) = self.direction(direction);
        stats.received.fetch_add(1, Ordering::Relaxed);
        let delays: Vec<Duration> = {
            let Ok(mut rng) = rng.lock() else { return };
            if rng.random::<f64>() < impairment.loss {
                stats.lost.fetch_add(1, Ordering::Relaxed);
                return;
            }
            let copies = if rng.random::<f64>() < impairment.duplicate {
                stats.duplicated.fetch_add(1, Ordering::Relaxed);
                2
            } else {
                1
            };
            (0..copies)
                .map(|_| {
                    let jitter = impairment.jitter.as_secs_f64() * rng.random::<f64>();
                    // A fraction of a configured duration: always in range.
                    impairment.delay + Duration::try_from_secs_f64(jitter).unwrap_or(Duration::ZERO)
                })
                .collect()
        };
        let now = Instant::now();
        for delay in delays {
            let delivery = Delivery {
                at: now + delay,
                seq: self.seq.fetch_add(1, Ordering::Relaxed),
                socket: socket.clone(),
                dest,
                data: data.to_vec(),
            };
            if queue.try_send(delivery).is_err() {
                stats.overflow.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    fn idle_for(&self) -> Duration {
        self.last_packet
            .lock()
            .map(|last| last.elapsed())
            .unwrap_or_default()
    }
}

struct Delivery {
    at: Instant,
    seq: u64,
    socket: Arc<UdpSocket>,
    dest: SocketAddr,
    data: Vec<u8>,
}

impl PartialEq for Delivery {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for Delivery {}
impl PartialOrd for Delivery {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Delivery {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.at, self.seq).cmp(&(other.at, other.seq))
    }
}

/// Sends each queued packet at its time, earliest first.
async fn deliver(
    mut queue: mpsc::Receiver<Delivery>,
    stats: Arc<ProxyStats>,
    direction: Direction,
) {
    let stats = match direction {
        Direction::ToServer => &stats.to_server,
        Direction::ToClient => &stats.to_client,
    };
    let mut heap: BinaryHeap<Reverse<Delivery>> = BinaryHeap::new();
    let mut highest_sent = None;
    loop {
        let next = heap.peek().map(|Reverse(d)| d.at);
        tokio::select! {
            packet = queue.recv() => match packet {
                Some(packet) => heap.push(Reverse(packet)),
                None => break,
            },
            () = sleep_until(next), if next.is_some() => {
                let now = Instant::now();
                while heap.peek().is_some_and(|Reverse(d)| d.at <= now) {
                    let Some(Reverse(packet)) = heap.pop() else { break };
                    if highest_sent.is_some_and(|h| packet.seq < h) {
                        stats.reordered.fetch_add(1, Ordering::Relaxed);
                    }
                    highest_sent = Some(highest_sent.map_or(packet.seq, |h: u64| h.max(packet.seq)));
                    if packet.socket.send_to(&packet.data, packet.dest).await.is_ok() {
                        stats.delivered.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }
    }
}

async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at.into()).await,
        None => std::future::pending().await,
    }
}

/// Receives from clients, creating one upstream socket (and reader) per client address.
async fn front_loop(
    front: Arc<UdpSocket>,
    server: SocketAddr,
    shared: Arc<Shared>,
    to_server: mpsc::Sender<Delivery>,
    to_client: mpsc::Sender<Delivery>,
) {
    let mut flows: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
    let mut readers = JoinSet::new();
    let mut buf = vec![0u8; 65_536];
    let idle_timeout = shared.config.idle_timeout;
    loop {
        let received = tokio::select! {
            received = front.recv_from(&mut buf) => received,
            () = tokio::time::sleep(idle_timeout) => {
                if shared.idle_for() >= idle_timeout {
                    tracing::debug!("impairment proxy idle; stopping");
                    break;
                }
                continue;
            }
        };
        let Ok((len, client)) = received else {
            continue;
        };
        let upstream = match flows.get(&client) {
            Some(socket) => socket.clone(),
            None => {
                let upstream: SocketAddr = if server.ip().is_loopback() {
                    ([127, 0, 0, 1], 0).into()
                } else if server.is_ipv6() {
                    (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
                } else {
                    ([0, 0, 0, 0], 0).into()
                };
                let Ok(socket) = UdpSocket::bind(upstream).await else {
                    continue;
                };
                let socket = Arc::new(socket);
                shared.stats.flows.fetch_add(1, Ordering::Relaxed);
                if let Ok(mut clients) = shared.stats.clients.lock() {
                    clients.push(client);
                }
                flows.insert(client, socket.clone());
                readers.spawn(upstream_loop(
                    socket.clone(),
                    front.clone(),
                    client,
                    shared.clone(),
                    to_client.clone(),
                ));
                socket
            }
        };
        shared.impair(
            Direction::ToServer,
            &buf[..len],
            &upstream,
            server,
            &to_server,
        );
    }
    readers.abort_all();
}

/// Receives the server's packets for one client and queues them towards it.
async fn upstream_loop(
    upstream: Arc<UdpSocket>,
    front: Arc<UdpSocket>,
    client: SocketAddr,
    shared: Arc<Shared>,
    to_client: mpsc::Sender<Delivery>,
) {
    let mut buf = vec![0u8; 65_536];
    while let Ok(len) = upstream.recv(&mut buf).await {
        shared.impair(Direction::ToClient, &buf[..len], &front, client, &to_client);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    async fn echo_server() -> (SocketAddr, tokio::task::JoinHandle<()>) {
        let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = socket.local_addr().unwrap();
        let task = tokio::spawn(async move {
            let mut buf = vec![0u8; 2048];
            while let Ok((len, from)) = socket.recv_from(&mut buf).await {
                let _ = socket.send_to(&buf[..len], from).await;
            }
        });
        (addr, task)
    }

    /// Sends `n` numbered packets while collecting the echoes, until `quiet` passes without one.
    /// Sending is paced and receiving concurrent so that no socket buffer on the way overflows
    /// (only the proxy drops).
    async fn exchange(client: &UdpSocket, to: SocketAddr, n: u32, quiet: Duration) -> Vec<u32> {
        let send = async {
            for i in 0..n {
                client.send_to(&i.to_be_bytes(), to).await.unwrap();
                if i % 20 == 19 {
                    tokio::time::sleep(Duration::from_millis(1)).await;
                }
            }
        };
        let receive = async {
            let mut got = Vec::new();
            let mut buf = [0u8; 16];
            while let Ok(Ok(len)) = tokio::time::timeout(quiet, client.recv(&mut buf)).await {
                if len == 4 {
                    got.push(u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]));
                }
            }
            got
        };
        tokio::join!(send, receive).1
    }

    #[tokio::test]
    async fn loss_applies_each_way_and_is_seeded() {
        let (server, _echo) = echo_server().await;
        let loss = Impairment {
            loss: 0.2,
            ..Impairment::NONE
        };
        let mut seen = Vec::new();
        for _ in 0..2 {
            let proxy = Proxy::start(server, ProxyConfig::symmetric(loss, 42))
                .await
                .unwrap();
            let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
            let got = exchange(&client, proxy.addr(), 500, Duration::from_millis(200)).await;
            let s = proxy.stats();
            let lost =
                s.to_server.lost.load(Ordering::Relaxed) + s.to_client.lost.load(Ordering::Relaxed);
            assert_eq!(got.len() as u64, 500 - lost);
            // Two independent 20% drops: 36% expected; 500 packets keep it well inside 25–47%.
            assert!((125..=235).contains(&lost), "lost {lost}");
            seen.push(got);
        }
        assert_eq!(seen[0], seen[1], "the same seed drops the same packets");
    }

    #[tokio::test]
    async fn jitter_reorders_and_duplicates_are_delivered_twice() {
        let (server, _echo) = echo_server().await;
        let config = ProxyConfig {
            to_server: Impairment {
                jitter: Duration::from_millis(20),
                duplicate: 0.5,
                ..Impairment::NONE
            },
            to_client: Impairment::NONE,
            seed: 7,
            max_queued: 4096,
            idle_timeout: Duration::from_secs(10),
        };
        let proxy = Proxy::start(server, config).await.unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let got = exchange(&client, proxy.addr(), 200, Duration::from_millis(200)).await;
        let dups = proxy.stats().to_server.duplicated.load(Ordering::Relaxed);
        assert!(dups > 50, "{dups} duplicated");
        assert_eq!(got.len() as u64, 200 + dups);
        assert!(got.windows(2).any(|w| w[1] < w[0]), "no reordering");
        assert!(proxy.stats().to_server.reordered.load(Ordering::Relaxed) > 0);
    }

    #[tokio::test]
    async fn a_rebound_client_is_a_new_flow() {
        let (server, _echo) = echo_server().await;
        let proxy = Proxy::start(server, ProxyConfig::symmetric(Impairment::NONE, 1))
            .await
            .unwrap();
        for _ in 0..2 {
            let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
            let got = exchange(&client, proxy.addr(), 3, Duration::from_millis(100)).await;
            assert_eq!(got, vec![0, 1, 2]);
        }
        assert_eq!(proxy.stats().flows.load(Ordering::Relaxed), 2);
    }
}
