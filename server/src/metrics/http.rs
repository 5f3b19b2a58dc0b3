//! The metrics listener: plain HTTP/1.1 on a TCP port of its own (`--metrics-listen`), for
//! Prometheus, for Kubernetes probes and for the people who run the fleet. The scheduler and
//! every worker serve it with [`serve`].
//!
//! - `GET /metrics`: [`Metrics::encode`], `Content-Type` [`CONTENT_TYPE`];
//! - `GET /ready`: 200 while the [`Readiness`] flag is set, 503 otherwise;
//! - a scheduler's only: `GET /` the fleet page (HTML, with `/fleet.js` and `/fleet.css`, served
//!   from the binary: no build step, no CDN) and `GET /api/fleet` its JSON snapshot
//!   ([`FleetView`]); a worker answers 404 there;
//! - `HEAD` of any: the same status and headers, no body;
//! - any other path 404, any other method 405, a request head that is not HTTP/1.x 400, one with
//!   more than [`MAX_HEADERS`] headers or over [`MAX_HEAD`] bytes 431, one not complete within
//!   [`HEAD_TIMEOUT`] 408.
//!
//! The request head is parsed by `httparse` (already in the tree through the websocket
//! library). Every response closes the connection (`Connection: close`): scrapes and probes are
//! one request every few seconds, so keep-alive buys nothing, and a connection never outlives
//! one request. Request bodies are never read.
//!
//! Each connection is served by a task of its own, so a slow or silent client delays nobody.
//! How many are held at once is bounded ([`MAX_CONNECTIONS`], [`MAX_CONNECTIONS_PER_ADDRESS`]),
//! and a new connection always displaces the oldest one still silent rather than waiting for a
//! place (see `listener.rs`): silent connections cannot delay `/ready`, which Kubernetes probes
//! with a one-second timeout. What this door refuses is counted in
//! `kairos_refusals_total{door="metrics",reason}`. Nothing here can be driven to allocate more
//! than [`MAX_HEAD`] bytes per connection.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use prometheus_client::metrics::counter::Counter;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use super::fleet::{FleetView, SAMPLE_EVERY};
use super::listener::{Limits, Slot, Table};
use super::{CONTENT_TYPE, Metrics, Readiness};

/// Largest request head (request line and headers) read, bytes.
pub const MAX_HEAD: usize = 8 * 1024;
/// Most header lines in a request head.
pub const MAX_HEADERS: usize = 32;
/// Longest a client may take to send its request head. Kubelet and Prometheus send theirs at
/// once; a head still incomplete after this is a client that will not finish it.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(2);
/// Longest writing a response may take.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// Connections held at once, all addresses together (each holds at most [`MAX_HEAD`] bytes).
pub const MAX_CONNECTIONS: usize = 512;
/// Connections held at once from one address.
pub const MAX_CONNECTIONS_PER_ADDRESS: usize = 64;

/// The refusal reasons of this door (`kairos_refusals_total{door="metrics",reason}`).
pub const REFUSAL_REASONS: [&str; 5] = [
    "evicted_idle",
    "at_capacity",
    "head_timeout",
    "head_too_large",
    "malformed",
];

/// The fleet page and its assets.
const PAGE_HTML: &str = include_str!("page/index.html");
const PAGE_JS: &str = include_str!("page/fleet.js");
const PAGE_CSS: &str = include_str!("page/fleet.css");

/// The page loads only its own script, style and snapshot.
const PAGE_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
                           connect-src 'self'; img-src 'self'; base-uri 'none'; \
                           frame-ancestors 'none'; form-action 'none'";

/// Binds the metrics listener's TCP socket.
pub async fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    TcpListener::bind(addr).await
}

/// The listener's bounds. [`serve`] uses [`ListenerOptions::default`]: the constants above.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ListenerOptions {
    /// Longest a client may take to send its request head ([`HEAD_TIMEOUT`]).
    pub head_timeout: Duration,
    /// Connections held at once ([`MAX_CONNECTIONS`]).
    pub max_connections: usize,
    /// Connections held at once from one address ([`MAX_CONNECTIONS_PER_ADDRESS`]).
    pub max_connections_per_address: usize,
}

impl Default for ListenerOptions {
    fn default() -> Self {
        ListenerOptions {
            head_timeout: HEAD_TIMEOUT,
            max_connections: MAX_CONNECTIONS,
            max_connections_per_address: MAX_CONNECTIONS_PER_ADDRESS,
        }
    }
}

/// What the connection tasks answer from.
struct Site {
    metrics: Metrics,
    ready: Readiness,
    fleet: Option<FleetView>,
    refusals: Refusals,
    head_timeout: Duration,
}

/// This door's refusal counters.
struct Refusals {
    evicted_idle: Counter,
    at_capacity: Counter,
    head_timeout: Counter,
    head_too_large: Counter,
    malformed: Counter,
}

impl Refusals {
    fn of(metrics: &Metrics) -> Refusals {
        let [
            evicted_idle,
            at_capacity,
            head_timeout,
            head_too_large,
            malformed,
        ] = REFUSAL_REASONS.map(|reason| metrics.refusal_counter("metrics", reason));
        Refusals {
            evicted_idle,
            at_capacity,
            head_timeout,
            head_too_large,
            malformed,
        }
    }
}

/// Serves `/metrics` from `metrics`, `/ready` from `ready` and (a scheduler's) the fleet page on
/// `listener` until `shutdown` resolves. Each connection is a tokio task of its own.
pub async fn serve(
    listener: TcpListener,
    metrics: Metrics,
    ready: Readiness,
    shutdown: impl std::future::Future<Output = ()>,
) {
    serve_with(
        listener,
        metrics,
        ready,
        ListenerOptions::default(),
        shutdown,
    )
    .await;
}

/// [`serve`] with other bounds.
pub async fn serve_with(
    listener: TcpListener,
    metrics: Metrics,
    ready: Readiness,
    options: ListenerOptions,
    shutdown: impl std::future::Future<Output = ()>,
) {
    let site = Arc::new(Site {
        fleet: FleetView::new(metrics.clone(), ready.clone()),
        refusals: Refusals::of(&metrics),
        metrics,
        ready,
        head_timeout: options.head_timeout,
    });
    let table = Table::new(Limits {
        total: options.max_connections,
        per_address: options.max_connections_per_address,
    });
    let mut sampling = tokio::time::interval(SAMPLE_EVERY);
    sampling.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    tokio::pin!(shutdown);
    loop {
        let accepted = tokio::select! {
            () = &mut shutdown => return,
            _ = sampling.tick(), if site.fleet.is_some() => {
                if let Some(fleet) = &site.fleet {
                    fleet.sample(Instant::now());
                }
                continue;
            }
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => accepted,
            Err(error) => {
                // Out of file descriptors and the like: wait a little rather than spin.
                tracing::warn!(%error, "metrics listener: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let admitted = table.admit(peer.ip());
        site.refusals
            .evicted_idle
            .inc_by(u64::try_from(admitted.evicted).unwrap_or(u64::MAX));
        let Some(slot) = admitted.slot else {
            site.refusals.at_capacity.inc();
            tracing::debug!(%peer, "metrics listener: at capacity, connection refused");
            continue;
        };
        let site = site.clone();
        tokio::spawn(async move {
            if let Err(error) = connection(stream, slot, &site).await {
                tracing::debug!(%error, "metrics listener: connection ended early");
            }
        });
    }
}

/// Reads one request head (bounded in size and time, given up if evicted), answers it, closes.
async fn connection(mut stream: TcpStream, mut slot: Slot, site: &Site) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(1024);
    let read = tokio::select! {
        read = tokio::time::timeout(site.head_timeout, read_head(&mut stream, &mut head)) => read,
        () = slot.evicted() => return Ok(()),
    };
    slot.answering();
    let response = match read {
        Err(_) => {
            site.refusals.head_timeout.inc();
            Response::plain(408, "request head not received in time")
        }
        Ok(Err(error)) => return Err(error),
        Ok(Ok(())) => {
            let response = respond(&head, site, Instant::now());
            let refused = match response.status {
                431 => Some(&site.refusals.head_too_large),
                400 => Some(&site.refusals.malformed),
                _ => None,
            };
            if let Some(counter) = refused {
                counter.inc();
            }
            response
        }
    };
    tokio::time::timeout(WRITE_TIMEOUT, async {
        stream.write_all(&response.to_bytes()).await?;
        stream.shutdown().await
    })
    .await
    .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "write timed out"))?
}

/// Reads into `head` until it holds a whole request head, a parse error, [`MAX_HEAD`] bytes or
/// the client's end of the stream; [`respond`] then tells which.
async fn read_head(stream: &mut TcpStream, head: &mut Vec<u8>) -> std::io::Result<()> {
    let mut buf = [0u8; 1024];
    loop {
        if !matches!(parse(head), Parsed::Partial) || head.len() >= MAX_HEAD {
            return Ok(());
        }
        let want = buf.len().min(MAX_HEAD - head.len());
        let n = stream.read(&mut buf[..want]).await?;
        if n == 0 {
            return Ok(());
        }
        head.extend_from_slice(&buf[..n]);
    }
}

/// What a request head asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Route {
    /// `/metrics`.
    Metrics,
    /// `/ready`.
    Ready,
    /// `/` (or `/index.html`): the fleet page.
    Page,
    /// `/fleet.js`.
    Script,
    /// `/fleet.css`.
    Style,
    /// `/api/fleet`.
    Fleet,
}

/// What the bytes received so far are.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Parsed {
    /// The start of a request head; more may complete it.
    Partial,
    /// A whole request head of `len` bytes: a `GET` or `HEAD` of a known route.
    Request {
        /// `HEAD`: headers only.
        head_only: bool,
        /// What it asks for.
        route: Route,
        /// The head's length, bytes.
        len: usize,
    },
    /// A request that gets an error status: 400, 404, 405 or 431.
    Refused(u16),
}

/// Parses a request head with `httparse`.
pub fn parse(bytes: &[u8]) -> Parsed {
    let mut headers = [httparse::EMPTY_HEADER; MAX_HEADERS];
    let mut request = httparse::Request::new(&mut headers);
    let len = match request.parse(bytes) {
        Ok(httparse::Status::Complete(len)) => len,
        Ok(httparse::Status::Partial) => return Parsed::Partial,
        Err(httparse::Error::TooManyHeaders) => return Parsed::Refused(431),
        Err(_) => return Parsed::Refused(400),
    };
    let (Some(method), Some(target)) = (request.method, request.path) else {
        return Parsed::Refused(400);
    };
    if !target.starts_with('/') {
        return Parsed::Refused(400);
    }
    let path = target.split(['?', '#']).next().unwrap_or(target);
    let route = match path {
        "/metrics" => Route::Metrics,
        "/ready" => Route::Ready,
        "/" | "/index.html" => Route::Page,
        "/fleet.js" => Route::Script,
        "/fleet.css" => Route::Style,
        "/api/fleet" => Route::Fleet,
        _ => return Parsed::Refused(404),
    };
    let head_only = match method {
        "GET" => false,
        "HEAD" => true,
        _ => return Parsed::Refused(405),
    };
    Parsed::Request {
        head_only,
        route,
        len,
    }
}

/// A response: status, content type, extra headers and body.
#[derive(Debug, PartialEq, Eq)]
pub struct Response {
    /// The status code.
    pub status: u16,
    content_type: &'static str,
    /// `Content-Security-Policy`, for the page.
    policy: Option<&'static str>,
    body: Vec<u8>,
    /// `HEAD`: headers only.
    head_only: bool,
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        _ => "Error",
    }
}

impl Response {
    fn plain(status: u16, body: &str) -> Response {
        Response::of(status, "text/plain; charset=utf-8", format!("{body}\n"))
    }

    fn of(status: u16, content_type: &'static str, body: impl Into<Vec<u8>>) -> Response {
        Response {
            status,
            content_type,
            policy: None,
            body: body.into(),
            head_only: false,
        }
    }

    /// The bytes sent: status line, headers and (unless `HEAD`) the body.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = format!(
            "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-store\r\n\
             X-Content-Type-Options: nosniff\r\nConnection: close\r\n",
            self.status,
            reason(self.status),
            self.content_type,
            self.body.len()
        );
        if let Some(policy) = self.policy {
            out.push_str("Content-Security-Policy: ");
            out.push_str(policy);
            out.push_str("\r\n");
        }
        out.push_str("\r\n");
        let mut out = out.into_bytes();
        if !self.head_only {
            out.extend_from_slice(&self.body);
        }
        out
    }
}

/// The response to `head`, the bytes [`read_head`] collected (whole, or cut short by the
/// client or by [`MAX_HEAD`]).
fn respond(head: &[u8], site: &Site, now: Instant) -> Response {
    answer(
        parse(head),
        head.len(),
        &site.metrics,
        &site.ready,
        site.fleet.as_ref(),
        now,
    )
}

/// The response to a parsed head of `received` bytes. Pure but for reading the metrics: the
/// fuzz target calls it with any bytes.
pub fn answer(
    parsed: Parsed,
    received: usize,
    metrics: &Metrics,
    ready: &Readiness,
    fleet: Option<&FleetView>,
    now: Instant,
) -> Response {
    let (head_only, route) = match parsed {
        Parsed::Partial if received >= MAX_HEAD => {
            return Response::plain(431, "request head too large");
        }
        // The client closed before finishing its head.
        Parsed::Partial => return Response::plain(400, "incomplete request"),
        Parsed::Refused(431) => return Response::plain(431, "too many headers"),
        Parsed::Refused(404) => return Response::plain(404, "not found"),
        Parsed::Refused(405) => return Response::plain(405, "only GET and HEAD"),
        Parsed::Refused(_) => return Response::plain(400, "malformed request"),
        Parsed::Request {
            head_only, route, ..
        } => (head_only, route),
    };
    let page = |content_type, body: &'static str| {
        let mut response = Response::of(200, content_type, body);
        response.policy = Some(PAGE_POLICY);
        response
    };
    let mut response = match (route, fleet) {
        (Route::Metrics, _) => Response::of(200, CONTENT_TYPE, metrics.encode()),
        (Route::Ready, _) if ready.is_ready() => Response::plain(200, "ready"),
        (Route::Ready, _) => Response::plain(503, "not ready"),
        (Route::Page, Some(_)) => page("text/html; charset=utf-8", PAGE_HTML),
        (Route::Script, Some(_)) => page("text/javascript; charset=utf-8", PAGE_JS),
        (Route::Style, Some(_)) => page("text/css; charset=utf-8", PAGE_CSS),
        (Route::Fleet, Some(fleet)) => Response::of(200, "application/json", fleet.json(now)),
        (Route::Page | Route::Script | Route::Style | Route::Fleet, None) => {
            Response::plain(404, "no fleet page: this is a worker's metrics listener")
        }
    };
    response.head_only = head_only;
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(ready: bool) -> Site {
        let metrics = Metrics::new();
        let flag = Readiness::new();
        flag.set(ready);
        Site {
            fleet: FleetView::new(metrics.clone(), flag.clone()),
            refusals: Refusals::of(&metrics),
            metrics,
            ready: flag,
            head_timeout: HEAD_TIMEOUT,
        }
    }

    fn status(head: &[u8], ready: bool) -> u16 {
        respond(head, &site(ready), Instant::now()).status
    }

    #[test]
    fn routes_methods_and_malformed_heads() {
        assert_eq!(
            status(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n", false),
            200
        );
        assert_eq!(status(b"GET /metrics?x=1 HTTP/1.0\r\n\r\n", false), 200);
        assert_eq!(status(b"GET /ready HTTP/1.1\r\n\r\n", true), 200);
        assert_eq!(status(b"GET /ready HTTP/1.1\r\n\r\n", false), 503);
        for page in ["/", "/index.html", "/fleet.js", "/fleet.css", "/api/fleet"] {
            let head = format!("GET {page} HTTP/1.1\r\n\r\n");
            assert_eq!(status(head.as_bytes(), false), 200, "{page}");
        }
        assert_eq!(status(b"GET /nope HTTP/1.1\r\n\r\n", true), 404);
        assert_eq!(status(b"POST /metrics HTTP/1.1\r\n\r\n", true), 405);
        for bad in [
            &b""[..],
            b"GET /metrics HTTP/1.1\r\n",
            b"GET /metrics\r\n\r\n",
            b"GET metrics HTTP/1.1\r\n\r\n",
            b"GET /metrics HTTP/2\r\n\r\n",
            b"GET /metrics HTTP/1.1\r\nno colon\r\n\r\n",
            b"GET /\xff HTTP/1.1\r\n\r\n",
        ] {
            assert_eq!(status(bad, true), 400, "{:?}", String::from_utf8_lossy(bad));
        }
        let many: String = (0..=MAX_HEADERS).map(|i| format!("X-{i}: y\r\n")).collect();
        let head = format!("GET /metrics HTTP/1.1\r\n{many}\r\n");
        assert_eq!(status(head.as_bytes(), true), 431);
        let long = vec![b'a'; MAX_HEAD];
        let head = [b"GET /metrics HTTP/1.1\r\nX: ".as_slice(), &long].concat();
        assert_eq!(status(&head[..MAX_HEAD], true), 431);
    }

    #[test]
    fn a_worker_has_no_fleet_page() {
        let metrics = Metrics::for_worker();
        let ready = Readiness::new();
        let site = Site {
            fleet: FleetView::new(metrics.clone(), ready.clone()),
            refusals: Refusals::of(&metrics),
            metrics,
            ready,
            head_timeout: HEAD_TIMEOUT,
        };
        for page in ["/", "/api/fleet", "/fleet.js"] {
            let head = format!("GET {page} HTTP/1.1\r\n\r\n");
            assert_eq!(respond(head.as_bytes(), &site, Instant::now()).status, 404);
        }
        let head = b"GET /metrics HTTP/1.1\r\n\r\n";
        assert_eq!(respond(head, &site, Instant::now()).status, 200);
    }

    #[test]
    fn head_answers_headers_without_the_body() {
        let site = site(true);
        let get = respond(b"GET /metrics HTTP/1.1\r\n\r\n", &site, Instant::now());
        let head = respond(b"HEAD /metrics HTTP/1.1\r\n\r\n", &site, Instant::now());
        let (get, head) = (get.to_bytes(), head.to_bytes());
        let text = String::from_utf8(head.clone()).unwrap();
        assert!(text.ends_with("\r\n\r\n"), "{text}");
        assert!(text.contains(CONTENT_TYPE), "{text}");
        assert!(get.starts_with(&head) && get.len() > head.len());
    }

    #[test]
    fn the_page_is_self_contained_and_locked_to_its_origin() {
        let page = respond(b"GET / HTTP/1.1\r\n\r\n", &site(true), Instant::now()).to_bytes();
        let text = String::from_utf8(page).unwrap();
        assert!(text.contains("Content-Security-Policy: default-src 'none'"));
        assert!(text.contains(r#"<script src="fleet.js""#), "{text}");
        for outside in ["http://", "https://", "//cdn"] {
            assert!(!PAGE_HTML.contains(outside), "{outside} in the page");
            assert!(!PAGE_JS.contains(outside), "{outside} in the script");
        }
    }
}
