//! The training settings every route shares, as the user gave them: a
//! `--config` JSON file of [`TrainParams`], then each flag over it. A
//! field left `None` is the route's to decide (its feature kind, its
//! scales, its passes), which is why the routes take these settings and
//! not the resolved parameters alone.

use super::RouteError;
use crate::train::ko8::NegativeSet;
use crate::train::loss::LossKind;
use crate::train::photo_augment::PhotoAugment;
use crate::train::TrainParams;
use crate::vision::cells::FeatureKind;
use crate::vision::energy::PairwiseMode;
use std::path::PathBuf;

/// Images of each other CMU_KO8 object used as negatives (`--other-negatives`).
pub const OTHER_NEGATIVES: usize = 10;

/// Negative scenes used (`--negative-scenes`).
pub const NEGATIVE_SCENES: usize = 100;

/// Every training setting; flags override the `--config` JSON file.
#[derive(clap::Args, Clone, Debug)]
pub struct TrainSettings {
    /// JSON file with any of the training settings (see `TrainParams` in
    /// the docs: c, k, template_scale, template, pyramid, segmentation,
    /// max_truncation, epsilon, max_passes, max_inner, init_locations,
    /// mining_passes, mining_budget, cache_size, positive_share, loss, seg_weight, hop,
    /// pairwise, occlusion, pair_mode, seed, background_regions, threshold).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Regularisation constant C.
    #[arg(long)]
    pub c: Option<f64>,
    /// Standard clique size K of the higher-order potentials.
    #[arg(long)]
    pub k: Option<usize>,
    /// Template size as a fraction of the median training box.
    #[arg(long)]
    pub template_scale: Option<f64>,
    /// Template size in cells, ROWSxCOLS (overrides --template-scale).
    #[arg(long, value_parser = parse_template)]
    pub template: Option<[usize; 2]>,
    /// What a cell's vector is: `hog` (Felzenszwalb's HOG) or `cnn` (the
    /// pretrained EfficientNet-Lite0 backbone's cells, built in; see
    /// docs/training.md, "Learned cells"). Default: `cnn` for `train
    /// --coco` and `mesh`, `hog` for the CMU_KO8 routes (what won on the
    /// development data of each).
    #[arg(long, value_parser = FeatureKind::parse)]
    pub features: Option<FeatureKind>,
    /// Both kinds per object: also train each object's model on these
    /// cells (`hog` beside `--features cnn`), with the same settings, and
    /// keep it in the model's file as its segmenter: each detection is
    /// placed and segmented by the segmenter's best location whose box
    /// overlaps it by 0.5 or more (the score and box stay the model's).
    /// Learned cells find better and HOG segments better (docs/training.md,
    /// "Both kinds per object"). Training takes the segmenter's time too,
    /// and detection its pyramid and a local search per answered detection.
    #[arg(long, value_parser = FeatureKind::parse)]
    pub segmenter: Option<FeatureKind>,
    /// Pyramid levels per octave (default 10; learned cells on the
    /// CMU_KO8 routes `train --ko8` and `cv`: 5, which costs half: eight
    /// models 1.2x HOG's eight instead of 2x, for a few thousandths of
    /// cross-object AUC on the eight objects' folds; docs/training.md,
    /// "Fewer levels, trained so").
    #[arg(long)]
    pub levels_per_octave: Option<u32>,
    /// Every how many pyramid levels the cells are computed from pixels,
    /// the levels between resampled from the computed level above
    /// (Dollár's fast feature pyramids). Default 1: every level, exact.
    /// Learned cells at 5 scan 2.8x faster but lost 0.08 AUC on the
    /// scissors' folds (docs/training.md, "Learned cells").
    #[arg(long)]
    pub computed_every: Option<u32>,
    /// Smallest pyramid scale.
    #[arg(long)]
    pub min_scale: Option<f32>,
    /// Largest pyramid scale (above 1: upsampled levels for small objects).
    #[arg(long)]
    pub max_scale: Option<f32>,
    /// Felzenszwalb-Huttenlocher k (segment size preference).
    #[arg(long)]
    pub seg_k: Option<f32>,
    /// Stopping tolerance of the cutting-plane algorithm.
    #[arg(long)]
    pub epsilon: Option<f64>,
    /// Full searches over every location, at most.
    #[arg(long)]
    pub max_passes: Option<usize>,
    /// Iterations over cached locations per full search, at most.
    #[arg(long)]
    pub max_inner: Option<usize>,
    /// Locations per image, in order of their bound, that a hard-example
    /// mining search reaches (default 300; `mesh --photos`: 1024).
    #[arg(long)]
    pub mining_budget: Option<usize>,
    /// First full searches that mine hard examples with a budget instead of
    /// being exact; a mining search that finds nothing is followed by an
    /// exact one, which decides convergence (default 0: every full search
    /// is exact; `mesh --photos`: every pass mines).
    #[arg(long)]
    pub mining_passes: Option<usize>,
    /// `mesh --photos`: check a mining search that finds nothing by an
    /// exact one before the training ends (slower; by default the mining
    /// search decides there).
    #[arg(long)]
    pub exact_check: bool,
    /// Most locations cached per image between full searches.
    #[arg(long)]
    pub cache_size: Option<usize>,
    /// Random seed (initial locations).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Each positive photograph also trains as this many negative examples,
    /// one per region of a grid over it, away from its instances (its own
    /// clutter as hard negatives; 0: none). See docs/training.md.
    #[arg(long)]
    pub background_regions: Option<usize>,
    /// Loss: sd-hop (eq. 3) or gao (ablation).
    #[arg(long, value_enum)]
    pub loss: Option<LossKind>,
    /// Ablation: no higher-order potentials.
    #[arg(long)]
    pub no_hop: bool,
    /// Ablation: no pairwise term.
    #[arg(long)]
    pub no_pairwise: bool,
    /// Ablation: no occlusion reasoning (plain HOG templates: every cell
    /// visible, the loss compares boxes only).
    #[arg(long)]
    pub no_occlusion: bool,
    /// Ablation: pairwise terms only between neighbouring cells along an
    /// image edge, as Gao et al. 2011 (default: every 4-connected pair).
    #[arg(long)]
    pub edge_pairwise: bool,
    /// Detection threshold saved in the models (default -0.75; -1.0 for
    /// models trained without masked photographs, `train --sources` without
    /// `single`).
    #[arg(long, allow_negative_numbers = true)]
    pub threshold: Option<f64>,
    /// Images of each other object used as negatives.
    #[arg(long, default_value_t = OTHER_NEGATIVES)]
    pub other_negatives: usize,
    /// Negative scenes used (from negative/).
    #[arg(long, default_value_t = NEGATIVE_SCENES)]
    pub negative_scenes: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[command(flatten)]
    pub augment: AugmentSettings,
}

/// The photographs' routes' augmentation (`train --coco`, `mesh
/// --photos`): crops of every boxed object seen again at other sizes,
/// mirrored, jittered, pasted (docs/training.md, "Augmentation"). `None`:
/// the route's default ([`PhotoAugment`]).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct AugmentSettings {
    /// Crops made from each box, each a training photograph of its own
    /// (0: none).
    #[arg(long)]
    pub augment: Option<usize>,
    /// Range of the factor on the object's size, MIN,MAX (drawn
    /// log-uniformly; never below the smallest box).
    #[arg(long, value_parser = parse_range)]
    pub augment_scale: Option<[f64; 2]>,
    /// Surroundings kept around the box, as a fraction of its size.
    #[arg(long)]
    pub augment_margin: Option<f64>,
    /// Mirror half of the crops (`false` for objects without a plane of
    /// symmetry).
    #[arg(long, action = clap::ArgAction::Set)]
    pub augment_mirror: Option<bool>,
    /// Colour jitter: contrast and brightness within 1 +- J.
    #[arg(long)]
    pub augment_jitter: Option<f64>,
    /// Share of the crops blurred.
    #[arg(long)]
    pub augment_blur: Option<f64>,
    /// Share of the crops whose object is pasted onto another
    /// photograph's background.
    #[arg(long)]
    pub augment_paste: Option<f64>,
    /// Share of the crops with a pasted occluder over part of the object.
    #[arg(long)]
    pub augment_occluded: Option<f64>,
}

impl AugmentSettings {
    /// `base` with what the flags set.
    pub fn over(&self, base: &PhotoAugment) -> PhotoAugment {
        let mut p = base.clone();
        set(&mut p.per_box, self.augment);
        set(&mut p.scale, self.augment_scale);
        set(&mut p.margin, self.augment_margin);
        set(&mut p.mirror, self.augment_mirror);
        set(&mut p.jitter, self.augment_jitter);
        set(&mut p.blur, self.augment_blur);
        set(&mut p.paste, self.augment_paste);
        set(&mut p.occluded, self.augment_occluded);
        p
    }
}

/// `MIN,MAX` of `--augment-scale`.
pub fn parse_range(s: &str) -> Result<[f64; 2], String> {
    let bad = || format!("{s:?}: expected MIN,MAX (e.g. 0.6,1.8)");
    let (a, b) = s.split_once(',').ok_or_else(bad)?;
    let a: f64 = a.trim().parse().map_err(|_| bad())?;
    let b: f64 = b.trim().parse().map_err(|_| bad())?;
    if !(a.is_finite() && b.is_finite() && a <= b) {
        return Err(bad());
    }
    Ok([a, b])
}

impl TrainSettings {
    /// The settings: the `--config` file's, then the flags'. `features` is
    /// the route's feature kind, taken where neither names one.
    pub fn params(&self, features: FeatureKind) -> Result<(TrainParams, NegativeSet), RouteError> {
        let p = self.train_params(features)?;
        if let Some(t) = self.threads {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build_global()
                .map_err(RouteError::io)?;
        }
        let neg = NegativeSet {
            scenes: self.negative_scenes,
            per_other_object: self.other_negatives,
        };
        Ok((p, neg))
    }

    /// The training parameters of [`Self::params`].
    fn train_params(&self, features: FeatureKind) -> Result<TrainParams, RouteError> {
        let mut p = match &self.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .map_err(|e| RouteError::io(format!("{}: {e}", path.display())))?;
                let json: serde_json::Value = serde_json::from_str(&text)
                    .map_err(|e| RouteError::input(format!("{}: {e}", path.display())))?;
                let named = json.pointer("/pyramid/features").is_some();
                let mut p: TrainParams = serde_json::from_value(json)
                    .map_err(|e| RouteError::input(format!("{}: {e}", path.display())))?;
                if !named {
                    p.pyramid.features = features;
                }
                p
            }
            None => {
                let mut p = TrainParams::default();
                p.pyramid.features = features;
                p
            }
        };
        set(&mut p.solver.c, self.c);
        set(&mut p.energy.k, self.k);
        set(&mut p.template_scale, self.template_scale);
        if self.template.is_some() {
            p.template = self.template;
        }
        set(&mut p.pyramid.features, self.features);
        set(&mut p.pyramid.levels_per_octave, self.levels_per_octave);
        set(&mut p.pyramid.computed_every, self.computed_every);
        set(&mut p.pyramid.min_scale, self.min_scale);
        set(&mut p.pyramid.max_scale, self.max_scale);
        set(&mut p.segmentation.k, self.seg_k);
        set(&mut p.solver.epsilon, self.epsilon);
        set(&mut p.solver.max_passes, self.max_passes);
        set(&mut p.solver.max_inner, self.max_inner);
        set(&mut p.solver.mining_budget, self.mining_budget);
        set(&mut p.solver.mining_passes, self.mining_passes);
        set(&mut p.solver.cache_size, self.cache_size);
        set(&mut p.examples.seed, self.seed);
        set(&mut p.examples.background_regions, self.background_regions);
        set(&mut p.energy.loss, self.loss);
        set(&mut p.threshold, self.threshold);
        p.energy.hop &= !self.no_hop;
        p.energy.pairwise &= !self.no_pairwise;
        p.energy.occlusion &= !self.no_occlusion;
        if self.edge_pairwise {
            p.energy.pair_mode = PairwiseMode::Edges;
        }
        p.validate().map_err(RouteError::input)?;
        Ok(p)
    }
}

impl TrainSettings {
    /// Refuses `--segmenter` on a route that does not train segmenters.
    pub fn no_segmenter(&self, route: &str) -> Result<(), RouteError> {
        match self.segmenter {
            Some(_) => Err(RouteError::input(format!(
                "--segmenter: {route} does not train segmenters (train --ko8 and cv do); pair models trained apart with `sdhop-train pair MODELS SEGMENTERS --out DIR`"
            ))),
            None => Ok(()),
        }
    }

    /// The settings of the segmenters (`--segmenter`), where asked: those
    /// of [`Self::params`] on the segmenter's cells. A segmenter on the
    /// models' own cells (`main`) is refused.
    pub fn segmenter_params(&self, main: &TrainParams) -> Result<Option<TrainParams>, RouteError> {
        let Some(kind) = self.segmenter else {
            return Ok(None);
        };
        if kind == main.pyramid.features {
            return Err(RouteError::input(format!(
                "--segmenter {}: the models are trained on {} cells already; a segmenter uses the other kind (`--features cnn --segmenter hog`)",
                kind.name(),
                kind.name()
            )));
        }
        let mut p = self.train_params(kind)?;
        p.pyramid.features = kind;
        // Learned cells' pyramids resample levels (`--computed-every`);
        // the segmenter's cells are computed at every level.
        p.pyramid.computed_every = 1;
        p.validate().map_err(RouteError::input)?;
        Ok(Some(p))
    }
}

pub fn parse_template(s: &str) -> Result<[usize; 2], String> {
    let (r, c) = s.split_once('x').ok_or("expected ROWSxCOLS")?;
    let r: usize = r.parse().map_err(|_| "bad rows")?;
    let c: usize = c.parse().map_err(|_| "bad cols")?;
    Ok([r, c])
}

/// `*dst = v` where a value is given.
fn set<T>(dst: &mut T, v: Option<T>) {
    if let Some(v) = v {
        *dst = v;
    }
}

impl Default for TrainSettings {
    /// Nothing set: every parameter the route's or [`TrainParams`]'s.
    fn default() -> Self {
        Self {
            config: None,
            c: None,
            k: None,
            template_scale: None,
            template: None,
            features: None,
            segmenter: None,
            levels_per_octave: None,
            computed_every: None,
            min_scale: None,
            max_scale: None,
            seg_k: None,
            epsilon: None,
            max_passes: None,
            max_inner: None,
            mining_budget: None,
            mining_passes: None,
            exact_check: false,
            cache_size: None,
            seed: None,
            background_regions: None,
            loss: None,
            no_hop: false,
            no_pairwise: false,
            no_occlusion: false,
            edge_pairwise: false,
            threshold: None,
            other_negatives: OTHER_NEGATIVES,
            negative_scenes: NEGATIVE_SCENES,
            threads: None,
            augment: AugmentSettings::default(),
        }
    }
}

impl TrainSettings {
    /// Whether the user set any of the template's size or the pyramid's
    /// scales (a `--config` file counts): the routes that choose scales
    /// from the data leave them alone then.
    pub fn scales_set(&self) -> bool {
        self.config.is_some()
            || self.template_scale.is_some()
            || self.template.is_some()
            || self.levels_per_octave.is_some()
            || self.min_scale.is_some()
            || self.max_scale.is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pyramid_computes_every_level_unless_told() {
        let none = TrainSettings::default();
        for kind in [FeatureKind::Hog, FeatureKind::Cnn] {
            let (p, _) = none.params(kind).unwrap();
            assert_eq!(p.pyramid.computed_every, 1);
        }
        let fast = TrainSettings {
            computed_every: Some(5),
            ..TrainSettings::default()
        };
        let (cnn, _) = fast.params(FeatureKind::Cnn).unwrap();
        assert_eq!(cnn.pyramid.computed_every, 5);
    }
}
