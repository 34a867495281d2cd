//! The one mapping from errors to HTTP statuses. Error bodies are JSON
//! `{"error": "...", "kind": "..."}`; nothing a client can send is a 500.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;
use thiserror::Error;

use crate::infer::InferError;
use crate::pose::PoseError;
use crate::vision::VisionError;

/// Seconds a client should wait before retrying a 503.
pub const RETRY_AFTER_SECONDS: u64 = 1;

/// Errors of the HTTP layer.
#[derive(Debug, Error)]
pub enum ApiError {
    #[error("{0}")]
    BadRequest(String),
    #[error("unknown model: {}", shorten(.0))]
    UnknownModel(String),
    #[error("{0}")]
    NotFound(String),
    #[error("method not allowed on this endpoint")]
    MethodNotAllowed,
    #[error("{0}")]
    PayloadTooLarge(String),
    #[error("{0}")]
    UnsupportedMediaType(String),
    #[error("{0}")]
    NotAcceptable(String),
    #[error("{0}")]
    Unprocessable(String),
    #[error("the {0} lane of the inference queue is full, retry later")]
    Overloaded(&'static str),
    /// The memory budget is taken (see `infer::budget`).
    #[error("{0}")]
    MemoryBusy(String),
    #[error("the service is not ready: {0}")]
    NotReady(String),
    #[error("the request's deadline passed before it was answered")]
    DeadlineExceeded,
    #[error("{0}")]
    RequestTimeout(String),
    #[error("internal error: {0}")]
    Internal(String),
}

/// The longest piece of a client's input echoed in an error message.
pub const ECHO_CHARS: usize = 64;

/// `text` as an error message echoes it: at most [`ECHO_CHARS`]
/// characters, with how long it was when cut.
pub fn shorten(text: &str) -> String {
    let n = text.chars().count();
    if n <= ECHO_CHARS {
        format!("{text:?}")
    } else {
        let head: String = text.chars().take(ECHO_CHARS).collect();
        format!("{head:?}... ({n} characters)")
    }
}

/// The JSON body of an error.
#[derive(Debug, Serialize)]
pub struct ErrorBody {
    pub error: String,
    pub kind: &'static str,
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        match self {
            ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::UnknownModel(_) | ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ApiError::PayloadTooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ApiError::NotAcceptable(_) => StatusCode::NOT_ACCEPTABLE,
            ApiError::Unprocessable(_) => StatusCode::UNPROCESSABLE_ENTITY,
            ApiError::Overloaded(_)
            | ApiError::MemoryBusy(_)
            | ApiError::NotReady(_)
            | ApiError::DeadlineExceeded => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::RequestTimeout(_) => StatusCode::REQUEST_TIMEOUT,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    pub fn kind(&self) -> &'static str {
        match self {
            ApiError::BadRequest(_) => "bad_request",
            ApiError::UnknownModel(_) => "unknown_model",
            ApiError::NotFound(_) => "not_found",
            ApiError::MethodNotAllowed => "method_not_allowed",
            ApiError::PayloadTooLarge(_) => "payload_too_large",
            ApiError::UnsupportedMediaType(_) => "unsupported_media_type",
            ApiError::NotAcceptable(_) => "not_acceptable",
            ApiError::Unprocessable(_) => "unprocessable",
            ApiError::Overloaded(_) => "overloaded",
            ApiError::MemoryBusy(_) => "memory_busy",
            ApiError::NotReady(_) => "not_ready",
            ApiError::DeadlineExceeded => "deadline_exceeded",
            ApiError::RequestTimeout(_) => "request_timeout",
            ApiError::Internal(_) => "internal",
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        let body = ErrorBody {
            error: self.to_string(),
            kind: self.kind(),
        };
        let mut resp = (status, Json(body)).into_response();
        // An error may be answered before the request's body was read
        // (admission, size limits), and then the connection cannot carry
        // another request: saying so keeps clients from reusing it.
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
        if status == StatusCode::SERVICE_UNAVAILABLE {
            resp.headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(RETRY_AFTER_SECONDS));
        }
        resp
    }
}

impl From<InferError> for ApiError {
    fn from(e: InferError) -> Self {
        match e {
            InferError::Overloaded(lane) => ApiError::Overloaded(lane.name()),
            InferError::ShuttingDown => ApiError::NotReady("shutting down".into()),
            InferError::DeadlineExceeded => ApiError::DeadlineExceeded,
            e @ InferError::TooCostly { .. } => ApiError::PayloadTooLarge(e.to_string()),
            e @ InferError::MemoryBusy { .. } => ApiError::MemoryBusy(e.to_string()),
            InferError::Vision(v) => v.into(),
            InferError::Backend(b) => ApiError::NotReady(b.to_string()),
            InferError::Pose(p) => p.into(),
            InferError::Internal(m) => ApiError::Internal(m),
        }
    }
}

impl From<VisionError> for ApiError {
    fn from(e: VisionError) -> Self {
        match e {
            VisionError::ImageTooLarge { .. } => ApiError::PayloadTooLarge(e.to_string()),
            VisionError::DeadlineExceeded => ApiError::DeadlineExceeded,
            // An image the detector cannot use (empty, smaller than a
            // template): the request was well formed, its content is not.
            _ => ApiError::Unprocessable(e.to_string()),
        }
    }
}

impl From<PoseError> for ApiError {
    fn from(e: PoseError) -> Self {
        match e {
            PoseError::MeshTooLarge { .. } => ApiError::PayloadTooLarge(e.to_string()),
            PoseError::UnknownModel(name) => ApiError::UnknownModel(name),
            PoseError::DeadlineExceeded => ApiError::DeadlineExceeded,
            // A well-formed request whose mesh, mask or parameters cannot
            // be used, or whose object shows too few edges.
            PoseError::InvalidMesh(_)
            | PoseError::InvalidParameter(_)
            | PoseError::NotEnoughEdges(_)
            | PoseError::NotDetected { .. } => ApiError::Unprocessable(e.to_string()),
        }
    }
}
