//! The worker loop: takes a batch off a lane (alternating between them),
//! drops what no longer needs computing, asks the backend for the batch's
//! pyramids, then runs the vision layer's detection of each request and
//! answers it, or hands a pose's refinement to the pose pool.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use super::memory::{self, LARGE_MESH_TRIANGLES};
use super::{InferError, Job, Lane, PoseTask, Shared, Work};
use crate::backend::{model_bounds, Backend, FeatureJob};
use crate::model::Model;
use crate::pipeline::{detect_prebuilt_with, feature_settings, DetectOptions};
use crate::pose::api::{estimate_with, Detected};
use crate::pose::PoseError;
use crate::vision::detect::DenseBounds;
use crate::vision::image::ColorImage;
use crate::vision::pyramid::FeaturePyramid;
use crate::vision::Deadline;

/// Runs until the lanes are closed and empty.
pub(super) fn run(mut backend: Box<dyn Backend>, shared: &Arc<Shared>) {
    let mut pose_turn = false;
    while let Some(batch) = next_batch(shared, &mut pose_turn) {
        process(batch, backend.as_mut(), shared);
    }
}

/// The next batch: one pose's detection when it is the pose lane's turn
/// (or the detect lane is empty), else up to `max_batch` detections (after
/// waiting at most `max_batch_delay` for more). The lanes take turns, so a
/// detection waits for at most one pose's detection. `None` once the
/// lanes are closed and empty.
fn next_batch(shared: &Shared, pose_turn: &mut bool) -> Option<Vec<Job>> {
    let inbox = &shared.inbox;
    let mut lanes = inbox.lanes.lock().unwrap_or_else(|e| e.into_inner());
    while lanes.detect.is_empty() && lanes.pose.is_empty() {
        if lanes.closed {
            return None;
        }
        lanes = inbox.arrived.wait(lanes).unwrap_or_else(|e| e.into_inner());
    }
    if !lanes.pose.is_empty() && (*pose_turn || lanes.detect.is_empty()) {
        *pose_turn = false;
        return lanes.pose.pop_front().map(|job| vec![job]);
    }
    *pose_turn = true;
    let mut batch: Vec<Job> = lanes.detect.pop_front().into_iter().collect();
    let mut pixels: usize = batch.iter().map(|j| j.work.pixels()).sum();
    let until = Instant::now() + shared.config.max_batch_delay;
    while batch.len() < shared.config.max_batch {
        if let Some(next) = lanes.detect.front() {
            // A batch is answered together: an image that would take it
            // past its pixels waits for the next one, in its turn.
            let more = pixels.saturating_add(next.work.pixels());
            if more > shared.config.max_batch_pixels {
                break;
            }
            if let Some(job) = lanes.detect.pop_front() {
                pixels = more;
                batch.push(job);
            }
            continue;
        }
        let now = Instant::now();
        if now >= until || lanes.closed {
            break;
        }
        lanes = inbox
            .arrived
            .wait_timeout(lanes, until - now)
            .map(|(l, _)| l)
            .unwrap_or_else(|e| e.into_inner().0);
    }
    drop(lanes);
    shared.release(Lane::Detect, batch.len());
    Some(batch)
}

/// Refines a pose on the pose pool, with the detection it needed (`None`
/// when it needed none), and answers it. A pose whose deadline passed or
/// whose caller left while it waited for the pool is not computed.
/// The compute time it reports runs from `job.enqueued` (the batch's start
/// for a pose detected first).
pub(super) fn refine_later(
    shared: &Arc<Shared>,
    job: Job,
    found: Option<Result<Detected, InferError>>,
) {
    let worker = Arc::clone(shared);
    shared.pose_pool.spawn(move || {
        let shared = worker;
        let metrics = &shared.metrics;
        // However the job ends, a large mesh's pages go back once it is
        // dropped (the guard is dropped last, after everything below).
        let large =
            matches!(&job.work, Work::Pose(t, _) if t.mesh.triangles.len() > LARGE_MESH_TRIANGLES);
        let _release = large.then(|| ReleaseOnDrop(&shared.pose_pool));
        let Job {
            work,
            deadline,
            enqueued: start,
        } = job;
        let Work::Pose(task, tx) = work else {
            work.fail(InferError::Internal("not a pose".into()));
            return;
        };
        if tx.is_closed() {
            metrics.job("cancelled");
            return;
        }
        if Instant::now() >= deadline {
            metrics.job("expired");
            let _ = tx.send(Err(InferError::DeadlineExceeded));
            return;
        }
        let deadline = Deadline::at(deadline);
        let result = catch_unwind(AssertUnwindSafe(|| {
            // The reservation is held until the refinement ends.
            let PoseTask {
                image,
                mesh,
                params,
                mask,
                cost: _cost,
                ..
            } = *task;
            let found = found.transpose()?;
            estimate_with(
                &image,
                &mesh,
                &params,
                mask,
                |name| found.ok_or_else(|| PoseError::UnknownModel(name.to_string())),
                deadline,
            )
            .map_err(InferError::from)
        }))
        .unwrap_or_else(|_| Err(InferError::Internal("pose refinement failed".into())));
        metrics.job(if result.is_ok() {
            "completed"
        } else {
            "failed"
        });
        metrics
            .compute_duration
            .observe(start.elapsed().as_secs_f64());
        let _ = tx.send(result);
    });
}

/// Hands the pose pool's freed pages back when dropped (after the job's
/// own buffers are gone).
struct ReleaseOnDrop<'a>(&'a rayon::ThreadPool);

impl Drop for ReleaseOnDrop<'_> {
    fn drop(&mut self) {
        memory::release_freed_pages_of(self.0);
    }
}

impl Work {
    /// The pixels of the request's image.
    fn pixels(&self) -> usize {
        let image = match self {
            Work::Detect(t, _) => &t.image,
            Work::Pose(t, _) => &t.image,
        };
        image.width().saturating_mul(image.height())
    }

    /// The image, models and options of the detection this request needs,
    /// if any (a pose request with `mask: "detect"` needs one).
    /// Its computation gives up at `deadline`.
    fn detection(
        &self,
        deadline: Deadline,
    ) -> Option<(&Arc<ColorImage>, Vec<&Model>, DetectOptions)> {
        match self {
            Work::Detect(t, _) => Some((
                &t.image,
                t.models.iter().map(|m| m.as_ref()).collect(),
                DetectOptions {
                    deadline,
                    ..t.opts.clone()
                },
            )),
            Work::Pose(t, _) => t.model.as_ref().map(|m| {
                (
                    &t.image,
                    vec![m.as_ref()],
                    DetectOptions {
                        deadline,
                        ..t.params.detect_options(&t.mesh)
                    },
                )
            }),
        }
    }
}

/// Computes one batch and answers every request in it: the backend builds
/// the pyramids (and bounds) of every detection in the batch, then the
/// detections and pose refinements run on the rayon pool.
fn process(batch: Vec<Job>, backend: &mut dyn Backend, shared: &Arc<Shared>) {
    let now = Instant::now();
    let metrics = &shared.metrics;
    let mut live = Vec::with_capacity(batch.len());
    for job in batch {
        if job.work.closed() {
            metrics.job("cancelled");
        } else if now >= job.deadline {
            metrics.job("expired");
            job.work.fail(InferError::DeadlineExceeded);
        } else {
            metrics
                .queue_duration
                .observe((now - job.enqueued).as_secs_f64());
            live.push(job);
        }
    }
    if live.is_empty() {
        return;
    }
    metrics.batch_size.observe(live.len() as f64);
    let start = Instant::now();
    // The watchdog: while the worker computes this batch, readiness turns
    // 503 once the batch's last deadline has passed.
    let _busy = shared.busy(live.iter().map(|job| job.deadline).max());
    let (items, deadlines): (Vec<Work>, Vec<Deadline>) = live
        .into_iter()
        .map(|job| (job.work, Deadline::at(job.deadline)))
        .unzip();
    let detections: Vec<_> = items
        .iter()
        .zip(&deadlines)
        .map(|(w, d)| w.detection(*d))
        .collect();
    let settings: Vec<_> = detections
        .iter()
        .map(|d| d.as_ref().map(|(_, models, _)| feature_settings(models)))
        .collect();
    let jobs: Vec<FeatureJob<'_>> = detections
        .iter()
        .zip(&settings)
        .zip(&deadlines)
        .filter_map(|((d, s), deadline)| {
            Some(FeatureJob {
                image: d.as_ref()?.0,
                settings: s.as_ref()?,
                deadline: *deadline,
            })
        })
        .collect();
    let built = if jobs.is_empty() {
        Vec::new()
    } else {
        match catch_unwind(AssertUnwindSafe(|| backend.pyramids(&jobs))) {
            Ok(p) if p.len() == jobs.len() => p,
            _ => {
                for item in items {
                    metrics.job("failed");
                    item.fail(InferError::Internal("the backend failed".into()));
                }
                return;
            }
        }
    };
    drop(jobs);
    // Each request's pyramids, in the batch's order (none where it needs
    // no detection).
    let mut built = built.into_iter();
    let pyramids: Vec<Option<Result<Vec<FeaturePyramid>, InferError>>> = detections
        .iter()
        .map(|d| {
            d.as_ref()
                .and_then(|_| built.next().map(|r| r.map_err(InferError::from)))
        })
        .collect();
    // The stage-1 bounds, where the backend computes them (on this thread,
    // which owns the backend).
    let bounds: Vec<(Vec<Option<DenseBounds>>, f64)> = items
        .iter()
        .zip(&detections)
        .zip(&pyramids)
        .map(|((item, d), pyrs)| match (d, pyrs) {
            (Some((_, models, opts)), Some(Ok(pyrs))) if opts.prune && !item.closed() => {
                let t = Instant::now();
                let b = catch_unwind(AssertUnwindSafe(|| model_bounds(backend, pyrs, models)))
                    .unwrap_or_default();
                (b, t.elapsed().as_secs_f64() * 1e3)
            }
            _ => (Vec::new(), 0.0),
        })
        .collect();
    let healthy = backend.healthy();
    shared.backend_healthy.store(healthy, Ordering::Release);
    metrics.backend_healthy.set(i64::from(healthy));
    *shared
        .backend_info
        .write()
        .unwrap_or_else(|e| e.into_inner()) = backend.info();
    drop(detections);
    items
        .into_par_iter()
        .zip(pyramids)
        .zip(bounds)
        .zip(deadlines)
        .for_each(|(((item, pyrs), (bounds, bounds_ms)), deadline)| {
            if item.closed() {
                metrics.job("cancelled");
                return;
            }
            // The detection, on the backend's pyramids.
            let detect = |models: &[&Model], opts: &DetectOptions| {
                let pyrs = pyrs.ok_or_else(|| InferError::Internal("no pyramids".into()))??;
                let refs: Vec<&FeaturePyramid> = pyrs.iter().collect();
                let pre: Vec<Option<&DenseBounds>> = bounds.iter().map(Option::as_ref).collect();
                let mut resp = detect_prebuilt_with(&refs, models, &pre, opts)?;
                resp.timing_ms.responses += bounds_ms;
                resp.timing_ms.total += bounds_ms;
                Ok::<_, InferError>(resp)
            };
            let ok = match item {
                Work::Detect(task, tx) => {
                    let result = catch_unwind(AssertUnwindSafe(|| {
                        let models: Vec<&Model> = task.models.iter().map(|m| m.as_ref()).collect();
                        detect(
                            &models,
                            &DetectOptions {
                                deadline,
                                ..task.opts
                            },
                        )
                    }))
                    .unwrap_or_else(|_| Err(InferError::Internal("detection failed".into())));
                    let ok = result.is_ok();
                    let _ = tx.send(result);
                    ok
                }
                Work::Pose(task, tx) => {
                    // The detection here, on the backend's pyramids; the
                    // refinement on the pose pool, so that the worker goes
                    // back to the lanes.
                    let found = catch_unwind(AssertUnwindSafe(|| {
                        let m = task
                            .model
                            .as_ref()
                            .ok_or_else(|| InferError::Internal("no model".into()))?;
                        let opts = DetectOptions {
                            deadline,
                            ..task.params.detect_options(&task.mesh)
                        };
                        Ok(Detected::from_response(detect(&[m.as_ref()], &opts)?, m))
                    }))
                    .unwrap_or_else(|_| Err(InferError::Internal("detection failed".into())));
                    let job = Job {
                        work: Work::Pose(task, tx),
                        enqueued: start,
                        deadline: deadline.instant().unwrap_or(start),
                    };
                    refine_later(shared, job, Some(found));
                    return;
                }
            };
            metrics.job(if ok { "completed" } else { "failed" });
            metrics
                .compute_duration
                .observe(start.elapsed().as_secs_f64());
        });
}
