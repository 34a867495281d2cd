//! Operations endpoints: liveness, readiness, metrics, service and model
//! information, and the OpenAPI document.

use std::sync::Arc;

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::Json;
use prometheus::{Encoder, TextEncoder};
use serde::Serialize;

use super::error::ApiError;
use super::state::AppState;
use crate::backend::BackendInfo;
use crate::model::{BoxCorrection, ViewMeta};

/// The API contract, served as is.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

#[derive(Serialize)]
pub struct Status {
    pub status: &'static str,
}

/// `GET /health/live`: the process answers.
pub async fn live() -> Json<Status> {
    Json(Status { status: "live" })
}

/// `GET /health/ready`: models loaded and warmed, backend healthy, not
/// draining or shutting down (503 says which); full lanes do not count
/// (see [`AppState::readiness`]).
pub async fn ready(State(state): State<Arc<AppState>>) -> Result<Json<Status>, ApiError> {
    state
        .readiness()
        .map(|()| Json(Status { status: "ready" }))
        .map_err(|r| ApiError::NotReady(r.reason()))
}

/// `GET /metrics`: Prometheus text exposition.
pub async fn metrics(State(state): State<Arc<AppState>>) -> Result<Response, ApiError> {
    let encoder = TextEncoder::new();
    let mut out = Vec::new();
    encoder
        .encode(&state.registry.gather(), &mut out)
        .map_err(|e| ApiError::Internal(e.to_string()))?;
    Ok((
        [(header::CONTENT_TYPE, encoder.format_type().to_string())],
        out,
    )
        .into_response())
}

#[derive(Serialize)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub max_pose_body_bytes: usize,
    pub max_pixels: usize,
    pub max_side: u32,
    pub max_detections: usize,
    pub default_timeout_ms: u64,
    pub max_timeout_ms: u64,
    pub max_mesh_vertices: usize,
    pub max_mesh_triangles: usize,
    pub queue_size: usize,
    pub pose_queue_size: usize,
    pub pose_threads: usize,
    pub max_batch: usize,
    pub max_batch_delay_ms: u64,
    pub max_batch_pixels: usize,
    pub memory_budget_mb: u32,
    pub min_body_rate: u64,
    pub body_grace_ms: u64,
    pub max_connections: usize,
    pub max_connections_per_client: usize,
}

#[derive(Serialize)]
pub struct Info {
    pub name: &'static str,
    pub version: &'static str,
    pub backend: BackendInfo,
    pub limits: Limits,
    pub models: Vec<String>,
}

/// `GET /info`: version, backend in use, effective limits, model names.
pub async fn info(State(state): State<Arc<AppState>>) -> Json<Info> {
    let c = state.config;
    let q = state.infer.config();
    Json(Info {
        name: env!("CARGO_PKG_NAME"),
        version: env!("CARGO_PKG_VERSION"),
        backend: state.infer.backend_info(),
        limits: Limits {
            max_body_bytes: c.max_body_bytes,
            max_pose_body_bytes: c.max_pose_body_bytes,
            max_pixels: c.image.max_pixels,
            max_side: c.image.max_side,
            max_detections: c.max_detections,
            default_timeout_ms: c.default_timeout.as_millis() as u64,
            max_timeout_ms: c.max_timeout.as_millis() as u64,
            max_mesh_vertices: c.mesh.max_vertices,
            max_mesh_triangles: c.mesh.max_triangles,
            queue_size: q.queue_size,
            pose_queue_size: q.pose_queue_size,
            pose_threads: q.pose_threads,
            max_batch: q.max_batch,
            max_batch_delay_ms: q.max_batch_delay.as_millis() as u64,
            max_batch_pixels: q.max_batch_pixels,
            memory_budget_mb: state.infer.budget().total_mib(),
            min_body_rate: c.min_body_rate,
            body_grace_ms: c.body_grace.as_millis() as u64,
            max_connections: c.connections.max_total,
            max_connections_per_client: c.connections.max_per_client,
        },
        models: state
            .models
            .iter()
            .map(|m| m.model.meta.name.clone())
            .collect(),
    })
}

#[derive(Serialize)]
pub struct ModelInfo {
    pub name: String,
    pub labels: Vec<String>,
    pub viewpoints: Vec<ViewMeta>,
    pub file: String,
    pub sha256: String,
    pub size_bytes: u64,
    /// What its cells are: `hog` or `cnn` (learned).
    pub features: &'static str,
    /// The cells of the model that segments its detections (`hog` beside
    /// learned cells: both kinds per object), if it has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub segmenter_features: Option<&'static str>,
    /// Default detection threshold.
    pub threshold: f64,
    /// How the reported boxes are corrected from the template's window, if
    /// the model learned it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub box_correction: Option<BoxCorrection>,
    /// Cross-validated figures stored in the model, if any.
    pub training: serde_json::Value,
}

/// `GET /models`: every loaded model.
pub async fn models(State(state): State<Arc<AppState>>) -> Json<Vec<ModelInfo>> {
    Json(
        state
            .models
            .iter()
            .map(|m| {
                let meta = &m.model.meta;
                ModelInfo {
                    name: meta.name.clone(),
                    labels: m.model.labels(),
                    viewpoints: meta.viewpoints.clone(),
                    file: m
                        .file
                        .file_name()
                        .map(|f| f.to_string_lossy().into_owned())
                        .unwrap_or_default(),
                    sha256: m.sha256.clone(),
                    size_bytes: m.size_bytes,
                    features: meta.pyramid.features.name(),
                    segmenter_features: m
                        .model
                        .segmenter
                        .as_ref()
                        .map(|s| s.meta.pyramid.features.name()),
                    threshold: meta.detection.threshold,
                    box_correction: meta.box_correction,
                    training: training_figures(&meta.provenance),
                }
            })
            .collect(),
    )
}

/// The cross-validated figures of a model's provenance, without curves.
fn training_figures(provenance: &serde_json::Value) -> serde_json::Value {
    let Some(cv) = provenance.get("cross_validation") else {
        return serde_json::Value::Null;
    };
    let mut figures = cv.get("figures").cloned().unwrap_or_default();
    if let Some(obj) = figures.as_object_mut() {
        obj.remove("curve");
        obj.remove("curve_cross");
    }
    serde_json::json!({
        "folds": cv.get("folds"),
        "c": cv.get("c"),
        "figures": figures,
    })
}

/// `GET /openapi.yaml`.
pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}
