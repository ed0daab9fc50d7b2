//! The front door of the live Foxglove view (`pntr-server --foxglove ADDR`): a TCP listener on the
//! user's address that hands each connection to the Foxglove SDK's WebSocket server (bound to
//! 127.0.0.1 on an ephemeral port) after one look at its HTTP upgrade request.
//!
//! Why: the SDK speaks the Foxglove WebSocket protocol under the subprotocol name `foxglove.sdk.v1`
//! (and `foxglove.sdk.v1.1`) only. Older Foxglove releases, Lichtblick before 1.22 and other
//! clients of the ws-protocol libraries ask for `foxglove.websocket.v1`, the same protocol under its
//! earlier name (Foxglove's own statement; Lichtblick added the new name by adding it to its list),
//! and the SDK answers them `400 Missing expected sec-websocket-protocol header`. Here such a request
//! is passed on offering `foxglove.sdk.v1`, and the answer's `Sec-WebSocket-Protocol` is given back
//! under the name the client asked for; everything after the handshake is copied unchanged both ways.
//! A WebSocket request that offers neither name gets a `400` naming the names that work. The
//! handshake's `Sec-WebSocket-Accept` depends only on the key, so renaming the subprotocol keeps it
//! valid (RFC 6455, 4.2.2).

use std::net::SocketAddr;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// The subprotocol names the SDK accepts as they are.
const SDK_NAMES: [&str; 2] = ["foxglove.sdk.v1", "foxglove.sdk.v1.1"];
/// The earlier name of the same protocol, renamed on the way in and back.
const LEGACY_NAME: &str = "foxglove.websocket.v1";
/// The longest request or response head read (HTTP headers of a browser's upgrade are ~1 KB).
const MAX_HEAD_BYTES: usize = 16 * 1024;
/// Time a client has to send its request head (a connection that sends nothing is closed).
const HEAD_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);
/// Viewers connected at once; more wait for one to leave (each holds a socket and a task).
pub const MAX_VIEWERS: usize = 64;

/// Accept connections on `listener` for ever, each handed to the SDK's server at `inner`.
pub async fn serve(listener: TcpListener, inner: SocketAddr) {
    let slots = std::sync::Arc::new(tokio::sync::Semaphore::new(MAX_VIEWERS));
    loop {
        let Ok(slot) = slots.clone().acquire_owned().await else {
            return;
        };
        match listener.accept().await {
            Ok((client, peer)) => {
                tokio::spawn(async move {
                    let _slot = slot;
                    if let Err(e) = connection(client, inner).await {
                        tracing::debug!(%peer, error = %e, "live view connection ended");
                    }
                });
            }
            Err(e) => {
                // Out of file descriptors, say: wait a little rather than spin.
                tracing::warn!(error = %e, "live view: accepting a connection failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
        }
    }
}

/// Read an HTTP head (up to the blank line) from `stream`: (head, bytes read after it).
async fn read_head(stream: &mut TcpStream) -> std::io::Result<(Vec<u8>, Vec<u8>)> {
    let mut buf = Vec::with_capacity(2048);
    let mut chunk = [0u8; 2048];
    loop {
        if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let rest = buf.split_off(end + 4);
            return Ok((buf, rest));
        }
        if buf.len() > MAX_HEAD_BYTES {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "HTTP head longer than 16 KiB",
            ));
        }
        let n = stream.read(&mut chunk).await?;
        if n == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

/// What to do with a request head.
#[derive(Debug, PartialEq, Eq)]
enum Route {
    /// Pass it on unchanged (an SDK name offered, or not a WebSocket upgrade).
    AsIs,
    /// Only the earlier name offered: rename it on the way in and back.
    Legacy,
    /// A WebSocket upgrade offering no name the view speaks (the names offered, possibly empty).
    Refuse(String),
}

/// The subprotocol names offered in a request head and whether it asks for a WebSocket.
fn route(head: &[u8]) -> Route {
    let mut headers = [httparse::EMPTY_HEADER; 64];
    let mut req = httparse::Request::new(&mut headers);
    if !matches!(req.parse(head), Ok(httparse::Status::Complete(_))) {
        return Route::AsIs;
    }
    let mut websocket = false;
    let mut offered: Vec<String> = Vec::new();
    for h in req.headers.iter() {
        let value = String::from_utf8_lossy(h.value);
        if h.name.eq_ignore_ascii_case("upgrade") && value.eq_ignore_ascii_case("websocket") {
            websocket = true;
        }
        if h.name.eq_ignore_ascii_case("sec-websocket-protocol") {
            offered.extend(
                value
                    .split(',')
                    .map(|s| s.trim().to_string())
                    .filter(|s| !s.is_empty()),
            );
        }
    }
    if !websocket || offered.iter().any(|o| SDK_NAMES.contains(&o.as_str())) {
        Route::AsIs
    } else if offered.iter().any(|o| o == LEGACY_NAME) {
        Route::Legacy
    } else {
        Route::Refuse(offered.join(", "))
    }
}

/// `head` with the value of every `header` line replaced by `value`; every other byte as it was
/// (other headers may hold bytes that are not UTF-8).
fn replace_header(head: &[u8], header: &str, value: &str) -> Vec<u8> {
    let mut out = Vec::with_capacity(head.len());
    let mut rest = head;
    while !rest.is_empty() {
        let end = rest
            .windows(2)
            .position(|w| w == b"\r\n")
            .map_or(rest.len(), |i| i + 2);
        let (line, tail) = rest.split_at(end);
        let name = line.iter().position(|&b| b == b':').map(|i| &line[..i]);
        match name {
            Some(n) if n.trim_ascii().eq_ignore_ascii_case(header.as_bytes()) => {
                out.extend_from_slice(n);
                out.extend_from_slice(format!(": {value}\r\n").as_bytes());
            }
            _ => out.extend_from_slice(line),
        }
        rest = tail;
    }
    out
}

async fn connection(mut client: TcpStream, inner: SocketAddr) -> std::io::Result<()> {
    client.set_nodelay(true)?;
    let (head, rest) = tokio::time::timeout(HEAD_TIMEOUT, read_head(&mut client))
        .await
        .map_err(|_| std::io::Error::from(std::io::ErrorKind::TimedOut))??;
    let legacy = match route(&head) {
        Route::AsIs => false,
        Route::Legacy => true,
        Route::Refuse(offered) => {
            let body = format!(
                "pntr's live view speaks the Foxglove WebSocket protocol: offer {} or {LEGACY_NAME} \
                 (older Foxglove and Lichtblick) in Sec-WebSocket-Protocol; this request offered {}\n",
                SDK_NAMES.join(" or "),
                if offered.is_empty() {
                    "none".to_string()
                } else {
                    offered
                }
            );
            let answer = format!(
                "HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            client.write_all(answer.as_bytes()).await?;
            return client.shutdown().await;
        }
    };
    let mut server = match TcpStream::connect(inner).await {
        Ok(s) => s,
        Err(e) => {
            let answer = "HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n";
            client.write_all(answer.as_bytes()).await?;
            return Err(e);
        }
    };
    server.set_nodelay(true)?;
    let head = if legacy {
        replace_header(&head, "sec-websocket-protocol", SDK_NAMES[0])
    } else {
        head
    };
    server.write_all(&head).await?;
    server.write_all(&rest).await?;
    if legacy {
        let (answer, more) = tokio::time::timeout(HEAD_TIMEOUT, read_head(&mut server))
            .await
            .map_err(|_| std::io::Error::from(std::io::ErrorKind::TimedOut))??;
        let answer = replace_header(&answer, "sec-websocket-protocol", LEGACY_NAME);
        client.write_all(&answer).await?;
        client.write_all(&more).await?;
    }
    tokio::io::copy_bidirectional(&mut client, &mut server).await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn upgrade(protocols: Option<&str>) -> Vec<u8> {
        let mut s = String::from(
            "GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n",
        );
        if let Some(p) = protocols {
            s += &format!("Sec-WebSocket-Protocol: {p}\r\n");
        }
        s += "\r\n";
        s.into_bytes()
    }

    #[test]
    fn subprotocols_are_routed_by_name() {
        assert_eq!(route(&upgrade(Some("foxglove.sdk.v1"))), Route::AsIs);
        assert_eq!(
            route(&upgrade(Some("foxglove.websocket.v1, foxglove.sdk.v1.1"))),
            Route::AsIs
        );
        assert_eq!(
            route(&upgrade(Some("foxglove.websocket.v1"))),
            Route::Legacy
        );
        assert_eq!(
            route(&upgrade(Some("graphql-ws"))),
            Route::Refuse("graphql-ws".into())
        );
        assert_eq!(route(&upgrade(None)), Route::Refuse(String::new()));
        // Not a WebSocket request, or not HTTP at all: the SDK answers it.
        assert_eq!(route(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"), Route::AsIs);
        assert_eq!(route(b"\x16\x03\x01 binary\r\n\r\n"), Route::AsIs);
    }

    #[test]
    fn only_the_named_header_is_replaced() {
        let head = upgrade(Some("foxglove.websocket.v1"));
        let out = String::from_utf8(replace_header(
            &head,
            "sec-websocket-protocol",
            "foxglove.sdk.v1",
        ))
        .unwrap();
        assert!(out.contains("Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n"));
        assert!(!out.contains("websocket.v1"));
        assert!(out.contains("Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"));
        assert!(out.ends_with("\r\n\r\n"));
        assert_eq!(
            out.len() + "websocket.v1".len() - "sdk.v1".len(),
            head.len()
        );
        // Bytes that are not UTF-8 in another header pass unchanged.
        let raw = b"GET / HTTP/1.1\r\nCookie: \xff\xfe\r\nsec-websocket-protocol:foxglove.websocket.v1\r\n\r\n";
        let got = replace_header(raw, "sec-websocket-protocol", "foxglove.sdk.v1");
        let want = b"GET / HTTP/1.1\r\nCookie: \xff\xfe\r\nsec-websocket-protocol: foxglove.sdk.v1\r\n\r\n";
        assert_eq!(got, want.to_vec());
    }
}
