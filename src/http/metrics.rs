//! Prometheus metrics of the HTTP layer, and the middleware that records
//! them: requests by route and status, and their durations.

use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::middleware::Next;
use axum::response::Response;
use prometheus::{HistogramOpts, HistogramVec, IntCounterVec, IntGauge, Opts, Registry};

#[derive(Clone)]
pub struct HttpMetrics {
    pub requests: IntCounterVec,
    pub duration: HistogramVec,
    /// Open connections.
    pub connections_open: IntGauge,
    /// Connections refused by a connection limit (`total`, `per_client`).
    pub connections_refused: IntCounterVec,
}

impl HttpMetrics {
    pub fn new(registry: &Registry) -> Result<Self, prometheus::Error> {
        let requests = IntCounterVec::new(
            Opts::new(
                "sdhop_http_requests_total",
                "HTTP requests by route and status",
            ),
            &["route", "status"],
        )?;
        let duration = HistogramVec::new(
            HistogramOpts::new(
                "sdhop_http_request_duration_seconds",
                "HTTP request durations by route",
            )
            .buckets(vec![
                0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
            ]),
            &["route"],
        )?;
        let connections_open =
            IntGauge::new("sdhop_http_connections_open", "Open HTTP connections")?;
        let connections_refused = IntCounterVec::new(
            Opts::new(
                "sdhop_http_connections_refused_total",
                "Connections answered 503 (total) or 429 (per_client) by a connection limit",
            ),
            &["limit"],
        )?;
        registry.register(Box::new(requests.clone()))?;
        registry.register(Box::new(duration.clone()))?;
        registry.register(Box::new(connections_open.clone()))?;
        registry.register(Box::new(connections_refused.clone()))?;
        Ok(Self {
            requests,
            duration,
            connections_open,
            connections_refused,
        })
    }
}

/// Records every request (the route label is the matched route pattern, so
/// its values are bounded).
pub async fn track(State(m): State<HttpMetrics>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or("unmatched", |m| m.as_str())
        .to_string();
    let start = Instant::now();
    let resp = next.run(req).await;
    m.requests
        .with_label_values(&[route.as_str(), resp.status().as_str()])
        .inc();
    m.duration
        .with_label_values(&[route.as_str()])
        .observe(start.elapsed().as_secs_f64());
    resp
}
