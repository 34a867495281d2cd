//! The inference queue: admission before any work, a bounded queue,
//! per-request deadlines, batching with a size cap and a maximum delay, and
//! one worker thread that owns the compute backend. CPU-heavy work (the
//! backend's pyramids, then the vision layer's min-cuts and masks) runs on
//! that thread and the rayon pool, never on the async runtime's threads.
//!
//! Admission comes first: a caller takes a [`Permit`] before it reads or
//! decodes anything, and a full queue refuses it at once
//! ([`InferError::Overloaded`]), so that an overload costs no decoding and
//! no memory beyond the queue's. A request whose deadline passes while it
//! waits is answered [`InferError::DeadlineExceeded`] and never computed; a
//! request whose caller went away (its reply channel closed) is dropped
//! unseen.

mod metrics;
mod queue;

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use thiserror::Error;
use tokio::sync::oneshot;

use crate::backend::{Backend, BackendError, BackendInfo};
use crate::model::Model;
use crate::pipeline::{DetectOptions, DetectResponse};
use crate::pose::api::{PoseParams, PoseResponse};
use crate::pose::{Mesh, PoseError};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::VisionError;

pub use metrics::InferMetrics;

/// Settings of the queue.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InferConfig {
    /// Requests admitted and not yet taken by the worker, at most (those
    /// being decoded count); more are refused with `Overloaded`.
    pub queue_size: usize,
    /// Requests computed together at most.
    pub max_batch: usize,
    /// How long the worker waits for more requests to fill a batch once it
    /// has one.
    pub max_batch_delay: Duration,
}

impl Default for InferConfig {
    fn default() -> Self {
        Self {
            queue_size: 32,
            max_batch: 4,
            max_batch_delay: Duration::from_millis(2),
        }
    }
}

/// Why a request was not answered with a result.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum InferError {
    #[error("the inference queue is full")]
    Overloaded,
    #[error("the service is shutting down")]
    ShuttingDown,
    #[error("the request's deadline passed before it was computed")]
    DeadlineExceeded,
    /// The input was refused by the vision layer.
    #[error(transparent)]
    Vision(#[from] VisionError),
    #[error("compute backend: {0}")]
    Backend(BackendError),
    /// The pose request was refused or could not be solved.
    #[error(transparent)]
    Pose(#[from] PoseError),
    /// A bug: the worker failed on this request.
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<BackendError> for InferError {
    fn from(e: BackendError) -> Self {
        match e {
            BackendError::Vision(v) => InferError::Vision(v),
            other => InferError::Backend(other),
        }
    }
}

/// A detection to compute: a decoded image, the models to run and options.
pub struct DetectTask {
    pub image: Arc<ColorImage>,
    pub models: Vec<Arc<Model>>,
    pub opts: DetectOptions,
}

/// A pose to refine: a decoded image, a parsed mesh, the checked
/// parameters, the client's mask, and the model whose detection gives the
/// mask (with `mask: "detect"`).
pub struct PoseTask {
    pub image: Arc<ColorImage>,
    pub mesh: Mesh,
    pub params: PoseParams,
    pub mask: Option<Mask>,
    pub model: Option<Arc<Model>>,
}

/// What the worker computes and where the answer goes.
enum Work {
    Detect(
        DetectTask,
        oneshot::Sender<Result<DetectResponse, InferError>>,
    ),
    Pose(
        Box<PoseTask>,
        oneshot::Sender<Result<PoseResponse, InferError>>,
    ),
}

/// A queued request.
struct Job {
    work: Work,
    enqueued: Instant,
    deadline: Instant,
}

impl Work {
    /// The caller stopped waiting: its reply channel is closed.
    fn closed(&self) -> bool {
        match self {
            Work::Detect(_, tx) => tx.is_closed(),
            Work::Pose(_, tx) => tx.is_closed(),
        }
    }

    /// Answers the request with an error.
    fn fail(self, e: InferError) {
        match self {
            Work::Detect(_, tx) => {
                let _ = tx.send(Err(e));
            }
            Work::Pose(_, tx) => {
                let _ = tx.send(Err(e));
            }
        }
    }
}

/// A place in the queue, from admission until the job is queued (or the
/// request is given up, when it is dropped).
pub struct Permit {
    shared: Arc<Shared>,
    held: bool,
}

impl Drop for Permit {
    fn drop(&mut self) {
        if self.held {
            let n = self.shared.queued.fetch_sub(1, Ordering::AcqRel) - 1;
            self.shared.metrics.queue_size.set(n as i64);
        }
    }
}

/// State shared by the handle and the worker.
struct Shared {
    config: InferConfig,
    sender: Mutex<Option<Sender<Job>>>,
    /// Permits held: requests admitted and not yet taken by the worker.
    queued: AtomicUsize,
    accepting: AtomicBool,
    backend_healthy: AtomicBool,
    backend_info: std::sync::RwLock<BackendInfo>,
    metrics: InferMetrics,
    /// The watchdog's clock: instants are kept as microseconds since it.
    epoch: Instant,
    /// The last deadline of the batch the worker computes (microseconds
    /// since `epoch`, plus one), 0 while it computes none.
    busy_until: AtomicU64,
}

/// Marks the worker busy with a batch until dropped (see
/// [`Infer::overrunning`]).
pub(crate) struct Busy<'a>(&'a Shared);

impl Drop for Busy<'_> {
    fn drop(&mut self) {
        self.0.busy_until.store(0, Ordering::Release);
    }
}

impl Shared {
    /// The worker computes a batch whose last deadline is `deadline`.
    pub(crate) fn busy(&self, deadline: Option<Instant>) -> Busy<'_> {
        let us = deadline.map_or(u64::MAX, |d| {
            d.saturating_duration_since(self.epoch).as_micros() as u64
        });
        self.busy_until
            .store(us.saturating_add(1), Ordering::Release);
        Busy(self)
    }
}

/// The handle to the queue, cheap to clone.
#[derive(Clone)]
pub struct Infer {
    shared: Arc<Shared>,
    worker: Arc<Mutex<Option<JoinHandle<()>>>>,
}

impl Infer {
    /// Starts the worker thread that owns `backend`.
    pub fn start(
        backend: Box<dyn Backend>,
        config: InferConfig,
        metrics: InferMetrics,
    ) -> Result<Self, InferError> {
        if config.queue_size == 0 || config.max_batch == 0 {
            return Err(InferError::Internal(
                "queue size and batch size must be at least 1".into(),
            ));
        }
        // Unbounded: the permits bound what is in it.
        let (tx, rx) = mpsc::channel();
        let shared = Arc::new(Shared {
            config,
            sender: Mutex::new(Some(tx)),
            queued: AtomicUsize::new(0),
            accepting: AtomicBool::new(true),
            backend_healthy: AtomicBool::new(backend.healthy()),
            backend_info: std::sync::RwLock::new(backend.info()),
            metrics,
            epoch: Instant::now(),
            busy_until: AtomicU64::new(0),
        });
        shared.metrics.backend_healthy.set(1);
        let worker_shared = Arc::clone(&shared);
        let handle = std::thread::Builder::new()
            .name("sdhop-infer".into())
            .spawn(move || queue::run(rx, backend, &worker_shared))
            .map_err(|e| InferError::Internal(format!("cannot start the worker: {e}")))?;
        Ok(Self {
            shared,
            worker: Arc::new(Mutex::new(Some(handle))),
        })
    }

    pub fn config(&self) -> InferConfig {
        self.shared.config
    }

    pub fn backend_info(&self) -> BackendInfo {
        self.shared
            .backend_info
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The backend has not failed.
    pub fn backend_healthy(&self) -> bool {
        self.shared.backend_healthy.load(Ordering::Acquire)
    }

    /// The worker is still computing a batch whose every deadline has
    /// passed: it should have given up, so the service is not ready
    /// (readiness answers 503 until it has).
    pub fn overrunning(&self) -> bool {
        let until = self.shared.busy_until.load(Ordering::Acquire);
        until != 0 && {
            let now = self.shared.epoch.elapsed().as_micros() as u64;
            now.saturating_add(1) > until
        }
    }

    /// Requests admitted and not yet taken by the worker.
    pub fn queued(&self) -> usize {
        self.shared.queued.load(Ordering::Acquire)
    }

    /// New requests are admitted.
    pub fn accepting(&self) -> bool {
        self.shared.accepting.load(Ordering::Acquire)
    }

    /// Admission: a place in the queue, refused at once when it is full or
    /// the service is shutting down. Take it before doing any work for the
    /// request; dropping it gives the place back.
    pub fn admit(&self) -> Result<Permit, InferError> {
        let m = &self.shared.metrics;
        if !self.accepting() {
            m.job("rejected");
            return Err(InferError::ShuttingDown);
        }
        let cap = self.shared.config.queue_size;
        let taken = self
            .shared
            .queued
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < cap).then_some(n + 1)
            });
        match taken {
            Ok(n) => {
                m.queue_size.set(n as i64 + 1);
                Ok(Permit {
                    shared: Arc::clone(&self.shared),
                    held: true,
                })
            }
            Err(_) => {
                m.job("rejected");
                Err(InferError::Overloaded)
            }
        }
    }

    /// Detects objects; waits at most until `deadline`.
    pub async fn detect(
        &self,
        permit: Permit,
        task: DetectTask,
        deadline: Instant,
    ) -> Result<DetectResponse, InferError> {
        let (tx, rx) = oneshot::channel();
        self.enqueue(permit, Work::Detect(task, tx), deadline)?;
        wait(rx, deadline).await
    }

    /// Refines a pose; waits at most until `deadline`.
    pub async fn pose(
        &self,
        permit: Permit,
        task: PoseTask,
        deadline: Instant,
    ) -> Result<PoseResponse, InferError> {
        let (tx, rx) = oneshot::channel();
        self.enqueue(permit, Work::Pose(Box::new(task), tx), deadline)?;
        wait(rx, deadline).await
    }

    /// Puts an admitted job in the queue; its permit's place passes to the
    /// job (the worker gives it back when it takes the job).
    fn enqueue(&self, mut permit: Permit, work: Work, deadline: Instant) -> Result<(), InferError> {
        let job = Job {
            work,
            enqueued: Instant::now(),
            deadline,
        };
        let guard = self
            .shared
            .sender
            .lock()
            .map_err(|_| InferError::Internal("queue lock poisoned".into()))?;
        let Some(tx) = guard.as_ref() else {
            return Err(InferError::ShuttingDown);
        };
        tx.send(job).map_err(|_| InferError::ShuttingDown)?;
        permit.held = false;
        Ok(())
    }

    /// Stops admitting requests; those already queued are still computed.
    pub fn stop_admitting(&self) {
        self.shared.accepting.store(false, Ordering::Release);
    }

    /// Stops admitting, lets the worker finish the queue, and waits for it
    /// at most `grace`. Returns whether the worker finished in time.
    pub async fn shutdown(&self, grace: Duration) -> bool {
        self.stop_admitting();
        if let Ok(mut s) = self.shared.sender.lock() {
            // Closing the channel ends the worker once the queue is empty.
            s.take();
        }
        let handle = self.worker.lock().ok().and_then(|mut h| h.take());
        let Some(handle) = handle else {
            return true;
        };
        let join = tokio::task::spawn_blocking(move || handle.join().is_ok());
        matches!(tokio::time::timeout(grace, join).await, Ok(Ok(true)))
    }
}

/// The worker's answer, or a deadline error when it comes too late.
async fn wait<T>(
    rx: oneshot::Receiver<Result<T, InferError>>,
    deadline: Instant,
) -> Result<T, InferError> {
    match tokio::time::timeout_at(deadline.into(), rx).await {
        Ok(Ok(result)) => result,
        Ok(Err(_)) => Err(InferError::Internal(
            "the worker dropped the request".into(),
        )),
        // Dropping the receiver here tells the worker not to compute it.
        Err(_) => Err(InferError::DeadlineExceeded),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::CpuBackend;

    #[test]
    fn the_watchdog_sees_a_batch_past_its_deadline() {
        let registry = prometheus::Registry::new();
        let infer = Infer::start(
            Box::new(CpuBackend),
            InferConfig::default(),
            InferMetrics::new(&registry).unwrap(),
        )
        .unwrap();
        let shared = &infer.shared;
        assert!(!infer.overrunning());
        {
            let _busy = shared.busy(Some(Instant::now() + Duration::from_secs(60)));
            assert!(!infer.overrunning(), "within its deadline");
        }
        {
            let _busy = shared.busy(Some(Instant::now() - Duration::from_millis(1)));
            assert!(infer.overrunning(), "past its deadline");
        }
        assert!(!infer.overrunning(), "idle again");
    }
}
