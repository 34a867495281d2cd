//! The bounds stage on the GPU: the filter response maps and the chain
//! bounds of exact pruning (`kernels/responses.wgsl`,
//! `kernels/dense_bounds.wgsl`) of every model, level and viewpoint.

use super::*;

/// One level and viewpoint in the layout of `struct Job`.
#[derive(Clone, Copy, Default)]
pub(super) struct JobDesc {
    pub(super) hog_off: u32,
    pub(super) mw: u32,
    pub(super) mh: u32,
    pub(super) x_lo: i32,
    pub(super) y_lo: i32,
    pub(super) nx: u32,
    pub(super) ny: u32,
    pub(super) weights_off: u32,
    pub(super) rows: u32,
    pub(super) cols: u32,
    pub(super) pair: f32,
    pub(super) chain_off: u32,
    pub(super) out_off: u32,
    pub(super) map_off: u32,
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
pub(super) const MAP_BUDGET: usize = 1 << 30;

/// The jobs of a bounds computation and the buffers they read.
pub(super) struct BoundsPlan {
    pub(super) jobs: Vec<JobDesc>,
    /// `(model, level, view)` of each job.
    pub(super) keys: Vec<(usize, usize, usize)>,
    pub(super) chain_n: usize,
    pub(super) out_n: usize,
    /// Response map entries (pairs of floats).
    pub(super) map_n: usize,
    pub(super) jobs_buf: wgpu::Buffer,
    pub(super) hog_buf: wgpu::Buffer,
    pub(super) weights_buf: wgpu::Buffer,
}

impl Context {
    /// Uploads a pyramid's features and the weights of `models`, and the
    /// job list of every (model, level, viewpoint) with positions.
    pub(super) fn bounds_setup(
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
    pub(super) fn dense_bounds(
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
    pub(super) fn dense_bounds_group(
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
    pub(super) fn responses(
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
