//! The HTTP layer: axum handlers, request and response types, the one
//! mapping from errors to statuses, metrics middleware and the router.
//! Only this layer knows about HTTP.

pub mod body;
pub mod conn;
pub mod detect;
pub mod error;
pub mod image;
pub mod metrics;
pub mod ops;
pub mod pose;
pub mod state;

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::DefaultBodyLimit;
use axum::http::Request;
use axum::routing::{get, post};
use axum::Router;
use tower_http::trace::{DefaultOnResponse, TraceLayer};
use tracing::Level;

use crate::infer::{DetectTask, InferError};
use crate::pipeline::{DetectOptions, MaskMode};
use crate::vision::image::ColorImage;
use error::ApiError;
pub use state::{load_models, AppState, HttpConfig, LoadedModel};

/// The service's routes.
pub fn router(state: Arc<AppState>) -> Router {
    let body_limit = state.config.max_body_bytes;
    let pose_limit = state.config.max_pose_body_bytes;
    Router::new()
        // Each body route reads an oversized body to its end before its
        // 413 (see `body`); the route's own limit wins over the router's
        // default.
        .route(
            "/detect",
            post(detect::detect).layer(body::drain_past(body_limit)),
        )
        .route(
            "/pose",
            post(pose::pose)
                .layer::<_, std::convert::Infallible>(DefaultBodyLimit::max(pose_limit))
                .layer(body::drain_past(pose_limit)),
        )
        .route("/health/live", get(ops::live))
        .route("/health/ready", get(ops::ready))
        .route("/metrics", get(ops::metrics))
        .route("/info", get(ops::info))
        .route("/models", get(ops::models))
        .route("/openapi.yaml", get(ops::openapi))
        .route_layer(axum::middleware::from_fn_with_state(
            state.metrics.clone(),
            metrics::track,
        ))
        .route_layer(axum::middleware::from_fn(body::release_large_bodies))
        .fallback(|| async { ApiError::NotFound("no such endpoint".into()) })
        .method_not_allowed_fallback(|| async { ApiError::MethodNotAllowed })
        .layer(DefaultBodyLimit::max(body_limit))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(|req: &Request<_>| {
                    tracing::info_span!("request", method = %req.method(), uri = %req.uri())
                })
                .on_request(())
                .on_response(DefaultOnResponse::new().level(Level::INFO)),
        )
        .with_state(state)
}

/// Runs one detection per model on a synthetic image, through the queue,
/// so that the first real request finds everything paged in; then marks
/// the service ready.
pub async fn warm_up(state: &AppState) -> Result<(), InferError> {
    let (w, h) = (320usize, 240usize);
    let data: Vec<f32> = (0..w * h * 3)
        .map(|i| ((i / 3) % w * 255 / w) as f32)
        .collect();
    let image = ColorImage::new(w, h, data).map_err(InferError::Vision)?;
    let task = DetectTask {
        image: Arc::new(image),
        models: state.models.iter().map(|m| Arc::clone(&m.model)).collect(),
        opts: DetectOptions {
            max_detections: Some(1),
            masks: MaskMode::Refined,
            ..DetectOptions::default()
        },
        cost: None,
    };
    let permit = state.infer.admit()?;
    state
        .infer
        .detect(permit, task, Instant::now() + Duration::from_secs(120))
        .await?;
    state.set_ready();
    Ok(())
}

/// How long before the end of the grace period the requests still waiting
/// are answered 503 (a quarter of the period when that is shorter).
const CUT_MARGIN: Duration = Duration::from_millis(500);

/// Serves until `shutdown` resolves, then becomes not ready, stops
/// admitting, lets requests in flight finish (at most `grace`), and drains
/// the queue. Returns whether everything finished within the grace period;
/// either way it returns within it (a computation still running is left
/// behind: the caller exits without waiting for it).
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: Arc<AppState>,
    shutdown: impl Future<Output = ()> + Send + 'static,
    grace: Duration,
) -> std::io::Result<bool> {
    let app = router(Arc::clone(&state));
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let signal_state = Arc::clone(&state);
    let listener =
        conn::LimitedListener::new(listener, state.config.connections, state.metrics.clone());
    let server = axum::serve(listener, app).with_graceful_shutdown(async move {
        shutdown.await;
        signal_state.begin_shutdown();
        tracing::info!("shutting down: not ready, draining requests in flight");
        let _ = tx.send(());
    });
    let server = tokio::spawn(async move { server.await });
    // Wait for the signal, then give the server and the queue one grace
    // period together. Just before it ends, every request still waiting is
    // answered 503, and the server has the rest of the period to send
    // those answers.
    let _ = rx.await;
    let until = tokio::time::Instant::now() + grace;
    let answer_by = until - (grace / 4).min(CUT_MARGIN);
    let mut server = server;
    let drained = match tokio::time::timeout_at(answer_by, &mut server).await {
        Ok(Ok(Ok(()))) => true,
        Ok(Ok(Err(e))) => return Err(e),
        Ok(Err(_)) => false,
        Err(_) => {
            tracing::warn!("grace period ending: answering the requests still waiting 503");
            state.infer.cut_waiting();
            match tokio::time::timeout_at(until, server).await {
                Ok(Ok(Err(e))) => return Err(e),
                _ => false,
            }
        }
    };
    let left = until.saturating_duration_since(tokio::time::Instant::now());
    let queue_done = state.infer.shutdown(left).await;
    Ok(drained && queue_done)
}
