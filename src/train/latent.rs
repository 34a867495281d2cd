//! Training from boxes alone (the paper's future work 1): a full-extent box
//! without a mask leaves the visibility labelling, and which component
//! explains the box, unknown. They are latent variables of a latent
//! structural SVM (Yu and Joachims 2009), trained by CCCP: impute them under
//! the current model (the location among those of the object's components
//! whose box overlaps the true one by at least `min_iou`, and its labelling,
//! with the least energy: one min-cut per location, exact), retrain with
//! the imputed labellings as truth, repeat.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::data::{box_mask, Sample};
use crate::model::Model;
use crate::vision::detect::{box_iou, Detector, Location, LossAugment};
use crate::vision::energy::BoxProblem;
use crate::vision::mask::{raw_mask, CellGrid, Mask};
use crate::vision::pyramid::FeaturePyramid;

use super::{PyramidCache, TrainError};

/// Plain inference: no loss added.
struct NoLoss;

impl LossAugment for NoLoss {
    fn max_loss(&self) -> f64 {
        0.0
    }
    fn augment(&self, _view: usize, _grid: &CellGrid, _problem: &mut BoxProblem) {}
}

/// The imputed latent variables of one box.
#[derive(Clone, Debug, PartialEq)]
pub struct Imputed {
    pub location: Location,
    /// The min-cut labelling of the location's cells.
    pub cells: Vec<bool>,
    pub energy: f64,
}

/// The locations of `views` whose box overlaps `bbox` by at least
/// `min_iou`.
pub fn box_locations(
    det: &Detector,
    pyr: &FeaturePyramid,
    bbox: (f64, f64, f64, f64),
    views: &[usize],
    max_truncation: f64,
    min_iou: f64,
) -> Vec<Location> {
    det.locations(pyr, max_truncation)
        .into_iter()
        .filter(|l| views.contains(&l.view))
        .filter(|l| box_iou(det.grid(pyr, l).pixel_box(), bbox) >= min_iou)
        .collect()
}

/// The least-energy location and labelling among `locations` (exact: a
/// min-cut at each); `None` when there is none.
pub fn impute(det: &Detector, pyr: &FeaturePyramid, locations: &[Location]) -> Option<Imputed> {
    let best = det.most_violated_among(pyr, locations, &NoLoss, f64::NEG_INFINITY)?;
    Some(Imputed {
        location: best.location,
        cells: best.cells,
        energy: -best.value,
    })
}

/// The least-energy location among `locations` with every cell visible
/// (the box's component only is latent); `None` when there is none.
pub fn impute_visible(
    det: &Detector,
    pyr: &FeaturePyramid,
    locations: &[Location],
) -> Option<Imputed> {
    locations
        .iter()
        .map(|l| {
            let (problem, _, _) = det.problem_at(pyr, l);
            let cells = vec![true; problem.len()];
            let energy = problem.energy(&cells);
            Imputed {
                location: *l,
                cells,
                energy,
            }
        })
        .min_by(|a, b| a.energy.total_cmp(&b.energy))
}

/// Figures of one imputation round.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ImputeRound {
    pub boxes: usize,
    /// Boxes no location of the object's components fits.
    pub unfit: usize,
    /// Boxes whose component changed since the last round.
    pub component_changes: usize,
    /// Mean share of the box's cells imputed visible.
    pub mean_visible: f64,
    /// Mean share of pixels whose imputed visibility changed.
    pub mean_pixel_change: f64,
}

/// Imputes every box-only sample's component and visible mask under
/// `model` (its components labelled `label`, from `first_component` on),
/// in place; samples with a known mask are left alone. Without
/// `latent_visibility` only the component is imputed and the whole box
/// stays visible.
pub fn impute_samples(
    model: &Model,
    label: &str,
    first_component: usize,
    samples: &mut [Sample],
    cache: &PyramidCache,
    min_iou: f64,
    latent_visibility: bool,
) -> Result<ImputeRound, TrainError> {
    use rayon::prelude::*;
    let det = Detector::new(&model.views)?;
    let views: Vec<usize> = model
        .meta
        .viewpoints
        .iter()
        .enumerate()
        .filter(|(i, v)| v.label == label && *i >= first_component)
        .map(|(i, _)| i)
        .collect();
    let max_trunc = model.meta.detection.max_truncation;
    let results: Vec<Option<(usize, Mask, f64)>> = samples
        .par_iter()
        .map(|s| {
            let a = s.annotation.as_ref().filter(|a| !a.mask_known)?;
            let pyr: Arc<FeaturePyramid> = cache.get(&s.image)?;
            let locs = box_locations(&det, &pyr, a.bbox, &views, max_trunc, min_iou);
            let imp = if latent_visibility {
                impute(&det, &pyr, &locs)?
            } else {
                impute_visible(&det, &pyr, &locs)?
            };
            let grid = det.grid(&pyr, &imp.location);
            let cells = raw_mask(&grid, &imp.cells, pyr.image_width, pyr.image_height);
            // Visible: the imputed visible cells within the true box.
            let within = box_mask(a.bbox, pyr.image_width, pyr.image_height);
            let mut visible = within.clone();
            if latent_visibility {
                for (v, c) in visible.data.iter_mut().zip(&cells.data) {
                    *v &= *c;
                }
            }
            let share =
                imp.cells.iter().filter(|&&c| c).count() as f64 / imp.cells.len().max(1) as f64;
            Some((imp.location.view, visible, share))
        })
        .collect();
    let mut round = ImputeRound::default();
    let mut vis_sum = 0.0;
    let mut change_sum = 0.0;
    for (s, r) in samples.iter_mut().zip(results) {
        let Some(a) = s.annotation.as_mut().filter(|a| !a.mask_known) else {
            continue;
        };
        round.boxes += 1;
        let Some((view, visible, share)) = r else {
            round.unfit += 1;
            continue;
        };
        if view != a.viewpoint {
            round.component_changes += 1;
        }
        let changed = visible
            .data
            .iter()
            .zip(&a.visible.data)
            .filter(|(x, y)| x != y)
            .count();
        change_sum += changed as f64 / a.visible.area().max(1) as f64;
        vis_sum += share;
        a.viewpoint = view;
        a.visible = if visible.area() > 0 {
            visible
        } else {
            a.visible.clone()
        };
    }
    let fit = (round.boxes - round.unfit).max(1) as f64;
    round.mean_visible = vis_sum / fit;
    round.mean_pixel_change = change_sum / fit;
    Ok(round)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::energy::ViewWeights;
    use crate::vision::image::ColorImage;
    use crate::vision::pyramid::PyramidParams;
    use crate::vision::rng::SplitMix64;
    use crate::vision::segment::SegmentParams;
    use std::path::PathBuf;

    /// A 96x80 image of noise with a 32x32 block of stripes at (x, y):
    /// vertical or horizontal, 4 px wide.
    fn striped(vertical: bool, x0: usize, y0: usize, seed: u64) -> (ColorImage, Mask) {
        let (w, h) = (96, 80);
        let mut rng = SplitMix64::new(seed);
        let mut data = vec![0.0f32; w * h * 3];
        let mut mask = Mask::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let inside = (x0..x0 + 32).contains(&x) && (y0..y0 + 32).contains(&y);
                let v = if inside {
                    mask.set(x, y, true);
                    let t = if vertical { x - x0 } else { y - y0 };
                    if (t / 4) % 2 == 0 {
                        220.0
                    } else {
                        40.0
                    }
                } else {
                    rng.range_f64(100.0, 150.0)
                };
                for c in 0..3 {
                    data[(y * w + x) * 3 + c] = v as f32;
                }
            }
        }
        (ColorImage::new(w, h, data).unwrap(), mask)
    }

    /// The component latent: a model trained on masked photographs of two
    /// kinds of the same size (vertical stripes: component 0, horizontal:
    /// component 1) assigns each box-only photograph, started in component
    /// 0, to the component of its kind, wherever the box lies.
    #[test]
    fn boxes_are_assigned_the_component_of_their_kind() {
        use crate::data::{box_mask, Annotation};
        use crate::train::{train_joint, TrainParams};
        let params = TrainParams {
            template: Some([4, 4]),
            pyramid: PyramidParams {
                levels_per_octave: 2,
                min_scale: 0.7,
                max_scale: 1.0,
                ..Default::default()
            },
            solver: crate::train::SolverParams {
                max_passes: 3,
                ..Default::default()
            },
            ..TrainParams::default()
        };
        let cache = PyramidCache::default();
        let add = |name: String, img: &ColorImage| {
            let pyr = FeaturePyramid::build(img, &params.pyramid, &params.segmentation).unwrap();
            cache.insert(PathBuf::from(&name), pyr);
            PathBuf::from(name)
        };
        let mut known = Vec::new();
        for i in 0..8u64 {
            let vertical = i % 2 == 0;
            let (x, y) = (8 + 6 * i as usize, 10 + 4 * (i as usize % 3));
            let (img, mask) = striped(vertical, x, y, i);
            known.push(Sample {
                image: add(format!("known{i}"), &img),
                id: format!("known{i}"),
                annotation: Some(Annotation {
                    label: "block".into(),
                    bbox: (x as f64, y as f64, 32.0, 32.0),
                    visible: mask,
                    viewpoint: usize::from(!vertical),
                    mask_known: true,
                }),
            });
        }
        for i in 0..6u64 {
            let mut rng = SplitMix64::new(50 + i);
            let data: Vec<f32> = (0..96 * 80 * 3)
                .map(|_| rng.range_f64(60.0, 190.0) as f32)
                .collect();
            let img = ColorImage::new(96, 80, data).unwrap();
            known.push(Sample::negative(add(format!("negative{i}"), &img)));
        }
        let refs: Vec<&Sample> = known.iter().collect();
        let (model, _) = train_joint(
            "block",
            &["block"],
            &refs,
            &cache,
            &params,
            &indicatif::ProgressBar::hidden(),
        )
        .unwrap();
        assert_eq!(model.meta.viewpoints.len(), 2);
        // Box-only photographs of both kinds at other places, all started
        // in component 0.
        let mut boxes = Vec::new();
        let mut kinds = Vec::new();
        for i in 0..6u64 {
            let vertical = i % 3 == 0;
            let (x, y) = (56 - 7 * i as usize, 40 - 5 * (i as usize % 4));
            let (img, _) = striped(vertical, x, y, 100 + i);
            let bbox = (x as f64, y as f64, 32.0, 32.0);
            boxes.push(Sample {
                image: add(format!("box{i}"), &img),
                id: format!("box{i}"),
                annotation: Some(Annotation {
                    label: "block".into(),
                    bbox,
                    visible: box_mask(bbox, 96, 80),
                    viewpoint: 0,
                    mask_known: false,
                }),
            });
            kinds.push(usize::from(!vertical));
        }
        for latent_visibility in [false, true] {
            let mut imputed = boxes.clone();
            let round = impute_samples(
                &model,
                "block",
                0,
                &mut imputed,
                &cache,
                0.6,
                latent_visibility,
            )
            .unwrap();
            assert_eq!((round.boxes, round.unfit), (6, 0));
            let got: Vec<usize> = imputed
                .iter()
                .map(|s| s.annotation.as_ref().unwrap().viewpoint)
                .collect();
            assert_eq!(got, kinds, "latent visibility {latent_visibility}");
            // Four horizontal boxes moved from component 0.
            assert_eq!(round.component_changes, 4);
            if !latent_visibility {
                // The whole box stays visible.
                for s in &imputed {
                    let a = s.annotation.as_ref().unwrap();
                    assert_eq!(a.visible.area(), 32 * 32);
                }
            }
        }
    }

    /// Imputation is exact: on a 2x3 template, its energy equals the least
    /// energy over every location and every one of the 64 labellings.
    #[test]
    fn imputation_equals_brute_force() {
        let mut rng = SplitMix64::new(11);
        let (w, h) = (64, 48);
        let data: Vec<f32> = (0..w * h * 3)
            .map(|i| {
                let (x, y) = ((i / 3) % w, (i / 3) / w);
                let stripe = if (x / 6 + y / 9) % 2 == 0 {
                    60.0
                } else {
                    190.0
                };
                (stripe + rng.range_f64(-20.0, 20.0)) as f32
            })
            .collect();
        let img = ColorImage::new(w, h, data).unwrap();
        let pyr = FeaturePyramid::build(
            &img,
            &PyramidParams {
                levels_per_octave: 2,
                min_scale: 0.7,
                ..PyramidParams::default()
            },
            &SegmentParams::default(),
        )
        .unwrap();
        for seed in 0..4u64 {
            let mut r = SplitMix64::new(100 + seed);
            let mut vw = ViewWeights::zeros(2, 3, 4);
            for x in vw.w_vis.iter_mut().chain(vw.w_occ.iter_mut()) {
                *x = r.range_f64(-0.3, 0.3) as f32;
            }
            for x in &mut vw.w_prior {
                *x = r.range_f64(-0.5, 0.5) as f32;
            }
            vw.w_pair = r.range_f64(0.0, 0.4) as f32;
            // A concave clique potential, as training keeps them.
            vw.w_hop = vec![-0.3, 0.0, 0.2, 0.3, 0.35];
            vw.bias = r.range_f64(-1.0, 1.0) as f32;
            let vws = [vw];
            let det = Detector::new(&vws).unwrap();
            let bbox = det.grid(&pyr, &det.locations(&pyr, 0.5)[5]).pixel_box();
            let locs = box_locations(&det, &pyr, bbox, &[0], 0.5, 0.3);
            assert!(locs.len() > 1);
            let got = impute(&det, &pyr, &locs).unwrap();
            let mut best = f64::INFINITY;
            for l in &locs {
                let (problem, _, _) = det.problem_at(&pyr, l);
                for bits in 0..(1u32 << 6) {
                    let v: Vec<bool> = (0..6).map(|i| bits >> i & 1 == 1).collect();
                    best = best.min(problem.energy(&v));
                }
            }
            assert!((got.energy - best).abs() < 1e-6, "{} vs {best}", got.energy);
            let (problem, _, _) = det.problem_at(&pyr, &got.location);
            assert!((problem.energy(&got.cells) - best).abs() < 1e-6);
        }
    }
}
