//! The metrics endpoint: plain HTTP/1.1 on a TCP port of its own (`--metrics-listen`), for
//! Prometheus and for Kubernetes probes. The scheduler and every worker serve it with
//! [`serve`].
//!
//! - `GET /metrics`: [`Metrics::encode`], `Content-Type` [`CONTENT_TYPE`];
//! - `GET /ready`: 200 while the [`Readiness`] flag is set, 503 otherwise;
//! - `HEAD` of either: the same status and headers, no body;
//! - any other path 404, any other method 405, anything that is not a request line and headers
//!   400, a head over [`MAX_HEAD`] bytes 431, a head not complete within [`HEAD_TIMEOUT`] 408.
//!
//! Every response closes the connection (`Connection: close`): scrapes and probes are a request
//! every few seconds, so keep-alive buys nothing and a connection never outlives one request.
//! At most [`MAX_CONNECTIONS`] are served at once; more wait in the kernel's accept queue.
//! Request bodies are never read. It is a responder for two read-only URLs, not a web server:
//! no hyper (not in the dependency tree), and nothing here can be driven to allocate more than
//! [`MAX_HEAD`] bytes per connection.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;

use super::{CONTENT_TYPE, Metrics, Readiness};

/// Largest request head (request line and headers) read, bytes.
pub const MAX_HEAD: usize = 8 * 1024;
/// Longest a client may take to send its request head.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest writing a response may take.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 32;

/// Binds the metrics endpoint's TCP socket.
pub async fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    TcpListener::bind(addr).await
}

/// Serves `/metrics` from `metrics` and `/ready` from `ready` on `listener` until `shutdown`
/// resolves. Each connection is one tokio task that only reads, encodes and writes (encoding the
/// registry is a few microseconds per series).
pub async fn serve(
    listener: TcpListener,
    metrics: Metrics,
    ready: Readiness,
    shutdown: impl std::future::Future<Output = ()>,
) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    tokio::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            () = &mut shutdown => return,
            permit = slots.clone().acquire_owned() => match permit {
                Ok(permit) => permit,
                Err(_) => return,
            },
        };
        let accepted = tokio::select! {
            () = &mut shutdown => return,
            accepted = listener.accept() => accepted,
        };
        let stream = match accepted {
            Ok((stream, _)) => stream,
            Err(error) => {
                // Out of file descriptors and the like: wait a little rather than spin.
                tracing::warn!(%error, "metrics endpoint: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let (metrics, ready) = (metrics.clone(), ready.clone());
        tokio::spawn(async move {
            let _permit = permit;
            if let Err(error) = answer(stream, &metrics, &ready).await {
                tracing::debug!(%error, "metrics endpoint: connection ended early");
            }
        });
    }
}

/// What a request head asks for.
#[derive(Debug, PartialEq, Eq)]
enum Route {
    Metrics,
    Ready,
}

/// A response: status line parts, content type and body.
#[derive(Debug, PartialEq, Eq)]
struct Response {
    status: u16,
    reason: &'static str,
    content_type: &'static str,
    body: String,
    /// `HEAD`: headers only.
    head_only: bool,
}

impl Response {
    fn plain(status: u16, reason: &'static str, body: &str) -> Response {
        Response {
            status,
            reason,
            content_type: "text/plain; charset=utf-8",
            body: format!("{body}\n"),
            head_only: false,
        }
    }

    fn to_bytes(&self) -> Vec<u8> {
        let mut out = format!(
            "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            self.status,
            self.reason,
            self.content_type,
            self.body.len()
        )
        .into_bytes();
        if !self.head_only {
            out.extend_from_slice(self.body.as_bytes());
        }
        out
    }
}

/// Reads one request head (bounded in size and time), answers it, closes.
async fn answer(
    mut stream: TcpStream,
    metrics: &Metrics,
    ready: &Readiness,
) -> std::io::Result<()> {
    let response = match tokio::time::timeout(HEAD_TIMEOUT, read_head(&mut stream)).await {
        Err(_) => Response::plain(408, "Request Timeout", "request head not received in time"),
        Ok(Err(error)) => return Err(error),
        Ok(Ok(None)) => Response::plain(
            431,
            "Request Header Fields Too Large",
            "request head too large",
        ),
        Ok(Ok(Some(head))) => respond(&head, metrics, ready),
    };
    tokio::time::timeout(WRITE_TIMEOUT, async {
        stream.write_all(&response.to_bytes()).await?;
        stream.shutdown().await
    })
    .await
    .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "write timed out"))?
}

/// The request head, up to and including the blank line; `None` if it exceeds [`MAX_HEAD`].
/// A client that closes early yields what it sent (then answered 400).
async fn read_head(stream: &mut TcpStream) -> std::io::Result<Option<Vec<u8>>> {
    let mut head = Vec::with_capacity(512);
    let mut buf = [0u8; 1024];
    loop {
        if head_end(&head).is_some() {
            return Ok(Some(head));
        }
        if head.len() >= MAX_HEAD {
            return Ok(None);
        }
        let want = buf.len().min(MAX_HEAD - head.len());
        let n = stream.read(&mut buf[..want]).await?;
        if n == 0 {
            return Ok(Some(head));
        }
        head.extend_from_slice(&buf[..n]);
    }
}

fn head_end(head: &[u8]) -> Option<usize> {
    head.windows(4).position(|w| w == b"\r\n\r\n")
}

/// The response to a request head (pure: the tests call it with any bytes).
fn respond(head: &[u8], metrics: &Metrics, ready: &Readiness) -> Response {
    let (method, route) = match parse(head) {
        Err(response) => return response,
        Ok(parsed) => parsed,
    };
    let mut response = match route {
        Route::Metrics => Response {
            status: 200,
            reason: "OK",
            content_type: CONTENT_TYPE,
            body: metrics.encode(),
            head_only: false,
        },
        Route::Ready if ready.is_ready() => Response::plain(200, "OK", "ready"),
        Route::Ready => Response::plain(503, "Service Unavailable", "not ready"),
    };
    response.head_only = method == "HEAD";
    response
}

/// The method and route of a request head, or the error response.
fn parse(head: &[u8]) -> Result<(&str, Route), Response> {
    let bad = || Response::plain(400, "Bad Request", "malformed request");
    let end = head_end(head).ok_or_else(bad)?;
    let text = std::str::from_utf8(&head[..end]).map_err(|_| bad())?;
    let mut lines = text.split("\r\n");
    let request_line = lines.next().ok_or_else(bad)?;
    let mut parts = request_line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(bad());
    };
    if !matches!(version, "HTTP/1.1" | "HTTP/1.0") || !target.starts_with('/') {
        return Err(bad());
    }
    // Header lines must at least look like `name: value`.
    if lines.any(|line| !line.contains(':')) {
        return Err(bad());
    }
    if method.is_empty() || !method.bytes().all(|b| b.is_ascii_uppercase()) {
        return Err(bad());
    }
    let path = target.split('?').next().unwrap_or(target);
    let route = match path {
        "/metrics" => Route::Metrics,
        "/ready" => Route::Ready,
        _ => return Err(Response::plain(404, "Not Found", "not found")),
    };
    if !matches!(method, "GET" | "HEAD") {
        return Err(Response::plain(
            405,
            "Method Not Allowed",
            "only GET and HEAD",
        ));
    }
    Ok((method, route))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(head: &[u8], ready: bool) -> u16 {
        let flag = Readiness::new();
        flag.set(ready);
        respond(head, &Metrics::new(), &flag).status
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
        assert_eq!(status(b"GET /nope HTTP/1.1\r\n\r\n", true), 404);
        assert_eq!(status(b"POST /metrics HTTP/1.1\r\n\r\n", true), 405);
        for bad in [
            &b""[..],
            b"GET /metrics HTTP/1.1\r\n",
            b"GET /metrics\r\n\r\n",
            b"GET  /metrics HTTP/1.1\r\n\r\n",
            b"GET metrics HTTP/1.1\r\n\r\n",
            b"GET /metrics HTTP/2\r\n\r\n",
            b"get /metrics HTTP/1.1\r\n\r\n",
            b"GET /metrics HTTP/1.1\r\nno colon\r\n\r\n",
            b"GET /\xff HTTP/1.1\r\n\r\n",
        ] {
            assert_eq!(status(bad, true), 400, "{:?}", String::from_utf8_lossy(bad));
        }
    }

    #[test]
    fn head_answers_headers_without_the_body() {
        let flag = Readiness::new();
        let get = respond(b"GET /metrics HTTP/1.1\r\n\r\n", &Metrics::new(), &flag);
        let head = respond(b"HEAD /metrics HTTP/1.1\r\n\r\n", &Metrics::new(), &flag);
        let (get, head) = (get.to_bytes(), head.to_bytes());
        let text = String::from_utf8(head.clone()).unwrap();
        assert!(text.ends_with("\r\n\r\n"), "{text}");
        assert!(text.contains(CONTENT_TYPE), "{text}");
        assert!(get.starts_with(&head) && get.len() > head.len());
    }
}
