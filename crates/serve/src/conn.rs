//! Connections: accepting them within a limit, timing out the slow ones, bounding request bodies.
//!
//! axum's own `serve` has no header timeout and no connection limit, so a client that opens
//! connections and never finishes a request can hold every descriptor of the process and stop the
//! server answering anyone. Here each connection is served by hyper's HTTP/1.1 connection with a
//! header read timeout (which also closes idle keep-alive connections), takes one of
//! `max_connections` slots, and a connection beyond them is answered 503 and closed at once. The
//! body of each request is read by [`read_body`] within its own timeout and size limit.

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};

use crate::ApiError;

/// Descriptors kept for the server itself (its listener, runtime, libtorch, stdio, the refusals
/// below) when the connection limit is derived from the process's descriptor limit.
pub const RESERVED_DESCRIPTORS: usize = 64;

/// The largest connection limit (as `--max-connections` bounds it).
pub const MAX_CONNECTIONS: usize = 1_000_000;

/// The connection limit when none is given, where the descriptor limit allows it.
pub const DEFAULT_MAX_CONNECTIONS: usize = 512;

/// Refusals (503 replies) written at once at most; beyond that an extra connection is closed
/// without a reply, so refusing never costs more than this many descriptors.
const REFUSING: usize = 32;

/// How long a refusal may take to write (the client may not read it).
const REFUSAL_WRITE: Duration = Duration::from_secs(1);

/// How long a refused connection's request is read (and dropped) after the reply.
const REFUSAL_DRAIN: Duration = Duration::from_millis(100);

/// The soft limit on open descriptors of this process (`ulimit -n`), where the system says
/// (Linux: `/proc/self/limits`); `None` when unknown or unlimited.
pub fn descriptor_limit() -> Option<usize> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = limits.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// Connections the descriptor limit leaves room for, or `None` when it is unknown.
pub fn connection_budget() -> Option<usize> {
    descriptor_limit().map(|n| n.saturating_sub(RESERVED_DESCRIPTORS))
}

/// What a connection is allowed.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ConnLimits {
    pub max_connections: usize,
    pub header_timeout: Duration,
}

/// What a request body is allowed (the state of [`read_body`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct BodyLimits {
    pub max_bytes: usize,
    pub timeout: Duration,
}

/// Accepts connections until `stop` fires, then lets the open ones finish (each is bounded by its
/// timeouts) for at most `header_timeout + grace`.
pub(crate) async fn accept_loop(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    grace: Duration,
    mut stop: tokio::sync::oneshot::Receiver<()>,
) {
    let slots = Arc::new(Semaphore::new(limits.max_connections));
    let refusing = Arc::new(Semaphore::new(REFUSING));
    let (closing_tx, closing_rx) = watch::channel(false);
    loop {
        let stream = tokio::select! {
            _ = &mut stop => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(_) => {
                    // Out of descriptors (EMFILE) or a connection reset before it was accepted:
                    // the listener itself is fine. Wait for descriptors to be freed, not spin.
                    tokio::time::sleep(Duration::from_millis(20)).await;
                    continue;
                }
            },
        };
        match Arc::clone(&slots).try_acquire_owned() {
            Ok(slot) => {
                let (app, closing) = (app.clone(), closing_rx.clone());
                tokio::spawn(serve_connection(stream, slot, app, limits.header_timeout, closing));
            }
            Err(_) => match Arc::clone(&refusing).try_acquire_owned() {
                Ok(permit) => {
                    tokio::spawn(refuse(stream, permit, limits.max_connections));
                }
                Err(_) => drop(stream),
            },
        }
    }
    let _ = closing_tx.send(true);
    // Every slot back means every connection has finished.
    let all = u32::try_from(limits.max_connections).unwrap_or(u32::MAX);
    let _ = tokio::time::timeout(limits.header_timeout + grace, slots.acquire_many(all)).await;
}

/// Serves one connection, holding its slot until it closes.
async fn serve_connection(
    stream: TcpStream,
    _slot: OwnedSemaphorePermit,
    app: Router,
    header_timeout: Duration,
    mut closing: watch::Receiver<bool>,
) {
    let _ = stream.set_nodelay(true);
    let mut http = hyper::server::conn::http1::Builder::new();
    // The timer makes the header timeout work; it runs from when the connection (or, kept alive,
    // its next request) starts to be read until the headers are complete.
    http.timer(TokioTimer::new()).header_read_timeout(header_timeout);
    let conn = http.serve_connection(TokioIo::new(stream), TowerToHyperService::new(app));
    tokio::pin!(conn);
    tokio::select! {
        _ = conn.as_mut() => {}
        // The one change is the stop (or its sender gone: stopping too).
        _ = closing.changed() => {
            conn.as_mut().graceful_shutdown();
            let _ = conn.await;
        }
    }
}

/// Answers a connection over the limit with 503 and closes it.
async fn refuse(mut stream: TcpStream, _permit: OwnedSemaphorePermit, max: usize) {
    let body = serde_json::json!({
        "error": format!(
            "{max} connections are open, the server's limit (--max-connections); retry shortly"
        )
    })
    .to_string();
    let reply = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n\
         content-length: {}\r\nretry-after: 1\r\nconnection: close\r\n\r\n{body}",
        body.len()
    );
    let written = tokio::time::timeout(REFUSAL_WRITE, async {
        stream.write_all(reply.as_bytes()).await?;
        stream.shutdown().await
    })
    .await;
    if matches!(written, Ok(Ok(()))) {
        // Read what the client has sent, briefly: closing a socket with unread input resets the
        // connection, and the client might lose the reply.
        let _ = tokio::time::timeout(REFUSAL_DRAIN, async {
            let mut sink = [0u8; 4096];
            while stream.read(&mut sink).await? > 0 {}
            Ok::<(), std::io::Error>(())
        })
        .await;
    }
}

/// Reads a request's body within `--body-timeout-s` and `--max-body-bytes` before the handler
/// sees it: a body declared too large is refused before a byte of it is read, and one that stops
/// coming is given up (408) rather than waited for.
pub(crate) async fn read_body(
    State(limits): State<BodyLimits>,
    req: Request,
    next: Next,
) -> Response {
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok());
    if let Some(n) = declared.filter(|&n| n > limits.max_bytes as u64) {
        return too_large(format!(
            "the request body declares {n} bytes, more than the server's limit of {} \
             (--max-body-bytes)",
            limits.max_bytes
        ));
    }
    let (parts, body) = req.into_parts();
    let bytes =
        match tokio::time::timeout(limits.timeout, axum::body::to_bytes(body, limits.max_bytes))
            .await
        {
            Ok(Ok(bytes)) => bytes,
            Ok(Err(e)) => {
                let e = e.into_inner();
                if e.is::<http_body_util::LengthLimitError>() {
                    return too_large(format!(
                        "the request body is larger than the server's limit of {} bytes \
                         (--max-body-bytes)",
                        limits.max_bytes
                    ));
                }
                return ApiError::bad(format!("the request body could not be read: {e}"))
                    .into_response();
            }
            Err(_) => {
                return ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    format!(
                        "the request body did not arrive within {:?} (--body-timeout-s)",
                        limits.timeout
                    ),
                )
                .into_response()
            }
        };
    next.run(Request::from_parts(parts, Body::from(bytes))).await
}

fn too_large(message: String) -> Response {
    ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, message).into_response()
}
