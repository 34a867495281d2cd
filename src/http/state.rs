//! What the handlers share: the queue, the loaded models, the limits, the
//! metrics registry and the readiness flag.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use prometheus::Registry;
use sha2::{Digest, Sha256};
use thiserror::Error;

use super::body::Pacing;
use super::conn::ConnLimits;
use super::image::ImageLimits;
use super::metrics::HttpMetrics;
use crate::infer::Infer;
use crate::model::{Model, ModelError};
use crate::pose::MeshLimits;

/// Limits and defaults of the HTTP layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HttpConfig {
    /// Largest request body of `POST /detect`, in bytes.
    pub max_body_bytes: usize,
    /// Largest request body of `POST /pose` (image, mesh and mask), in
    /// bytes: scanned meshes are large.
    pub max_pose_body_bytes: usize,
    pub image: ImageLimits,
    /// Largest mesh of `POST /pose`, checked from the counts its file
    /// declares before anything is allocated.
    pub mesh: MeshLimits,
    /// Deadline of a request that sets no `timeout_ms`.
    pub default_timeout: Duration,
    /// Largest `timeout_ms` a request may ask for.
    pub max_timeout: Duration,
    /// Largest `max_detections` a request may ask for.
    pub max_detections: usize,
    /// A request body must arrive at least this fast (bytes per second,
    /// on average once `body_grace` has passed); 0: only the deadline.
    pub min_body_rate: u64,
    /// How long a body may take before `min_body_rate` applies.
    pub body_grace: Duration,
    /// Open connections at most, in all and per client address.
    pub connections: ConnLimits,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            max_body_bytes: 20 << 20,
            max_pose_body_bytes: 64 << 20,
            image: ImageLimits::default(),
            mesh: DEFAULT_MESH_LIMITS,
            default_timeout: Duration::from_secs(30),
            max_timeout: Duration::from_secs(300),
            max_detections: 100,
            min_body_rate: 16 << 10,
            body_grace: Duration::from_secs(5),
            connections: ConnLimits::default(),
        }
    }
}

/// The service's default mesh limits: a scanned mesh of a million
/// triangles keeps a pose request within about 300 MB (measured, see
/// docs/benchmarks.md); the pose needs only the outline at image
/// resolution, so larger meshes are better simplified by the client.
pub const DEFAULT_MESH_LIMITS: MeshLimits = MeshLimits {
    max_vertices: 1_000_000,
    max_triangles: 1_000_000,
};

/// A model loaded from its weights file.
pub struct LoadedModel {
    pub model: Arc<Model>,
    pub file: PathBuf,
    /// SHA-256 of the file, hex.
    pub sha256: String,
    pub size_bytes: u64,
}

/// Errors loading the models directory.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Model { path: String, source: ModelError },
    #[error("no weights file (*.safetensors) in {0}")]
    Empty(String),
    #[error("two models are named {0}")]
    Duplicate(String),
}

/// Loads every `*.safetensors` file of `dir`, sorted by name.
pub fn load_models(dir: &Path) -> Result<Vec<LoadedModel>, LoadError> {
    let io = |source| LoadError::Io {
        path: dir.display().to_string(),
        source,
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "safetensors"))
        .collect();
    files.sort();
    let mut out: Vec<LoadedModel> = Vec::new();
    for file in files {
        let bytes = std::fs::read(&file).map_err(|source| LoadError::Io {
            path: file.display().to_string(),
            source,
        })?;
        let model = Model::from_bytes(&bytes).map_err(|source| LoadError::Model {
            path: file.display().to_string(),
            source,
        })?;
        if out.iter().any(|m| m.model.meta.name == model.meta.name) {
            return Err(LoadError::Duplicate(model.meta.name));
        }
        let digest = Sha256::digest(&bytes);
        out.push(LoadedModel {
            model: Arc::new(model),
            file,
            sha256: digest.iter().map(|b| format!("{b:02x}")).collect(),
            size_bytes: bytes.len() as u64,
        });
    }
    if out.is_empty() {
        return Err(LoadError::Empty(dir.display().to_string()));
    }
    Ok(out)
}

/// The handlers' shared state.
pub struct AppState {
    pub infer: Infer,
    pub models: Vec<LoadedModel>,
    pub config: HttpConfig,
    pub registry: Registry,
    pub metrics: HttpMetrics,
    /// Set once the models are warmed; cleared when shutting down.
    ready: AtomicBool,
    /// Set on SIGTERM: still serving, but asking to be sent no more
    /// traffic (see [`AppState::begin_drain`]).
    draining: AtomicBool,
    shutting_down: AtomicBool,
}

/// Why the service is not ready, if it is not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NotReady {
    WarmingUp,
    /// Still serving, about to stop: send traffic elsewhere.
    Draining,
    ShuttingDown,
    BackendUnhealthy,
    Overrunning,
}

impl NotReady {
    pub fn reason(self) -> String {
        match self {
            NotReady::WarmingUp => "models are warming up".into(),
            NotReady::Draining => {
                "draining before shutdown: still answering, send new requests elsewhere".into()
            }
            NotReady::ShuttingDown => "shutting down".into(),
            NotReady::BackendUnhealthy => "the compute backend failed".into(),
            NotReady::Overrunning => {
                "a computation is running more than 2 s past its deadline".into()
            }
        }
    }
}

impl AppState {
    pub fn new(
        infer: Infer,
        models: Vec<LoadedModel>,
        config: HttpConfig,
        registry: Registry,
    ) -> Result<Arc<Self>, prometheus::Error> {
        let metrics = HttpMetrics::new(&registry)?;
        Ok(Arc::new(Self {
            infer,
            models,
            config,
            registry,
            metrics,
            ready: AtomicBool::new(false),
            draining: AtomicBool::new(false),
            shutting_down: AtomicBool::new(false),
        }))
    }

    /// `Ok` when the service should be sent traffic, else why not.
    /// Readiness means "send me requests": it does not follow how full the
    /// lanes are. A pod whose pose lane is full still serves `/detect`, the
    /// main kind of request, and a full lane refuses its own requests with
    /// 503 and `Retry-After` and shows in `/metrics` (`sdhop_lane_occupancy`,
    /// on which the autoscaler may scale): taking a busy pod out of the
    /// Service would only move its load to the others and, with every pod
    /// busy, take `/detect` down everywhere (see docs/design.md).
    pub fn readiness(&self) -> Result<(), NotReady> {
        if self.shutting_down.load(Ordering::Acquire) || !self.infer.accepting() {
            Err(NotReady::ShuttingDown)
        } else if self.draining.load(Ordering::Acquire) {
            Err(NotReady::Draining)
        } else if !self.infer.backend_healthy() {
            Err(NotReady::BackendUnhealthy)
        } else if self.infer.overrunning() {
            Err(NotReady::Overrunning)
        } else if !self.ready.load(Ordering::Acquire) {
            Err(NotReady::WarmingUp)
        } else {
            Ok(())
        }
    }

    /// The drain before a shutdown (SIGTERM): readiness answers 503 so
    /// that the orchestrator stops routing here, while connections are
    /// still accepted and requests admitted and answered (those routed
    /// before the endpoints were updated).
    pub fn begin_drain(&self) {
        self.draining.store(true, Ordering::Release);
    }

    pub fn set_ready(&self) {
        self.ready.store(true, Ordering::Release);
    }

    /// Not ready from now on, and no new request is admitted.
    pub fn begin_shutdown(&self) {
        self.shutting_down.store(true, Ordering::Release);
        self.infer.stop_admitting();
    }

    /// How a request body with this deadline must arrive.
    pub fn pacing(&self, deadline: std::time::Instant) -> Pacing {
        Pacing {
            deadline,
            min_rate: self.config.min_body_rate,
            grace: self.config.body_grace,
        }
    }

    /// The model named `name`.
    pub fn model(&self, name: &str) -> Option<&LoadedModel> {
        self.models.iter().find(|m| m.model.meta.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{hand_model, HandModelParams, SynthObject};

    #[test]
    fn a_model_file_changed_after_training_is_refused_naming_the_file() {
        let obj = SynthObject {
            cols: 6,
            rows: 5,
            seed: 2,
        };
        let model = hand_model(&obj, "widget", true, &HandModelParams::default()).unwrap();
        let dir = std::env::temp_dir().join(format!("sdhop-load-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("widget.safetensors");
        model.save(&path).unwrap();
        assert_eq!(load_models(&dir).unwrap().len(), 1);
        // One flipped byte in the last tensor's data.
        let mut bytes = std::fs::read(&path).unwrap();
        let last = bytes.len() - 3;
        bytes[last] ^= 0x40;
        std::fs::write(&path, &bytes).unwrap();
        let err = match load_models(&dir) {
            Ok(_) => panic!("a changed file was loaded"),
            Err(e) => e.to_string(),
        };
        std::fs::remove_dir_all(&dir).ok();
        assert!(err.contains("widget.safetensors"), "{err}");
        assert!(err.contains("digest"), "{err}");
        assert_eq!(err.lines().count(), 1, "{err}");
    }
}
