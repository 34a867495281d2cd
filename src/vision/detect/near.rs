//! The best location near a box: the location of least energy among those
//! (of every level and viewpoint) whose box overlaps a given box by at
//! least a given fraction. It lets one model place and segment what
//! another found (issue 63: a learned-cell detection segmented by a HOG
//! model of the same object, `examples/mask_transfer.rs`), solved exactly:
//! each location's min-cut is pruned by the stage-2 bounds against the
//! best energy found so far, the location centred on the box first.

use super::*;

impl Detector<'_> {
    /// The detection of least energy among the locations whose box
    /// overlaps `target` (image pixels `(x, y, width, height)`) by at least
    /// `min_iou` (intersection over union), or `None` where none does.
    /// Locations with more than `max_truncation` of their cells outside
    /// the image are left out, as the scan leaves them out.
    pub fn best_near(
        &self,
        pyr: &FeaturePyramid,
        target: (f64, f64, f64, f64),
        min_iou: f64,
        max_truncation: f64,
    ) -> Option<Detection> {
        self.best_near_until(pyr, target, min_iou, max_truncation, Deadline::NONE)
            .unwrap_or(None)
    }

    /// [`Self::best_near`] that gives up with
    /// [`VisionError::DeadlineExceeded`] once `deadline` has passed (looked
    /// at every few locations), as a request's masks must.
    pub fn best_near_until(
        &self,
        pyr: &FeaturePyramid,
        target: (f64, f64, f64, f64),
        min_iou: f64,
        max_truncation: f64,
        deadline: Deadline,
    ) -> Result<Option<Detection>, VisionError> {
        let mut near: Vec<(f64, Candidate)> = Vec::new();
        for (level, lv) in pyr.levels.iter().enumerate() {
            let (mw, mh) = (lv.hog.width() as isize, lv.hog.height() as isize);
            for (view, v) in self.views.iter().enumerate() {
                let (rows, cols) = (v.w.rows as isize, v.w.cols as isize);
                let origin = Location {
                    level,
                    view,
                    y: 0,
                    x: 0,
                };
                let (_, _, w, h) = self.grid(pyr, &origin).pixel_box();
                // Boxes of this size overlap the target enough only if
                // their sizes do, centred on each other.
                if box_iou((0.0, 0.0, w, h), (0.0, 0.0, target.2, target.3)) < min_iou {
                    continue;
                }
                let (cw, ch) = (w / cols as f64, h / rows as f64);
                let cx = ((target.0 + 0.5 * (target.2 - w)) / cw).round() as isize;
                let cy = ((target.1 + 0.5 * (target.3 - h)) / ch).round() as isize;
                // Two boxes of width w at least min_iou apart overlap by
                // at most (w - d) / (w + d): d <= w (1 - t) / (1 + t).
                let reach =
                    |n: isize| (n as f64 * (1.0 - min_iou) / (1.0 + min_iou)).ceil() as isize + 1;
                let (rx, ry) = (reach(cols), reach(rows));
                // As the scan's locations: enough of the box inside.
                let n = (rows * cols) as f64;
                let min_inside = (((1.0 - max_truncation) * n).ceil() as usize).max(1);
                for y in cy - ry..=cy + ry {
                    for x in cx - rx..=cx + rx {
                        let inside = overlap(x, cols as usize, mw as usize)
                            * overlap(y, rows as usize, mh as usize);
                        if inside < min_inside {
                            continue;
                        }
                        let loc = Location { level, view, y, x };
                        let o = box_iou(self.grid(pyr, &loc).pixel_box(), target);
                        if o >= min_iou {
                            let cand = Candidate {
                                view,
                                level,
                                x,
                                y,
                                bound: f64::NEG_INFINITY,
                            };
                            near.push((o, cand));
                        }
                    }
                }
            }
        }
        // The best-placed locations first: their energies tighten the cut.
        near.sort_by(|a, b| {
            b.0.total_cmp(&a.0)
                .then((a.1.level, a.1.view, a.1.y, a.1.x).cmp(&(b.1.level, b.1.view, b.1.y, b.1.x)))
        });
        let mut s = Scratch::default();
        let mut best: Option<Solved> = None;
        for (i, (_, cand)) in near.into_iter().enumerate() {
            if i % 16 == 0 && deadline.passed() {
                return Err(VisionError::DeadlineExceeded);
            }
            let cut = best.as_ref().map_or(f64::INFINITY, |b| b.energy);
            if let Some(r) = self.solve(pyr, &cand, cut, best.is_some(), None, &mut s) {
                if best.as_ref().is_none_or(|b| r.energy < b.energy) {
                    best = Some(r);
                }
            }
        }
        Ok(best.map(|b| self.detection_of(pyr, b)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{hand_model, scene, HandModelParams, SceneParams, SynthObject};

    #[test]
    fn the_best_location_near_a_box_is_the_best_of_all_that_overlap_it() {
        let obj = SynthObject {
            cols: 12,
            rows: 10,
            seed: 11,
        };
        let m = hand_model(&obj, "obj", true, &HandModelParams::default()).unwrap();
        let sc = scene(&obj, &SceneParams::default()).unwrap();
        let pyr = FeaturePyramid::build(&sc.image, &m.meta.pyramid, &m.meta.segmentation).unwrap();
        let det = Detector::new(&m.views).unwrap();
        let params = DetectParams {
            threshold: -1e9,
            max_detections: 1,
            ..m.meta.detection
        };
        let (top, _) = det.detect(&pyr, &params).unwrap();
        let top = &top[0];
        // Around the best detection, the best is that detection.
        let near = det
            .best_near(&pyr, top.bbox, 0.5, params.max_truncation)
            .unwrap();
        assert_eq!((near.level, near.viewpoint), (top.level, top.viewpoint));
        assert_eq!(
            (near.grid.cell_x, near.grid.cell_y),
            (top.grid.cell_x, top.grid.cell_y)
        );
        assert!((near.score - top.score).abs() < 1e-9);
        assert_eq!(near.cells, top.cells);
        // Elsewhere, it is the best of every scanned location overlapping
        // the box enough, each solved without pruning.
        let all = det.locations(&pyr, params.max_truncation);
        let (x, y, w, h) = top.bbox;
        let mut some = 0;
        for (i, t) in [0.5, 0.7].iter().enumerate() {
            for (dx, dy, sw) in [
                (0.3, 0.0, 1.0),
                (-0.4, 0.25, 1.2),
                (0.0, -0.5, 0.8),
                (1.5, 1.0, 1.0),
            ] {
                let target = (x + dx * w, y + dy * h, w * sw, h * sw);
                let want = all
                    .iter()
                    .filter(|l| box_iou(det.grid(&pyr, l).pixel_box(), target) >= *t)
                    .map(|l| {
                        let (mut p, _, _) = det.problem_at(&pyr, l);
                        -p.solve(&mut Graph::new(), &mut Vec::new())
                    })
                    .fold(None, |b: Option<f64>, e| Some(b.map_or(e, |b| b.max(e))));
                let got = det.best_near(&pyr, target, *t, params.max_truncation);
                match (want, got) {
                    (Some(s), Some(d)) => {
                        some += 1;
                        assert!((d.score - s).abs() < 1e-6, "{i}: {} against {s}", d.score);
                        assert!(box_iou(d.bbox, target) >= *t);
                    }
                    (None, None) => {}
                    (want, got) => panic!("{i}: {want:?} against {:?}", got.map(|d| d.score)),
                }
            }
        }
        assert!(some >= 4, "{some}");
        // A passed deadline: refused, not answered late.
        let passed = Deadline::at(std::time::Instant::now());
        assert_eq!(
            det.best_near_until(&pyr, top.bbox, 0.5, params.max_truncation, passed),
            Err(VisionError::DeadlineExceeded)
        );
    }
}
