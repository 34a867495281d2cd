//! Reading the rest of an oversized body before answering 413.
//!
//! A server that answers while the client is still sending, and closes,
//! leaves unread bytes in its socket: the kernel then resets the
//! connection, and the client sees a broken pipe instead of the 413. So a
//! request body is wrapped in [`DrainPastLimit`]: once the bytes pass the
//! route's limit it reads and discards the rest of the body (up to
//! [`DRAIN_BYTES`] more) before it hands on the frame that passed the
//! limit, which the extractors' own limit then refuses with the usual 413.
//! A client sending still more may see the connection reset.
//!
//! Every body is read whole, paced by the request's deadline and a least
//! rate ([`buffer`]), before the request takes a place in the queue: a
//! client that is not sending holds no place.

use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::Request;
use axum::response::Response;
use http_body::{Frame, SizeHint};
use http_body_util::BodyExt;
use tower::util::MapRequestLayer;

use super::error::ApiError;
use crate::infer::memory::{release_freed_pages, LARGE_BODY_BYTES};

/// How many bytes past a route's limit are read and discarded.
pub const DRAIN_BYTES: usize = 64 << 20;

/// A body that reads to the end (within `drain` more bytes) before it
/// yields the frame that takes it past `limit`.
pub struct DrainPastLimit<B> {
    inner: B,
    limit: usize,
    drain: usize,
    seen: usize,
    discarded: usize,
    /// The frame that passed the limit, held back while draining.
    held: Option<Frame<Bytes>>,
    /// Draining stopped (the end, the cap or an error).
    drained: bool,
}

impl<B> DrainPastLimit<B> {
    /// Wraps `inner` for a route whose body limit is `limit` bytes,
    /// discarding at most `drain` bytes past it.
    pub fn new(inner: B, limit: usize, drain: usize) -> Self {
        Self {
            inner,
            limit,
            drain,
            seen: 0,
            discarded: 0,
            held: None,
            drained: false,
        }
    }
}

impl<B> HttpBody for DrainPastLimit<B>
where
    B: HttpBody<Data = Bytes> + Unpin,
{
    type Data = Bytes;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, B::Error>>> {
        let this = &mut *self;
        if this.held.is_none() {
            let frame = match Pin::new(&mut this.inner).poll_frame(cx) {
                Poll::Ready(Some(Ok(frame))) => frame,
                other => return other,
            };
            let len = frame.data_ref().map_or(0, Bytes::len);
            this.seen = this.seen.saturating_add(len);
            if this.seen <= this.limit || this.drained {
                return Poll::Ready(Some(Ok(frame)));
            }
            this.held = Some(frame);
        }
        while !this.drained {
            match Pin::new(&mut this.inner).poll_frame(cx) {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(Some(Ok(frame))) => {
                    let len = frame.data_ref().map_or(0, Bytes::len);
                    this.discarded = this.discarded.saturating_add(len);
                    this.drained = this.discarded > this.drain;
                }
                // The end, or a broken body: either way nothing more to read.
                Poll::Ready(_) => this.drained = true,
            }
        }
        Poll::Ready(this.held.take().map(Ok))
    }

    fn is_end_stream(&self) -> bool {
        self.held.is_none() && self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        // Past the limit some bytes are discarded: the inner hint no longer
        // holds.
        if self.seen > self.limit {
            SizeHint::default()
        } else {
            self.inner.size_hint()
        }
    }
}

/// A layer that wraps each request's body in [`DrainPastLimit`].
pub fn drain_past(limit: usize) -> MapRequestLayer<impl Fn(Request) -> Request + Clone> {
    MapRequestLayer::new(move |req: Request| {
        req.map(|body| Body::new(DrainPastLimit::new(body, limit, DRAIN_BYTES)))
    })
}

/// The body length a request declares (`Content-Length`), if any.
fn declared_length(headers: &axum::http::HeaderMap) -> Option<u64> {
    headers
        .get(axum::http::header::CONTENT_LENGTH)?
        .to_str()
        .ok()?
        .parse()
        .ok()
}

/// A middleware that, once a request declaring a body over
/// [`LARGE_BODY_BYTES`] is answered, hands the pages its body took back to
/// the system (it was read and freed on this runtime's thread; mimalloc
/// would otherwise keep them while the service idles).
pub async fn release_large_bodies(req: Request, next: axum::middleware::Next) -> Response {
    let large = declared_length(req.headers()).is_some_and(|n| n > LARGE_BODY_BYTES);
    let resp = next.run(req).await;
    if large {
        release_freed_pages();
    }
    resp
}

/// How a request's body must arrive: by the request's deadline, and at
/// least at `min_rate` bytes per second on average once `grace` has
/// passed (a client that stops sending is cut off after about `grace`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pacing {
    pub deadline: Instant,
    pub min_rate: u64,
    pub grace: Duration,
}

impl Pacing {
    /// When the next bytes are due, `seen` bytes having arrived since
    /// `start`.
    fn due(&self, start: Instant, seen: usize) -> Instant {
        let allowed = if self.min_rate == 0 {
            Duration::MAX
        } else {
            self.grace
                .saturating_add(Duration::from_secs_f64(seen as f64 / self.min_rate as f64))
        };
        start
            .checked_add(allowed)
            .map_or(self.deadline, |t| t.min(self.deadline))
    }
}

/// Reads a request's whole body (within `limit` bytes, as `pacing` asks)
/// before anything else is done with the request: a client that is slow
/// or stalls is answered 408 and holds no place in the queue, a body over
/// the limit 413 (after it was read on, see [`DrainPastLimit`]). Returns
/// the request with its body in memory. A body still arriving when
/// `grace_ended` resolves (the end of the shutdown's grace period) is
/// answered 503, so that its client gets a status rather than a closed
/// connection.
pub async fn buffer(
    req: Request,
    limit: usize,
    pacing: &Pacing,
    grace_ended: impl std::future::Future<Output = ()>,
) -> Result<Request, ApiError> {
    let (parts, mut body) = req.into_parts();
    let mut grace_ended = std::pin::pin!(grace_ended);
    let start = Instant::now();
    // Room for the declared length (within the limit) at once: growing by
    // doubling would copy a large body several times and hold twice its
    // size. Reserved pages cost nothing until the bytes arrive.
    let declared = declared_length(&parts.headers).unwrap_or(0);
    let mut buf: Vec<u8> = Vec::with_capacity(declared.min(limit as u64) as usize);
    loop {
        let due = pacing.due(start, buf.len());
        let next = tokio::select! {
            next = tokio::time::timeout_at(due.into(), body.frame()) => next,
            () = &mut grace_ended => {
                return Err(ApiError::NotReady(format!(
                    "shutting down: the grace period ended while the body was arriving ({} bytes in {:.1} s)",
                    buf.len(),
                    start.elapsed().as_secs_f64()
                )));
            }
        };
        let frame = match next {
            Err(_) => {
                let why = if due >= pacing.deadline {
                    "before the request's deadline".to_string()
                } else {
                    format!(
                        "at the least rate of {} bytes/s (after {} ms)",
                        pacing.min_rate,
                        pacing.grace.as_millis()
                    )
                };
                return Err(ApiError::RequestTimeout(format!(
                    "the request body did not arrive {why}: {} bytes in {:.1} s",
                    buf.len(),
                    start.elapsed().as_secs_f64()
                )));
            }
            Ok(None) => break,
            Ok(Some(Err(e))) => {
                return Err(ApiError::BadRequest(format!("cannot read the body: {e}")))
            }
            Ok(Some(Ok(frame))) => frame,
        };
        if let Ok(data) = frame.into_data() {
            if buf.len() + data.len() > limit {
                return Err(ApiError::PayloadTooLarge(format!(
                    "the body exceeds {limit} bytes"
                )));
            }
            buf.extend_from_slice(&data);
        }
    }
    Ok(Request::from_parts(parts, Body::from(buf)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use http_body_util::Limited;
    use std::convert::Infallible;

    /// A body of `chunks` frames of `size` bytes that counts what was read.
    struct Chunked {
        chunks: usize,
        size: usize,
        read: usize,
    }

    impl HttpBody for Chunked {
        type Data = Bytes;
        type Error = Infallible;

        fn poll_frame(
            mut self: Pin<&mut Self>,
            _: &mut Context<'_>,
        ) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
            if self.chunks == 0 {
                return Poll::Ready(None);
            }
            self.chunks -= 1;
            self.read += self.size;
            Poll::Ready(Some(Ok(Frame::data(Bytes::from(vec![7u8; self.size])))))
        }

        fn size_hint(&self) -> SizeHint {
            SizeHint::with_exact((self.chunks * self.size) as u64)
        }
    }

    fn chunked(chunks: usize, size: usize) -> Chunked {
        Chunked {
            chunks,
            size,
            read: 0,
        }
    }

    /// Whether a body within `limit` is accepted, and how much was read,
    /// draining at most 1000 bytes past the limit.
    async fn read_limited(chunks: usize, size: usize, limit: usize) -> (bool, usize) {
        let mut body = DrainPastLimit::new(chunked(chunks, size), limit, 1000);
        assert_eq!(body.size_hint().exact(), Some((chunks * size) as u64));
        let ok = Limited::new(&mut body, limit).collect().await.is_ok();
        if !ok {
            // Bytes were discarded: the inner length no longer holds.
            assert_eq!(body.size_hint().exact(), None);
        }
        (ok, body.inner.read)
    }

    #[tokio::test]
    async fn a_body_within_the_limit_passes_whole() {
        let body = DrainPastLimit::new(chunked(10, 100), 1000, 0);
        let bytes = body.collect().await.unwrap().to_bytes();
        assert_eq!(bytes.len(), 1000);
        assert!(bytes.iter().all(|&b| b == 7));
    }

    #[tokio::test]
    async fn an_oversized_body_is_read_to_its_end_and_then_refused() {
        // 1500 bytes against a limit of 1000: all of it is read, and the
        // limit still refuses it.
        assert_eq!(read_limited(15, 100, 1000).await, (false, 1500));
        assert_eq!(read_limited(21, 100, 1000).await, (false, 2100));
    }

    #[tokio::test]
    async fn draining_stops_past_its_bound() {
        // 10 000 bytes against a limit of 1000: reading stops once more
        // than the 1000 bytes allowed past the frame that crossed the
        // limit were discarded.
        assert_eq!(read_limited(100, 100, 1000).await, (false, 2200));
    }
}
