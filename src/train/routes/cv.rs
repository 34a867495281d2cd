//! `sdhop-train cv`: k-fold cross-validation of training on CMU_KO8 (all
//! objects' photographs of a fold held out together), for each value of C
//! to compare; detection runs once at the lowest threshold, every
//! threshold above it is scored on the same detections, and the highest
//! that keeps (nearly) the best figures is chosen. The best C's report is
//! what `train --cv-report` stores in the models.

use super::{RouteError, TrainSettings};
use crate::data::Sample;
use crate::pipeline::DetectResponse;
use crate::train::ko8::{
    above_threshold, choose_threshold, cross_validate, score, selection_key, threshold_sweep,
    EvalDetect, Evaluation, FoldModels, Ko8Data, ThresholdScore,
};
use crate::train::PyramidCache;
use crate::vision::cells::FeatureKind;
use crate::vision::refine::PixelRefine;
use std::path::{Path, PathBuf};

/// The cells `cv` trains on unless the settings name others, as the
/// CMU_KO8 routes.
pub const CV_FEATURES: FeatureKind = super::ko8::KO8_FEATURES;

/// Step between the thresholds scored on one run's detections.
pub const THRESHOLD_STEP: f64 = 0.125;

/// What a cross-validation runs on and how it scores.
#[derive(Clone, Debug)]
pub struct CvSettings {
    /// CMU_KO8 root.
    pub ko8: PathBuf,
    /// Objects (empty: all eight).
    pub objects: Vec<String>,
    pub folds: usize,
    /// Only these folds (numbered from 0; empty: all).
    pub only_folds: Vec<usize>,
    /// Values of C to compare (empty: the settings' C).
    pub c_values: Vec<f64>,
    /// Save each fold's models in DIR/fold-F/ (DIR/c-C/fold-F/ with
    /// several C).
    pub save_models: Option<PathBuf>,
    /// Load each fold's models from there instead of training.
    pub load_models: Option<PathBuf>,
    /// Detections kept per image.
    pub max_detections: usize,
    /// Detection threshold of the run (default: the models').
    pub detect_threshold: Option<f64>,
    /// Pixel refinement of the masks, overriding the models'.
    pub pixel_refine: Option<PixelRefine>,
    /// How much of the selection figure a higher threshold may give up.
    pub threshold_tolerance: f64,
}

impl Default for CvSettings {
    fn default() -> Self {
        Self {
            ko8: PathBuf::new(),
            objects: Vec::new(),
            folds: 5,
            only_folds: Vec::new(),
            c_values: Vec::new(),
            save_models: None,
            load_models: None,
            max_detections: 20,
            detect_threshold: None,
            pixel_refine: None,
            threshold_tolerance: 0.002,
        }
    }
}

/// One value of C as cross-validated.
pub struct CResult {
    pub c: f64,
    pub seconds: f64,
    /// The threshold chosen, and every threshold's figures.
    pub threshold: f64,
    pub sweep: Vec<ThresholdScore>,
    /// The figures at the chosen threshold.
    pub evaluation: Evaluation,
}

/// The best C's cross-validation.
pub struct CvOutcome {
    /// What `train --cv-report` reads: folds, C, threshold, settings,
    /// figures, the training reports and the search over C.
    pub report: serde_json::Value,
    pub evaluation: Evaluation,
    /// The scored photographs' ids and their responses at the threshold.
    pub ids: Vec<String>,
    pub responses: Vec<DetectResponse>,
}

/// Cross-validates each value of C; `each` sees every C's result as it
/// comes (the CLI prints it).
pub fn cross_validate_route(
    s: &CvSettings,
    settings: &TrainSettings,
    mut each: impl FnMut(&CResult),
) -> Result<CvOutcome, RouteError> {
    let (params, neg) = settings.params(CV_FEATURES)?;
    let mut params = super::ko8::ko8_levels(params, settings);
    let seg_params = settings.segmenter_params(&params)?;
    if s.folds < 2 {
        return Err(RouteError::input("--folds must be at least 2"));
    }
    let data = Ko8Data::load(&s.ko8, &s.objects).map_err(RouteError::input)?;
    let cache = PyramidCache::default();
    let cs = if s.c_values.is_empty() {
        vec![params.solver.c]
    } else {
        s.c_values.clone()
    };
    let mut best: Option<(f64, CvOutcome)> = None;
    let mut summary = Vec::new();
    for &c in &cs {
        params.solver.c = c;
        let t = std::time::Instant::now();
        // With several values of C, each keeps its models in DIR/c-C.
        let per_c = |d: &Path| {
            if cs.len() > 1 {
                d.join(format!("c-{c}"))
            } else {
                d.to_path_buf()
            }
        };
        let (save, load) = (
            s.save_models.as_deref().map(per_c),
            s.load_models.as_deref().map(per_c),
        );
        let source = match (&save, &load) {
            (_, Some(d)) => FoldModels::Load(d),
            (Some(d), None) => FoldModels::TrainAndSave(d),
            (None, None) => FoldModels::Train,
        };
        let how = EvalDetect {
            max_detections: s.max_detections,
            threshold: s.detect_threshold,
            pixel: s.pixel_refine,
        };
        let cv = cross_validate(
            &data,
            s.folds,
            &s.only_folds,
            &params,
            &neg,
            &cache,
            how,
            source,
            seg_params.as_ref(),
        )
        .map_err(RouteError::input)?;
        let seconds = t.elapsed().as_secs_f64();
        // Thresholds at or above the one detection ran with, scored on the
        // same responses; the highest that keeps (nearly) the best figures.
        let floor = s.detect_threshold.unwrap_or(params.threshold);
        let grid: Vec<f64> = (0..)
            .map(|i| floor + THRESHOLD_STEP * f64::from(i))
            .take_while(|t| *t <= 1.0 + 1e-9)
            .collect();
        let refs: Vec<&Sample> = cv.images.iter().collect();
        let sweep = threshold_sweep(&data, &refs, &cv.responses, &grid);
        let chosen = choose_threshold(&sweep, s.threshold_tolerance).map_or(floor, |t| t.threshold);
        let responses = above_threshold(&cv.responses, chosen);
        let evaluation = score(&data, &refs, &responses);
        let result = CResult {
            c,
            seconds,
            threshold: chosen,
            sweep,
            evaluation,
        };
        each(&result);
        summary.push(serde_json::json!({
            "c": c,
            "threshold": chosen,
            "mean": result.evaluation.mean,
            "seconds": seconds,
            "threshold_search": result.sweep,
        }));
        let key = selection_key(&result.evaluation.mean);
        if best.as_ref().is_none_or(|b| key > b.0) {
            let report = serde_json::json!({
                "folds": s.folds,
                "only_folds": s.only_folds,
                "c": c,
                "threshold": chosen,
                "detect_threshold": floor,
                "max_detections": s.max_detections,
                "params": params,
                "segmenter": seg_params,
                "negatives": neg,
                "evaluation": strip_curves(&result.evaluation),
                "train_reports": cv.reports,
            });
            let outcome = CvOutcome {
                report,
                evaluation: result.evaluation,
                ids: cv.images.iter().map(|s| s.id.clone()).collect(),
                responses,
            };
            best = Some((key, outcome));
        }
    }
    let Some((_, mut outcome)) = best else {
        return Err(RouteError::input("no value of C to try"));
    };
    outcome.report["c_search"] = serde_json::Value::Array(summary);
    Ok(outcome)
}

/// An evaluation as a report stores it: every curve thinned to a tenth.
pub fn strip_curves(e: &Evaluation) -> serde_json::Value {
    let mut e = e.clone();
    for o in &mut e.objects {
        o.curve = thin(&o.curve);
        o.curve_cross = thin(&o.curve_cross);
    }
    serde_json::to_value(e).unwrap_or_default()
}

/// Every tenth point of a 1001-point curve (FPPI 0, 0.01, ..., 1).
fn thin(c: &[f64]) -> Vec<f64> {
    c.iter().step_by(10).copied().collect()
}
