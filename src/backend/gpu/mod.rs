//! The wgpu backend: the WGSL kernels of `kernels/` build the HOG pyramid
//! (area resize, gradients and orientation bins, cell histograms, block
//! normalisation) of every level of every image of a batch in one
//! submission, and the stage-1 chain bounds of every location, level and
//! viewpoint of every model, so the CPU only runs the min-cuts where they can
//! matter. Learned cells (the backbone and projection of
//! `kernels/backbone.wgsl`) are computed on the device too, in one more
//! submission; where they do not fit its limits, on the CPU. The
//! over-segmentation stays on the CPU and runs while the GPU works.
//!
//! The backend is owned by one thread (the inference worker), which owns the
//! device and queue. Buffers live in a pool keyed by role and grow to the
//! largest batch seen, so a steady stream of requests allocates nothing. A
//! lost device, an out-of-memory or a validation error marks the backend
//! unhealthy (readiness turns 503) and every later batch runs on the CPU
//! backend instead of failing.

mod bounds;
mod cells;
mod features;

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

use rayon::prelude::*;
use thiserror::Error;

use super::{Backend, BackendError, BackendInfo, CpuBackend, FeatureJob};
use crate::vision::cells::FeatureKind;
use crate::vision::detect::{chain_pair_weight, scan_range, DenseBounds, LevelBounds, Location};
use crate::vision::energy::ViewWeights;
use crate::vision::hog::{HogMap, CELL_SIZE, HOG_STRIDE};
use crate::vision::image::ColorImage;
use crate::vision::pyramid::{
    approximate_levels, feature_levels, FeaturePyramid, Level, PyramidParams, PyramidTiming,
};
use crate::vision::segment::{segment_until, SegmentParams, Segmentation};
use crate::vision::{Deadline, VisionError};
use features::level_sizes;

const RESIZE_WGSL: &str = include_str!("../../../kernels/resize_area.wgsl");
const HOG_WGSL: &str = include_str!("../../../kernels/hog.wgsl");
const BOUNDS_WGSL: &str = include_str!("../../../kernels/dense_bounds.wgsl");
const RESPONSES_WGSL: &str = include_str!("../../../kernels/responses.wgsl");
const BACKBONE_WGSL: &str = include_str!("../../../kernels/backbone.wgsl");

/// Most workgroups along one dispatch dimension that every device allows.
const MAX_GROUPS: u32 = 65_535;

/// Errors of the GPU backend.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum GpuError {
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    #[error("the only GPU adapter is a software one ({0})")]
    SoftwareOnly(String),
    #[error("could not open the GPU device: {0}")]
    Device(String),
    #[error("GPU device lost: {0}")]
    Lost(String),
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    #[error("GPU error: {0}")]
    Validation(String),
    /// The work does not fit the device's buffer limits (not a failure of
    /// the device: the CPU takes that work).
    #[error("too large for the GPU: {0}")]
    TooLarge(String),
}

impl GpuError {
    /// Whether the device can no longer be trusted.
    fn is_fatal(&self) -> bool {
        !matches!(self, GpuError::TooLarge(_))
    }
}

/// Which adapters [`GpuBackend::new`] may take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Graphics APIs to look at: Vulkan, unless wgpu's `WGPU_BACKEND`
    /// environment variable names others (e.g. `vulkan,gl`).
    pub backends: wgpu::Backends,
    /// Take a software adapter (llvmpipe, lavapipe) when it is the best
    /// there is. `auto` selection refuses them: the CPU backend is faster.
    pub allow_software: bool,
}

impl Default for GpuOptions {
    fn default() -> Self {
        Self {
            backends: wgpu::Backends::from_env().unwrap_or(wgpu::Backends::VULKAN),
            allow_software: false,
        }
    }
}

/// The adapter a backend runs on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AdapterSummary {
    pub name: String,
    pub api: String,
    pub driver: String,
    pub software: bool,
}

impl std::fmt::Display for AdapterSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}", self.name, self.api)?;
        if !self.driver.is_empty() {
            write!(f, ", {}", self.driver)?;
        }
        if self.software {
            write!(f, ", software")?;
        }
        write!(f, ")")
    }
}

fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 4,
        wgpu::DeviceType::IntegratedGpu => 3,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 1,
        wgpu::DeviceType::Cpu => 0,
    }
}

/// The adapters `options` can see, best first (hardware before software,
/// Vulkan before GL).
pub fn adapters(options: &GpuOptions) -> Vec<AdapterSummary> {
    let instance = instance(options);
    let mut list = pollster::block_on(instance.enumerate_adapters(options.backends));
    sort_adapters(&mut list);
    list.iter().map(summary).collect()
}

fn instance(options: &GpuOptions) -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = options.backends;
    wgpu::Instance::new(desc)
}

fn sort_adapters(list: &mut [wgpu::Adapter]) {
    list.sort_by_key(|a| {
        let i = a.get_info();
        (
            std::cmp::Reverse(rank(i.device_type)),
            i.backend != wgpu::Backend::Vulkan,
        )
    });
}

fn summary(a: &wgpu::Adapter) -> AdapterSummary {
    let i = a.get_info();
    AdapterSummary {
        name: i.name.clone(),
        api: format!("{:?}", i.backend),
        driver: format!("{} {}", i.driver, i.driver_info).trim().to_string(),
        software: i.device_type == wgpu::DeviceType::Cpu,
    }
}

/// Buffers kept between batches, by role; each grows to the largest size
/// asked for and is never shrunk.
struct Pool {
    buffers: HashMap<&'static str, wgpu::Buffer>,
    allocations: usize,
}

impl Pool {
    fn get(
        &mut self,
        device: &wgpu::Device,
        name: &'static str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        if let Some(b) = self.buffers.get(name) {
            if b.size() >= bytes {
                return b.clone();
            }
        }
        // Powers of two, so that slowly growing inputs reallocate rarely.
        let size = bytes.max(256).next_power_of_two();
        let b = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(name),
            size,
            usage,
            mapped_at_creation: false,
        });
        self.allocations += 1;
        self.buffers.insert(name, b.clone());
        b
    }
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);
const READBACK: wgpu::BufferUsages =
    wgpu::BufferUsages::MAP_READ.union(wgpu::BufferUsages::COPY_DST);

struct Kernels {
    resize_h: wgpu::ComputePipeline,
    resize_v: wgpu::ComputePipeline,
    gradient: wgpu::ComputePipeline,
    histogram: wgpu::ComputePipeline,
    normalise: wgpu::ComputePipeline,
    chains: wgpu::ComputePipeline,
    sum_chains: wgpu::ComputePipeline,
    responses: wgpu::ComputePipeline,
    response_maps: wgpu::ComputePipeline,
    cnn_stem: wgpu::ComputePipeline,
    cnn_pointwise: wgpu::ComputePipeline,
    cnn_depthwise: wgpu::ComputePipeline,
    cnn_cells: wgpu::ComputePipeline,
}

/// An open device with the compiled kernels.
struct Context {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: AdapterSummary,
    max_binding: u64,
    kernels: Kernels,
    pool: Pool,
    /// The learned cells' weights, uploaded at their first use.
    learned: Option<cells::LearnedWeights>,
    lost: Arc<AtomicBool>,
    uncaptured: Arc<Mutex<Option<String>>>,
}

fn to_u32(v: usize, what: &str) -> Result<u32, GpuError> {
    u32::try_from(v).map_err(|_| GpuError::TooLarge(format!("{what} = {v}")))
}

fn groups(n: usize, per: usize) -> Result<u32, GpuError> {
    let g = n.div_ceil(per).max(1);
    let g = to_u32(g, "workgroups")?;
    if g > MAX_GROUPS {
        return Err(GpuError::TooLarge(format!(
            "{g} workgroups in one dimension"
        )));
    }
    Ok(g)
}

impl Context {
    fn open(options: &GpuOptions) -> Result<Self, GpuError> {
        let instance = instance(options);
        let mut list = pollster::block_on(instance.enumerate_adapters(options.backends));
        sort_adapters(&mut list);
        let Some(adapter) = list.into_iter().next() else {
            return Err(GpuError::NoAdapter(format!(
                "none for {:?} (is a Vulkan driver installed?)",
                options.backends
            )));
        };
        let info = summary(&adapter);
        if info.software && !options.allow_software {
            return Err(GpuError::SoftwareOnly(info.to_string()));
        }
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("sdhop"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        let lost = Arc::new(AtomicBool::new(false));
        let flag = lost.clone();
        device.set_device_lost_callback(move |reason, msg| {
            tracing::error!(?reason, %msg, "GPU device lost");
            flag.store(true, Ordering::Release);
        });
        let uncaptured = Arc::new(Mutex::new(None));
        let sink = uncaptured.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!(error = %e, "GPU error");
            if let Ok(mut s) = sink.lock() {
                s.get_or_insert_with(|| e.to_string());
            }
        }));
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = |label: &'static str, src: &'static str| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(src)),
            })
        };
        let resize = module("resize_area.wgsl", RESIZE_WGSL);
        let hog = module("hog.wgsl", HOG_WGSL);
        let bounds = module("dense_bounds.wgsl", BOUNDS_WGSL);
        let resp = module("responses.wgsl", RESPONSES_WGSL);
        let backbone = module("backbone.wgsl", BACKBONE_WGSL);
        let pipeline = |m: &wgpu::ShaderModule, entry: &'static str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: m,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let kernels = Kernels {
            resize_h: pipeline(&resize, "resize_h"),
            resize_v: pipeline(&resize, "resize_v"),
            gradient: pipeline(&hog, "gradient"),
            histogram: pipeline(&hog, "histogram"),
            normalise: pipeline(&hog, "normalise"),
            chains: pipeline(&bounds, "chains"),
            sum_chains: pipeline(&bounds, "sum_chains"),
            responses: pipeline(&resp, "responses"),
            response_maps: pipeline(&resp, "response_maps"),
            cnn_stem: pipeline(&backbone, "stem"),
            cnn_pointwise: pipeline(&backbone, "pointwise"),
            cnn_depthwise: pipeline(&backbone, "depthwise"),
            cnn_cells: pipeline(&backbone, "cells"),
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Validation(format!("kernels: {e}")));
        }
        let max_binding = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        Ok(Self {
            device,
            queue,
            adapter: info,
            max_binding,
            kernels,
            pool: Pool {
                buffers: HashMap::new(),
                allocations: 0,
            },
            learned: None,
            lost,
            uncaptured,
        })
    }

    fn check_lost(&self) -> Result<(), GpuError> {
        if self.lost.load(Ordering::Acquire) {
            return Err(GpuError::Lost("the device reported its loss".into()));
        }
        if let Some(e) = self.uncaptured.lock().ok().and_then(|s| s.clone()) {
            return Err(GpuError::Validation(e));
        }
        Ok(())
    }

    /// A storage buffer of role `name` holding `data` (at least 256 bytes).
    fn upload<T: bytemuck::Pod>(
        &mut self,
        name: &'static str,
        data: &[T],
    ) -> Result<wgpu::Buffer, GpuError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let buf = self.scratch(name, bytes.len())?;
        if !bytes.is_empty() {
            self.queue.write_buffer(&buf, 0, bytes);
        }
        Ok(buf)
    }

    /// A storage buffer of role `name` with room for `bytes`.
    fn scratch(&mut self, name: &'static str, bytes: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = bytes as u64;
        if bytes > self.max_binding {
            return Err(GpuError::TooLarge(format!(
                "{name} needs {bytes} bytes, the device binds at most {}",
                self.max_binding
            )));
        }
        Ok(self.pool.get(&self.device, name, bytes, STORAGE))
    }

    /// The mappable buffer that results are copied to.
    fn readback(&mut self, floats: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (floats * 4).max(4) as u64;
        if bytes > self.max_binding {
            return Err(GpuError::TooLarge(format!("{bytes} bytes of results")));
        }
        Ok(self.pool.get(&self.device, "readback", bytes, READBACK))
    }

    fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        entries: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = entries
            .iter()
            .map(|(binding, b)| wgpu::BindGroupEntry {
                binding: *binding,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Runs `record`, submits, copies `reads` (buffer, float count) back
    /// and checks for errors.
    fn submit_and_read(
        &self,
        staging: &wgpu::Buffer,
        record: impl FnOnce(&mut wgpu::CommandEncoder),
        reads: &[(&wgpu::Buffer, usize)],
    ) -> Result<Vec<Vec<f32>>, GpuError> {
        self.check_lost()?;
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let val = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let total: usize = reads.iter().map(|(_, n)| n * 4).sum();
        if (staging.size() as usize) < total {
            return Err(GpuError::Validation("read-back buffer too small".into()));
        }
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("sdhop"),
            });
        record(&mut enc);
        let mut at = 0u64;
        for (b, n) in reads {
            let bytes = (*n * 4) as u64;
            if bytes > 0 {
                enc.copy_buffer_to_buffer(b, 0, staging, at, bytes);
            }
            at += bytes;
        }
        self.queue.submit([enc.finish()]);
        let mut out = Vec::with_capacity(reads.len());
        if total > 0 {
            let slice = staging.slice(..total as u64);
            let (tx, rx) = mpsc::channel();
            slice.map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
            self.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::Lost(e.to_string()))?;
            match rx.recv() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => return Err(GpuError::Lost(format!("mapping the results: {e}"))),
                Err(_) => return Err(GpuError::Lost("the mapping never completed".into())),
            }
            {
                let view = slice
                    .get_mapped_range()
                    .map_err(|e| GpuError::Validation(e.to_string()))?;
                let all: &[f32] = bytemuck::cast_slice(&view);
                let mut at = 0;
                for (_, n) in reads {
                    out.push(all[at..at + n].to_vec());
                    at += n;
                }
            }
            staging.unmap();
        } else {
            self.device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| GpuError::Lost(e.to_string()))?;
            out.resize(reads.len(), Vec::new());
        }
        let v = pollster::block_on(val.pop());
        let o = pollster::block_on(oom.pop());
        if let Some(e) = o {
            return Err(GpuError::OutOfMemory(e.to_string()));
        }
        if let Some(e) = v {
            return Err(GpuError::Validation(e.to_string()));
        }
        self.check_lost()?;
        Ok(out)
    }
}

/// The GPU backend, with the CPU backend as its fallback.
pub struct GpuBackend {
    ctx: Option<Context>,
    cpu: CpuBackend,
    adapter: AdapterSummary,
    failure: Option<String>,
}

impl GpuBackend {
    /// Opens the best adapter `options` allow and compiles the kernels.
    pub fn new(options: &GpuOptions) -> Result<Self, GpuError> {
        let ctx = Context::open(options)?;
        let adapter = ctx.adapter.clone();
        Ok(Self {
            ctx: Some(ctx),
            cpu: CpuBackend,
            adapter,
            failure: None,
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterSummary {
        &self.adapter
    }

    /// Why the device was given up, if it was.
    pub fn failure(&self) -> Option<&str> {
        self.failure.as_deref()
    }

    /// Buffers allocated so far (constant in a steady state of requests no
    /// larger than those seen).
    pub fn allocations(&self) -> usize {
        self.ctx.as_ref().map_or(0, |c| c.pool.allocations)
    }

    /// Destroys the device, as a driver reset would (for tests of the
    /// fallback).
    pub fn destroy_device(&mut self) {
        if let Some(c) = &self.ctx {
            c.device.destroy();
        }
    }

    fn give_up(&mut self, e: &GpuError) {
        tracing::error!(error = %e, "GPU backend failed; serving on the CPU from now on");
        self.failure = Some(e.to_string());
        self.ctx = None;
    }

    /// Runs `f` on the device; a fatal error gives the device up.
    fn with_ctx<T>(&mut self, f: impl FnOnce(&mut Context) -> Result<T, GpuError>) -> Option<T> {
        let ctx = self.ctx.as_mut()?;
        match f(ctx) {
            Ok(v) => Some(v),
            Err(e) if e.is_fatal() => {
                self.give_up(&e);
                None
            }
            Err(e) => {
                tracing::debug!(error = %e, "work left to the CPU");
                None
            }
        }
    }

    /// The open device, or why it was given up.
    fn device(&mut self) -> Result<&mut Context, GpuError> {
        let failure = self.failure.clone().unwrap_or_default();
        self.ctx.as_mut().ok_or(GpuError::Lost(failure))
    }

    /// The resized level images of `img` (for parity tests of
    /// `kernels/resize_area.wgsl`).
    pub fn resized_levels(
        &mut self,
        img: &ColorImage,
        params: &PyramidParams,
    ) -> Result<Vec<ColorImage>, GpuError> {
        let ctx = self.device()?;
        Ok(ctx
            .features(&[(img, *params)], true)?
            .images
            .pop()
            .unwrap_or_default())
    }

    /// The HOG maps of every level of `img` (for parity tests of
    /// `kernels/hog.wgsl`).
    pub fn hog_levels(
        &mut self,
        img: &ColorImage,
        params: &PyramidParams,
    ) -> Result<Vec<HogMap>, GpuError> {
        let ctx = self.device()?;
        Ok(ctx
            .features(&[(img, *params)], false)?
            .hogs
            .pop()
            .unwrap_or_default())
    }

    /// The learned cells of every level of `img` (for parity tests of
    /// `kernels/backbone.wgsl`; `params.features` is ignored).
    pub fn learned_levels(
        &mut self,
        img: &ColorImage,
        params: &PyramidParams,
    ) -> Result<Vec<HogMap>, GpuError> {
        let ctx = self.device()?;
        Ok(ctx
            .learned_cells(&[(img, *params)])?
            .pop()
            .unwrap_or_default())
    }

    /// The filter responses at `locations` (for parity tests of
    /// `kernels/responses.wgsl`).
    pub fn responses(
        &mut self,
        pyr: &FeaturePyramid,
        views: &[ViewWeights],
        locations: &[Location],
    ) -> Result<Vec<Vec<(f32, f32)>>, GpuError> {
        let ctx = self.device()?;
        ctx.responses(pyr, views, locations)
    }

    /// The GPU's own dense bounds, without the CPU fallback (for parity
    /// tests of `kernels/dense_bounds.wgsl`).
    pub fn gpu_dense_bounds(
        &mut self,
        pyr: &FeaturePyramid,
        models: &[(&[ViewWeights], f64)],
    ) -> Result<Vec<DenseBounds>, GpuError> {
        let ctx = self.device()?;
        ctx.dense_bounds(pyr, models)
    }
}

/// Segmentation and the cells' segments on the CPU, around HOG maps built
/// elsewhere.
fn assemble(
    img: &std::sync::Arc<ColorImage>,
    params: &PyramidParams,
    seg_params: &SegmentParams,
    hogs: Vec<HogMap>,
    segmentation: Segmentation,
    mut timing: PyramidTiming,
) -> FeaturePyramid {
    let (w, h) = (img.width(), img.height());
    let t = Instant::now();
    let sizes = level_sizes(w, h, params);
    let levels = hogs
        .into_par_iter()
        .zip(sizes)
        .map(|(hog, (lw, lh))| Level {
            scale_x: lw as f64 / w as f64,
            scale_y: lh as f64 / h as f64,
            cell_segments: segmentation.cell_labels(lw, lh, hog.width(), hog.height(), CELL_SIZE),
            hog,
        })
        .collect();
    timing.cell_segments_ms = t.elapsed().as_secs_f64() * 1e3;
    FeaturePyramid {
        image_width: w,
        image_height: h,
        image: std::sync::Arc::clone(img),
        levels,
        segmentation,
        timing,
        params: *params,
        seg_params: *seg_params,
    }
}

type JobResult = Result<Vec<FeaturePyramid>, BackendError>;

/// Images above this many pixels have their learned cells computed a level
/// per submission, their deadline looked at between levels (a 16 MP
/// image's levels are seconds of work on a small device); smaller ones
/// share one submission.
const LEVELWISE_PIXELS: usize = 2_000_000;

impl GpuBackend {
    /// The learned cells of each job, one level per submission, giving up
    /// on a job (with [`VisionError::DeadlineExceeded`]) once its deadline
    /// has passed; `None` when the device failed (the CPU then computes
    /// them).
    fn learned_levelwise(
        &mut self,
        learned: &[(&ColorImage, PyramidParams, Deadline)],
    ) -> Option<Vec<Result<Vec<HogMap>, VisionError>>> {
        let mut out = Vec::with_capacity(learned.len());
        for (img, p, deadline) in learned {
            let levels = level_sizes(img.width(), img.height(), p).len();
            let mut maps = Vec::with_capacity(levels);
            let mut result = Ok(());
            for l in 0..levels {
                if deadline.passed() {
                    result = Err(VisionError::DeadlineExceeded);
                    break;
                }
                let mut level = self.with_ctx(|c| c.learned_cells_of(&[(*img, *p)], Some(l)))?;
                maps.append(level.first_mut()?);
            }
            out.push(result.map(|()| maps));
        }
        Some(out)
    }
}

/// What a batch asks of the device and the CPU: each setting's HOG or
/// learned cells, and each job's segmentations, one per distinct
/// segmentation setting of the job (a model's and its segmenter's
/// pyramids share one).
struct Plan<'a> {
    work: Vec<(&'a ColorImage, PyramidParams)>,
    learned: Vec<(&'a ColorImage, PyramidParams, Deadline)>,
    segs: Vec<(&'a ColorImage, SegmentParams, Deadline)>,
    /// For each job, each setting's index into `segs`.
    seg_of: Vec<Vec<usize>>,
}

impl<'a> Plan<'a> {
    fn of(batch: &'a [FeatureJob<'_>], checked: &[Result<(), VisionError>]) -> Self {
        let mut p = Plan {
            work: Vec::new(),
            learned: Vec::new(),
            segs: Vec::new(),
            seg_of: Vec::with_capacity(batch.len()),
        };
        for (j, ok) in batch.iter().zip(checked) {
            let mut of = Vec::new();
            if ok.is_ok() {
                let first = p.segs.len();
                for (q, s) in j.settings {
                    match q.features {
                        FeatureKind::Hog => p.work.push((j.image.as_ref(), *q)),
                        FeatureKind::Cnn => p.learned.push((j.image.as_ref(), *q, j.deadline)),
                    }
                    let shared = p.segs[first..].iter().position(|(_, t, _)| t == s);
                    of.push(match shared {
                        Some(i) => first + i,
                        None => {
                            p.segs.push((j.image.as_ref(), *s, j.deadline));
                            p.segs.len() - 1
                        }
                    });
                }
            }
            p.seg_of.push(of);
        }
        p
    }
}

impl Backend for GpuBackend {
    fn info(&self) -> BackendInfo {
        let mut device = self.adapter.to_string();
        if let Some(f) = &self.failure {
            device.push_str(&format!("; failed ({f}), serving on the CPU"));
        }
        BackendInfo {
            kind: "gpu".into(),
            device,
        }
    }

    fn healthy(&self) -> bool {
        self.failure.is_none()
    }

    fn pyramids(&mut self, batch: &[FeatureJob<'_>]) -> Vec<JobResult> {
        let start = Instant::now();
        // Settings are checked per job: a bad one refuses its job only.
        let checked: Vec<Result<(), VisionError>> = batch
            .iter()
            .map(|j| {
                j.settings.iter().try_for_each(|(p, s)| {
                    p.validate()?;
                    s.validate()
                })
            })
            .collect();
        // HOG cells and learned cells on the device (learned cells left to
        // the CPU where the device cannot take them), the segmentations on
        // the CPU meanwhile.
        let Plan {
            work,
            learned,
            segs,
            seg_of,
        } = Plan::of(batch, &checked);
        let (features, segmentations) = rayon::join(
            || {
                let t = Instant::now();
                let hogs = if work.is_empty() {
                    Vec::new()
                } else {
                    self.with_ctx(|c| c.features(&work, false))?.hogs
                };
                let hog_ms = t.elapsed().as_secs_f64() * 1e3;
                let t = Instant::now();
                let cells = if learned.is_empty() {
                    Some(Vec::new())
                } else if learned.iter().any(|(_, _, d)| d.passed()) {
                    None
                } else if learned
                    .iter()
                    .all(|(img, _, _)| img.width() * img.height() <= LEVELWISE_PIXELS)
                {
                    let jobs: Vec<(&ColorImage, PyramidParams)> =
                        learned.iter().map(|(img, p, _)| (*img, *p)).collect();
                    self.with_ctx(|c| c.learned_cells(&jobs))
                        .map(|maps| maps.into_iter().map(Ok).collect())
                } else {
                    self.learned_levelwise(&learned)
                };
                Some((hogs, hog_ms, cells, t.elapsed().as_secs_f64() * 1e3))
            },
            || {
                segs.par_iter()
                    .map(|(img, s, deadline)| {
                        let t = Instant::now();
                        segment_until(img, s, *deadline)
                            .map(|r| (r, t.elapsed().as_secs_f64() * 1e3))
                    })
                    .collect::<Vec<_>>()
            },
        );
        let Some((hogs, gpu_ms, cells, cells_ms)) = features else {
            return self.cpu.pyramids(batch);
        };
        let learned: Vec<Result<(Vec<HogMap>, f64), VisionError>> = match cells {
            // Every level from the device; those the settings resample
            // replaced as the CPU makes them.
            Some(maps) => maps
                .into_iter()
                .zip(&learned)
                .map(|(m, (img, p, deadline))| {
                    let m = approximate_levels((img.width(), img.height()), p, m?, *deadline)?;
                    Ok((m, cells_ms))
                })
                .collect(),
            // On the CPU, level by level within each deadline.
            None => learned
                .par_iter()
                .map(|(img, p, deadline)| {
                    let t = Instant::now();
                    feature_levels(img, p, *deadline).map(|l| {
                        let maps = l.into_iter().map(|(_, _, m)| m).collect::<Vec<_>>();
                        (maps, t.elapsed().as_secs_f64() * 1e3)
                    })
                })
                .collect(),
        };
        let mut hogs = hogs.into_iter();
        let mut learned = learned.into_iter();
        let mut used = vec![false; segmentations.len()];
        let mut out = Vec::with_capacity(batch.len());
        for ((j, ok), of) in batch.iter().zip(checked).zip(&seg_of) {
            if let Err(e) = ok {
                out.push(Err(BackendError::from(e)));
                continue;
            }
            let mut pyrs = Vec::with_capacity(j.settings.len());
            let mut failed = None;
            for ((p, s), &si) in j.settings.iter().zip(of) {
                let (hog, features_ms) = match p.features {
                    FeatureKind::Hog => (hogs.next().unwrap_or_default(), gpu_ms),
                    FeatureKind::Cnn => match learned.next() {
                        Some(Ok(l)) => l,
                        Some(Err(e)) => {
                            failed = Some(BackendError::from(e));
                            (Vec::new(), 0.0)
                        }
                        None => (Vec::new(), 0.0),
                    },
                };
                // A shared segmentation's time counts once.
                let first_use = !std::mem::replace(&mut used[si], true);
                match segmentations.get(si) {
                    Some(Ok((seg, seg_ms))) => {
                        let timing = PyramidTiming {
                            features_ms,
                            segmentation_ms: if first_use { *seg_ms } else { 0.0 },
                            cell_segments_ms: 0.0,
                            total_ms: 0.0,
                        };
                        let mut pyr = assemble(j.image, p, s, hog, seg.clone(), timing);
                        pyr.timing.total_ms = start.elapsed().as_secs_f64() * 1e3;
                        pyrs.push(pyr);
                    }
                    Some(Err(e)) => failed = Some(BackendError::from(e.clone())),
                    None => failed = Some(BackendError::DeviceLost("missing segmentation".into())),
                }
            }
            out.push(match failed {
                Some(e) => Err(e),
                None => Ok(pyrs),
            });
        }
        out
    }

    fn dense_bounds(
        &mut self,
        pyr: &FeaturePyramid,
        models: &[(&[ViewWeights], f64)],
    ) -> Result<Option<Vec<DenseBounds>>, BackendError> {
        Ok(self.with_ctx(|c| c.dense_bounds(pyr, models)))
    }
}
