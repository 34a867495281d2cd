//! From an image and models to the detection JSON (the response shape of
//! `POST /detect`): one pyramid per distinct feature setting, every model's
//! scan, masks, timings, and a PNG overlay for inspection.

use rayon::prelude::*;
use std::sync::OnceLock;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::model::{Model, SEGMENTER_MIN_IOU};
use crate::vision::detect::{
    detection_masks, DenseBounds, DetectParams, DetectStats, Detection, Detector, Location,
    PlanarMaps, Region, Transfer,
};
use crate::vision::energy::ViewWeights;
use crate::vision::image::ColorImage;
use crate::vision::mask::{CompressedRle, Mask, Rle};
use crate::vision::pyramid::{FeaturePyramid, PyramidParams};
use crate::vision::segment::SegmentParams;
use crate::vision::shape::{colour_agreement, image_colours};
use crate::vision::{Deadline, VisionError};

/// Default upper limit on the pixels of an input image.
pub const DEFAULT_MAX_PIXELS: usize = 40_000_000;

/// Which masks a response carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum MaskMode {
    #[default]
    Refined,
    Raw,
    Both,
    None,
}

/// Request options; `None` means the model's default.
#[derive(Clone, Debug, PartialEq)]
pub struct DetectOptions {
    pub threshold: Option<f64>,
    /// Each model finds this many at most (per object for a model of
    /// several objects trained jointly, whose objects' detections are
    /// suppressed and counted on their own), and the answer keeps the best
    /// this many of all.
    pub max_detections: Option<usize>,
    pub masks: MaskMode,
    /// Exact pruning (off only to check it).
    pub prune: bool,
    pub max_pixels: usize,
    /// Only detections about here (see [`Region`]).
    pub region: Option<Region>,
    /// Give up once this passes.
    pub deadline: Deadline,
    /// Response transfer between the models (paper, Algorithm 1): they
    /// run in the given order, and each model's best detection at or above
    /// its own threshold claims the cells of its visible mask for the
    /// models after it (see [`crate::vision::detect::Transfer`]).
    pub transfer: bool,
    /// Only the detections of this object (label), e.g. one object of a
    /// model of several.
    pub label: Option<String>,
}

impl Default for DetectOptions {
    fn default() -> Self {
        Self {
            threshold: None,
            max_detections: None,
            masks: MaskMode::Refined,
            prune: true,
            max_pixels: DEFAULT_MAX_PIXELS,
            region: None,
            deadline: Deadline::NONE,
            transfer: false,
            label: None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageSize {
    pub width: usize,
    pub height: usize,
}

/// A box in pixels: top-left corner and size; may extend outside the image.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoxJson {
    pub x: f64,
    pub y: f64,
    pub width: f64,
    pub height: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectionJson {
    pub label: String,
    pub model: String,
    pub score: f64,
    #[serde(rename = "box")]
    pub bbox: BoxJson,
    /// The viewpoint component that fired (index into the model's
    /// components).
    pub viewpoint: usize,
    /// Where that component came from: the training view it represents
    /// (the medoid of its views), or `single-pose`; absent for models
    /// trained without views.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub view: Option<String>,
    /// Pyramid level the detection was found at (0 = largest).
    pub level: usize,
    pub visible_fraction: f64,
    pub truncated: bool,
    /// Refined visible mask (COCO uncompressed RLE over the whole image);
    /// made by the model's segmenter where it has one
    /// ([`Model::segmenter`]), as `raw_mask` and `visible_fraction` are.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub mask: Option<Rle>,
    /// Cell-level visible mask.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub raw_mask: Option<Rle>,
}

/// How the masks of the JSON are written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum RleFormat {
    /// COCO uncompressed RLE: `counts` is an array of run lengths.
    #[default]
    Uncompressed,
    /// COCO compressed RLE: `counts` is pycocotools' string.
    Compressed,
}

impl DetectResponse {
    /// The response as JSON with its masks in `format`.
    pub fn to_json(&self, format: RleFormat) -> Result<serde_json::Value, serde_json::Error> {
        let mut v = serde_json::to_value(self)?;
        if format == RleFormat::Compressed {
            let dets = v["detections"].as_array_mut().into_iter().flatten();
            for (json, det) in dets.zip(&self.detections) {
                for (key, rle) in [("mask", &det.mask), ("raw_mask", &det.raw_mask)] {
                    if let Some(r) = rle {
                        json[key] = serde_json::to_value::<CompressedRle>(r.compress())?;
                    }
                }
            }
        }
        Ok(v)
    }
}

/// Wall-clock milliseconds per stage, summed over pyramids and models
/// (features and segmentation run concurrently), and the pruning counts.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    pub features: f64,
    pub segmentation: f64,
    pub cell_segments: f64,
    pub responses: f64,
    pub mincut: f64,
    pub masks: f64,
    pub total: f64,
    pub locations: usize,
    pub min_cuts: usize,
    pub pruned_fraction: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DetectResponse {
    pub image: ImageSize,
    pub detections: Vec<DetectionJson>,
    pub timing_ms: Timing,
}

/// The distinct feature settings (pyramid and over-segmentation) of
/// `models` and of their segmenters ([`Model::segmenter`]), in the order
/// they are first used: one pyramid per setting serves every model.
pub fn feature_settings(models: &[&Model]) -> Vec<(PyramidParams, SegmentParams)> {
    let mut out: Vec<(PyramidParams, SegmentParams)> = Vec::new();
    for m in models {
        for m in std::iter::once(*m).chain(m.segmenter.as_deref()) {
            let s = (m.meta.pyramid, m.meta.segmentation);
            if !out.contains(&s) {
                out.push(s);
            }
        }
    }
    out
}

/// Checks an image's size against the pixel limit.
pub fn check_pixels(width: usize, height: usize, max_pixels: usize) -> Result<(), VisionError> {
    if width.saturating_mul(height) > max_pixels {
        return Err(VisionError::ImageTooLarge { width, height });
    }
    Ok(())
}

/// Runs every model on one image.
pub fn detect_image(
    img: &ColorImage,
    models: &[&Model],
    opts: &DetectOptions,
) -> Result<DetectResponse, VisionError> {
    check_pixels(img.width(), img.height(), opts.max_pixels)?;
    let img = std::sync::Arc::new(img.clone());
    let pyramids = FeaturePyramid::build_all(&img, &feature_settings(models), Deadline::NONE)?;
    let refs: Vec<&FeaturePyramid> = pyramids.iter().collect();
    detect_prebuilt(&refs, models, opts)
}

/// Runs every model on an image whose pyramid is already built; models whose
/// feature settings differ from the pyramid's are refused, while their
/// segmenters' pyramids are built beside it where needed.
pub fn detect_pyramid(
    pyr: &FeaturePyramid,
    models: &[&Model],
    opts: &DetectOptions,
) -> Result<DetectResponse, VisionError> {
    let segmenters: Vec<&Model> = models
        .iter()
        .filter_map(|m| m.segmenter.as_deref())
        .collect();
    let others = pyr.build_others(&feature_settings(&segmenters), opts.deadline)?;
    let all: Vec<&FeaturePyramid> = std::iter::once(pyr).chain(&others).collect();
    detect_prebuilt(&all, models, opts)
}

/// Runs every model on pyramids of one image built elsewhere (by a compute
/// backend): each model uses the pyramid with its feature settings, and a
/// model without one is refused. The timings include the pyramids' own
/// (the total adds the build times of the pyramids used).
pub fn detect_prebuilt(
    pyramids: &[&FeaturePyramid],
    models: &[&Model],
    opts: &DetectOptions,
) -> Result<DetectResponse, VisionError> {
    detect_prebuilt_with(pyramids, models, &[], opts)
}

/// [`detect_prebuilt`] with the stage-1 chain bounds of some models computed
/// by a backend (`bounds[i]` for `models[i]`; missing ones are computed by
/// the detector).
pub fn detect_prebuilt_with(
    pyramids: &[&FeaturePyramid],
    models: &[&Model],
    bounds: &[Option<&DenseBounds>],
    opts: &DetectOptions,
) -> Result<DetectResponse, VisionError> {
    let Some(first) = pyramids.first() else {
        return Err(VisionError::InvalidParameter("no pyramid".into()));
    };
    let (w, h) = (first.image_width, first.image_height);
    let start = Instant::now();
    let mut timing = Timing::default();
    let mut stats = DetectStats::default();
    let mut detections: Vec<DetectionJson> = Vec::new();
    let mut scanned: Vec<Scanned> = Vec::new();
    let mut used = vec![false; pyramids.len()];
    let mut built_ms = 0.0;
    // One claim map per pyramid (models of other feature settings never
    // share cells).
    let mut transfers: Vec<Option<Transfer>> = pyramids
        .iter()
        .map(|p| (opts.transfer && models.len() > 1).then(|| Transfer::new(p)))
        .collect();
    // The pyramid of each model, and of its segmenter.
    let of_model: Vec<usize> = models
        .iter()
        .map(|model| pyramid_of(pyramids, model))
        .collect::<Result<_, _>>()?;
    let of_segmenter: Vec<Option<usize>> = models
        .iter()
        .map(|model| {
            model
                .segmenter
                .as_deref()
                .map(|s| pyramid_of(pyramids, s))
                .transpose()
        })
        .collect::<Result<_, _>>()?;
    // Stage 1's feature planes, once per pyramid that several models scan
    // with bounds of their own.
    let t = Instant::now();
    let shared: Vec<Option<PlanarMaps>> = pyramids
        .iter()
        .enumerate()
        .map(|(idx, pyr)| {
            let views: Vec<&[ViewWeights]> = models
                .iter()
                .enumerate()
                .filter(|&(mi, _)| {
                    of_model[mi] == idx
                        && bounds.get(mi).copied().flatten().is_none()
                        && !uses_low_rank()
                })
                .map(|(_, model)| model.views.as_slice())
                .collect();
            (opts.prune && views.len() > 1).then(|| PlanarMaps::new(pyr, &views))
        })
        .collect();
    timing.responses += t.elapsed().as_secs_f64() * 1e3;
    // The image's colours, made once per pyramid for the models that weigh
    // colours.
    let colours: Vec<OnceLock<Vec<f32>>> = pyramids.iter().map(|_| OnceLock::new()).collect();
    for (mi, model) in models.iter().enumerate() {
        let idx = of_model[mi];
        let pyr = pyramids[idx];
        for i in std::iter::once(idx).chain(of_segmenter[mi]) {
            let pyr = pyramids[i];
            if (pyr.image_width, pyr.image_height) != (w, h) {
                return Err(VisionError::InvalidParameter(
                    "pyramids of different images".into(),
                ));
            }
            if !used[i] {
                used[i] = true;
                timing.features += pyr.timing.features_ms;
                timing.segmentation += pyr.timing.segmentation_ms;
                timing.cell_segments += pyr.timing.cell_segments_ms;
                built_ms += pyr.timing.total_ms;
            }
        }
        let pre = bounds.get(mi).copied().flatten();
        let segmenter = model
            .segmenter
            .as_deref()
            .zip(of_segmenter[mi].map(|i| pyramids[i]));
        scanned.push(
            scan_model(
                pyr,
                model,
                pre,
                shared[idx].as_ref(),
                opts,
                transfers[idx].as_mut(),
                &colours[idx],
                &mut timing,
                &mut stats,
            )?
            .segmented_by(segmenter),
        );
    }
    // Every model's masks in one parallel batch, in model order.
    let t = Instant::now();
    let jobs: Vec<(&Scanned, &Detection)> = scanned
        .iter()
        .flat_map(|s| s.dets.iter().map(move |d| (s, d)))
        .collect();
    let made: Vec<Option<DetectionJson>> = jobs
        .into_par_iter()
        .map(|(s, d)| detection_json(s, d, opts))
        .collect::<Result<_, _>>()?;
    detections.extend(made.into_iter().flatten());
    timing.masks += t.elapsed().as_secs_f64() * 1e3;
    let mut resp = finish(w, h, detections, timing, stats, opts, start);
    resp.timing_ms.total += built_ms;
    Ok(resp)
}

/// The index of the pyramid built with `model`'s feature settings.
fn pyramid_of(pyramids: &[&FeaturePyramid], model: &Model) -> Result<usize, VisionError> {
    let m = &model.meta;
    pyramids
        .iter()
        .position(|p| p.params == m.pyramid && p.seg_params == m.segmentation)
        .ok_or_else(|| {
            VisionError::InvalidParameter(format!(
                "model {} needs other pyramid settings than the image's",
                m.name
            ))
        })
}

/// One model's detections, before their masks.
struct Scanned<'a> {
    pyr: &'a FeaturePyramid,
    model: &'a Model,
    params: DetectParams,
    dets: Vec<Detection>,
    /// The image's colours, for the colour agreement of models that use it.
    image_colours: Option<&'a [f32]>,
    /// The model's segmenter and its pyramid ([`Model::segmenter`]).
    segmenter: Option<(&'a Model, &'a FeaturePyramid)>,
}

impl<'a> Scanned<'a> {
    fn segmented_by(mut self, segmenter: Option<(&'a Model, &'a FeaturePyramid)>) -> Self {
        self.segmenter = segmenter;
        self
    }

    /// Detection `d`'s raw and refined masks and its visible fraction: by
    /// the segmenter's best location whose box overlaps `d`'s by
    /// [`SEGMENTER_MIN_IOU`] or more where the model has a segmenter and
    /// one does, else by `d` itself.
    fn masks(&self, d: &Detection) -> Result<(Mask, Mask, f64), VisionError> {
        if let Some((seg, pyr)) = self.segmenter {
            let p = &seg.meta.detection;
            let near = Detector::new(&seg.views)?.best_near_until(
                pyr,
                d.bbox,
                SEGMENTER_MIN_IOU,
                p.max_truncation,
                self.params.deadline,
            )?;
            if let Some(n) = near {
                let shape = seg.shapes.get(n.viewpoint).and_then(Option::as_ref);
                let (raw, refined) = detection_masks(&n, pyr, &p.refine, shape);
                return Ok((raw, refined, n.visible_fraction));
            }
        }
        let shape = self.model.shapes.get(d.viewpoint).and_then(Option::as_ref);
        let (raw, refined) = detection_masks(d, self.pyr, &self.params.refine, shape);
        Ok((raw, refined, d.visible_fraction))
    }
}

/// One model's scan; with a `transfer`, the scan sees the cells earlier
/// models claimed, and this model's best detection at or above its own
/// threshold claims its visible cells, with its mean object response per
/// visible cell.
#[allow(clippy::too_many_arguments)]
fn scan_model<'a>(
    pyr: &'a FeaturePyramid,
    model: &'a Model,
    pre: Option<&DenseBounds>,
    maps: Option<&PlanarMaps>,
    opts: &DetectOptions,
    transfer: Option<&mut Transfer>,
    colours: &'a OnceLock<Vec<f32>>,
    timing: &mut Timing,
    stats: &mut DetectStats,
) -> Result<Scanned<'a>, VisionError> {
    let m = &model.meta;
    let mut params = m.detection;
    if let Some(t) = opts.threshold {
        params.threshold = t;
    }
    if let Some(k) = opts.max_detections {
        params.max_detections = k;
    }
    params.prune = opts.prune;
    params.region = opts.region;
    params.deadline = opts.deadline;
    // A model of several objects (trained jointly): each object's
    // detections are suppressed and counted on their own, as separate
    // models' would be.
    let labels = model.labels();
    let groups: Vec<usize> = m
        .viewpoints
        .iter()
        .map(|v| labels.iter().position(|l| *l == v.label).unwrap_or(0))
        .collect();
    let mut detector = Detector::new(&model.views)?.with_groups(groups)?;
    if uses_low_rank() {
        detector = detector.with_low_rank(model.low_rank());
    } else if let Some(maps) = maps {
        detector = detector.with_maps(maps);
    }
    // A colour-weighted model's colour term only ever lowers a score
    // ([`colour_term`]), so the search by the SD-HOP score at the
    // threshold finds every detection whose answered score reaches it;
    // `max_detections` keeps the best by the SD-HOP score, and those whose
    // colour term takes them below the threshold are dropped
    // ([`detection_json`]). An answer at a lower threshold, cut at this
    // one, is then this answer.
    let (dets, s) = match transfer.as_deref() {
        Some(t) => detector
            .with_transfer(t)
            .detect_with_bounds(pyr, &params, pre)?,
        None => detector.detect_with_bounds(pyr, &params, pre)?,
    };
    if let Some(t) = transfer {
        if let Some(d) = dets.first().filter(|d| d.score >= m.detection.threshold) {
            let detector = Detector::new(&model.views)?;
            let loc = Location {
                level: d.level,
                view: d.viewpoint,
                y: d.grid.cell_y,
                x: d.grid.cell_x,
            };
            let (problem, _, _) = detector.problem_at(pyr, &loc);
            let (sum, n) = d
                .cells
                .iter()
                .zip(&problem.u1)
                .filter(|(v, _)| **v)
                .fold((0.0, 0usize), |(s, n), (_, u)| (s + u, n + 1));
            if n > 0 {
                let shape = model.shapes.get(d.viewpoint).and_then(Option::as_ref);
                let (_, refined) = detection_masks(d, pyr, &params.refine, shape);
                t.claim(pyr, &refined, (sum / n as f64) as f32);
            }
        }
    }
    stats.locations += s.locations;
    stats.min_cuts += s.min_cuts;
    timing.responses += s.responses_ms;
    timing.mincut += s.mincut_ms;
    let image_colours = (params.colour_weight > 0.0)
        .then(|| colours.get_or_init(|| image_colours(&pyr.image)).as_slice());
    Ok(Scanned {
        pyr,
        model,
        params,
        dets,
        image_colours,
        segmenter: None,
    })
}

/// Colour agreement at which a detection keeps its whole SD-HOP score
/// (the agreement itself reaches [`crate::vision::shape::AGREEMENT_CLAMP`]).
pub const COLOUR_FULL_AGREEMENT: f64 = 1.0;

/// What a model's colour weight adds to a detection's score: the weight
/// times how far the colour agreement falls short of
/// [`COLOUR_FULL_AGREEMENT`], never more than 0. Colours that agree
/// better rank a detection higher, as the colour weight was chosen (by
/// the mesh route and `join`, both signs counting), yet a score is never
/// raised above its SD-HOP score, so that the search's pruning by the
/// threshold on the SD-HOP score is exact for the score answered, and an
/// answer at a threshold holds exactly the detections a lower threshold
/// finds at or above it.
pub fn colour_term(weight: f64, agreement: f64) -> f64 {
    weight * (agreement.min(COLOUR_FULL_AGREEMENT) - COLOUR_FULL_AGREEMENT)
}

/// A detection's answer with its masks (and its colour agreement where the
/// model weighs it); `None` for another label than the one asked.
fn detection_json(
    s: &Scanned,
    d: &Detection,
    opts: &DetectOptions,
) -> Result<Option<DetectionJson>, VisionError> {
    let (pyr, model, params) = (s.pyr, s.model, &s.params);
    let m = &model.meta;
    if opts.deadline.passed() {
        return Err(VisionError::DeadlineExceeded);
    }
    let label = &m.viewpoints[d.viewpoint].label;
    if opts.label.as_ref().is_some_and(|l| l != label) {
        return Ok(None);
    }
    let shape = model.shapes.get(d.viewpoint).and_then(Option::as_ref);
    let mut score = d.score;
    let object_colours = shape.and_then(|s| s.colours.as_ref());
    let masks = match (&s.image_colours, object_colours) {
        (Some(ic), Some(oc)) => {
            let masks = s.masks(d)?;
            score += colour_term(
                params.colour_weight,
                colour_agreement(&pyr.image, &masks.1, oc, ic),
            );
            Some(masks)
        }
        _ => None,
    };
    // Answers true to their threshold: the score with its colour term is
    // the one the threshold bounds.
    if score < params.threshold {
        return Ok(None);
    }
    let (raw, refined, visible_fraction) = if opts.masks == MaskMode::None {
        (None, None, d.visible_fraction)
    } else {
        let (raw, refined, visible) = match masks {
            Some(m) => m,
            None => s.masks(d)?,
        };
        let want_raw = matches!(opts.masks, MaskMode::Raw | MaskMode::Both);
        let want_refined = matches!(opts.masks, MaskMode::Refined | MaskMode::Both);
        (
            want_raw.then(|| raw.to_rle()),
            want_refined.then(|| refined.to_rle()),
            visible,
        )
    };
    // The template's window, corrected where the model learned how.
    let (x, y, width, height) = m.box_correction.map_or(d.bbox, |c| c.apply(d.bbox));
    Ok(Some(DetectionJson {
        label: label.clone(),
        model: m.name.clone(),
        score,
        bbox: BoxJson {
            x,
            y,
            width,
            height,
        },
        viewpoint: d.viewpoint,
        view: m.viewpoints[d.viewpoint].views.first().cloned(),
        level: d.level,
        visible_fraction,
        truncated: d.truncated,
        mask: refined,
        raw_mask: raw,
    }))
}

fn finish(
    w: usize,
    h: usize,
    mut detections: Vec<DetectionJson>,
    mut timing: Timing,
    stats: DetectStats,
    opts: &DetectOptions,
    start: Instant,
) -> DetectResponse {
    detections.sort_by(|a, b| b.score.total_cmp(&a.score));
    if let Some(k) = opts.max_detections {
        detections.truncate(k);
    }
    timing.locations = stats.locations;
    timing.min_cuts = stats.min_cuts;
    timing.pruned_fraction = stats.pruned_fraction();
    timing.total = start.elapsed().as_secs_f64() * 1e3;
    DetectResponse {
        image: ImageSize {
            width: w,
            height: h,
        },
        detections,
        timing_ms: timing,
    }
}

/// Draws the detections over the image: visible pixels tinted, boxes outlined.
pub fn overlay(img: &ColorImage, resp: &DetectResponse) -> image::RgbImage {
    let mut out = img.to_rgb8();
    let (w, h) = (img.width() as i64, img.height() as i64);
    const COLORS: [[u8; 3]; 6] = [
        [255, 40, 40],
        [40, 220, 40],
        [60, 120, 255],
        [255, 200, 0],
        [220, 0, 220],
        [0, 220, 220],
    ];
    for (k, d) in resp.detections.iter().enumerate().rev() {
        let c = COLORS[k % COLORS.len()];
        if let Some(m) = d
            .mask
            .as_ref()
            .or(d.raw_mask.as_ref())
            .and_then(Mask::from_rle)
        {
            for y in 0..m.height {
                for x in 0..m.width {
                    if m.get(x, y) {
                        let p = out.get_pixel_mut(x as u32, y as u32);
                        for (v, tint) in p.0.iter_mut().zip(c) {
                            *v = ((u16::from(*v) + u16::from(tint)) / 2) as u8;
                        }
                    }
                }
            }
        }
        let (x0, y0) = (d.bbox.x.round() as i64, d.bbox.y.round() as i64);
        let (x1, y1) = (
            x0 + d.bbox.width.round() as i64 - 1,
            y0 + d.bbox.height.round() as i64 - 1,
        );
        for t in 0..2 {
            for x in x0..=x1 {
                for y in [y0 + t, y1 - t] {
                    if x >= 0 && y >= 0 && x < w && y < h {
                        out.put_pixel(x as u32, y as u32, image::Rgb(c));
                    }
                }
            }
            for y in y0..=y1 {
                for x in [x0 + t, x1 - t] {
                    if x >= 0 && y >= 0 && x < w && y < h {
                        out.put_pixel(x as u32, y as u32, image::Rgb(c));
                    }
                }
            }
        }
    }
    out
}

/// Whether stage 1 bounds through the low-rank basis of a model's
/// components' filters ([`crate::vision::detect::LowRank`]): only where
/// `SDHOP_STAGE1=low-rank` asks for it. The detections are the same either
/// way, but measured on the CMU_KO8 photographs with eight 3-component
/// models it is slower: the bound stage takes half the time (739 against
/// 1392 ms per image on one thread), but the looser bounds send 1604
/// locations to the min-cut stage instead of 905 (6.4 s against 0.64 s).
pub fn uses_low_rank() -> bool {
    static MODE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *MODE.get_or_init(|| std::env::var("SDHOP_STAGE1").as_deref() == Ok("low-rank"))
}

#[cfg(test)]
mod tests {
    use super::{colour_term, COLOUR_FULL_AGREEMENT};

    #[test]
    fn the_colour_term_ranks_by_agreement_and_never_raises_a_score() {
        let full = COLOUR_FULL_AGREEMENT;
        // Better agreement ranks higher, by the weight times the gain.
        assert!((colour_term(0.5, 0.4) - colour_term(0.5, -0.6) - 0.5).abs() < 1e-12);
        // Full agreement keeps the SD-HOP score; more counts no further.
        assert_eq!(colour_term(0.5, full), 0.0);
        assert_eq!(colour_term(0.5, 2.5), 0.0);
        // Disagreeing colours lower it.
        assert!((colour_term(0.5, -2.0) + 0.5 * (2.0 + full)).abs() < 1e-12);
        assert_eq!(colour_term(0.0, -2.5), 0.0);
    }
}
