//! The CMU Kitchen Occlusion (CMU_KO8) single-pose layout: training
//! masks, test images with their `.bbox` (a box CENTRE, see NOTES.md) and
//! occluder masks, and the negatives.

use std::path::{Path, PathBuf};

use super::{check_box, file_stem, invalid, load_mask, Annotation, DatasetError, Loaded, Sample};
use crate::vision::mask::Mask;

/// Parses a CMU_KO8 `.bbox`: `cx cy w h` (the box CENTRE), separated by
/// spaces or commas, numbers possibly in exponent notation.
pub fn parse_ko8_bbox(text: &str) -> Option<(f64, f64, f64, f64)> {
    let v: Vec<f64> = text
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<f64>())
        .collect::<Result<_, _>>()
        .ok()?;
    match v[..] {
        [cx, cy, w, h] if v.iter().all(|x| x.is_finite()) && w > 0.0 && h > 0.0 => {
            Some((cx, cy, w, h))
        }
        _ => None,
    }
}

/// The visible ground truth of a CMU_KO8 test image (NOTES.md): the training
/// mask cropped to its tight box, resized (nearest) to `round(w) x
/// round(h)`, placed at `(round(cx - w/2), round(cy - h/2))` and clipped,
/// minus the occluder pattern. `None` when the training mask is empty.
pub fn ko8_visible_mask(
    train_mask: &Mask,
    centre_box: (f64, f64, f64, f64),
    occluder: &Mask,
) -> Option<Mask> {
    let (cx, cy, w, h) = centre_box;
    let (tx0, ty0, tx1, ty1) = train_mask.tight_box()?;
    let (cw, ch) = (tx1 - tx0, ty1 - ty0);
    // Python's round() is round-half-even.
    let round = |v: f64| v.round_ties_even() as i64;
    let (bw, bh) = (round(w).max(0) as usize, round(h).max(0) as usize);
    let (x0, y0) = (round(cx - w / 2.0), round(cy - h / 2.0));
    let mut out = Mask::new(occluder.width, occluder.height);
    for yy in 0..bh {
        let py = y0 + yy as i64;
        if py < 0 || py >= out.height as i64 {
            continue;
        }
        // PIL's nearest: source = floor((dst + 0.5) * src / dst).
        let sy = (((yy as f64 + 0.5) * ch as f64 / bh as f64) as usize).min(ch - 1);
        for xx in 0..bw {
            let px = x0 + xx as i64;
            if px < 0 || px >= out.width as i64 {
                continue;
            }
            let sx = (((xx as f64 + 0.5) * cw as f64 / bw as f64) as usize).min(cw - 1);
            let (px, py) = (px as usize, py as usize);
            if train_mask.get(tx0 + sx, ty0 + sy) && !occluder.get(px, py) {
                out.set(px, py, true);
            }
        }
    }
    Some(out)
}

/// The CMU_KO8 single-pose layout: `single/train/<obj>/<obj>_mask.png`,
/// `single/test/<obj>/<obj>_NNN.{jpg,bbox,occ.png}` and `negative/*.jpg`.
#[derive(Clone, Debug)]
pub struct Ko8 {
    pub root: PathBuf,
}

/// The eight objects of CMU_KO8.
pub const KO8_OBJECTS: [&str; 8] = [
    "bakingpan",
    "colander",
    "cup",
    "pitcher",
    "saucepan",
    "scissors",
    "shaker",
    "thermos",
];

fn sorted_files(dir: &Path, suffix: &str) -> Result<Vec<PathBuf>, DatasetError> {
    let rd = std::fs::read_dir(dir).map_err(|source| DatasetError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut out: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(suffix))
        .collect();
    out.sort();
    Ok(out)
}

impl Ko8 {
    /// Opens a dataset root; checks that it has the expected layout.
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        if !root.join("single/test").is_dir() {
            return Err(invalid(root, "not a CMU_KO8 root (no single/test)"));
        }
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    /// The objects that have a test folder, in the standard order.
    pub fn objects(&self) -> Vec<String> {
        KO8_OBJECTS
            .iter()
            .filter(|o| self.root.join("single/test").join(o).is_dir())
            .map(|o| o.to_string())
            .collect()
    }

    /// The occluded test images of one object with their ground truth.
    pub fn test_samples(&self, object: &str) -> Result<Loaded, DatasetError> {
        let train_path = self
            .root
            .join("single/train")
            .join(object)
            .join(format!("{object}_mask.png"));
        let train = load_mask(&train_path)?;
        if train.tight_box().is_none() {
            return Err(invalid(&train_path, "training mask is empty"));
        }
        let dir = self.root.join("single/test").join(object);
        let mut out = Loaded::default();
        for bbox_path in sorted_files(&dir, ".bbox")? {
            let stem = file_stem(&bbox_path);
            match self.test_sample(object, &train, &dir, &stem) {
                Ok(s) => out.samples.push(s),
                Err(e) => out.skipped.push(e.to_string()),
            }
        }
        Ok(out)
    }

    fn test_sample(
        &self,
        object: &str,
        train: &Mask,
        dir: &Path,
        stem: &str,
    ) -> Result<Sample, DatasetError> {
        let bbox_path = dir.join(format!("{stem}.bbox"));
        let text = std::fs::read_to_string(&bbox_path).map_err(|source| DatasetError::Io {
            path: bbox_path.clone(),
            source,
        })?;
        let cb = parse_ko8_bbox(&text)
            .ok_or_else(|| invalid(&bbox_path, "expected four numbers cx cy w h, w, h > 0"))?;
        let image = dir.join(format!("{stem}.jpg"));
        if !image.is_file() {
            return Err(invalid(&image, "missing image"));
        }
        let occ = load_mask(&dir.join(format!("{stem}.occ.png")))?;
        let bbox = (cb.0 - cb.2 / 2.0, cb.1 - cb.3 / 2.0, cb.2, cb.3);
        check_box(&bbox_path, bbox, occ.width, occ.height)?;
        let visible = ko8_visible_mask(train, cb, &occ)
            .ok_or_else(|| invalid(&bbox_path, "empty training mask"))?;
        if visible.area() == 0 {
            return Err(invalid(&bbox_path, "the object is wholly hidden"));
        }
        Ok(Sample {
            image,
            id: stem.to_string(),
            annotation: Some(Annotation {
                label: object.to_string(),
                bbox,
                visible,
                viewpoint: 0,
                mask_known: true,
            }),
        })
    }

    /// Whether the multi-view part (`multiple/`) is there.
    pub fn has_multiple(&self) -> bool {
        self.root.join("multiple/train").is_dir()
    }

    /// The unoccluded views of one object (multi-view part:
    /// `multiple/train/<obj>/<obj>_NNN.jpg` with `<obj>_NNN_mask.png`), in
    /// sorted order (the camera's order around the object). Each view's
    /// box is its mask's tight box. A view without its mask, or with an
    /// empty one, is reported in `skipped`, naming the file.
    pub fn views(&self, object: &str) -> Result<Loaded, DatasetError> {
        let dir = self.root.join("multiple/train").join(object);
        let mut out = Loaded::default();
        for image in sorted_files(&dir, ".jpg")? {
            let stem = file_stem(&image);
            let mask_path = dir.join(format!("{stem}_mask.png"));
            if !mask_path.is_file() {
                out.skipped.push(format!(
                    "{}: view without its mask ({} is missing)",
                    image.display(),
                    mask_path.display()
                ));
                continue;
            }
            let visible = match load_mask(&mask_path) {
                Ok(m) => m,
                Err(e) => {
                    out.skipped.push(e.to_string());
                    continue;
                }
            };
            let Some((x0, y0, x1, y1)) = visible.tight_box() else {
                out.skipped
                    .push(format!("{}: empty mask", mask_path.display()));
                continue;
            };
            out.samples.push(Sample {
                image,
                id: stem.clone(),
                annotation: Some(Annotation {
                    label: object.to_string(),
                    bbox: (x0 as f64, y0 as f64, (x1 - x0) as f64, (y1 - y0) as f64),
                    visible,
                    viewpoint: 0,
                    mask_known: true,
                }),
            });
        }
        if out.samples.is_empty() {
            return Err(invalid(&dir, "no view with a mask"));
        }
        Ok(out)
    }

    /// The box-only photographs of one object (multi-view part:
    /// `multiple/test/<obj>/<obj>_NNN.jpg` with a `.bbox` centre box and no
    /// mask): annotations whose visibility is latent (`mask_known` false,
    /// `visible` the whole box).
    pub fn box_photos(&self, object: &str) -> Result<Loaded, DatasetError> {
        let dir = self.root.join("multiple/test").join(object);
        let mut out = Loaded::default();
        for bbox_path in sorted_files(&dir, ".bbox")? {
            let stem = file_stem(&bbox_path);
            match box_photo(object, &dir, &stem) {
                Ok(s) => out.samples.push(s),
                Err(e) => out.skipped.push(e.to_string()),
            }
        }
        Ok(out)
    }

    /// The negative kitchen scenes (no object).
    pub fn negatives(&self) -> Result<Vec<Sample>, DatasetError> {
        Ok(sorted_files(&self.root.join("negative"), ".jpg")?
            .into_iter()
            .map(Sample::negative)
            .collect())
    }
}

/// One box-only photograph of the multi-view part.
fn box_photo(object: &str, dir: &Path, stem: &str) -> Result<Sample, DatasetError> {
    let bbox_path = dir.join(format!("{stem}.bbox"));
    let text = std::fs::read_to_string(&bbox_path).map_err(|source| DatasetError::Io {
        path: bbox_path.clone(),
        source,
    })?;
    let cb = parse_ko8_bbox(&text)
        .ok_or_else(|| invalid(&bbox_path, "expected four numbers cx cy w h, w, h > 0"))?;
    let image = dir.join(format!("{stem}.jpg"));
    let (w, h) = image::image_dimensions(&image)
        .map_err(|e| invalid(&image, format!("cannot read the image: {e}")))?;
    let (w, h) = (w as usize, h as usize);
    let bbox = (cb.0 - cb.2 / 2.0, cb.1 - cb.3 / 2.0, cb.2, cb.3);
    check_box(&bbox_path, bbox, w, h)?;
    Ok(Sample {
        image,
        id: stem.to_string(),
        annotation: Some(Annotation {
            label: object.to_string(),
            bbox,
            visible: super::coco::box_mask(bbox, w, h),
            viewpoint: 0,
            mask_known: false,
        }),
    })
}

// ---------------------------------------------------------------- COCO ----

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ko8_bbox_is_a_centre_with_spaces_commas_and_exponents() {
        assert_eq!(
            parse_ko8_bbox("282.0 237.0 140.0 130.0 \n"),
            Some((282.0, 237.0, 140.0, 130.0))
        );
        assert_eq!(
            parse_ko8_bbox("4.835000e+02,2.1e2, 50,60"),
            Some((483.5, 210.0, 50.0, 60.0))
        );
        assert_eq!(parse_ko8_bbox("1 2 3"), None);
        assert_eq!(parse_ko8_bbox("1 2 0 3"), None);
        assert_eq!(parse_ko8_bbox("1 2 x 3"), None);
    }

    #[test]
    fn visible_mask_places_the_resized_crop_and_removes_the_occluder() {
        // Training mask: a 4x2 block at (3, 5).
        let mut train = Mask::new(20, 20);
        for y in 5..7 {
            for x in 3..7 {
                train.set(x, y, true);
            }
        }
        let mut occ = Mask::new(10, 10);
        occ.set(2, 1, true);
        // Centre (4, 2), size 8x4: top-left (0, 0).
        let vis = ko8_visible_mask(&train, (4.0, 2.0, 8.0, 4.0), &occ).unwrap();
        assert_eq!(vis.area(), 8 * 4 - 1);
        assert!(!vis.get(2, 1) && vis.get(7, 3) && !vis.get(8, 0));
        // Clipped at the border: centre (0, 0) keeps the bottom-right quarter.
        let vis = ko8_visible_mask(&train, (0.0, 0.0, 8.0, 4.0), &Mask::new(10, 10)).unwrap();
        assert_eq!(vis.area(), 4 * 2);
    }
}
