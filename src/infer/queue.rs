//! The worker loop: takes a batch off the queue, drops what no longer needs
//! computing, asks the backend for the batch's pyramids, then runs the
//! vision layer's detection on each request and answers it.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::Instant;

use rayon::prelude::*;

use super::{InferError, Job, Shared, Work};
use crate::backend::{model_bounds, Backend, FeatureJob};
use crate::model::Model;
use crate::pipeline::{detect_prebuilt_with, feature_settings};
use crate::vision::detect::DenseBounds;
use crate::vision::pyramid::FeaturePyramid;

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

/// Computes one batch and answers every request in it.
fn process(batch: Vec<Job>, backend: &mut dyn Backend, shared: &Shared) {
    let now = Instant::now();
    let metrics = &shared.metrics;
    let mut live = Vec::with_capacity(batch.len());
    for job in batch {
        if job.cancelled() {
            metrics.job("cancelled");
        } else if now >= job.deadline {
            metrics.job("expired");
            job.fail(InferError::DeadlineExceeded);
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
    let tasks: Vec<_> = live
        .into_iter()
        .map(|job| match job.work {
            Work::Detect(task, tx) => (task, tx),
        })
        .collect();
    let settings: Vec<_> = tasks
        .iter()
        .map(|(t, _)| {
            let refs: Vec<&Model> = t.models.iter().map(|m| m.as_ref()).collect();
            feature_settings(&refs)
        })
        .collect();
    let jobs: Vec<FeatureJob<'_>> = tasks
        .iter()
        .zip(&settings)
        .map(|((t, _), s)| FeatureJob {
            image: &t.image,
            settings: s,
        })
        .collect();
    let pyramids = match catch_unwind(AssertUnwindSafe(|| backend.pyramids(&jobs))) {
        Ok(p) if p.len() == tasks.len() => p,
        _ => {
            for (_, tx) in tasks {
                metrics.job("failed");
                let _ = tx.send(Err(InferError::Internal("the backend failed".into())));
            }
            return;
        }
    };
    drop(jobs);
    // The stage-1 bounds, where the backend computes them (on this thread,
    // which owns the backend).
    let bounds: Vec<(Vec<Option<DenseBounds>>, f64)> = tasks
        .iter()
        .zip(&pyramids)
        .map(|((task, tx), pyrs)| match pyrs {
            Ok(pyrs) if task.opts.prune && !tx.is_closed() => {
                let t = Instant::now();
                let models: Vec<&Model> = task.models.iter().map(|m| m.as_ref()).collect();
                let b = catch_unwind(AssertUnwindSafe(|| model_bounds(backend, pyrs, &models)))
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
    tasks.into_par_iter().zip(pyramids).zip(bounds).for_each(
        |(((task, tx), pyrs), (bounds, bounds_ms))| {
            if tx.is_closed() {
                metrics.job("cancelled");
                return;
            }
            let result = catch_unwind(AssertUnwindSafe(|| {
                let pyrs = pyrs.map_err(InferError::from)?;
                let refs: Vec<&FeaturePyramid> = pyrs.iter().collect();
                let models: Vec<&Model> = task.models.iter().map(|m| m.as_ref()).collect();
                let pre: Vec<Option<&DenseBounds>> = bounds.iter().map(Option::as_ref).collect();
                let mut resp = detect_prebuilt_with(&refs, &models, &pre, &task.opts)
                    .map_err(InferError::from)?;
                resp.timing_ms.responses += bounds_ms;
                resp.timing_ms.total += bounds_ms;
                Ok(resp)
            }))
            .unwrap_or_else(|_| Err(InferError::Internal("detection failed".into())));
            metrics.job(if result.is_ok() {
                "completed"
            } else {
                "failed"
            });
            metrics
                .compute_duration
                .observe(start.elapsed().as_secs_f64());
            let _ = tx.send(result);
        },
    );
}
