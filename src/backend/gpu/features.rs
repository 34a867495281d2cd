//! The feature stage on the GPU: the pyramid levels of a batch of images
//! planned once for both kinds of cells ([`plan_levels`]: each level's
//! resize as its kind wants it), and the HOG maps
//! (`kernels/resize_area.wgsl`, `kernels/hog.wgsl`) in one submission.

use super::*;

/// One pyramid level in the layout the kernels read (`struct Level`).
#[derive(Clone, Copy, Default)]
pub(super) struct LevelDesc {
    pub(super) src_w: u32,
    pub(super) src_h: u32,
    pub(super) src_off: u32,
    pub(super) dst_w: u32,
    pub(super) dst_h: u32,
    pub(super) dst_off: u32,
    pub(super) tmp_off: u32,
    pub(super) xtap_off: u32,
    pub(super) ytap_off: u32,
    pub(super) cw: u32,
    pub(super) ch: u32,
    pub(super) hist_off: u32,
    pub(super) hog_off: u32,
    pub(super) grad_off: u32,
}

impl LevelDesc {
    pub(super) fn words(&self) -> [u32; 16] {
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

pub(super) use crate::vision::pyramid::level_sizes;

/// The pyramid levels of a batch laid out in the device's buffers: one
/// copy of each image, each level's resize descriptor (taps of its
/// kind's resize) and scratch offsets; the cells' offsets are the
/// caller's to fill.
#[derive(Default)]
pub(super) struct LevelPlan {
    /// The images' pixels, each image once.
    pub(super) src: Vec<f32>,
    pub(super) taps: Vec<u32>,
    pub(super) descs: Vec<LevelDesc>,
    /// Each level's `(image, settings)` pair, by index.
    pub(super) owner: Vec<usize>,
    /// Floats of the resize's intermediate and of the level images.
    pub(super) tmp_n: usize,
    pub(super) dst_n: usize,
}

/// Plans the levels of every `(image, settings)` pair (of level `only`
/// alone, the index among `level_sizes`, when given), in order.
pub(super) fn plan_levels(
    work: &[(&ColorImage, PyramidParams)],
    only: Option<usize>,
) -> Result<LevelPlan, GpuError> {
    let mut plan = LevelPlan::default();
    let mut src_offs: Vec<(usize, usize)> = Vec::new();
    for (k, (img, p)) in work.iter().enumerate() {
        // One copy of each image, shared by its settings.
        let key = *img as *const _ as usize;
        let src_off = match src_offs.iter().find(|(ptr, _)| *ptr == key) {
            Some(&(_, off)) => off,
            None => {
                let off = plan.src.len();
                plan.src.extend_from_slice(img.data());
                src_offs.push((key, off));
                off
            }
        };
        let (w, h) = (img.width(), img.height());
        let wanted = level_sizes(w, h, p)
            .into_iter()
            .enumerate()
            .filter(|(i, _)| only.is_none_or(|o| o == *i))
            .map(|(_, s)| s);
        for (lw, lh) in wanted {
            plan.descs.push(LevelDesc {
                src_w: to_u32(w, "width")?,
                src_h: to_u32(h, "height")?,
                src_off: to_u32(src_off, "image offset")?,
                dst_w: to_u32(lw, "level width")?,
                dst_h: to_u32(lh, "level height")?,
                dst_off: to_u32(plan.dst_n, "level offset")?,
                tmp_off: to_u32(plan.tmp_n, "resize offset")?,
                xtap_off: push_taps(&mut plan.taps, &p.features.resize_weights(w, lw))?,
                ytap_off: push_taps(&mut plan.taps, &p.features.resize_weights(h, lh))?,
                ..LevelDesc::default()
            });
            plan.owner.push(k);
            plan.tmp_n += h * lw * 3;
            plan.dst_n += lw * lh * 3;
        }
    }
    Ok(plan)
}

pub(super) fn push_taps(taps: &mut Vec<u32>, table: &[Vec<(usize, f32)>]) -> Result<u32, GpuError> {
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

/// The two passes of the resize (`kernels/resize_area.wgsl`) over every
/// level of a batch, bound and sized: the HOG path and the learned cells'
/// both start with it.
pub(super) struct ResizeDispatch {
    horizontal: wgpu::BindGroup,
    vertical: wgpu::BindGroup,
    /// Levels (workgroups along z).
    pub(super) levels: u32,
    /// Workgroups along the widest level and the tallest level (and the
    /// tallest source image, which the horizontal pass covers).
    pub(super) gw: u32,
    pub(super) gh: u32,
    gsh: u32,
}

impl ResizeDispatch {
    /// Records both passes.
    pub(super) fn record(&self, k: &Kernels, pass: &mut wgpu::ComputePass<'_>) {
        for (p, bg, y) in [
            (&k.resize_h, &self.horizontal, self.gsh),
            (&k.resize_v, &self.vertical, self.gh),
        ] {
            pass.set_pipeline(p);
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(self.gw, y, self.levels);
        }
    }
}

/// The HOG maps (and optionally the resized images) of every level of every
/// (image, setting) pair, in the order asked.
pub(super) struct Features {
    pub(super) hogs: Vec<Vec<HogMap>>,
    pub(super) images: Vec<Vec<ColorImage>>,
}

impl Context {
    /// The resize of every level of `descs` from the images in `src` into
    /// `dst` (through `tmp`), with the tap tables in `taps`.
    pub(super) fn resize_dispatch(
        &self,
        descs: &[LevelDesc],
        [levels, taps, src, tmp, dst]: [&wgpu::Buffer; 5],
    ) -> Result<ResizeDispatch, GpuError> {
        let nl = to_u32(descs.len(), "levels")?;
        if nl > MAX_GROUPS {
            return Err(GpuError::TooLarge(format!("{nl} levels in one batch")));
        }
        let max = |f: fn(&LevelDesc) -> u32| descs.iter().map(f).max().unwrap_or(1) as usize;
        let k = &self.kernels;
        Ok(ResizeDispatch {
            horizontal: self.bind(&k.resize_h, &[(0, levels), (1, taps), (2, src), (3, tmp)]),
            vertical: self.bind(&k.resize_v, &[(0, levels), (1, taps), (3, tmp), (4, dst)]),
            levels: nl,
            gw: groups(max(|d| d.dst_w), 8)?,
            gh: groups(max(|d| d.dst_h), 8)?,
            gsh: groups(max(|d| d.src_h), 8)?,
        })
    }

    /// HOG maps of every level of every `(image, pyramid settings)` pair in
    /// one submission; with `images`, also the resized level images.
    pub(super) fn features(
        &mut self,
        work: &[(&ColorImage, PyramidParams)],
        images: bool,
    ) -> Result<Features, GpuError> {
        let LevelPlan {
            src,
            taps,
            mut descs,
            owner,
            tmp_n,
            dst_n,
        } = plan_levels(work, None)?;
        let (mut grad_n, mut hist_n, mut hog_n) = (0, 0, 0);
        for d in &mut descs {
            let (lw, lh) = (d.dst_w as usize, d.dst_h as usize);
            let (cw, ch) = (lw / CELL_SIZE, lh / CELL_SIZE);
            d.cw = to_u32(cw, "cells")?;
            d.ch = to_u32(ch, "cells")?;
            d.hist_off = to_u32(hist_n, "histogram offset")?;
            d.hog_off = to_u32(hog_n, "feature offset")?;
            d.grad_off = to_u32(grad_n, "gradient offset")?;
            grad_n += lw * lh;
            hist_n += cw * ch * 18;
            hog_n += cw * ch * HOG_STRIDE;
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
        let resize = self.resize_dispatch(
            &descs,
            [&levels_buf, &taps_buf, &src_buf, &tmp_buf, &dst_buf],
        )?;
        let k = &self.kernels;
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
        let (nl, gw, gh) = (resize.levels, resize.gw, resize.gh);
        let (gcw, gch) = (groups(max(|d| d.cw), 8)?, groups(max(|d| d.ch), 8)?);
        let pipes = [
            (&k.gradient, &bg_g, (gw, gh)),
            (&k.histogram, &bg_h, (gcw, gch)),
            (&k.normalise, &bg_n, (gcw, gch)),
        ];
        let record = |enc: &mut wgpu::CommandEncoder| {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("pyramid"),
                timestamp_writes: None,
            });
            resize.record(k, &mut pass);
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
}
