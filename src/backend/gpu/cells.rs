//! Learned cells on the GPU: every level of every image resized smoothly
//! (`kernels/resize_area.wgsl` with [`smooth_weights`]' taps, as
//! `ColorImage::resize_smooth`), then the backbone and the projection of
//! `kernels/backbone.wgsl`, one dispatch per layer and level, every level
//! of a batch in one submission. The activations of one level at a time
//! live in four buffers reused from level to level (the block's input and
//! output, the expanded map, the depthwise output), each as large as the
//! largest level needs.

use std::num::NonZeroU64;

use super::features::{plan_levels, LevelPlan};
use super::*;
use crate::vision::cells::LearnedCells;
use crate::vision::cnn::same_padding;
use crate::vision::hog::HOG_DIM;

/// Words of one layer's descriptor (`struct Layer` of the kernel).
const LAYER_WORDS: usize = 16;
/// `Layer.flags`: ReLU6 after the sum.
const RELU6: u32 = 1;
/// `Layer.flags`: the block's input added (projection of a residual block).
const SKIP: u32 = 2;

/// Where a layer's weights and its biases start in the weights buffer.
type Offsets = (u32, u32);

/// The offsets of a block's expansion (if any), depthwise convolution and
/// projection.
type BlockOffsets = (Option<Offsets>, Offsets, Offsets);

/// The backbone's and projection's numbers in one device buffer, uploaded
/// once, and where each layer's weights and biases start in it.
#[derive(Clone)]
pub(super) struct LearnedWeights {
    buffer: wgpu::Buffer,
    /// Weights and biases (then mean and std) of the stem.
    stem: Offsets,
    /// Per block.
    blocks: Vec<BlockOffsets>,
    /// The projection's basis and bias.
    cells: Offsets,
}

impl LearnedWeights {
    pub(super) fn upload(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        lc: &LearnedCells,
    ) -> Result<Self, GpuError> {
        let mut all: Vec<f32> = Vec::new();
        let mut push = |v: &[f32]| -> Result<u32, GpuError> {
            let off = to_u32(all.len(), "weights")?;
            all.extend_from_slice(v);
            Ok(off)
        };
        let (sw, sb, mean, std) = lc.backbone.stem_parts();
        let mut bias_norm = sb.to_vec();
        bias_norm.extend_from_slice(&mean);
        bias_norm.extend_from_slice(&std);
        let stem = (push(sw)?, push(&bias_norm)?);
        let mut blocks = Vec::new();
        for b in lc.backbone.blocks() {
            let expand = match &b.expand {
                Some(e) => Some((push(&e.weight)?, push(&e.bias)?)),
                None => None,
            };
            let dw = (push(&b.depthwise.weight)?, push(&b.depthwise.bias)?);
            let pr = (push(&b.project.weight)?, push(&b.project.bias)?);
            blocks.push((expand, dw, pr));
        }
        let cells = (push(&lc.projection.basis)?, push(&lc.projection.bias())?);
        let bytes: &[u8] = bytemuck::cast_slice(&all);
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("backbone weights"),
            size: (bytes.len() as u64).max(256),
            usage: STORAGE,
            mapped_at_creation: false,
        });
        queue.write_buffer(&buffer, 0, bytes);
        Ok(Self {
            buffer,
            stem,
            blocks,
            cells,
        })
    }
}

/// The kernel of a step.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Entry {
    Stem,
    Pointwise,
    Depthwise,
    Cells,
}

/// The buffer a step reads or writes.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Slot {
    /// The level images.
    Image,
    /// A block's input or output (the two swap roles block by block).
    A,
    B,
    /// The expanded map.
    Expanded,
    /// The depthwise convolution's output.
    Depthwise,
    /// The cells of every level.
    Cells,
}

/// One dispatch.
struct Step {
    entry: Entry,
    words: [u32; LAYER_WORDS],
    src: Slot,
    dst: Slot,
    skip: Option<Slot>,
    /// Workgroups along x, y and z.
    groups: (u32, u32, u32),
}

/// Floats each reused activation buffer needs.
#[derive(Default, Clone, Copy)]
struct Sizes {
    block: usize,
    expanded: usize,
    depthwise: usize,
}

#[allow(clippy::too_many_arguments)]
fn layer(
    (in_w, in_h): (usize, usize),
    (out_w, out_h): (usize, usize),
    (cin, cout): (usize, usize),
    (k, stride, left, top): (usize, usize, usize, usize),
    (w_off, b_off): Offsets,
    src_off: usize,
    dst_off: usize,
    flags: u32,
) -> Result<[u32; LAYER_WORDS], GpuError> {
    let u = |v: usize| to_u32(v, "layer size");
    Ok([
        u(in_w)?,
        u(in_h)?,
        u(out_w)?,
        u(out_h)?,
        u(cin)?,
        u(cout)?,
        u(k)?,
        u(stride)?,
        u(left)?,
        u(top)?,
        w_off,
        b_off,
        u(src_off)?,
        u(dst_off)?,
        flags,
        0,
    ])
}

/// The dispatches of one `lw x lh` level whose image starts at `image_off`
/// of the level images and whose `cw x ch` cells go to `cells_off`, and
/// the activation sizes it needs.
#[allow(clippy::too_many_arguments)]
fn plan_level(
    lc: &LearnedCells,
    wts: &LearnedWeights,
    (lw, lh): (usize, usize),
    image_off: usize,
    (cw, ch): (usize, usize),
    cells_off: usize,
    steps: &mut Vec<Step>,
    sizes: &mut Sizes,
) -> Result<(), GpuError> {
    let (sw, _, _, _) = lc.backbone.stem_parts();
    let stem_out = sw.len() / 27;
    let (ow, left) = same_padding(lw, 3, 2);
    let (oh, top) = same_padding(lh, 3, 2);
    let grid = |w: usize, h: usize, c: usize| -> Result<(u32, u32, u32), GpuError> {
        Ok((groups(w, 8)?, groups(h, 8)?, groups(c, 1)?))
    };
    steps.push(Step {
        entry: Entry::Stem,
        words: layer(
            (lw, lh),
            (ow, oh),
            (3, stem_out),
            (3, 2, left, top),
            wts.stem,
            image_off,
            0,
            RELU6,
        )?,
        src: Slot::Image,
        dst: Slot::A,
        skip: None,
        groups: grid(ow, oh, stem_out)?,
    });
    sizes.block = sizes.block.max(stem_out * ow * oh);
    let (mut w, mut h) = (ow, oh);
    let (mut cur, mut other) = (Slot::A, Slot::B);
    for (b, &(expand, dw_offs, pr_offs)) in lc.backbone.blocks().iter().zip(&wts.blocks) {
        let mut src = cur;
        if let (Some(e), Some(offs)) = (&b.expand, expand) {
            steps.push(Step {
                entry: Entry::Pointwise,
                words: layer(
                    (w, h),
                    (w, h),
                    (e.inp, e.out),
                    (1, 1, 0, 0),
                    offs,
                    0,
                    0,
                    RELU6,
                )?,
                src: cur,
                dst: Slot::Expanded,
                // Not read (no SKIP flag); bound to a read-only buffer.
                skip: Some(cur),
                groups: grid(w, h, e.out)?,
            });
            sizes.expanded = sizes.expanded.max(e.out * w * h);
            src = Slot::Expanded;
        }
        let d = &b.depthwise;
        let (dw_w, left) = same_padding(w, d.k, d.stride);
        let (dw_h, top) = same_padding(h, d.k, d.stride);
        steps.push(Step {
            entry: Entry::Depthwise,
            words: layer(
                (w, h),
                (dw_w, dw_h),
                (d.channels, d.channels),
                (d.k, d.stride, left, top),
                dw_offs,
                0,
                0,
                RELU6,
            )?,
            src,
            dst: Slot::Depthwise,
            skip: None,
            groups: grid(dw_w, dw_h, d.channels)?,
        });
        sizes.depthwise = sizes.depthwise.max(d.channels * dw_w * dw_h);
        let p = &b.project;
        steps.push(Step {
            entry: Entry::Pointwise,
            words: layer(
                (dw_w, dw_h),
                (dw_w, dw_h),
                (p.inp, p.out),
                (1, 1, 0, 0),
                pr_offs,
                0,
                0,
                if b.skip { SKIP } else { 0 },
            )?,
            src: Slot::Depthwise,
            dst: other,
            skip: Some(cur),
            groups: grid(dw_w, dw_h, p.out)?,
        });
        sizes.block = sizes.block.max(p.out * dw_w * dw_h);
        (w, h) = (dw_w, dw_h);
        std::mem::swap(&mut cur, &mut other);
    }
    if cw > w || ch > h {
        return Err(GpuError::Validation(format!(
            "a {lw}x{lh} level gives a {w}x{h} map, fewer than its {cw}x{ch} cells"
        )));
    }
    steps.push(Step {
        entry: Entry::Cells,
        words: layer(
            (w, h),
            (cw, ch),
            (lc.projection.channels, HOG_DIM),
            (1, 1, 0, 0),
            wts.cells,
            0,
            cells_off,
            0,
        )?,
        src: cur,
        dst: Slot::Cells,
        skip: None,
        groups: grid(cw, ch, 1)?,
    });
    Ok(())
}

impl Context {
    /// The learned cells of every level of every `(image, pyramid
    /// settings)` pair, in the order asked (`floor(w / 8) x floor(h / 8)`
    /// cells a level, as the CPU's `feature_levels`).
    pub(super) fn learned_cells(
        &mut self,
        work: &[(&ColorImage, PyramidParams)],
    ) -> Result<Vec<Vec<HogMap>>, GpuError> {
        self.learned_cells_of(work, None)
    }

    /// [`Self::learned_cells`] of level `only` alone (the index among
    /// `level_sizes`), when given: a large image's levels are computed one
    /// submission each, so that its deadline is looked at between them.
    pub(super) fn learned_cells_of(
        &mut self,
        work: &[(&ColorImage, PyramidParams)],
        only: Option<usize>,
    ) -> Result<Vec<Vec<HogMap>>, GpuError> {
        let mut out: Vec<Vec<HogMap>> = vec![Vec::new(); work.len()];
        if work.is_empty() {
            return Ok(out);
        }
        let lc = LearnedCells::builtin().map_err(|e| GpuError::Validation(e.to_string()))?;
        if lc.backbone.stride != crate::vision::hog::CELL_SIZE {
            return Err(GpuError::Validation(format!(
                "the GPU computes learned cells of stride-8 backbones only ({} has stride {})",
                lc.backbone.name, lc.backbone.stride
            )));
        }
        if self.learned.is_none() {
            self.learned = Some(LearnedWeights::upload(&self.device, &self.queue, lc)?);
        }
        let Some(wts) = self.learned.clone() else {
            return Err(GpuError::Validation("backbone weights missing".into()));
        };
        // The level images, as the HOG path lays them out, with the
        // learned cells' smooth taps.
        let LevelPlan {
            src,
            taps,
            descs,
            owner,
            tmp_n,
            dst_n,
        } = plan_levels(work, only)?;
        let mut cells: Vec<(usize, usize, usize, usize)> = Vec::new();
        let mut cells_n = 0usize;
        let mut steps: Vec<Step> = Vec::new();
        let mut sizes = Sizes::default();
        for (d, &k) in descs.iter().zip(&owner) {
            let (lw, lh) = (d.dst_w as usize, d.dst_h as usize);
            let (cw, ch) = (lw / CELL_SIZE, lh / CELL_SIZE);
            if cw > 0 && ch > 0 {
                plan_level(
                    lc,
                    &wts,
                    (lw, lh),
                    d.dst_off as usize,
                    (cw, ch),
                    cells_n,
                    &mut steps,
                    &mut sizes,
                )?;
            }
            cells.push((k, cw, ch, cells_n));
            cells_n += cw * ch * HOG_STRIDE;
        }
        // Each step's descriptor at an offset the device can bind.
        let align = (self.device.limits().min_storage_buffer_offset_alignment as usize)
            .max(LAYER_WORDS * 4);
        let stride = align.div_ceil(4);
        let mut layer_words = vec![0u32; steps.len() * stride];
        for (i, s) in steps.iter().enumerate() {
            layer_words[i * stride..i * stride + LAYER_WORDS].copy_from_slice(&s.words);
        }
        let words: Vec<u32> = descs.iter().flat_map(|d| d.words()).collect();
        let levels_buf = self.upload("cnn levels", &words)?;
        let taps_buf = self.upload("cnn taps", &taps)?;
        let src_buf = self.upload("cnn image", &src)?;
        let layers_buf = self.upload("cnn layers", &layer_words)?;
        let tmp_buf = self.scratch("cnn resize", tmp_n * 4)?;
        let img_buf = self.scratch("cnn level images", dst_n * 4)?;
        let a_buf = self.scratch("cnn block a", sizes.block * 4)?;
        let b_buf = self.scratch("cnn block b", sizes.block * 4)?;
        let e_buf = self.scratch("cnn expanded", sizes.expanded * 4)?;
        let d_buf = self.scratch("cnn depthwise", sizes.depthwise * 4)?;
        let cells_buf = self.scratch("cnn cells", cells_n * 4)?;
        let staging = self.readback(cells_n)?;
        let resize = self.resize_dispatch(
            &descs,
            [&levels_buf, &taps_buf, &src_buf, &tmp_buf, &img_buf],
        )?;
        let k = &self.kernels;
        let slot = |s: Slot| match s {
            Slot::Image => &img_buf,
            Slot::A => &a_buf,
            Slot::B => &b_buf,
            Slot::Expanded => &e_buf,
            Slot::Depthwise => &d_buf,
            Slot::Cells => &cells_buf,
        };
        let size = NonZeroU64::new((LAYER_WORDS * 4) as u64);
        let mut bound = Vec::with_capacity(steps.len());
        for (i, s) in steps.iter().enumerate() {
            let pipeline = match s.entry {
                Entry::Stem => &k.cnn_stem,
                Entry::Pointwise => &k.cnn_pointwise,
                Entry::Depthwise => &k.cnn_depthwise,
                Entry::Cells => &k.cnn_cells,
            };
            let mut entries = vec![
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &layers_buf,
                        offset: (i * stride * 4) as u64,
                        size,
                    }),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wts.buffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: slot(s.src).as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: slot(s.dst).as_entire_binding(),
                },
            ];
            if let (Entry::Pointwise, Some(skip)) = (s.entry, s.skip) {
                entries.push(wgpu::BindGroupEntry {
                    binding: 4,
                    resource: slot(skip).as_entire_binding(),
                });
            }
            let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            });
            bound.push((pipeline, bg, s.groups));
        }
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("learned cells"),
                timestamp_writes: None,
            });
            resize.record(k, &mut pass);
            for (p, bg, (x, y, z)) in &bound {
                pass.set_pipeline(p);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(*x, *y, *z);
            }
        };
        let mut read = self.submit_and_read(&staging, record, &[(&cells_buf, cells_n)])?;
        let feats = read.pop().unwrap_or_default();
        for (k, cw, ch, off) in cells {
            let raw = feats
                .get(off..off + cw * ch * HOG_STRIDE)
                .ok_or_else(|| GpuError::Validation("short read of the cells".into()))?
                .to_vec();
            out[k].push(
                HogMap::from_raw(cw, ch, raw).map_err(|e| GpuError::Validation(e.to_string()))?,
            );
        }
        Ok(out)
    }
}
