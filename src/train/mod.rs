//! Structured SVM training of SD-HOP models (paper section 2.3): the 1-slack
//! cutting-plane algorithm (Joachims, Finley and Yu 2009) with the loss of
//! eq. (3), loss-augmented inference by the detector's own exact min-cut
//! search over every location, level and viewpoint, and the dual QP solved by
//! clarabel with `W >= 0` and `D^2 w_HOP >= 0`.
//!
//! The HOP weights are trained in a parametrisation where the curvature
//! constraint is a sign constraint: `w_k = a + b k - sum_{j<k} (k - j) c_j`
//! with `c_j = (D^2 w)_j >= 0`, so the saved weights satisfy it exactly.
//!
//! Work per image is cached: pyramids and segmentations are computed once,
//! and the locations found by full searches are kept per image, so that
//! inner iterations search only those (exact over the cache) and a full
//! search over everything runs only to find new constraints or to prove
//! convergence.
//!
//! The structural SVM's parts are modules of their own: the examples and
//! their ground truth (`examples.rs`), the separation oracle
//! (`search.rs`), the cutting-plane solver's steps (`solver.rs`), the QP
//! (`qp.rs`) and the loss (`loss.rs`); [`train_joint`] puts them
//! together. The routes a user trains by are in [`routes`].

pub mod box_correction;
pub mod cache;
pub mod components;
mod examples;
pub mod ko8;
pub mod latent;
pub mod layout;
pub mod loss;
pub mod mesh;
pub mod mirror;
pub mod multiview;
pub mod photo_augment;
pub mod qp;
pub mod routes;
pub mod scales;
mod search;
mod solver;
pub mod views;

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::data::{load_image, DatasetError, Sample};
use crate::model::{Model, ModelError, ModelMeta, ViewMeta, FORMAT_VERSION};
use crate::vision::detect::{DetectParams, Detector, Location};
use crate::vision::energy::PairwiseMode;
use crate::vision::hog::CELL_SIZE;
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::pyramid::PyramidParams;
use crate::vision::segment::SegmentParams;
use crate::vision::shape::{learn_colours, ShapeModel};
use crate::vision::VisionError;

use loss::LossKind;
use qp::Plane;

pub use crate::progress::progress_bar;
pub use cache::PyramidCache;
pub use layout::{exact_concave, Layout, PLAIN_HOG_PRIOR};
pub use scales::small_object_scales;

/// Errors of training.
#[derive(Debug, Error)]
pub enum TrainError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error(transparent)]
    Vision(#[from] VisionError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("QP solver: {0}")]
    Qp(String),
    #[error("no usable training data: {0}")]
    NoData(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Most background regions per positive photograph
/// ([`TrainParams::background_regions`]).
pub const MAX_BACKGROUND_REGIONS: usize = 16;

/// Every setting of training, grouped by concern; saved in the model's
/// provenance (flat: a group's fields sit beside the others in the JSON,
/// as in a `--config` file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainParams {
    /// Template size: the median training box times this, in cells of 8 px
    /// (so the median object is found on the pyramid level of this scale).
    pub template_scale: f64,
    /// Template size in cells `[rows, cols]`, overriding `template_scale`.
    pub template: Option<[usize; 2]>,
    pub pyramid: PyramidParams,
    pub segmentation: SegmentParams,
    /// Largest fraction of a box's cells outside the image.
    pub max_truncation: f64,
    /// is what 5-fold cross-validation on CMU_KO8 chose with C = 10
    /// (`sdhop-train cv`): the highest threshold that keeps the best figures.
    /// Held-out objects often score below the margin, so thresholds at 0 or
    /// above lose recall.
    pub threshold: f64,
    /// The energy the model scores with, and the loss it is trained on.
    #[serde(flatten)]
    pub energy: EnergyParams,
    /// The cutting-plane solver's regularisation, passes and searches.
    #[serde(flatten)]
    pub solver: SolverParams,
    /// How the training examples are made and weighted.
    #[serde(flatten)]
    pub examples: ExampleParams,
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            template_scale: 0.8,
            template: None,
            pyramid: PyramidParams::default(),
            segmentation: SegmentParams::default(),
            max_truncation: 0.5,
            threshold: -0.75,
            energy: EnergyParams::default(),
            solver: SolverParams::default(),
            examples: ExampleParams::default(),
        }
    }
}

/// The energy a model scores with (paper eq. 1) and the loss it is
/// trained on (eq. 3), with the ablations that turn parts of them off.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EnergyParams {
    /// Standard clique size `K` of the higher-order potentials.
    pub k: usize,
    pub loss: LossKind,
    /// Weight of the loss's visibility (Hamming) term against its box
    /// term (1: eq. (3) of the paper).
    pub seg_weight: f64,
    /// Train the higher-order potentials (false: the no-HOP ablation).
    pub hop: bool,
    /// Train the pairwise term (false: no pairwise ablation).
    pub pairwise: bool,
    /// Occlusion reasoning (false: the plain-HOG ablation: every cell is
    /// visible in training and detection, the occlusion filter and the
    /// visibility prior are unused and the loss compares boxes only).
    pub occlusion: bool,
    /// Which neighbour pairs carry the pairwise term: every 4-connected
    /// pair (SD-HOP) or only pairs along image edges (the Gao et al. 2011
    /// ablation).
    pub pair_mode: PairwiseMode,
}

impl Default for EnergyParams {
    fn default() -> Self {
        Self {
            k: 4,
            loss: LossKind::SdHop,
            seg_weight: 1.0,
            hop: true,
            pairwise: true,
            occlusion: true,
            pair_mode: PairwiseMode::Grid,
        }
    }
}

/// The 1-slack cutting-plane solver: its regularisation, stopping
/// tolerance, passes, mining searches and caches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SolverParams {
    /// Regularisation constant `C` of the 1-slack QP.
    pub c: f64,
    /// Stop when a full search finds no constraint violated by more than
    /// this beyond the working set's slack.
    pub epsilon: f64,
    /// Full searches over every location of every image, at most.
    pub max_passes: usize,
    /// at most (fewer when the cache stops yielding violated constraints).
    pub max_inner: usize,
    /// The first `mining_passes` full searches are hard-example mining:
    /// each image's search reaches at most `mining_budget` locations (in
    /// order of the stage-1 bound) instead of every one whose bound says
    /// it might win. A mining search that finds no violated constraint is
    /// followed by an exact one, which decides convergence (when it finds
    /// violations, mining resumes), or, without `exact_check`, ends the
    /// training itself. The default mines none; the mesh
    /// route mines: there an exact search reached about 9,600 locations
    /// per example, nearly all cut off before their min-cut finished, and
    /// where it beat the example's cached best it did so among the first
    /// 256 in 97% of the first round's searches (LM-O duck) and never
    /// beyond 4,096.
    pub mining_passes: usize,
    pub mining_budget: usize,
    /// Whether a mining search that finds nothing is checked by an exact
    /// one (true), or ends the training as converged as far as the budget
    /// sees (false: the mesh route, where an exact search cost as much as
    /// 7-10 mining ones, and on the LM-O duck each round's first exact
    /// check found nothing beyond the tolerance).
    pub exact_check: bool,
    /// Most locations kept in an image's cache (the least recently most
    /// violated leave first).
    pub cache_size: usize,
}

impl Default for SolverParams {
    fn default() -> Self {
        Self {
            c: 10.0,
            epsilon: 0.01,
            max_passes: 5,
            max_inner: 30,
            mining_passes: 0,
            mining_budget: 300,
            exact_check: true,
            cache_size: 12,
        }
    }
}

/// How the training examples are made and weighted: seeds, shares of
/// the objective, background regions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ExampleParams {
    /// Random locations per image that seed the cache (initialisation).
    pub init_locations: usize,
    /// Share of the objective carried by the positive images (the negatives
    /// carry the rest).
    pub positive_share: f64,
    /// Share of the positives' weight carried by the box-only positives
    /// (photographs whose visibility training imputes) when there are also
    /// positives with known masks (renders, masked photographs); `None`:
    /// every positive weighs the same.
    pub box_share: Option<f64>,
    /// overlapping none of the photograph's instances by IoU 0.3 or more;
    /// [`loss::Background`]): the photograph's own clutter as hard
    /// negatives, where the 1-slack loss of the positive itself weighs only
    /// its single most violated window. 0: none.
    pub background_regions: usize,
    /// Renders drawn over the training photographs: they give no
    /// background examples (their regions would repeat the photographs'
    /// own). Not saved: the provenance names the route that set it.
    #[serde(skip)]
    pub renders: Arc<HashSet<PathBuf>>,
    pub seed: u64,
}

impl Default for ExampleParams {
    fn default() -> Self {
        Self {
            init_locations: 30,
            positive_share: 0.5,
            box_share: None,
            background_regions: 0,
            renders: Arc::default(),
            seed: 1,
        }
    }
}

impl TrainParams {
    /// Checks the settings before any work.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::NoData(format!("invalid setting: {m}")));
        if !self.solver.c.is_finite() || self.solver.c <= 0.0 {
            return bad(format!("C must be > 0, got {}", self.solver.c));
        }
        if self.energy.k < 1 {
            return bad("K must be >= 1".into());
        }
        if self.template_scale.is_nan() || self.template_scale <= 0.0 || self.template_scale > 4.0 {
            return bad(format!(
                "template_scale must be in (0, 4], got {}",
                self.template_scale
            ));
        }
        if self.solver.epsilon.is_nan() || self.solver.epsilon <= 0.0 {
            return bad("epsilon must be > 0".into());
        }
        if !self.energy.seg_weight.is_finite() || self.energy.seg_weight < 0.0 {
            return bad(format!(
                "seg_weight must be >= 0, got {}",
                self.energy.seg_weight
            ));
        }
        if !(0.0..=1.0).contains(&self.examples.positive_share) {
            return bad("positive_share must be in [0, 1]".into());
        }
        if self
            .examples
            .box_share
            .is_some_and(|b| !(0.0..1.0).contains(&b) || b == 0.0)
        {
            return bad("box_share must be in (0, 1)".into());
        }
        if !(0.0..1.0).contains(&self.max_truncation) || !self.threshold.is_finite() {
            return bad("max_truncation must be in [0, 1) and the threshold finite".into());
        }
        if self.examples.background_regions > MAX_BACKGROUND_REGIONS {
            return bad(format!(
                "background_regions must be at most {MAX_BACKGROUND_REGIONS}, got {}",
                self.examples.background_regions
            ));
        }
        self.pyramid.validate()?;
        self.segmentation.validate()?;
        Ok(())
    }
}

/// What one cutting-plane round found.
struct Round {
    plane: Plane,
    /// Mean loss of the predictions (argmin of the energy) is not computed
    /// here; this is the weighted mean loss of the most violated outputs.
    loss: f64,
    /// Min-cuts the round ran.
    min_cuts: usize,
}

/// The most violated output of one example.
struct Found {
    /// Its weighted share of the plane: `w_i (Psi(y_hat) - Psi(y))`.
    g: Vec<f64>,
    /// Its weighted loss.
    b: f64,
    loss: f64,
    location: Option<Location>,
    min_cuts: usize,
    /// Further hard locations met by the search.
    extra: Vec<Location>,
}

/// Progress figures of one training run.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TrainReport {
    pub passes: usize,
    pub iterations: usize,
    pub planes: usize,
    pub converged: bool,
    /// Full searches that were exact (no min-cut budget).
    pub exact_passes: usize,
    /// Primal objective `1/2 |w|^2 + C xi` after each QP.
    pub objective: Vec<f64>,
    /// Slack of the most violated constraint of each full search.
    pub full_violation: Vec<f64>,
    /// Min-cuts run by each full search (all images).
    pub full_min_cuts: Vec<usize>,
    pub seconds: f64,
    /// Time in full searches, cached searches and QP solves.
    pub full_seconds: f64,
    pub cached_seconds: f64,
    pub qp_seconds: f64,
    pub positives: usize,
    pub negatives: usize,
    /// Of the negatives, the background examples of positive photographs.
    pub background_negatives: usize,
    pub skipped: Vec<String>,
}

/// Trains one model for `label` from positives (samples annotated with
/// `label`) and negatives (samples without, or annotated otherwise).
pub fn train_model(
    label: &str,
    samples: &[&Sample],
    cache: &PyramidCache,
    params: &TrainParams,
    progress: &ProgressBar,
) -> Result<(Model, TrainReport), TrainError> {
    train_joint(label, &[label], samples, cache, params, progress)
}

/// Trains one model named `name` for several objects jointly (the paper's
/// compatible components): the samples annotated with any of `labels` are
/// the positives, their annotations' viewpoints index the model's
/// components across all objects (each component belongs to one object),
/// and a box of another object's component is a false positive on every
/// image (loss 1), so the objects' scores are trained to be comparable.
/// Samples without an annotation of `labels` are negatives.
pub fn train_joint(
    name: &str,
    labels: &[&str],
    samples: &[&Sample],
    cache: &PyramidCache,
    params: &TrainParams,
    progress: &ProgressBar,
) -> Result<(Model, TrainReport), TrainError> {
    let start = Instant::now();
    let mut report = TrainReport::default();
    let ours = |s: &Sample| -> bool {
        s.annotation
            .as_ref()
            .is_some_and(|a| labels.contains(&a.label.as_str()))
    };
    let positives: Vec<&Sample> = samples.iter().copied().filter(|s| ours(s)).collect();
    let negatives: Vec<&Sample> = samples.iter().copied().filter(|s| !ours(s)).collect();
    let label = labels.join("+");
    if positives.is_empty() {
        return Err(TrainError::NoData(format!("no positive image of {label}")));
    }
    let view_labels = component_labels(&positives, &label)?;
    // Each object's components, once per object (a joint model only).
    let views_of: HashMap<&str, Arc<Vec<bool>>> = labels
        .iter()
        .map(|&l| (l, Arc::new(view_labels.iter().map(|v| v == l).collect())))
        .collect();
    let shapes: Vec<(usize, usize)> = (0..view_labels.len())
        .map(|v| template_shape(&positives, v, params))
        .collect::<Result<_, _>>()?;
    let mut layout = Layout::new(shapes.clone(), params.energy.k, params.energy.pair_mode);
    layout.occlusion = params.energy.occlusion;
    cache.fill(samples, &params.pyramid, &params.segmentation, progress)?;
    // Ground truth of every positive: the location with the best box IoU.
    let zero = layout.to_views(&vec![0.0; layout.len]);
    let det0 = Detector::new(&zero)?;
    let cx = examples::ExampleContext {
        label: &label,
        labels,
        layout: &layout,
        det0: &det0,
        views_of: &views_of,
        cache,
        params,
    };
    let mut examples = examples::build_examples(&cx, &positives, &negatives, &mut report)?;
    let w = solver::cutting_plane(
        &layout,
        &mut examples,
        params,
        &label,
        progress,
        &mut report,
    )?;
    report.seconds = start.elapsed().as_secs_f64();
    examples::remember_hard(&examples, cache);
    let meta = model_meta(name, &shapes, &view_labels, params, &report)?;
    let model = Model::new(meta, layout.to_views(&w))?;
    let shapes = learn_shapes(&model, samples, Some(cache));
    Ok((model.with_shapes(shapes)?, report))
}

/// Each component's object: the label of its annotations (one object per
/// component, every component with a positive).
fn component_labels(positives: &[&Sample], label: &str) -> Result<Vec<String>, TrainError> {
    let n_views = positives
        .iter()
        .filter_map(|s| s.annotation.as_ref().map(|a| a.viewpoint + 1))
        .max()
        .unwrap_or(1);
    let mut view_labels: Vec<Option<&str>> = vec![None; n_views];
    for a in positives.iter().filter_map(|s| s.annotation.as_ref()) {
        match view_labels[a.viewpoint] {
            None => view_labels[a.viewpoint] = Some(a.label.as_str()),
            Some(l) if l != a.label => {
                return Err(TrainError::NoData(format!(
                    "viewpoint {} is annotated as {l} and as {}: a component belongs to one object",
                    a.viewpoint, a.label
                )))
            }
            Some(_) => {}
        }
    }
    view_labels
        .iter()
        .enumerate()
        .map(|(v, l)| {
            l.map(str::to_string).ok_or_else(|| {
                TrainError::NoData(format!("viewpoint {v} of {label}: no positive image"))
            })
        })
        .collect()
}

/// The metadata of a model trained with `params`: its components' shapes
/// and labels, the detection settings and the training's provenance.
fn model_meta(
    name: &str,
    shapes: &[(usize, usize)],
    view_labels: &[String],
    params: &TrainParams,
    report: &TrainReport,
) -> Result<ModelMeta, TrainError> {
    Ok(ModelMeta {
        format_version: FORMAT_VERSION,
        name: name.to_string(),
        cell_size: CELL_SIZE,
        hop_k: params.energy.k,
        pairwise: params.energy.pair_mode,
        pyramid: params.pyramid,
        cells: params.pyramid.features.fingerprint()?,
        segmentation: params.segmentation,
        detection: DetectParams {
            threshold: params.threshold,
            max_truncation: params.max_truncation,
            refine: crate::vision::refine::RefineParams::for_cells(params.pyramid.features),
            ..DetectParams::default()
        },
        viewpoints: shapes
            .iter()
            .zip(view_labels)
            .map(|(&(rows, cols), label)| ViewMeta {
                label: label.clone(),
                rows,
                cols,
                direction: None,
                rotations: Vec::new(),
                views: Vec::new(),
            })
            .collect(),
        box_correction: None,
        segmenter: None,
        provenance: serde_json::json!({
            "source": "sdhop-train: 1-slack structural SVM (cutting plane, clarabel dual QP)",
            "params": params,
            "report": {
                "passes": report.passes,
                "iterations": report.iterations,
                "converged": report.converged,
                "positives": report.positives,
                "negatives": report.negatives,
                "seconds": report.seconds,
            },
        }),
    })
}

/// Each viewpoint's pixel shape model ([`ShapeModel`]) from the visible
/// masks and full-extent boxes of the samples annotated with its label and
/// viewpoint, with the object's colours from those samples' images
/// (`None` for a viewpoint without any; an image that cannot be read
/// adds no colours). The images come from `cache`'s pyramids where it has
/// them, else from their files.
pub fn learn_shapes(
    model: &Model,
    samples: &[&Sample],
    cache: Option<&PyramidCache>,
) -> Vec<Option<ShapeModel>> {
    (0..model.views.len())
        .map(|a| {
            let label = &model.meta.viewpoints[a].label;
            let (w, h) = model.shape_size(a);
            let mut mine: Vec<&Sample> = samples
                .iter()
                .copied()
                .filter(|s| {
                    s.annotation
                        .as_ref()
                        .is_some_and(|an| &an.label == label && an.viewpoint == a)
                })
                .collect();
            // Imputed masks (box-only annotations) only where no mask is
            // known.
            if mine
                .iter()
                .any(|s| s.annotation.as_ref().is_some_and(|an| an.mask_known))
            {
                mine.retain(|s| s.annotation.as_ref().is_some_and(|an| an.mask_known));
            }
            let mut shape = ShapeModel::learn(
                w,
                h,
                mine.iter()
                    .filter_map(|s| s.annotation.as_ref())
                    .map(|an| (&an.visible, an.bbox)),
            )?;
            let images: Vec<(Arc<ColorImage>, &Mask)> = mine
                .par_iter()
                .filter_map(|s| {
                    let an = s.annotation.as_ref()?;
                    let img = match cache.and_then(|c| c.get(&s.image)) {
                        Some(p) if p.has_pixels() => p.image.clone(),
                        _ => Arc::new(load_image(&s.image).ok()?),
                    };
                    Some((img, &an.visible))
                })
                .collect();
            shape.colours = learn_colours(images.iter().map(|(i, m)| (&**i, *m)));
            Some(shape)
        })
        .collect()
}

/// Template `(rows, cols)` of a viewpoint from its training boxes.
fn template_shape(
    positives: &[&Sample],
    view: usize,
    params: &TrainParams,
) -> Result<(usize, usize), TrainError> {
    if let Some([r, c]) = params.template {
        if r == 0 || c == 0 {
            return Err(TrainError::NoData("template size must be positive".into()));
        }
        return Ok((r, c));
    }
    let mut ws: Vec<f64> = Vec::new();
    let mut hs: Vec<f64> = Vec::new();
    for a in positives.iter().filter_map(|s| s.annotation.as_ref()) {
        if a.viewpoint == view {
            ws.push(a.bbox.2);
            hs.push(a.bbox.3);
        }
    }
    if ws.is_empty() {
        return Err(TrainError::NoData(format!("viewpoint {view} has no box")));
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let s = params.template_scale / CELL_SIZE as f64;
    let cols = (median(&mut ws) * s).round().max(1.0) as usize;
    let rows = (median(&mut hs) * s).round().max(1.0) as usize;
    Ok((rows, cols))
}

#[cfg(test)]
mod tests;
