//! The scales a training chooses from its boxes where the settings leave
//! them open: small objects get larger templates and upsampled levels,
//! and each feature kind wants its own share of the pyramid (the
//! `FeatureKind` methods below).

use super::TrainParams;
use crate::vision::cells::FeatureKind;
use crate::vision::hog::CELL_SIZE;

/// Cells of a small object's template along its longer side (see
/// [`small_object_scales`]); the mesh route's templates come out about as
/// large.
pub const SMALL_OBJECT_CELLS: f64 = 12.0;

/// Below this many cells on the side of a square of the median box's area
/// (at the default template scale) a template is too coarse to tell an
/// object (LM-O's 40-100 px objects came out 5x5 and found nothing; the
/// glue, 41x82 px, 4x8).
pub const SMALL_TEMPLATE_CELLS: f64 = 8.0;

/// Cells of a small object's learned-cell template across its shorter side,
/// at least: the LM-O glue (41x82 px), 12 cells along and 6 across, scored
/// 0.192 where 20x10 scored 0.408 (the backbone's cells see about 100
/// pixels each, so a thin object needs more of them across). With
/// background examples 16x8 scored 0.400 against 20x10's 0.244 (box-only,
/// no box correction; one run each, and the glue's figure moves by about
/// 0.1 between runs whose scales differ by 0.1%) and trained 3.5 times
/// faster (297 s against 1027 s): a min-cut over 200 cells costs several
/// times one over 128.
pub const LEARNED_CELLS_ACROSS: f64 = 8.0;

/// How far below the template scale the pyramid of a small object on
/// learned cells goes (a factor; HOG's is 4): an octave, objects up to
/// twice the median box. LM-O box-only (the other 150 photographs show
/// the glue at a median 1.35 times its training boxes, a tenth of them
/// over twice): ape 0.601, cat 0.651, duck 0.645, glue 0.350, mean 0.562,
/// against half an octave's 0.604, 0.643, 0.622, 0.340, mean 0.552 (one
/// run each; the training 10% longer).
pub const LEARNED_SCALES_BELOW: f64 = 2.0;

/// Pyramid levels per octave of small objects (see [`small_object_scales`]).
pub const SMALL_OBJECT_LEVELS_PER_OCTAVE: u32 = 5;

/// Template scale and pyramid for small objects: when the median box of
/// `sizes` (`(width, height)` in pixels) would make a template of under
/// [`SMALL_TEMPLATE_CELLS`] (on the side of a square of its area) at
/// `params`' template scale, the template is scaled up to
/// [`SMALL_OBJECT_CELLS`] along the median box's longer side (learned
/// cells: and at least [`LEARNED_CELLS_ACROSS`] across), and the
/// pyramid upsamples far enough that the smallest box is seen at the
/// template's size (up to 4x; learned cells: by its area, rounded to whole
/// levels above the template scale, HOG: by its longer side) and goes down
/// to a quarter of the template scale (objects four times the median;
/// learned cells: [`LEARNED_SCALES_BELOW`]), at 5 levels per octave;
/// `None`: the boxes are large enough for `params` as they are.
pub fn small_object_scales(sizes: &[(f64, f64)], params: &TrainParams) -> Option<TrainParams> {
    let good: Vec<(f64, f64)> = sizes
        .iter()
        .copied()
        .filter(|&(w, h)| w.is_finite() && h.is_finite() && w > 0.0 && h > 0.0)
        .collect();
    if good.is_empty() || params.template.is_some() {
        return None;
    }
    let median_of = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[v.len() / 2], v[0])
    };
    let (side, smallest_side) = median_of(good.iter().map(|&(w, h)| (w * h).sqrt()).collect());
    let (median, smallest) = median_of(good.iter().map(|&(w, h)| w.max(h)).collect());
    let (across, _) = median_of(good.iter().map(|&(w, h)| w.min(h)).collect());
    if side * params.template_scale / CELL_SIZE as f64 >= SMALL_TEMPLATE_CELLS {
        return None;
    }
    let kind = params.pyramid.features;
    let mut scale = SMALL_OBJECT_CELLS * CELL_SIZE as f64 / median;
    if let Some(cells) = kind.cells_across() {
        scale = scale.max(cells * CELL_SIZE as f64 / across);
    }
    let scale = scale.min(4.0);
    let max_scale = kind.small_object_max_scale(scale, (median, smallest), (side, smallest_side));
    let mut out = params.clone();
    out.template_scale = scale;
    out.pyramid.max_scale = max_scale as f32;
    // Learned cells go down an octave below the template scale, not two
    // as HOG: their large receptive fields make far smaller levels (the
    // objects seen four times the median) a source of false positives
    // (an earlier build: 0.426 down to a quarter; the LM-O glue down to a
    // quarter on this one: 0.346 against 0.350).
    out.pyramid.min_scale = match kind {
        FeatureKind::Hog => ((scale / kind.scales_below()) as f32).min(out.pyramid.min_scale),
        FeatureKind::Cnn => ((scale / kind.scales_below()) as f32).min(max_scale as f32),
    };
    out.pyramid.levels_per_octave = SMALL_OBJECT_LEVELS_PER_OCTAVE;
    Some(out)
}

/// The largest pyramid scale for learned cells: `scale * below` rounded to
/// a whole number of levels above the template's `scale` (levels are
/// counted down from the largest, 5 per octave), so that one level sits at
/// the template scale itself, and at most 4. The LM-O duck's largest scale
/// of 1.98 left its levels at 1.72 and 1.50 around its template's 1.60:
/// 0.599 AUC against 0.657 with a level at 1.60.
pub(super) fn anchored_max_scale(scale: f64, below: f64) -> f64 {
    let lpo = f64::from(SMALL_OBJECT_LEVELS_PER_OCTAVE);
    let mut levels = (below.max(1.0).log2() * lpo).round();
    while levels > 0.0 && scale * (levels / lpo).exp2() > 4.0 {
        levels -= 1.0;
    }
    (scale * (levels / lpo).exp2()).min(4.0).max(scale)
}

/// What scales each kind of cell wants for small objects.
impl FeatureKind {
    /// Cells a small object's template needs across its shorter side, at
    /// least: learned cells see about 100 pixels each
    /// ([`LEARNED_CELLS_ACROSS`]); HOG's cells need no such floor.
    pub fn cells_across(&self) -> Option<f64> {
        match self {
            FeatureKind::Hog => None,
            FeatureKind::Cnn => Some(LEARNED_CELLS_ACROSS),
        }
    }

    /// How far below the template scale a small object's pyramid goes (a
    /// factor): two octaves for HOG, [`LEARNED_SCALES_BELOW`] for learned
    /// cells, whose large receptive fields make far smaller levels a
    /// source of false positives.
    pub fn scales_below(&self) -> f64 {
        match self {
            FeatureKind::Hog => 4.0,
            FeatureKind::Cnn => LEARNED_SCALES_BELOW,
        }
    }

    /// The largest pyramid scale of a small object at template `scale`:
    /// HOG's brings the smallest box's longer side to the template's
    /// (`longer`: the median box's longer side and the smallest's);
    /// learned cells' the smallest box by its area (`area_side`: the
    /// sides of squares of the median's and the smallest's areas),
    /// anchored so that a level sits at the template scale. The LM-O
    /// glue's 44x40 box, a bottle seen from above, asked for 3.64 by its
    /// longer side against 2.66 by its area: twice the pixels to search,
    /// the training over 50 min.
    pub fn small_object_max_scale(
        &self,
        scale: f64,
        longer: (f64, f64),
        area_side: (f64, f64),
    ) -> f64 {
        match self {
            FeatureKind::Hog => (scale * longer.0 / longer.1).clamp(scale, 4.0),
            FeatureKind::Cnn => anchored_max_scale(scale, area_side.0 / area_side.1),
        }
    }
}
