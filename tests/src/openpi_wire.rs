//! A raw openpi client at the byte level, for probing the openpi endpoint as a hostile client
//! would: an HTTP upgrade written by hand (whole, half, with any key), masked websocket frames
//! whose header may announce more than follows, and the server's frames read back one by one.
//! A well-behaved client (`openpi-client` from PyPI) is driven by `tests/python/openpi_check.py`
//! instead.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, bail};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// Websocket opcodes the endpoint sends.
pub mod opcode {
    /// A text message (the endpoint's errors).
    pub const TEXT: u8 = 0x1;
    /// A binary message (metadata and replies).
    pub const BINARY: u8 = 0x2;
    /// A close.
    pub const CLOSE: u8 = 0x8;
}

/// Opens a TCP connection to `server` from `source` (any loopback address on Linux, so that
/// tests can play several client addresses on one machine).
pub async fn connect_from(source: &str, server: SocketAddr) -> anyhow::Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind(format!("{source}:0").parse()?)?;
    Ok(socket.connect(server).await?)
}

/// The upgrade request, with `Authorization: Api-Key <key>` when `key` is given.
pub fn upgrade_request(server: SocketAddr, key: Option<&str>) -> String {
    let auth = key
        .map(|key| format!("Authorization: Api-Key {key}\r\n"))
        .unwrap_or_default();
    format!(
        "GET / HTTP/1.1\r\nHost: {server}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n{auth}\r\n"
    )
}

/// The HTTP status of the response to an upgrade, and the response head; the stream is left
/// just after the head (at the first websocket frame when the status is 101).
pub async fn read_response_head(stream: &mut TcpStream) -> anyhow::Result<(u16, String)> {
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        if stream.read(&mut byte).await? == 0 {
            bail!(
                "connection closed after {} bytes of response head: {:?}",
                head.len(),
                String::from_utf8_lossy(&head)
            );
        }
        head.push(byte[0]);
        if head.len() > 16 << 10 {
            bail!("response head over 16 KiB");
        }
    }
    let head = String::from_utf8_lossy(&head).into_owned();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .with_context(|| format!("no status in {head:?}"))?;
    Ok((status, head))
}

/// Connects from `source`, upgrades with `key` and returns the HTTP status (and, on 101, the
/// stream positioned at the server's first frame).
pub async fn upgrade(
    source: &str,
    server: SocketAddr,
    key: Option<&str>,
) -> anyhow::Result<(u16, String, TcpStream)> {
    let mut stream = connect_from(source, server).await?;
    stream
        .write_all(upgrade_request(server, key).as_bytes())
        .await?;
    let (status, head) = read_response_head(&mut stream).await?;
    Ok((status, head, stream))
}

/// The header of a final, masked client frame of `opcode` announcing `len` payload bytes, with
/// the mask `mask`.
pub fn frame_header(opcode: u8, len: u64, mask: [u8; 4]) -> Vec<u8> {
    let mut header = vec![0x80 | opcode];
    if len < 126 {
        header.push(0x80 | len as u8);
    } else if let Ok(len) = u16::try_from(len) {
        header.push(0x80 | 126);
        header.extend_from_slice(&len.to_be_bytes());
    } else {
        header.push(0x80 | 127);
        header.extend_from_slice(&len.to_be_bytes());
    }
    header.extend_from_slice(&mask);
    header
}

/// A whole masked client frame carrying `payload`.
pub fn frame(opcode: u8, payload: &[u8]) -> Vec<u8> {
    let mask = [0x37, 0xfa, 0x21, 0x3d];
    let mut out = frame_header(opcode, payload.len() as u64, mask);
    out.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    out
}

/// One frame from the server (unmasked): its opcode and payload.
pub async fn read_frame<R: AsyncRead + Unpin>(stream: &mut R) -> anyhow::Result<(u8, Vec<u8>)> {
    let mut head = [0u8; 2];
    stream.read_exact(&mut head).await?;
    let opcode = head[0] & 0x0f;
    let len = match head[1] & 0x7f {
        126 => u64::from(stream.read_u16().await?),
        127 => stream.read_u64().await?,
        n => u64::from(n),
    };
    if len > 64 << 20 {
        bail!("a server frame of {len} bytes");
    }
    let mut payload = vec![0u8; len as usize];
    stream.read_exact(&mut payload).await?;
    Ok((opcode, payload))
}

/// How the server ended a connection: the text messages it sent, and its close code.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Ending {
    /// Text messages (the endpoint's error messages).
    pub texts: Vec<String>,
    /// The close frame's code, if a close frame came.
    pub close_code: Option<u16>,
}

/// Reads the server's frames until its close frame (or the end of the stream), skipping binary
/// ones; gives up after `guard` (a hang guard, not a timing margin).
pub async fn read_until_close<R: AsyncRead + Unpin>(
    stream: &mut R,
    guard: Duration,
) -> anyhow::Result<Ending> {
    let read = async {
        let mut ending = Ending::default();
        loop {
            match read_frame(stream).await {
                Ok((opcode::TEXT, payload)) => {
                    ending
                        .texts
                        .push(String::from_utf8_lossy(&payload).into_owned());
                }
                Ok((opcode::CLOSE, payload)) => {
                    ending.close_code = payload
                        .get(..2)
                        .map(|code| u16::from_be_bytes([code[0], code[1]]));
                    return ending;
                }
                Ok(_) => {}
                Err(_) => return ending,
            }
        }
    };
    tokio::time::timeout(guard, read)
        .await
        .context("the server did not end the connection")
}
