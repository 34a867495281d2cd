//! Connection limits: at most `max_total` open connections, and at most
//! `max_per_client` from one client address, so that one client holding
//! idle or stalled sockets cannot take the service from the others. A
//! connection over a limit is answered at once (429 over the per-client
//! limit, 503 over the total, both with `Retry-After` and
//! `Connection: close`) without reaching the router, and closed.

use std::collections::HashMap;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::serve::Listener;
use serde::Serialize;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};

use super::error::{ErrorBody, RETRY_AFTER_SECONDS};
use super::metrics::HttpMetrics;

/// How long a refused connection is read (and discarded) after its answer,
/// so that the client reads the answer rather than a reset connection.
const LINGER: Duration = Duration::from_secs(1);
/// How much of a refused connection's request is read and discarded.
const LINGER_BYTES: usize = 1 << 20;

/// The limits on open connections.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ConnLimits {
    pub max_total: usize,
    pub max_per_client: usize,
}

impl Default for ConnLimits {
    fn default() -> Self {
        Self {
            max_total: 512,
            max_per_client: 128,
        }
    }
}

/// The open connections, in all and per client address.
#[derive(Debug, Default)]
struct Counts {
    total: usize,
    per_client: HashMap<IpAddr, usize>,
}

/// Open connections, shared by the listener and its connections.
#[derive(Clone, Debug, Default)]
pub struct ConnTracker {
    counts: Arc<Mutex<Counts>>,
}

impl ConnTracker {
    /// Open connections now.
    pub fn open(&self) -> usize {
        self.counts.lock().map_or(0, |c| c.total)
    }

    /// Takes a place for a connection from `ip`, or says which limit
    /// refuses it.
    fn take(&self, ip: IpAddr, limits: &ConnLimits) -> Result<Slot, Refusal> {
        let mut c = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        let mine = c.per_client.get(&ip).copied().unwrap_or(0);
        if mine >= limits.max_per_client {
            return Err(Refusal::PerClient);
        }
        if c.total >= limits.max_total {
            return Err(Refusal::Total);
        }
        c.total += 1;
        *c.per_client.entry(ip).or_insert(0) += 1;
        Ok(Slot {
            tracker: self.clone(),
            ip,
        })
    }
}

/// A connection's place; given back when dropped.
#[derive(Debug)]
struct Slot {
    tracker: ConnTracker,
    ip: IpAddr,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut c = self
            .tracker
            .counts
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        c.total = c.total.saturating_sub(1);
        if let Some(n) = c.per_client.get_mut(&self.ip) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                c.per_client.remove(&self.ip);
            }
        }
    }
}

/// Which limit refused a connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Refusal {
    PerClient,
    Total,
}

impl Refusal {
    /// The raw HTTP/1.1 answer.
    fn response(self, limits: &ConnLimits) -> Vec<u8> {
        let (status, body) = match self {
            Refusal::PerClient => (
                "429 Too Many Requests",
                ErrorBody {
                    error: format!(
                        "too many open connections from this client address (at most {})",
                        limits.max_per_client
                    ),
                    kind: "too_many_connections",
                },
            ),
            Refusal::Total => (
                "503 Service Unavailable",
                ErrorBody {
                    error: format!("too many open connections (at most {})", limits.max_total),
                    kind: "too_many_connections",
                },
            ),
        };
        let json = serde_json::to_string(&body).unwrap_or_default();
        format!(
            "HTTP/1.1 {status}\r\ncontent-type: application/json\r\nretry-after: {RETRY_AFTER_SECONDS}\r\nconnection: close\r\ncontent-length: {}\r\n\r\n{json}",
            json.len()
        )
        .into_bytes()
    }
}

/// A TCP listener that enforces [`ConnLimits`] and counts connections in
/// `metrics`.
pub struct LimitedListener {
    inner: TcpListener,
    limits: ConnLimits,
    tracker: ConnTracker,
    metrics: HttpMetrics,
}

impl LimitedListener {
    pub fn new(inner: TcpListener, limits: ConnLimits, metrics: HttpMetrics) -> Self {
        Self {
            inner,
            limits,
            tracker: ConnTracker::default(),
            metrics,
        }
    }

    /// The counts of open connections, for metrics and tests.
    pub fn tracker(&self) -> ConnTracker {
        self.tracker.clone()
    }
}

/// Answers a refused connection, reads what it sends for a moment, and
/// closes it.
async fn refuse(mut stream: TcpStream, answer: Vec<u8>) {
    let _ = tokio::time::timeout(LINGER, async {
        stream.write_all(&answer).await?;
        stream.shutdown().await?;
        let mut buf = vec![0u8; 16 << 10];
        let mut read = 0;
        while read < LINGER_BYTES {
            match stream.read(&mut buf).await? {
                0 => break,
                n => read += n,
            }
        }
        Ok::<_, io::Error>(())
    })
    .await;
}

impl Listener for LimitedListener {
    type Io = Counted;
    type Addr = SocketAddr;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        loop {
            let (stream, addr) = Listener::accept(&mut self.inner).await;
            match self.tracker.take(addr.ip(), &self.limits) {
                Ok(slot) => {
                    let _ = stream.set_nodelay(true);
                    self.metrics.connections_open.inc();
                    return (
                        Counted {
                            stream,
                            _slot: slot,
                            open: self.metrics.connections_open.clone(),
                        },
                        addr,
                    );
                }
                Err(why) => {
                    let limit = match why {
                        Refusal::PerClient => "per_client",
                        Refusal::Total => "total",
                    };
                    self.metrics
                        .connections_refused
                        .with_label_values(&[limit])
                        .inc();
                    tracing::warn!(client = %addr.ip(), ?why, "connection refused by the connection limits");
                    tokio::spawn(refuse(stream, why.response(&self.limits)));
                }
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

/// A connection that holds its place until dropped.
pub struct Counted {
    stream: TcpStream,
    _slot: Slot,
    open: prometheus::IntGauge,
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.open.dec();
    }
}

impl AsyncRead for Counted {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl AsyncWrite for Counted {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn places_are_limited_per_client_and_in_all_and_given_back() {
        let t = ConnTracker::default();
        let limits = ConnLimits {
            max_total: 3,
            max_per_client: 2,
        };
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let a1 = t.take(a, &limits).unwrap();
        let _a2 = t.take(a, &limits).unwrap();
        assert_eq!(t.take(a, &limits).unwrap_err(), Refusal::PerClient);
        let _b1 = t.take(b, &limits).unwrap();
        assert_eq!(t.take(b, &limits).unwrap_err(), Refusal::Total);
        assert_eq!(t.open(), 3);
        drop(a1);
        assert_eq!(t.open(), 2);
        let _a3 = t.take(a, &limits).unwrap();
    }

    #[test]
    fn refusals_are_http_answers_with_retry_after() {
        let limits = ConnLimits::default();
        for (why, status) in [(Refusal::PerClient, "429"), (Refusal::Total, "503")] {
            let text = String::from_utf8(why.response(&limits)).unwrap();
            assert!(text.starts_with(&format!("HTTP/1.1 {status} ")), "{text}");
            assert!(text.contains("retry-after: 1\r\n"));
            assert!(text.contains("connection: close\r\n"));
            let (head, body) = text.split_once("\r\n\r\n").unwrap();
            assert!(head.contains(&format!("content-length: {}", body.len())));
            let v: serde_json::Value = serde_json::from_str(body).unwrap();
            assert_eq!(v["kind"], "too_many_connections");
        }
    }
}
