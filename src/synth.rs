//! Synthetic scenes the project generates itself, with exact ground truth:
//! a procedurally textured object pasted into a cluttered background and
//! partly hidden by an occluder. Also a model built by hand from the object's
//! HOG (no training), with or without occlusion reasoning, so the detector
//! can be demonstrated and tested on a fresh clone with no data.

use crate::model::{Model, ModelError, ModelMeta, ViewMeta, FORMAT_VERSION};
use crate::vision::detect::DetectParams;
use crate::vision::energy::{PairwiseMode, ViewWeights};
use crate::vision::hog::{hog, CELL_SIZE, HOG_DIM, HOG_STRIDE};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::pyramid::PyramidParams;
use crate::vision::rng::SplitMix64;
use crate::vision::segment::SegmentParams;
use crate::vision::VisionError;

/// A procedural object: a rounded box with an outline, stripes and rings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SynthObject {
    /// Template size in cells (`cols x rows`), i.e. its size at scale 1.
    pub cols: usize,
    pub rows: usize,
    pub seed: u64,
}

impl SynthObject {
    pub fn width_px(&self) -> usize {
        self.cols * CELL_SIZE
    }

    pub fn height_px(&self) -> usize {
        self.rows * CELL_SIZE
    }

    /// Colour at normalised coordinates `(u, v)` in `[0, 1]^2`, or `None`
    /// outside the object's shape. `px` is the size of one unit in pixels
    /// (to keep the outline a constant number of pixels).
    fn color_at(&self, u: f64, v: f64, px: (f64, f64)) -> Option<[f32; 3]> {
        let mut rng = SplitMix64::new(self.seed);
        let base = [
            rng.range_f64(150.0, 240.0),
            rng.range_f64(60.0, 200.0),
            rng.range_f64(20.0, 120.0),
        ];
        let freq = rng.range_f64(3.0, 5.0);
        let angle = rng.range_f64(0.3, 1.2);
        let (ru, rv) = (rng.range_f64(0.3, 0.7), rng.range_f64(0.3, 0.7));
        // Rounded corners: radius 15% of the smaller side.
        let r = 0.15;
        let (w, h) = (px.0, px.1);
        let ax = r * w.min(h) / w;
        let ay = r * w.min(h) / h;
        let cu = u.clamp(ax, 1.0 - ax);
        let cv = v.clamp(ay, 1.0 - ay);
        let du = (u - cu) / ax;
        let dv = (v - cv) / ay;
        if du * du + dv * dv > 1.0 || !(0.0..=1.0).contains(&u) || !(0.0..=1.0).contains(&v) {
            return None;
        }
        // Outline of about 4 pixels.
        let edge = (u * w).min((1.0 - u) * w).min((v * h).min((1.0 - v) * h));
        if edge < 4.0 || du * du + dv * dv > 0.55 {
            return Some([30.0, 25.0, 40.0]);
        }
        let s = ((u * angle.cos() + v * angle.sin()) * freq * std::f64::consts::TAU).sin();
        let d = ((u - ru).powi(2) + (v - rv).powi(2)).sqrt();
        let ring = (d * 14.0).sin();
        let k = if s > 0.0 { 1.0 } else { 0.35 } * if ring > 0.6 { 0.5 } else { 1.0 };
        Some([
            (base[0] * k) as f32,
            (base[1] * k) as f32,
            (base[2] * k) as f32,
        ])
    }

    /// Paints the object with its top-left at `(x0, y0)` and size `w x h`
    /// pixels; returns its mask over the image.
    #[allow(clippy::too_many_arguments)]
    pub fn paint(
        &self,
        img: &mut [f32],
        width: usize,
        height: usize,
        x0: f64,
        y0: f64,
        w: f64,
        h: f64,
    ) -> Mask {
        let mut mask = Mask::new(width, height);
        let xs = x0.floor().max(0.0) as usize;
        let ys = y0.floor().max(0.0) as usize;
        let xe = ((x0 + w).ceil() as usize).min(width);
        let ye = ((y0 + h).ceil() as usize).min(height);
        // 4x4 supersampling: anti-aliased edges, as a camera would see them.
        const SS: usize = 4;
        for y in ys..ye {
            for x in xs..xe {
                let mut acc = [0.0f32; 3];
                let mut hits = 0usize;
                for sy in 0..SS {
                    for sx in 0..SS {
                        let u = (x as f64 + (sx as f64 + 0.5) / SS as f64 - x0) / w;
                        let v = (y as f64 + (sy as f64 + 0.5) / SS as f64 - y0) / h;
                        if let Some(c) = self.color_at(u, v, (w, h)) {
                            acc.iter_mut().zip(c).for_each(|(a, c)| *a += c);
                            hits += 1;
                        }
                    }
                }
                if hits == 0 {
                    continue;
                }
                let p = (y * width + x) * 3;
                let cover = hits as f32 / (SS * SS) as f32;
                for c in 0..3 {
                    let fg = acc[c] / hits as f32;
                    img[p + c] = cover * fg + (1.0 - cover) * img[p + c];
                }
                if 2 * hits >= SS * SS {
                    mask.set(x, y, true);
                }
            }
        }
        mask
    }
}

/// Settings of one synthetic scene.
#[derive(Clone, Copy, Debug)]
pub struct SceneParams {
    pub width: usize,
    pub height: usize,
    /// Object size relative to its template, drawn uniformly from this range.
    pub scale: (f64, f64),
    /// Fraction of the object's box width or height hidden by the occluder.
    pub occlusion: (f64, f64),
    pub seed: u64,
}

impl Default for SceneParams {
    fn default() -> Self {
        Self {
            width: 320,
            height: 240,
            scale: (1.0, 1.4),
            occlusion: (0.2, 0.5),
            seed: 1,
        }
    }
}

/// A generated scene and its ground truth.
#[derive(Clone, Debug)]
pub struct Scene {
    pub image: ColorImage,
    /// Full extent of the object `(x, y, w, h)` in pixels.
    pub truth_box: (f64, f64, f64, f64),
    /// Visible object pixels.
    pub visible: Mask,
    /// All object pixels (hidden ones included).
    pub object: Mask,
}

/// A cluttered background: smooth shading, muted rectangles and lines, noise.
fn background(width: usize, height: usize, rng: &mut SplitMix64) -> Vec<f32> {
    let mut img = vec![0.0f32; width * height * 3];
    let base: Vec<f64> = (0..3).map(|_| rng.range_f64(70.0, 170.0)).collect();
    let (gx, gy) = (rng.range_f64(-0.15, 0.15), rng.range_f64(-0.15, 0.15));
    for y in 0..height {
        for x in 0..width {
            for c in 0..3 {
                img[(y * width + x) * 3 + c] = (base[c] + gx * x as f64 + gy * y as f64) as f32;
            }
        }
    }
    let rects = 6 + rng.range_usize(0, 6);
    for _ in 0..rects {
        let (rw, rh) = (
            rng.range_usize(10, width / 3),
            rng.range_usize(10, height / 3),
        );
        let (rx, ry) = (
            rng.range_usize(0, width - rw),
            rng.range_usize(0, height - rh),
        );
        let col: Vec<f32> = (0..3).map(|_| rng.range_f64(50.0, 200.0) as f32).collect();
        for y in ry..ry + rh {
            for x in rx..rx + rw {
                img[(y * width + x) * 3..(y * width + x) * 3 + 3].copy_from_slice(&col);
            }
        }
    }
    let lines = 4 + rng.range_usize(0, 6);
    for _ in 0..lines {
        let (x0, y0) = (
            rng.range_f64(0.0, width as f64),
            rng.range_f64(0.0, height as f64),
        );
        let a = rng.range_f64(0.0, std::f64::consts::PI);
        let len = rng.range_f64(20.0, width as f64 / 2.0);
        let shade = rng.range_f64(20.0, 230.0) as f32;
        for t in 0..len as usize {
            for off in 0..2 {
                let x = (x0 + a.cos() * t as f64 + off as f64) as isize;
                let y = (y0 + a.sin() * t as f64) as isize;
                if x >= 0 && y >= 0 && (x as usize) < width && (y as usize) < height {
                    let p = (y as usize * width + x as usize) * 3;
                    img[p..p + 3].copy_from_slice(&[shade, shade, shade]);
                }
            }
        }
    }
    for v in img.iter_mut() {
        *v = (*v + rng.range_f64(-6.0, 6.0) as f32).clamp(0.0, 255.0);
    }
    img
}

/// Generates a scene: background, the object at a random place and scale,
/// and an occluder entering from a random side.
pub fn scene(obj: &SynthObject, p: &SceneParams) -> Result<Scene, VisionError> {
    let mut rng = SplitMix64::new(p.seed.wrapping_mul(0x2545_F491_4F6C_DD1D) ^ obj.seed);
    let (width, height) = (p.width, p.height);
    let mut img = background(width, height, &mut rng);
    let s = rng.range_f64(p.scale.0, p.scale.1);
    let (ow, oh) = (obj.width_px() as f64 * s, obj.height_px() as f64 * s);
    if ow + 2.0 > width as f64 || oh + 2.0 > height as f64 {
        return Err(VisionError::InvalidParameter(format!(
            "object of {ow:.0}x{oh:.0} px does not fit a {width}x{height} scene"
        )));
    }
    let ox = rng.range_f64(1.0, width as f64 - ow - 1.0);
    let oy = rng.range_f64(1.0, height as f64 - oh - 1.0);
    let object = obj.paint(&mut img, width, height, ox, oy, ow, oh);
    // Occluder: a flat slab over a fraction of the box from one side,
    // extending past the object.
    let frac = rng.range_f64(p.occlusion.0, p.occlusion.1);
    let side = rng.range_usize(0, 4);
    let (mut x0, mut y0, mut x1, mut y1) = (ox - 20.0, oy - 20.0, ox + ow + 20.0, oy + oh + 20.0);
    match side {
        0 => x1 = ox + frac * ow,
        1 => x0 = ox + (1.0 - frac) * ow,
        2 => y1 = oy + frac * oh,
        _ => y0 = oy + (1.0 - frac) * oh,
    }
    let col: Vec<f32> = (0..3).map(|_| rng.range_f64(40.0, 220.0) as f32).collect();
    let mut visible = object.clone();
    for y in 0..height {
        for x in 0..width {
            let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
            if cx >= x0 && cx < x1 && cy >= y0 && cy < y1 {
                let p = (y * width + x) * 3;
                for c in 0..3 {
                    img[p + c] = (col[c] + rng.range_f64(-3.0, 3.0) as f32).clamp(0.0, 255.0);
                }
                visible.set(x, y, false);
            }
        }
    }
    Ok(Scene {
        image: ColorImage::new(width, height, img)?,
        truth_box: (ox, oy, ow, oh),
        visible,
        object,
    })
}

/// HOG features of the object's template cells, from a clean view of it on a
/// flat background (the "training image"), row-major `rows x cols`.
pub fn object_template(obj: &SynthObject) -> Result<Vec<[f32; HOG_DIM]>, VisionError> {
    let margin = 2 * CELL_SIZE;
    let (w, h) = (obj.width_px() + 2 * margin, obj.height_px() + 2 * margin);
    let mut img = vec![128.0f32; w * h * 3];
    obj.paint(
        &mut img,
        w,
        h,
        margin as f64,
        margin as f64,
        obj.width_px() as f64,
        obj.height_px() as f64,
    );
    let map = hog(&ColorImage::new(w, h, img)?);
    let off = (margin / CELL_SIZE) as isize;
    Ok((0..obj.rows)
        .flat_map(|y| (0..obj.cols).map(move |x| (x, y)))
        .map(|(x, y)| map.cell_or_zero(x as isize + off, y as isize + off))
        .collect())
}

/// Relative weights of the hand-built model.
#[derive(Clone, Copy, Debug)]
pub struct HandModelParams {
    /// A cell is occluded when its match is below `alpha` of its template energy.
    pub alpha: f32,
    /// Potts weight relative to the mean template energy.
    pub pairwise: f32,
    /// Height of the concave HOP curve relative to the mean template energy.
    pub hop: f32,
    /// Score threshold relative to the total template energy.
    pub threshold: f64,
}

impl Default for HandModelParams {
    fn default() -> Self {
        Self {
            alpha: 0.5,
            pairwise: 0.15,
            hop: 0.3,
            threshold: 0.05,
        }
    }
}

/// A model built by hand from the object's HOG: object filter `-t_i`, the
/// occluded label costs `-alpha |t_i|^2`. With `occlusion_reasoning = false`
/// every cell is forced visible (a plain HOG template detector).
pub fn hand_model(
    obj: &SynthObject,
    name: &str,
    occlusion_reasoning: bool,
    hp: &HandModelParams,
) -> Result<Model, ModelError> {
    let t = object_template(obj)?;
    let k = 4;
    let mut w = ViewWeights::zeros(obj.rows, obj.cols, k);
    // Zero-mean within each feature group (sensitive, insensitive, energy),
    // so that isotropic texture such as sensor noise scores nothing.
    let groups = [(0usize, 18usize), (18, 27), (27, HOG_DIM)];
    let filters: Vec<[f32; HOG_DIM]> = t
        .iter()
        .map(|cell| {
            let mut f = *cell;
            for &(a, b) in &groups {
                let mean = cell[a..b].iter().sum::<f32>() / (b - a) as f32;
                f[a..b].iter_mut().for_each(|v| *v -= mean);
            }
            f
        })
        .collect();
    // A cell's response to its own appearance.
    let energies: Vec<f32> = t
        .iter()
        .zip(&filters)
        .map(|(c, f)| c.iter().zip(f).map(|(a, b)| a * b).sum::<f32>().max(0.0))
        .collect();
    let total: f32 = energies.iter().sum();
    let mean = total / energies.len() as f32;
    for (i, f) in filters.iter().enumerate() {
        for (d, &v) in f.iter().enumerate() {
            w.w_vis[i * HOG_STRIDE + d] = -v;
        }
        w.w_prior[i] = if occlusion_reasoning {
            -hp.alpha * energies[i]
        } else {
            // Never worth labelling occluded.
            1e3
        };
    }
    if occlusion_reasoning {
        w.w_pair = hp.pairwise * mean;
        let h = hp.hop * mean;
        w.w_hop = vec![0.0, 0.75 * h, h, 0.75 * h, 0.0];
    }
    // Truncated cells are no evidence either way: as costly as occluded ones.
    w.w_trunc = hp.alpha * mean;
    w.bias = hp.alpha * total;
    let detection = DetectParams {
        threshold: hp.threshold * f64::from(total),
        ..DetectParams::default()
    };
    let meta = ModelMeta {
        format_version: FORMAT_VERSION,
        name: name.to_string(),
        cell_size: CELL_SIZE,
        hop_k: k,
        pairwise: PairwiseMode::Grid,
        pyramid: PyramidParams::default(),
        cells: None,
        segmentation: SegmentParams::default(),
        detection,
        viewpoints: vec![ViewMeta {
            label: name.to_string(),
            rows: obj.rows,
            cols: obj.cols,
            direction: None,
            rotations: Vec::new(),
            views: Vec::new(),
        }],
        box_correction: None,
        segmenter: None,
        provenance: serde_json::json!({
            "source": "hand-built from the HOG of a synthetic object (no training)",
            "object_seed": obj.seed,
            "occlusion_reasoning": occlusion_reasoning,
        }),
    };
    Model::new(meta, vec![w])
}
