//! The wgpu backend: the WGSL kernels of `kernels/` build the HOG pyramid
//! (area resize, gradients and orientation bins, cell histograms, block
//! normalisation) of every level of every image of a batch in one
//! submission, and the stage-1 chain bounds of every location, level and
//! viewpoint of every model, so the CPU only runs the min-cuts where they can
//! matter. The over-segmentation stays on the CPU and runs while the GPU
//! works.
//!
//! The backend is owned by one thread (the inference worker), which owns the
//! device and queue. Buffers live in a pool keyed by role and grow to the
//! largest batch seen, so a steady stream of requests allocates nothing. A
//! lost device, an out-of-memory or a validation error marks the backend
//! unhealthy (readiness turns 503) and every later batch runs on the CPU
//! backend instead of failing.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

use rayon::prelude::*;
use thiserror::Error;

use super::{Backend, BackendError, BackendInfo, CpuBackend, FeatureJob};
use crate::vision::detect::{chain_pair_weight, scan_range, DenseBounds, LevelBounds, Location};
use crate::vision::energy::ViewWeights;
use crate::vision::hog::{HogMap, CELL_SIZE, HOG_STRIDE};
use crate::vision::image::{area_weights, ColorImage};
use crate::vision::pyramid::{FeaturePyramid, Level, PyramidParams, PyramidTiming};
use crate::vision::segment::{segment, SegmentParams, Segmentation};
use crate::vision::VisionError;

const RESIZE_WGSL: &str = include_str!("../../kernels/resize_area.wgsl");
const HOG_WGSL: &str = include_str!("../../kernels/hog.wgsl");
const BOUNDS_WGSL: &str = include_str!("../../kernels/dense_bounds.wgsl");
const RESPONSES_WGSL: &str = include_str!("../../kernels/responses.wgsl");

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
}

/// An open device with the compiled kernels.
struct Context {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: AdapterSummary,
    max_binding: u64,
    kernels: Kernels,
    pool: Pool,
    lost: Arc<AtomicBool>,
    uncaptured: Arc<Mutex<Option<String>>>,
}

/// One pyramid level in the layout the kernels read (`struct Level`).
#[derive(Clone, Copy, Default)]
struct LevelDesc {
    src_w: u32,
    src_h: u32,
    src_off: u32,
    dst_w: u32,
    dst_h: u32,
    dst_off: u32,
    tmp_off: u32,
    xtap_off: u32,
    ytap_off: u32,
    cw: u32,
    ch: u32,
    hist_off: u32,
    hog_off: u32,
    grad_off: u32,
}

impl LevelDesc {
    fn words(&self) -> [u32; 16] {
        [
            self.src_w,
            self.src_h,
            self.src_off,
            self.dst_w,
            self.dst_h,
            self.dst_off,
            self.tmp_off,
            self.xtap_off,
            self.ytap_off,
            self.cw,
            self.ch,
            self.hist_off,
            self.hog_off,
            self.grad_off,
            0,
            0,
        ]
    }
}

/// One level and viewpoint in the layout of `struct Job`.
#[derive(Clone, Copy, Default)]
struct JobDesc {
    hog_off: u32,
    mw: u32,
    mh: u32,
    x_lo: i32,
    y_lo: i32,
    nx: u32,
    ny: u32,
    weights_off: u32,
    rows: u32,
    cols: u32,
    pair: f32,
    chain_off: u32,
    out_off: u32,
    map_off: u32,
}

impl JobDesc {
    fn words(&self) -> [u32; 16] {
        [
            self.hog_off,
            self.mw,
            self.mh,
            self.x_lo as u32,
            self.y_lo as u32,
            self.nx,
            self.ny,
            self.weights_off,
            self.rows,
            self.cols,
            self.pair.to_bits(),
            self.chain_off,
            self.out_off,
            self.map_off,
            0,
            0,
        ]
    }
}

/// Most bytes of response maps and chain minima in one submission.
const MAP_BUDGET: usize = 1 << 30;

/// The jobs of a bounds computation and the buffers they read.
struct BoundsPlan {
    jobs: Vec<JobDesc>,
    /// `(model, level, view)` of each job.
    keys: Vec<(usize, usize, usize)>,
    chain_n: usize,
    out_n: usize,
    /// Response map entries (pairs of floats).
    map_n: usize,
    jobs_buf: wgpu::Buffer,
    hog_buf: wgpu::Buffer,
    weights_buf: wgpu::Buffer,
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

/// The levels a pyramid has: `(width, height)` of each, as
/// [`FeaturePyramid::build`] chooses them.
fn level_sizes(w: usize, h: usize, p: &PyramidParams) -> Vec<(usize, usize)> {
    p.scales()
        .into_iter()
        .filter_map(|s| {
            let lw = (w as f64 * s).round() as usize;
            let lh = (h as f64 * s).round() as usize;
            (lw >= CELL_SIZE && lh >= CELL_SIZE).then_some((lw, lh))
        })
        .collect()
}

fn push_taps(taps: &mut Vec<u32>, table: &[Vec<(usize, f32)>]) -> Result<u32, GpuError> {
    let off = to_u32(taps.len(), "taps")?;
    let n = table.len();
    let mut at = n + 1;
    taps.push(to_u32(at, "taps")?);
    for t in table {
        at += 2 * t.len();
        taps.push(to_u32(at, "taps")?);
    }
    for t in table {
        for &(i, w) in t {
            taps.push(to_u32(i, "tap index")?);
            taps.push(w.to_bits());
        }
    }
    Ok(off)
}

/// The HOG maps (and optionally the resized images) of every level of every
/// (image, setting) pair, in the order asked.
struct Features {
    hogs: Vec<Vec<HogMap>>,
    images: Vec<Vec<ColorImage>>,
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

    /// HOG maps of every level of every `(image, pyramid settings)` pair in
    /// one submission; with `images`, also the resized level images.
    fn features(
        &mut self,
        work: &[(&ColorImage, PyramidParams)],
        images: bool,
    ) -> Result<Features, GpuError> {
        let mut src: Vec<f32> = Vec::new();
        let mut taps: Vec<u32> = Vec::new();
        let mut descs: Vec<LevelDesc> = Vec::new();
        let mut owner: Vec<usize> = Vec::new();
        let (mut tmp_n, mut dst_n, mut grad_n, mut hist_n, mut hog_n) = (0, 0, 0, 0, 0);
        let mut src_offs: Vec<(usize, usize)> = Vec::new();
        for (k, (img, p)) in work.iter().enumerate() {
            // One copy of each image, shared by its settings.
            let src_off = match src_offs
                .iter()
                .find(|(ptr, _)| *ptr == *img as *const _ as usize)
            {
                Some(&(_, off)) => off,
                None => {
                    let off = src.len();
                    src.extend_from_slice(img.data());
                    src_offs.push((*img as *const _ as usize, off));
                    off
                }
            };
            let (w, h) = (img.width(), img.height());
            for (lw, lh) in level_sizes(w, h, p) {
                let (cw, ch) = (lw / CELL_SIZE, lh / CELL_SIZE);
                let d = LevelDesc {
                    src_w: to_u32(w, "width")?,
                    src_h: to_u32(h, "height")?,
                    src_off: to_u32(src_off, "image offset")?,
                    dst_w: to_u32(lw, "level width")?,
                    dst_h: to_u32(lh, "level height")?,
                    dst_off: to_u32(dst_n, "level offset")?,
                    tmp_off: to_u32(tmp_n, "resize offset")?,
                    xtap_off: push_taps(&mut taps, &area_weights(w, lw))?,
                    ytap_off: push_taps(&mut taps, &area_weights(h, lh))?,
                    cw: to_u32(cw, "cells")?,
                    ch: to_u32(ch, "cells")?,
                    hist_off: to_u32(hist_n, "histogram offset")?,
                    hog_off: to_u32(hog_n, "feature offset")?,
                    grad_off: to_u32(grad_n, "gradient offset")?,
                };
                tmp_n += h * lw * 3;
                dst_n += lw * lh * 3;
                grad_n += lw * lh;
                hist_n += cw * ch * 18;
                hog_n += cw * ch * HOG_STRIDE;
                descs.push(d);
                owner.push(k);
            }
        }
        let mut hogs: Vec<Vec<HogMap>> = vec![Vec::new(); work.len()];
        let mut imgs: Vec<Vec<ColorImage>> = vec![Vec::new(); work.len()];
        if descs.is_empty() {
            return Ok(Features { hogs, images: imgs });
        }
        let words: Vec<u32> = descs.iter().flat_map(|d| d.words()).collect();
        let levels_buf = self.upload("levels", &words)?;
        let taps_buf = self.upload("taps", &taps)?;
        let src_buf = self.upload("image", &src)?;
        let tmp_buf = self.scratch("resize", tmp_n * 4)?;
        let dst_buf = self.scratch("level images", dst_n * 4)?;
        let grad_buf = self.scratch("gradients", grad_n * 8)?;
        let hist_buf = self.scratch("histograms", hist_n * 4)?;
        let hog_buf = self.scratch("features", hog_n * 4)?;
        let staging = self.readback(hog_n + if images { dst_n } else { 0 })?;
        let k = &self.kernels;
        let bg_rh = self.bind(
            &k.resize_h,
            &[
                (0, &levels_buf),
                (1, &taps_buf),
                (2, &src_buf),
                (3, &tmp_buf),
            ],
        );
        let bg_rv = self.bind(
            &k.resize_v,
            &[
                (0, &levels_buf),
                (1, &taps_buf),
                (3, &tmp_buf),
                (4, &dst_buf),
            ],
        );
        let bg_g = self.bind(
            &k.gradient,
            &[(0, &levels_buf), (1, &dst_buf), (2, &grad_buf)],
        );
        let bg_h = self.bind(
            &k.histogram,
            &[(0, &levels_buf), (2, &grad_buf), (3, &hist_buf)],
        );
        let bg_n = self.bind(
            &k.normalise,
            &[(0, &levels_buf), (3, &hist_buf), (4, &hog_buf)],
        );
        let max = |f: fn(&LevelDesc) -> u32| descs.iter().map(f).max().unwrap_or(1) as usize;
        let nl = to_u32(descs.len(), "levels")?;
        if nl > MAX_GROUPS {
            return Err(GpuError::TooLarge(format!("{nl} levels in one batch")));
        }
        let (gw, gsh) = (groups(max(|d| d.dst_w), 8)?, groups(max(|d| d.src_h), 8)?);
        let gh = groups(max(|d| d.dst_h), 8)?;
        let (gcw, gch) = (groups(max(|d| d.cw), 8)?, groups(max(|d| d.ch), 8)?);
        let pipes = [
            (&k.resize_h, &bg_rh, (gw, gsh)),
            (&k.resize_v, &bg_rv, (gw, gh)),
            (&k.gradient, &bg_g, (gw, gh)),
            (&k.histogram, &bg_h, (gcw, gch)),
            (&k.normalise, &bg_n, (gcw, gch)),
        ];
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("pyramid"),
                timestamp_writes: None,
            });
            for (p, bg, (x, y)) in pipes {
                pass.set_pipeline(p);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, nl);
            }
        };
        let reads: Vec<(&wgpu::Buffer, usize)> = if images {
            vec![(&hog_buf, hog_n), (&dst_buf, dst_n)]
        } else {
            vec![(&hog_buf, hog_n)]
        };
        let mut out = self.submit_and_read(&staging, record, &reads)?;
        let level_images = if images { out.pop() } else { None };
        let feats = out.pop().unwrap_or_default();
        for (d, &k) in descs.iter().zip(&owner) {
            let (cw, ch) = (d.cw as usize, d.ch as usize);
            let o = d.hog_off as usize;
            let raw = feats
                .get(o..o + cw * ch * HOG_STRIDE)
                .ok_or_else(|| GpuError::Validation("short read of the features".into()))?
                .to_vec();
            hogs[k].push(
                HogMap::from_raw(cw, ch, raw).map_err(|e| GpuError::Validation(e.to_string()))?,
            );
            if let Some(li) = &level_images {
                let (lw, lh) = (d.dst_w as usize, d.dst_h as usize);
                let o = d.dst_off as usize;
                let px = li
                    .get(o..o + lw * lh * 3)
                    .ok_or_else(|| GpuError::Validation("short read of the levels".into()))?
                    .to_vec();
                imgs[k].push(
                    ColorImage::new(lw, lh, px).map_err(|e| GpuError::Validation(e.to_string()))?,
                );
            }
        }
        Ok(Features { hogs, images: imgs })
    }

    /// Uploads a pyramid's features and the weights of `models`, and the
    /// job list of every (model, level, viewpoint) with positions.
    fn bounds_setup(
        &mut self,
        pyr: &FeaturePyramid,
        models: &[(&[ViewWeights], f64)],
    ) -> Result<BoundsPlan, GpuError> {
        let mut hog: Vec<f32> = Vec::new();
        let mut hog_offs = Vec::with_capacity(pyr.levels.len());
        for l in &pyr.levels {
            hog_offs.push(hog.len());
            hog.extend_from_slice(l.hog.raw());
        }
        let mut weights: Vec<f32> = Vec::new();
        let mut jobs: Vec<JobDesc> = Vec::new();
        let mut keys: Vec<(usize, usize, usize)> = Vec::new();
        let (mut chain_n, mut out_n, mut map_n) = (0usize, 0usize, 0usize);
        for (mi, (views, max_truncation)) in models.iter().enumerate() {
            for (vi, w) in views.iter().enumerate() {
                let n = w.rows * w.cols;
                let weights_off = weights.len();
                weights.extend_from_slice(&w.w_vis[..n * HOG_STRIDE]);
                weights.extend_from_slice(&w.w_occ[..n * HOG_STRIDE]);
                weights.extend_from_slice(&w.w_prior[..n]);
                for (li, level) in pyr.levels.iter().enumerate() {
                    let (mw, mh) = (level.hog.width(), level.hog.height());
                    let Some((x_lo, x_hi, y_lo, y_hi, _)) =
                        scan_range(mw, mh, w.rows, w.cols, *max_truncation)
                    else {
                        continue;
                    };
                    let nx = (x_hi - x_lo + 1) as usize;
                    let ny = (y_hi - y_lo + 1) as usize;
                    let i32_of = |v: isize| {
                        i32::try_from(v).map_err(|_| GpuError::TooLarge("position".into()))
                    };
                    jobs.push(JobDesc {
                        hog_off: to_u32(hog_offs[li], "feature offset")?,
                        mw: to_u32(mw, "map width")?,
                        mh: to_u32(mh, "map height")?,
                        x_lo: i32_of(x_lo)?,
                        y_lo: i32_of(y_lo)?,
                        nx: to_u32(nx, "positions")?,
                        ny: to_u32(ny, "positions")?,
                        weights_off: to_u32(weights_off, "weights offset")?,
                        rows: to_u32(w.rows, "rows")?,
                        cols: to_u32(w.cols, "cols")?,
                        pair: chain_pair_weight(w),
                        chain_off: to_u32(chain_n, "chain offset")?,
                        out_off: to_u32(out_n, "bound offset")?,
                        map_off: to_u32(map_n, "response offset")?,
                    });
                    keys.push((mi, li, vi));
                    chain_n += nx * ny * (w.rows + w.cols);
                    out_n += nx * ny;
                    map_n += n * mw * mh;
                }
            }
        }
        let words: Vec<u32> = jobs.iter().flat_map(|j| j.words()).collect();
        let jobs_buf = self.upload("jobs", &words)?;
        let hog_buf = self.upload("features", &hog)?;
        let weights_buf = self.upload("weights", &weights)?;
        Ok(BoundsPlan {
            jobs,
            keys,
            chain_n,
            out_n,
            map_n,
            jobs_buf,
            hog_buf,
            weights_buf,
        })
    }

    /// Chain bounds of every model's locations on one pyramid, in as few
    /// submissions as the response maps' memory allows.
    fn dense_bounds(
        &mut self,
        pyr: &FeaturePyramid,
        models: &[(&[ViewWeights], f64)],
    ) -> Result<Vec<DenseBounds>, GpuError> {
        // Bytes of a model's response maps and chain minima.
        let need = |views: &[ViewWeights]| -> usize {
            let cells: usize = pyr
                .levels
                .iter()
                .map(|l| l.hog.width() * l.hog.height())
                .sum();
            views
                .iter()
                .map(|w| cells * (w.rows * w.cols * 8 + 4 * (w.rows + w.cols) + 4))
                .sum()
        };
        let budget = (self.max_binding as usize).min(MAP_BUDGET);
        let mut out = Vec::with_capacity(models.len());
        let mut start = 0;
        while start < models.len() {
            let mut end = start + 1;
            let mut used = need(models[start].0);
            while end < models.len() && used + need(models[end].0) <= budget {
                used += need(models[end].0);
                end += 1;
            }
            out.extend(self.dense_bounds_group(pyr, &models[start..end])?);
            start = end;
        }
        Ok(out)
    }

    /// Chain bounds of every model's locations on one pyramid, in one
    /// submission: the response maps, every chain's minimum, the sums.
    fn dense_bounds_group(
        &mut self,
        pyr: &FeaturePyramid,
        models: &[(&[ViewWeights], f64)],
    ) -> Result<Vec<DenseBounds>, GpuError> {
        let BoundsPlan {
            jobs,
            keys,
            chain_n,
            out_n,
            map_n,
            jobs_buf,
            hog_buf,
            weights_buf: w_buf,
        } = self.bounds_setup(pyr, models)?;
        let mut out: Vec<DenseBounds> = models
            .iter()
            .map(|(views, _)| DenseBounds {
                levels: vec![vec![None; views.len()]; pyr.levels.len()],
            })
            .collect();
        if jobs.is_empty() {
            return Ok(out);
        }
        let chain_buf = self.scratch("chains", chain_n * 4)?;
        let bounds_buf = self.scratch("bounds", out_n * 4)?;
        let maps_buf = self.scratch("response maps", map_n * 8)?;
        let staging = self.readback(out_n)?;
        let k = &self.kernels;
        let bg_m = self.bind(
            &k.response_maps,
            &[(0, &jobs_buf), (1, &hog_buf), (2, &w_buf), (5, &maps_buf)],
        );
        let bg_c = self.bind(
            &k.chains,
            &[(0, &jobs_buf), (2, &w_buf), (3, &chain_buf), (5, &maps_buf)],
        );
        let bg_s = self.bind(
            &k.sum_chains,
            &[(0, &jobs_buf), (3, &chain_buf), (4, &bounds_buf)],
        );
        let max_locs = jobs
            .iter()
            .map(|j| (j.nx * j.ny) as usize)
            .max()
            .unwrap_or(1);
        let max_chains = jobs
            .iter()
            .map(|j| (j.rows + j.cols) as usize)
            .max()
            .unwrap_or(1);
        let max_cells = jobs
            .iter()
            .map(|j| (j.mw * j.mh) as usize)
            .max()
            .unwrap_or(1);
        let max_rows = jobs.iter().map(|j| j.rows as usize).max().unwrap_or(1);
        let (mx, my) = (groups(max_cells, 64)?, groups(max_rows, 1)?);
        let gx = groups(max_locs, 64)?;
        let gy = groups(max_chains, 1)?;
        let nj = to_u32(jobs.len(), "jobs")?;
        if nj > MAX_GROUPS {
            return Err(GpuError::TooLarge(format!("{nj} level-viewpoint jobs")));
        }
        let (m, c, s) = (&k.response_maps, &k.chains, &k.sum_chains);
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("bounds"),
                timestamp_writes: None,
            });
            pass.set_pipeline(m);
            pass.set_bind_group(0, &bg_m, &[]);
            pass.dispatch_workgroups(mx, my, nj);
            pass.set_pipeline(c);
            pass.set_bind_group(0, &bg_c, &[]);
            pass.dispatch_workgroups(gx, gy, nj);
            pass.set_pipeline(s);
            pass.set_bind_group(0, &bg_s, &[]);
            pass.dispatch_workgroups(gx, 1, nj);
        };
        let values = self
            .submit_and_read(&staging, record, &[(&bounds_buf, out_n)])?
            .pop()
            .unwrap_or_default();
        for (j, &(mi, li, vi)) in jobs.iter().zip(&keys) {
            let (o, len) = (j.out_off as usize, (j.nx * j.ny) as usize);
            let v = values
                .get(o..o + len)
                .ok_or_else(|| GpuError::Validation("short read of the bounds".into()))?;
            out[mi].levels[li][vi] = Some(LevelBounds {
                x_lo: j.x_lo as isize,
                y_lo: j.y_lo as isize,
                nx: j.nx as usize,
                ny: j.ny as usize,
                values: v.to_vec(),
            });
        }
        Ok(out)
    }

    /// `(F_i, B_i + R_i)` of every cell of each listed location.
    fn responses(
        &mut self,
        pyr: &FeaturePyramid,
        views: &[ViewWeights],
        locations: &[Location],
    ) -> Result<Vec<Vec<(f32, f32)>>, GpuError> {
        // Every location is scanned only within the positions of a scan
        // with no truncation limit; build one job per (level, view).
        let BoundsPlan {
            jobs,
            keys,
            jobs_buf,
            hog_buf,
            weights_buf: w_buf,
            ..
        } = self.bounds_setup(pyr, &[(views, 0.999)])?;
        let mut queries: Vec<u32> = Vec::new();
        let mut out_n = 0usize;
        let mut sizes = Vec::new();
        for loc in locations {
            let ji = keys
                .iter()
                .position(|&(_, l, v)| l == loc.level && v == loc.view)
                .ok_or_else(|| GpuError::TooLarge(format!("no positions at {loc:?}")))?;
            let n = jobs[ji].rows as usize * jobs[ji].cols as usize;
            let xy = |v: isize| {
                i32::try_from(v)
                    .map(|v| v as u32)
                    .map_err(|_| GpuError::TooLarge("position".into()))
            };
            queries.extend_from_slice(&[
                to_u32(ji, "job")?,
                xy(loc.x)?,
                xy(loc.y)?,
                to_u32(out_n, "offset")?,
            ]);
            sizes.push((out_n, n));
            out_n += 2 * n;
        }
        if locations.is_empty() {
            return Ok(Vec::new());
        }
        let q_buf = self.upload("queries", &queries)?;
        let out_buf = self.scratch("responses", out_n * 4)?;
        let staging = self.readback(out_n)?;
        let k = &self.kernels;
        let bg = self.bind(
            &k.responses,
            &[
                (0, &jobs_buf),
                (1, &hog_buf),
                (2, &w_buf),
                (3, &q_buf),
                (4, &out_buf),
            ],
        );
        let max_cells = sizes.iter().map(|s| s.1).max().unwrap_or(1);
        let gx = groups(max_cells, 64)?;
        let nq = locations.len();
        let gy = to_u32(nq.min(MAX_GROUPS as usize), "locations")?;
        let gz = groups(nq, MAX_GROUPS as usize)?;
        let p = &k.responses;
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("responses"),
                timestamp_writes: None,
            });
            pass.set_pipeline(p);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, gz);
        };
        let values = self
            .submit_and_read(&staging, record, &[(&out_buf, out_n)])?
            .pop()
            .unwrap_or_default();
        Ok(sizes
            .iter()
            .map(|&(o, n)| {
                (0..n)
                    .map(|i| (values[o + 2 * i], values[o + 2 * i + 1]))
                    .collect()
            })
            .collect())
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
    img: &ColorImage,
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
        levels,
        segmentation,
        timing,
        params: *params,
        seg_params: *seg_params,
    }
}

type JobResult = Result<Vec<FeaturePyramid>, BackendError>;

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
        let mut work: Vec<(&ColorImage, PyramidParams)> = Vec::new();
        let mut segs: Vec<(&ColorImage, SegmentParams)> = Vec::new();
        for (j, ok) in batch.iter().zip(&checked) {
            if ok.is_ok() {
                for (p, s) in j.settings {
                    work.push((j.image, *p));
                    segs.push((j.image, *s));
                }
            }
        }
        let (features, segmentations) = rayon::join(
            || {
                let t = Instant::now();
                self.with_ctx(|c| c.features(&work, false))
                    .map(|f| (f, t.elapsed().as_secs_f64() * 1e3))
            },
            || {
                segs.par_iter()
                    .map(|(img, s)| {
                        let t = Instant::now();
                        segment(img, s).map(|r| (r, t.elapsed().as_secs_f64() * 1e3))
                    })
                    .collect::<Vec<_>>()
            },
        );
        let Some((features, gpu_ms)) = features else {
            return self.cpu.pyramids(batch);
        };
        let mut hogs = features.hogs.into_iter();
        let mut segmentations = segmentations.into_iter();
        let mut out = Vec::with_capacity(batch.len());
        for (j, ok) in batch.iter().zip(checked) {
            if let Err(e) = ok {
                out.push(Err(BackendError::from(e)));
                continue;
            }
            let mut pyrs = Vec::with_capacity(j.settings.len());
            let mut failed = None;
            for (p, s) in j.settings {
                let hog = hogs.next().unwrap_or_default();
                match segmentations.next() {
                    Some(Ok((seg, seg_ms))) => {
                        let timing = PyramidTiming {
                            features_ms: gpu_ms,
                            segmentation_ms: seg_ms,
                            cell_segments_ms: 0.0,
                            total_ms: 0.0,
                        };
                        let mut pyr = assemble(j.image, p, s, hog, seg, timing);
                        pyr.timing.total_ms = start.elapsed().as_secs_f64() * 1e3;
                        pyrs.push(pyr);
                    }
                    Some(Err(e)) => failed = Some(BackendError::from(e)),
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
