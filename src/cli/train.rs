//! `sdhop-train train`: one model per object (CMU_KO8 or a COCO-style
//! file), saved as weights files.

use super::*;
use crate::train::ko8::Source;
use crate::train::multiview::MultiViewParams;
use crate::train::routes::coco::{train_coco, CocoRoute};
use crate::train::routes::ko8::{train_ko8, Ko8Route};
use crate::train::routes::photos::{COCO_BOX_FOLDS, COCO_BOX_FOLD_ROUNDS, COCO_MIRROR};
use crate::train::views::{AugmentParams, OccluderKinds};

#[derive(clap::Args)]
pub(crate) struct TrainArgs {
    /// CMU_KO8 root (with single/ and negative/).
    #[arg(long, required_unless_present = "coco")]
    pub(crate) ko8: Option<PathBuf>,
    /// COCO-style JSON of your own objects (see docs/training.md).
    #[arg(long, conflicts_with = "ko8", requires_all = ["images", "category"])]
    pub(crate) coco: Option<PathBuf>,
    /// Folder the COCO file names are relative to.
    #[arg(long)]
    pub(crate) images: Option<PathBuf>,
    /// COCO category to train (repeat for several).
    #[arg(long)]
    pub(crate) category: Vec<String>,
    /// Objects to train (CMU_KO8; default all eight).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
    /// Folder for the weights files (one per object, named after it).
    #[arg(long, default_value = "models")]
    pub(crate) out: PathBuf,
    /// Training sources (CMU_KO8), comma-separated: `single` (masked
    /// occluded photographs of one viewpoint), `views` (the multi-view
    /// part's unoccluded views, grouped into components and augmented with
    /// occluders), `boxes` (its box-only photographs; visibility and
    /// component latent). With --coco: `views` treats the masked
    /// annotations as unoccluded views to augment, `boxes` uses box-only
    /// annotations (no segmentation). Default: `single,views,boxes` with
    /// --ko8 (`single` where the multi-view part is absent), `single,boxes`
    /// with --coco.
    #[arg(long, value_delimiter = ',', value_parser = Source::parse)]
    pub(crate) sources: Option<Vec<Source>>,
    /// View components per object (the views are grouped by appearance and
    /// aspect ratio; capped at the number of views). With box-only
    /// photographs alone (no views, no masks) the boxes are grouped by
    /// aspect ratio into components of equal size and the latent rounds
    /// reassign them. Several numbers,
    /// comma-separated (e.g. `1,2,3`), are chosen among by cross-validation
    /// over the views (`--cv-folds` folds: each trains from the other
    /// views and is scored on occluded photographs made from its own); the
    /// figures are saved in the model's provenance.
    #[arg(long, value_delimiter = ',', default_value = "1")]
    pub(crate) components: Vec<usize>,
    /// Folds of the cross-validation that chooses among several
    /// `--components`.
    #[arg(long, default_value_t = MultiViewParams::default().cv_folds)]
    pub(crate) cv_folds: usize,
    /// Photographs made from each view (plus as many mirrored).
    #[arg(long, default_value_t = AugmentParams::default().per_view)]
    pub(crate) per_view: usize,
    /// Do not add mirrored views (for objects without a plane of
    /// symmetry).
    #[arg(long)]
    pub(crate) no_mirror: bool,
    /// Occluders pasted over the view photographs, as weights
    /// OBJECTS,PATCHES,SMOOTH (other objects' masked crops, background
    /// patches, smooth colours).
    #[arg(long, value_name = "O,P,S")]
    pub(crate) occluders: Option<String>,
    /// Share of the view photographs whose surroundings are replaced by a
    /// crop of a negative scene (the object pasted onto clutter).
    #[arg(long, default_value_t = AugmentParams::default().backdrop)]
    pub(crate) backdrop: f64,
    /// Range of an occluder's depth into the box, as a share of the box
    /// (MIN,MAX).
    #[arg(long, value_name = "MIN,MAX")]
    pub(crate) occlusion: Option<String>,
    /// Share of the view photographs with an occluder.
    #[arg(long, default_value_t = AugmentParams::default().occluded_share)]
    pub(crate) occluded_share: f64,
    /// Range of the factor on a view's size in its crops (MIN,MAX; drawn
    /// uniformly; default 0.9,1.1).
    #[arg(long, value_name = "MIN,MAX")]
    pub(crate) view_scale: Option<String>,
    /// Use only the first N box-only photographs of each object (sorted
    /// by name; default all), e.g. to score the others with `eval --part
    /// multiple --skip-first N`.
    #[arg(long)]
    pub(crate) boxes_first: Option<usize>,
    /// Leave out fold `K` of `N` of each object's box-only photographs
    /// (`K/N`, K from 0: the K-th of N runs of consecutive photographs,
    /// sorted by name): the fold models whose held-out photographs `join
    /// --check-folds` scores.
    #[arg(long, value_parser = parse_box_fold)]
    pub(crate) box_fold: Option<(usize, usize)>,
    /// CCCP rounds of the box-only photographs (impute, retrain).
    #[arg(long, default_value_t = MultiViewParams::default().latent_rounds)]
    pub(crate) latent_rounds: usize,
    /// Negative scenes for --coco (a folder of images without the object).
    #[arg(long, requires = "coco")]
    pub(crate) negatives: Option<PathBuf>,
    /// With --coco: folds of the cross-validation over the training
    /// photographs that fits each model's box correction (the reported box
    /// rescaled and moved as held-out photographs showed; 0: the template's
    /// window as it is). Each fold trains one more model.
    #[arg(long, default_value_t = COCO_BOX_FOLDS, requires = "coco")]
    pub(crate) box_folds: usize,
    /// With --coco and box-only photographs: CCCP rounds of each box
    /// correction fold's training. The folds start from the visibility and
    /// components the full training imputed to the box-only photographs,
    /// so 0 (the default) trains each fold once with them; more re-impute
    /// from the fold's own model.
    #[arg(long, default_value_t = COCO_BOX_FOLD_ROUNDS, requires = "coco")]
    pub(crate) box_fold_rounds: usize,
    /// With --coco: each annotated photograph also trains as its mirror
    /// image (box and mask mirrored; with `views` among the sources, only
    /// the box-only photographs): `--mirror-photos true`. Twice the
    /// photographs, about three times the training time; measured in
    /// docs/training.md.
    #[arg(long, default_value_t = COCO_MIRROR, action = clap::ArgAction::Set, requires = "coco")]
    pub(crate) mirror_photos: bool,
    /// Cross-validation figures (JSON written by `cv`) to store in the
    /// models' metadata.
    #[arg(long)]
    pub(crate) cv_report: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) settings: TrainSettings,
}

/// `K/N` of `--box-fold`.
fn parse_box_fold(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("{s:?}: expected K/N with 0 <= K < N, N >= 2 (e.g. 0/2)");
    let (k, n) = s.split_once('/').ok_or_else(bad)?;
    let (k, n): (usize, usize) = (
        k.trim().parse().map_err(|_| bad())?,
        n.trim().parse().map_err(|_| bad())?,
    );
    if n < 2 || k >= n {
        return Err(bad());
    }
    Ok((k, n))
}

pub(crate) fn run_train(args: &TrainArgs) -> Result<(), Failure> {
    std::fs::create_dir_all(&args.out)
        .map_err(|e| Failure::io(format!("{}: {e}", args.out.display())))?;
    let cv = match &args.cv_report {
        Some(p) => Some(read_json(p)?),
        None => None,
    };
    let mv = args.multiview()?;
    let trained = match (&args.coco, &args.ko8) {
        (Some(coco), _) => {
            let route = CocoRoute {
                coco: coco.clone(),
                images: args.images.clone().unwrap_or_default(),
                categories: args.category.clone(),
                negatives: args.negatives.clone(),
                sources: args.sources.clone(),
                mirror_photos: args.mirror_photos,
                box_folds: args.box_folds,
                box_fold_rounds: args.box_fold_rounds,
            };
            train_coco(&route, &args.settings, &mv)?
        }
        (None, Some(root)) => {
            let route = Ko8Route {
                root: root.clone(),
                objects: args.objects.clone(),
                sources: args.sources.clone(),
                box_fold: args.box_fold,
                boxes_first: args.boxes_first,
            };
            train_ko8(&route, &args.settings, &mv)?
        }
        (None, None) => return Err(Failure::input("--ko8 or --coco is required")),
    };
    for (mut model, report) in trained {
        if let Some(cv) = &cv {
            add_cv_figures(&mut model, cv);
        }
        let path = args.out.join(format!("{}.safetensors", model.meta.name));
        model.save(&path).map_err(Failure::io)?;
        eprintln!(
            "{}: full-search violations {:?}, min-cuts {:?}",
            model.meta.name, report.full_violation, report.full_min_cuts
        );
        println!(
            "{:10} {} components, {}x{} cells, {} positives, {} negatives, {} passes, {} iterations, converged {}, {:.1} s (full {:.1}, cached {:.1}, qp {:.1}) -> {}",
            model.meta.name,
            model.views.len(),
            model.views[0].rows,
            model.views[0].cols,
            report.positives,
            report.negatives,
            report.passes,
            report.iterations,
            report.converged,
            report.seconds,
            report.full_seconds,
            report.cached_seconds,
            report.qp_seconds,
            path.display()
        );
    }
    Ok(())
}

impl TrainArgs {
    /// The multi-view settings from the flags.
    fn multiview(&self) -> Result<MultiViewParams, Failure> {
        let mut mv = MultiViewParams {
            components: self.components.first().copied().unwrap_or(1),
            choose_from: if self.components.len() > 1 {
                self.components.clone()
            } else {
                Vec::new()
            },
            cv_folds: self.cv_folds,
            latent_rounds: self.latent_rounds,
            ..MultiViewParams::default()
        };
        mv.augment.per_view = self.per_view;
        mv.augment.mirror = !self.no_mirror;
        mv.augment.backdrop = self.backdrop;
        mv.augment.occluded_share = self.occluded_share;
        if let Some(o) = &self.occlusion {
            let [lo, hi] = numbers(o, "--occlusion", "MIN,MAX")?;
            mv.augment.occlusion = [lo, hi];
        }
        if let Some(o) = &self.view_scale {
            mv.augment.scale = numbers(o, "--view-scale", "MIN,MAX")?;
        }
        if let Some(o) = &self.occluders {
            let [objects, patches, smooth] =
                numbers(o, "--occluders", "three weights OBJECTS,PATCHES,SMOOTH")?;
            mv.augment.kinds = OccluderKinds {
                objects,
                patches,
                smooth,
            };
        }
        mv.validate().map_err(Failure::input)?;
        Ok(mv)
    }
}

/// `N` comma-separated numbers of `flag`, or an error naming the `expected`
/// form.
fn numbers<const N: usize>(o: &str, flag: &str, expected: &str) -> Result<[f64; N], Failure> {
    let v: Vec<f64> = o
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| Failure::input(format!("{flag} {o:?}: {e}")))?;
    v.try_into()
        .map_err(|_| Failure::input(format!("{flag} {o:?}: expected {expected}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_folds_parse_as_k_of_n() {
        assert_eq!(parse_box_fold("1/2"), Ok((1, 2)));
        for bad in ["2/2", "0/1", "x/2", "1", "-1/2"] {
            assert!(parse_box_fold(bad).is_err(), "{bad}");
        }
    }
}
