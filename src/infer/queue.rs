//! The worker loop: takes a batch off the queue, drops what no longer needs
//! computing, asks the backend for the batch's pyramids, then runs the
//! vision layer's detection (or the pose refinement) of each request and
//! answers it.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::Instant;

use rayon::prelude::*;

use super::{InferError, Job, PoseTask, Shared, Work};
use crate::backend::{model_bounds, Backend, FeatureJob};
use crate::model::Model;
use crate::pipeline::{detect_prebuilt_with, feature_settings, DetectOptions};
use crate::pose::api::{estimate_with, Detected};
use crate::pose::PoseError;
use crate::vision::detect::DenseBounds;
use crate::vision::image::ColorImage;
use crate::vision::pyramid::FeaturePyramid;
use crate::vision::Deadline;

/// Runs until the queue's channel is closed and empty.
pub(super) fn run(rx: Receiver<Job>, mut backend: Box<dyn Backend>, shared: &Shared) {
    while let Ok(first) = rx.recv() {
        let mut batch = vec![first];
        let until = Instant::now() + shared.config.max_batch_delay;
        while batch.len() < shared.config.max_batch {
            let now = Instant::now();
            let next = if now >= until {
                rx.try_recv().map_err(|_| RecvTimeoutError::Timeout)
            } else {
                rx.recv_timeout(until - now)
            };
            match next {
                Ok(job) => batch.push(job),
                Err(_) => break,
            }
        }
        let left = shared.queued.fetch_sub(batch.len(), Ordering::AcqRel) - batch.len();
        shared.metrics.queue_size.set(left as i64);
        process(batch, backend.as_mut(), shared);
    }
}

impl Work {
    /// The image, models and options of the detection this request needs,
    /// if any (a pose request with `mask: "detect"` needs one).
    /// Its computation gives up at `deadline`.
    fn detection(&self, deadline: Deadline) -> Option<(&ColorImage, Vec<&Model>, DetectOptions)> {
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
                    t.image.as_ref(),
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
fn process(batch: Vec<Job>, backend: &mut dyn Backend, shared: &Shared) {
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
                    let result = catch_unwind(AssertUnwindSafe(|| {
                        let PoseTask {
                            image,
                            mesh,
                            params,
                            mask,
                            model,
                        } = *task;
                        let found = match &model {
                            Some(m) => Some(Detected::from_response(
                                detect(
                                    &[m.as_ref()],
                                    &DetectOptions {
                                        deadline,
                                        ..params.detect_options(&mesh)
                                    },
                                )?,
                                m,
                            )),
                            None => None,
                        };
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
                    let ok = result.is_ok();
                    let _ = tx.send(result);
                    ok
                }
            };
            metrics.job(if ok { "completed" } else { "failed" });
            metrics
                .compute_duration
                .observe(start.elapsed().as_secs_f64());
        });
}
