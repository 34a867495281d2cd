//! The inference queue: admission before any work, bounded lanes,
//! per-request deadlines, batching with a size cap and a maximum delay, and
//! one worker thread that owns the compute backend. CPU-heavy work (the
//! backend's pyramids, then the vision layer's min-cuts and masks) runs on
//! that thread and the rayon pool, never on the async runtime's threads.
//!
//! Two lanes, so that a kind of request that costs seconds cannot take
//! every worker from one that costs milliseconds:
//! - **detect**: `POST /detect`, [`InferConfig::queue_size`] places, held
//!   from admission until the worker takes the request;
//! - **pose**: `POST /pose`, [`InferConfig::pose_queue_size`] places, held
//!   from admission until the answer. A pose's detection (for its mask, or
//!   its start poses) runs on the worker, which alternates between the
//!   lanes (a batch of detections, then one pose's detection), and its
//!   refinement on a pool of its own ([`InferConfig::pose_threads`]
//!   threads), never on the worker.
//!
//! Admission comes first: a caller takes a [`Permit`] before it reads or
//! decodes anything, and a full queue refuses it at once
//! ([`InferError::Overloaded`]), so that an overload costs no decoding and
//! no memory beyond the queue's. A request whose deadline passes while it
//! waits is answered [`InferError::DeadlineExceeded`] and never computed; a
//! request whose caller went away (its reply channel closed) is dropped
//! unseen.

pub mod budget;
pub mod memory;
mod metrics;
mod queue;

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use thiserror::Error;
use tokio::sync::{oneshot, watch};

use crate::backend::{Backend, BackendError, BackendInfo};
use crate::model::Model;
use crate::pipeline::{DetectOptions, DetectResponse};
use crate::pose::api::{PoseParams, PoseResponse};
use crate::pose::{Mesh, PoseError};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::VisionError;

pub use budget::{MemoryBudget, Reservation};
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
    /// Pose requests admitted at once (waiting or computing); more are
    /// refused with `Overloaded` while detections are still admitted.
    pub pose_queue_size: usize,
    /// Threads of the pose pool (at most as many refinements at once; a
    /// refinement alone uses them all). They run at a lower priority than
    /// the detections ([`POSE_NICENESS`]).
    pub pose_threads: usize,
    /// The memory that the requests being decoded, waiting or computed
    /// may take together, in bytes ([`budget`]): each reserves its
    /// estimated cost before its image is decoded.
    pub memory_budget_bytes: u64,
    /// Pixels a batch of detections holds at most (the first request of a
    /// batch is taken whatever its size): a large image is computed alone,
    /// so that it cannot make the small ones batched with it miss their
    /// deadlines.
    pub max_batch_pixels: usize,
}

impl Default for InferConfig {
    fn default() -> Self {
        Self {
            queue_size: 32,
            max_batch: 4,
            max_batch_delay: Duration::from_millis(2),
            pose_queue_size: 8,
            pose_threads: 1,
            memory_budget_bytes: budget::default_budget_bytes(),
            max_batch_pixels: DEFAULT_MAX_BATCH_PIXELS,
        }
    }
}

/// How long past its batch's last deadline the worker may still compute
/// before readiness says the service is stuck ([`Infer::overrunning`]).
pub const OVERRUN_GRACE: Duration = Duration::from_secs(2);

/// The default [`InferConfig::max_batch_pixels`]: four VGA photographs.
pub const DEFAULT_MAX_BATCH_PIXELS: usize = 4 * 640 * 480;

impl InferConfig {
    /// The places of `lane`.
    pub fn places(&self, lane: Lane) -> usize {
        match lane {
            Lane::Detect => self.queue_size,
            Lane::Pose => self.pose_queue_size,
        }
    }
}

/// The kinds of request, each with its own places.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lane {
    Detect,
    Pose,
}

impl Lane {
    pub const ALL: [Lane; 2] = [Lane::Detect, Lane::Pose];

    pub fn name(self) -> &'static str {
        match self {
            Lane::Detect => "detect",
            Lane::Pose => "pose",
        }
    }
}

/// Why a request was not answered with a result.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum InferError {
    #[error("the {} lane of the inference queue is full", .0.name())]
    Overloaded(Lane),
    #[error("the service is shutting down")]
    ShuttingDown,
    #[error("the request's deadline passed before it was computed")]
    DeadlineExceeded,
    /// The request alone needs more memory than the server's budget.
    #[error("this image with these models needs about {needed_mib} MiB to compute, more than the server's memory budget of {budget_mib} MiB (--memory-budget-mb): send a smaller image or fewer models")]
    TooCostly { needed_mib: u64, budget_mib: u64 },
    /// The budget stayed taken by requests in progress until the deadline.
    #[error("the server's memory budget of {budget_mib} MiB stayed taken by requests in progress until this request's deadline (it needs about {needed_mib} MiB): retry later")]
    MemoryBusy { needed_mib: u64, budget_mib: u64 },
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

/// A detection to compute: a decoded image, the models to run and options,
/// and the memory reserved for it (given back when the worker drops the
/// task).
pub struct DetectTask {
    pub image: Arc<ColorImage>,
    pub models: Vec<Arc<Model>>,
    pub opts: DetectOptions,
    pub cost: Option<Reservation>,
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
    /// The memory reserved for its detection, if it needs one.
    pub cost: Option<Reservation>,
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
    /// A pose that needs the worker's detection first (for its mask, or
    /// for its start poses).
    fn needs_detection(&self) -> bool {
        matches!(self, Work::Pose(t, _) if t.model.is_some())
    }

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

/// A place in a lane: in the detect lane from admission until the job is
/// queued (then the job holds it until the worker takes it), in the pose
/// lane until the permit is dropped (the request answered or given up).
pub struct Permit {
    shared: Arc<Shared>,
    lane: Lane,
    held: bool,
}

impl Drop for Permit {
    fn drop(&mut self) {
        if self.held {
            self.shared.release(self.lane, 1);
        }
    }
}

/// The worker's inbound jobs, by lane (unbounded: the permits bound what
/// is in them).
struct Lanes {
    detect: VecDeque<Job>,
    pose: VecDeque<Job>,
    /// No more jobs come: the worker ends once both lanes are empty.
    closed: bool,
}

/// The lanes and the signal that a job arrived (or they closed).
struct Inbox {
    lanes: Mutex<Lanes>,
    arrived: Condvar,
}

/// State shared by the handle and the worker.
struct Shared {
    config: InferConfig,
    inbox: Inbox,
    /// Places taken in the detect lane: requests admitted and not yet
    /// taken by the worker.
    queued: AtomicUsize,
    /// Places taken in the pose lane: pose requests admitted and not yet
    /// answered.
    poses: AtomicUsize,
    /// The pool that refines poses.
    pose_pool: rayon::ThreadPool,
    /// Set when the shutdown's grace period ends: every request still
    /// waiting is answered `ShuttingDown`.
    cut: watch::Sender<bool>,
    accepting: AtomicBool,
    backend_healthy: AtomicBool,
    backend_info: std::sync::RwLock<BackendInfo>,
    metrics: InferMetrics,
    /// The watchdog's clock: instants are kept as microseconds since it.
    epoch: Instant,
    /// The last deadline of the batch the worker computes (microseconds
    /// since `epoch`, plus one), 0 while it computes none.
    busy_until: AtomicU64,
    budget: MemoryBudget,
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
    fn counter(&self, lane: Lane) -> (&AtomicUsize, usize) {
        let counter = match lane {
            Lane::Detect => &self.queued,
            Lane::Pose => &self.poses,
        };
        (counter, self.config.places(lane))
    }

    /// Gives `n` places of `lane` back.
    fn release(&self, lane: Lane, n: usize) {
        let (counter, _) = self.counter(lane);
        let left = counter.fetch_sub(n, Ordering::AcqRel).saturating_sub(n);
        self.metrics.set_lane(lane, left);
    }

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
        if config.queue_size == 0
            || config.max_batch == 0
            || config.pose_queue_size == 0
            || config.pose_threads == 0
            || config.max_batch_pixels == 0
            || config.memory_budget_bytes < budget::MIN_BUDGET_BYTES
        {
            return Err(InferError::Internal(format!(
                "queue sizes, batch size, batch pixels and pose threads must be at least 1, the memory budget at least {} MiB",
                budget::MIN_BUDGET_BYTES >> 20
            )));
        }
        let pose_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.pose_threads)
            .thread_name(|i| format!("sdhop-pose-{i}"))
            .start_handler(|_| yield_to_detections())
            .build()
            .map_err(|e| InferError::Internal(format!("cannot start the pose pool: {e}")))?;
        for lane in Lane::ALL {
            metrics.set_capacity(lane, config.places(lane));
        }
        let shared = Arc::new(Shared {
            config,
            inbox: Inbox {
                lanes: Mutex::new(Lanes {
                    detect: VecDeque::new(),
                    pose: VecDeque::new(),
                    closed: false,
                }),
                arrived: Condvar::new(),
            },
            queued: AtomicUsize::new(0),
            poses: AtomicUsize::new(0),
            pose_pool,
            cut: watch::Sender::new(false),
            accepting: AtomicBool::new(true),
            backend_healthy: AtomicBool::new(backend.healthy()),
            backend_info: std::sync::RwLock::new(backend.info()),
            metrics,
            epoch: Instant::now(),
            busy_until: AtomicU64::new(0),
            budget: MemoryBudget::new(config.memory_budget_bytes),
        });
        shared.metrics.backend_healthy.set(1);
        let worker_shared = Arc::clone(&shared);
        let handle = std::thread::Builder::new()
            .name("sdhop-infer".into())
            .spawn(move || queue::run(backend, &worker_shared))
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

    /// The worker is still computing a batch whose every deadline passed
    /// more than [`OVERRUN_GRACE`] ago: every stage of the computation
    /// looks at the deadline at a grain of milliseconds, so a worker that
    /// far behind is stuck, and the service is not ready until it lets go.
    /// A worker still finishing a request that just missed its deadline is
    /// no reason to leave the Service.
    pub fn overrunning(&self) -> bool {
        let until = self.shared.busy_until.load(Ordering::Acquire);
        until != 0 && {
            let now = self.shared.epoch.elapsed().as_micros() as u64;
            now.saturating_add(1) > until.saturating_add(OVERRUN_GRACE.as_micros() as u64)
        }
    }

    /// Requests admitted and not yet taken by the worker.
    pub fn queued(&self) -> usize {
        self.shared.queued.load(Ordering::Acquire)
    }

    /// Places taken in `lane` and its capacity.
    pub fn lane(&self, lane: Lane) -> (usize, usize) {
        let (counter, cap) = self.shared.counter(lane);
        (counter.load(Ordering::Acquire), cap)
    }

    /// New requests are admitted.
    pub fn accepting(&self) -> bool {
        self.shared.accepting.load(Ordering::Acquire)
    }

    /// The memory budget (see [`budget`]).
    pub fn budget(&self) -> &MemoryBudget {
        &self.shared.budget
    }

    /// Reserves the estimated memory of detecting with `models` on a
    /// `width x height` image, waiting for it in order of arrival at most
    /// until `deadline`; call it once the image's header is read and
    /// before it is decoded.
    pub async fn reserve(
        &self,
        width: usize,
        height: usize,
        models: &[&Model],
        deadline: Instant,
    ) -> Result<Reservation, InferError> {
        let bytes = budget::request_bytes(width, height, models, rayon::current_num_threads());
        self.shared.budget.reserve(bytes, deadline).await
    }

    /// Admission to the detect lane (see [`Self::admit_to`]).
    pub fn admit(&self) -> Result<Permit, InferError> {
        self.admit_to(Lane::Detect)
    }

    /// Admission: a place in `lane`, refused at once when the lane is full
    /// or the service is shutting down. Take it before doing any work for
    /// the request; dropping it gives the place back.
    pub fn admit_to(&self, lane: Lane) -> Result<Permit, InferError> {
        let m = &self.shared.metrics;
        if !self.accepting() {
            m.job("rejected");
            return Err(InferError::ShuttingDown);
        }
        let (counter, cap) = self.shared.counter(lane);
        let taken = counter.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (n < cap).then_some(n + 1)
        });
        match taken {
            Ok(n) => {
                m.set_lane(lane, n + 1);
                Ok(Permit {
                    shared: Arc::clone(&self.shared),
                    lane,
                    held: true,
                })
            }
            Err(_) => {
                m.job("rejected");
                m.reject(lane);
                Err(InferError::Overloaded(lane))
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
        self.wait(rx, deadline).await
    }

    /// Refines a pose with a permit of the pose lane (held until the
    /// answer); waits at most until `deadline`. A pose that needs a
    /// detection queues for the worker first; one that does not goes to
    /// the pose pool at once.
    pub async fn pose(
        &self,
        permit: Permit,
        task: PoseTask,
        deadline: Instant,
    ) -> Result<PoseResponse, InferError> {
        if permit.lane != Lane::Pose {
            return Err(InferError::Internal(
                "a pose needs a place in the pose lane".into(),
            ));
        }
        let (tx, rx) = oneshot::channel();
        let job = Job {
            work: Work::Pose(Box::new(task), tx),
            enqueued: Instant::now(),
            deadline,
        };
        if job.work.needs_detection() {
            self.push(job)?;
        } else {
            queue::refine_later(&self.shared, job, None);
        }
        let result = self.wait(rx, deadline).await;
        drop(permit);
        result
    }

    /// Runs `f` on the pose pool, at its lower priority, and waits for it
    /// at most until `deadline`: the reading of a pose request's inputs
    /// (mesh, image, mask), whose cost is the client's to choose, runs
    /// where pose work runs and not on the runtime's blocking threads.
    /// Nothing runs when the caller stopped waiting before its turn.
    pub async fn on_pose_pool<T, F>(&self, deadline: Instant, f: F) -> Result<T, InferError>
    where
        T: Send + 'static,
        F: FnOnce() -> T + Send + 'static,
    {
        let (tx, rx) = oneshot::channel();
        self.shared.pose_pool.spawn(move || {
            if tx.is_closed() {
                return;
            }
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
                .map_err(|_| InferError::Internal("reading the pose request failed".into()));
            let _ = tx.send(result);
        });
        self.wait(rx, deadline).await
    }

    /// Puts an admitted detection in the detect lane; its permit's place
    /// passes to the job (the worker gives it back when it takes the job).
    fn enqueue(&self, mut permit: Permit, work: Work, deadline: Instant) -> Result<(), InferError> {
        if permit.lane != Lane::Detect {
            return Err(InferError::Internal(
                "a detection needs a place in the detect lane".into(),
            ));
        }
        self.push(Job {
            work,
            enqueued: Instant::now(),
            deadline,
        })?;
        permit.held = false;
        Ok(())
    }

    /// Hands a job to the worker, in its lane.
    fn push(&self, job: Job) -> Result<(), InferError> {
        let inbox = &self.shared.inbox;
        let mut lanes = inbox
            .lanes
            .lock()
            .map_err(|_| InferError::Internal("queue lock poisoned".into()))?;
        if lanes.closed {
            return Err(InferError::ShuttingDown);
        }
        match job.work {
            Work::Detect(..) => lanes.detect.push_back(job),
            Work::Pose(..) => lanes.pose.push_back(job),
        }
        drop(lanes);
        inbox.arrived.notify_one();
        Ok(())
    }

    /// The worker's answer, or a deadline error when it comes too late, or
    /// `ShuttingDown` once the shutdown's grace period has ended.
    async fn wait<T>(
        &self,
        rx: oneshot::Receiver<Result<T, InferError>>,
        deadline: Instant,
    ) -> Result<T, InferError> {
        let cut_now = self.grace_ended();
        tokio::select! {
            r = tokio::time::timeout_at(deadline.into(), rx) => match r {
                Ok(Ok(result)) => result,
                Ok(Err(_)) => Err(InferError::Internal(
                    "the worker dropped the request".into(),
                )),
                // Dropping the receiver here tells the worker not to
                // compute it.
                Err(_) => Err(InferError::DeadlineExceeded),
            },
            () = cut_now => Err(InferError::ShuttingDown),
        }
    }

    /// Stops admitting requests; those already queued are still computed.
    pub fn stop_admitting(&self) {
        self.shared.accepting.store(false, Ordering::Release);
    }

    /// Resolves once the shutdown's grace period ends
    /// ([`Self::cut_waiting`]): what still waits then (a body still
    /// arriving, an answer) is answered `ShuttingDown`.
    pub fn grace_ended(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut cut = self.shared.cut.subscribe();
        async move {
            // Resolves once the cut is set (or can no longer be).
            let _ = cut.wait_for(|&c| c).await;
        }
    }

    /// Answers every request still waiting with `ShuttingDown` (the end of
    /// the shutdown's grace period); nothing is computed for them any
    /// more, since their callers are gone.
    pub fn cut_waiting(&self) {
        self.shared.cut.send_replace(true);
    }

    /// Stops admitting, lets the worker finish the queue, and waits for it
    /// at most `grace`. Returns whether the worker finished in time.
    pub async fn shutdown(&self, grace: Duration) -> bool {
        self.stop_admitting();
        if let Ok(mut lanes) = self.shared.inbox.lanes.lock() {
            // The worker ends once the lanes are empty.
            lanes.closed = true;
        }
        self.shared.inbox.arrived.notify_all();
        let handle = self.worker.lock().ok().and_then(|mut h| h.take());
        let Some(handle) = handle else {
            return true;
        };
        let join = tokio::task::spawn_blocking(move || handle.join().is_ok());
        matches!(tokio::time::timeout(grace, join).await, Ok(Ok(true)))
    }
}

/// How much nicer (Linux niceness) the pose pool's threads are than the
/// rest: while detections and poses both compute, the scheduler gives the
/// cores to the detections first; alone, a pose still has every core.
pub const POSE_NICENESS: i32 = 10;

/// Lowers the calling thread's scheduling priority by [`POSE_NICENESS`]
/// (Linux; elsewhere nothing). Lowering one's own priority needs no
/// privilege; a failure leaves the thread as it was.
fn yield_to_detections() {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid and setpriority take plain integers and change only
    // the calling thread's niceness.
    unsafe {
        let tid = libc::gettid();
        let _ = libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, POSE_NICENESS);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::CpuBackend;

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_large_image_is_batched_alone_and_each_request_holds_its_memory() {
        use crate::synth::{hand_model, HandModelParams, SynthObject};
        let obj = SynthObject {
            cols: 6,
            rows: 5,
            seed: 3,
        };
        let model = Arc::new(hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap());
        let registry = prometheus::Registry::new();
        let infer = Infer::start(
            Box::new(CpuBackend),
            InferConfig {
                max_batch: 4,
                // Long enough that the three small requests always meet in
                // one batch, however loaded the machine.
                max_batch_delay: Duration::from_secs(2),
                max_batch_pixels: 3 * 64 * 48,
                ..InferConfig::default()
            },
            InferMetrics::new(&registry).unwrap(),
        )
        .unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        let image = |w: usize, h: usize| Arc::new(crate::vision::image::noise_image(w, h, 1));
        let refs = [model.as_ref()];
        let mut waiting = Vec::new();
        // One large image, then three small ones: the large one is computed
        // alone, the small ones together.
        for (w, h) in [(320, 240), (64, 48), (64, 48), (64, 48)] {
            let cost = infer.reserve(w, h, &refs, deadline).await.unwrap();
            let task = DetectTask {
                image: image(w, h),
                models: vec![Arc::clone(&model)],
                opts: DetectOptions::default(),
                cost: Some(cost),
            };
            let permit = infer.admit().unwrap();
            let infer = infer.clone();
            waiting.push(tokio::spawn(async move {
                infer.detect(permit, task, deadline).await
            }));
        }
        assert!(infer.budget().free_mib() < infer.budget().total_mib());
        for w in waiting {
            w.await.unwrap().unwrap();
        }
        let batches = &infer.shared.metrics.batch_size;
        assert_eq!(batches.get_sample_sum(), 4.0);
        assert_eq!(
            batches.get_sample_count(),
            2,
            "the large image alone, the rest together"
        );
        // Every reservation is back once the worker dropped its request
        // (just after answering it).
        let until = Instant::now() + Duration::from_secs(5);
        while infer.budget().free_mib() < infer.budget().total_mib() && Instant::now() < until {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(infer.budget().free_mib(), infer.budget().total_mib());
    }

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
            assert!(!infer.overrunning(), "just past its deadline: finishing");
        }
        // (Instants are kept from the queue's start: wait until a deadline
        // past the grace lies after it.)
        std::thread::sleep(OVERRUN_GRACE + Duration::from_millis(20));
        {
            let _busy = shared.busy(Some(
                Instant::now() - OVERRUN_GRACE - Duration::from_millis(1),
            ));
            assert!(infer.overrunning(), "past its deadline and the grace");
        }
        assert!(!infer.overrunning(), "idle again");
    }
}
