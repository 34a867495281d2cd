//! Training and evaluation data: the CMU Kitchen Occlusion (CMU_KO8) layout
//! and a COCO-style JSON format for users' own objects.
//!
//! Every positive sample carries the object's full-extent box (also where it
//! is hidden or cut by the image border) and its visible pixels; negative
//! samples contain no instance. Bad annotations are reported with the file
//! name and skipped ([`Loaded::skipped`]), never a panic.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use thiserror::Error;

use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;

/// Errors of the dataset readers.
#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode image: {msg}")]
    Image { path: PathBuf, msg: String },
    #[error("{path}: {msg}")]
    Invalid { path: PathBuf, msg: String },
}

fn invalid(path: &Path, msg: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        msg: msg.into(),
    }
}

/// The ground truth of one object instance.
#[derive(Clone, Debug, PartialEq)]
pub struct Annotation {
    /// Object label (the model name it trains).
    pub label: String,
    /// Full-extent box `(x, y, width, height)` in pixels.
    pub bbox: (f64, f64, f64, f64),
    /// Visible pixels of the object over the whole image.
    pub visible: Mask,
    /// Viewpoint (component) index.
    pub viewpoint: usize,
}

/// One image: a positive with its annotation, or a negative without.
#[derive(Clone, Debug)]
pub struct Sample {
    pub image: PathBuf,
    /// Short unique name (the file stem).
    pub id: String,
    pub annotation: Option<Annotation>,
}

/// Samples read from a dataset, plus the ones refused and why.
#[derive(Debug, Default)]
pub struct Loaded {
    pub samples: Vec<Sample>,
    /// `file: reason` for every annotation that was skipped.
    pub skipped: Vec<String>,
}

/// Reads an image file as RGB.
pub fn load_image(path: &Path) -> Result<ColorImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let img = image::load_from_memory(&bytes).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })?;
    ColorImage::from_rgb8(&img.to_rgb8()).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })
}

/// Reads a binary mask PNG: grey value > 0 is true.
pub fn load_mask(path: &Path) -> Result<Mask, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| DatasetError::Image {
            path: path.to_path_buf(),
            msg: e.to_string(),
        })?
        .to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok(Mask {
        width: w,
        height: h,
        data: img.as_raw().iter().map(|&v| u8::from(v > 0)).collect(),
    })
}

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
            let stem = bbox_path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
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
            }),
        })
    }

    /// The negative kitchen scenes (no object).
    pub fn negatives(&self) -> Result<Vec<Sample>, DatasetError> {
        Ok(sorted_files(&self.root.join("negative"), ".jpg")?
            .into_iter()
            .map(|p| Sample {
                id: p
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                image: p,
                annotation: None,
            })
            .collect())
    }
}

/// Refuses a box that is degenerate or lies wholly outside the image.
fn check_box(
    path: &Path,
    b: (f64, f64, f64, f64),
    width: usize,
    height: usize,
) -> Result<(), DatasetError> {
    let (x, y, w, h) = b;
    let finite = [x, y, w, h].iter().all(|v| v.is_finite());
    if !finite || w <= 0.0 || h <= 0.0 {
        return Err(invalid(path, format!("degenerate box {b:?}")));
    }
    if x + w <= 0.0 || y + h <= 0.0 || x >= width as f64 || y >= height as f64 {
        return Err(invalid(
            path,
            format!("box {b:?} lies outside the {width}x{height} image"),
        ));
    }
    Ok(())
}

// ---------------------------------------------------------------- COCO ----

#[derive(Deserialize)]
struct CocoFile {
    images: Vec<CocoImage>,
    #[serde(default)]
    annotations: Vec<CocoAnnotation>,
    categories: Vec<CocoCategory>,
}

#[derive(Deserialize)]
struct CocoImage {
    id: u64,
    file_name: String,
    width: usize,
    height: usize,
}

#[derive(Deserialize)]
struct CocoCategory {
    id: u64,
    name: String,
}

#[derive(Deserialize)]
struct CocoAnnotation {
    image_id: u64,
    category_id: u64,
    bbox: [f64; 4],
    segmentation: serde_json::Value,
    #[serde(default)]
    viewpoint: Option<usize>,
}

/// Decodes COCO's compressed RLE string (the LEB128-like text of
/// `pycocotools`' `rleToString`) into run lengths.
pub fn decode_coco_rle_string(s: &str) -> Option<Vec<u32>> {
    let bytes = s.as_bytes();
    let mut counts: Vec<i64> = Vec::new();
    let mut p = 0;
    while p < bytes.len() {
        let mut x: i64 = 0;
        let mut k = 0;
        loop {
            let c = i64::from(*bytes.get(p)?) - 48;
            if !(0..64).contains(&c) || k > 60 {
                return None;
            }
            x |= (c & 0x1f) << (5 * k);
            let more = c & 0x20 != 0;
            p += 1;
            k += 1;
            if !more {
                if c & 0x10 != 0 {
                    x |= -1 << (5 * k);
                }
                break;
            }
        }
        if counts.len() > 2 {
            x += counts[counts.len() - 2];
        }
        counts.push(x);
    }
    counts.into_iter().map(|c| u32::try_from(c).ok()).collect()
}

/// A mask from COCO uncompressed run lengths (column-major, zeros first).
fn mask_from_counts(counts: &[u32], width: usize, height: usize) -> Option<Mask> {
    let total: u64 = counts.iter().map(|&c| u64::from(c)).sum();
    if total != (width * height) as u64 {
        return None;
    }
    let mut m = Mask::new(width, height);
    let mut pos = 0usize;
    for (k, &c) in counts.iter().enumerate() {
        if k % 2 == 1 {
            for q in pos..pos + c as usize {
                m.set(q / height, q % height, true);
            }
        }
        pos += c as usize;
    }
    Some(m)
}

/// Fills polygons `[x0, y0, x1, y1, ...]` (even-odd rule, pixel centres).
fn mask_from_polygons(polys: &[Vec<f64>], width: usize, height: usize) -> Option<Mask> {
    let mut m = Mask::new(width, height);
    for poly in polys {
        if poly.len() < 6 || poly.len() % 2 != 0 || poly.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let pts: Vec<(f64, f64)> = poly.chunks(2).map(|c| (c[0], c[1])).collect();
        for y in 0..height {
            let yc = y as f64 + 0.5;
            let mut xs: Vec<f64> = Vec::new();
            for i in 0..pts.len() {
                let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
                if (a.1 <= yc) != (b.1 <= yc) {
                    xs.push(a.0 + (yc - a.1) / (b.1 - a.1) * (b.0 - a.0));
                }
            }
            xs.sort_by(f64::total_cmp);
            for pair in xs.chunks(2) {
                if let [x0, x1] = pair {
                    let lo = (x0 - 0.5).ceil().max(0.0) as usize;
                    let hi = ((x1 - 0.5).floor() + 1.0).clamp(0.0, width as f64) as usize;
                    for x in lo..hi {
                        let v = m.get(x, y);
                        m.set(x, y, !v);
                    }
                }
            }
        }
    }
    Some(m)
}

fn coco_mask(seg: &serde_json::Value, width: usize, height: usize) -> Result<Mask, String> {
    match seg {
        serde_json::Value::Array(_) => {
            let polys: Vec<Vec<f64>> =
                serde_json::from_value(seg.clone()).map_err(|e| format!("polygons: {e}"))?;
            mask_from_polygons(&polys, width, height).ok_or_else(|| "bad polygon".to_string())
        }
        serde_json::Value::Object(o) => {
            let size: [usize; 2] = o
                .get("size")
                .and_then(|s| serde_json::from_value(s.clone()).ok())
                .ok_or("RLE without size [h, w]")?;
            if size != [height, width] {
                return Err(format!(
                    "RLE size {size:?} disagrees with the image {height}x{width}"
                ));
            }
            let counts = match o.get("counts") {
                Some(serde_json::Value::String(s)) => {
                    decode_coco_rle_string(s).ok_or("undecodable compressed RLE")?
                }
                Some(c) => serde_json::from_value(c.clone()).map_err(|e| format!("counts: {e}"))?,
                None => return Err("RLE without counts".into()),
            };
            mask_from_counts(&counts, width, height)
                .ok_or_else(|| "RLE counts do not cover the image".to_string())
        }
        _ => Err("segmentation must be polygons or an RLE object".into()),
    }
}

/// Reads a COCO-style JSON file for one category: images with an annotation
/// of `category` are positives (the first annotation per image; further ones
/// are reported as skipped), every other image is a negative. Image paths are
/// relative to `image_dir`.
pub fn load_coco(json: &Path, image_dir: &Path, category: &str) -> Result<Loaded, DatasetError> {
    let text = std::fs::read_to_string(json).map_err(|source| DatasetError::Io {
        path: json.to_path_buf(),
        source,
    })?;
    let file: CocoFile =
        serde_json::from_str(&text).map_err(|e| invalid(json, format!("not COCO JSON: {e}")))?;
    let cat = file
        .categories
        .iter()
        .find(|c| c.name == category)
        .ok_or_else(|| invalid(json, format!("no category named {category:?}")))?
        .id;
    let mut by_image: HashMap<u64, Vec<&CocoAnnotation>> = HashMap::new();
    for a in &file.annotations {
        if a.category_id == cat {
            by_image.entry(a.image_id).or_default().push(a);
        }
    }
    let mut out = Loaded::default();
    for img in &file.images {
        let path = image_dir.join(&img.file_name);
        let id = Path::new(&img.file_name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| img.id.to_string());
        if !path.is_file() {
            out.skipped
                .push(format!("{}: missing image file", path.display()));
            continue;
        }
        let Some(anns) = by_image.get(&img.id) else {
            out.samples.push(Sample {
                image: path,
                id,
                annotation: None,
            });
            continue;
        };
        for extra in &anns[1..] {
            out.skipped.push(format!(
                "{}: more than one {category} (only the first is used; bbox {:?})",
                path.display(),
                extra.bbox
            ));
        }
        let a = anns[0];
        let bbox = (a.bbox[0], a.bbox[1], a.bbox[2], a.bbox[3]);
        if let Err(e) = check_box(&path, bbox, img.width, img.height) {
            out.skipped.push(e.to_string());
            continue;
        }
        let visible = match coco_mask(&a.segmentation, img.width, img.height) {
            Ok(m) if m.area() > 0 => m,
            Ok(_) => {
                out.skipped
                    .push(format!("{}: empty segmentation", path.display()));
                continue;
            }
            Err(e) => {
                out.skipped.push(format!("{}: {e}", path.display()));
                continue;
            }
        };
        out.samples.push(Sample {
            image: path,
            id,
            annotation: Some(Annotation {
                label: category.to_string(),
                bbox,
                visible,
                viewpoint: a.viewpoint.unwrap_or(0),
            }),
        });
    }
    Ok(out)
}

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

    #[test]
    fn coco_masks_from_rle_polygons_and_compressed_strings() {
        // 3x2 image (w=3, h=2), column-major counts.
        let m = mask_from_counts(&[1, 2, 3], 3, 2).unwrap();
        assert_eq!(m.data, vec![0, 1, 0, 1, 0, 0]);
        assert!(mask_from_counts(&[1, 2], 3, 2).is_none());
        let rle = m.to_rle();
        assert_eq!(rle.counts, vec![1, 2, 3]);
        // A square polygon covering pixels 1..3 x 1..3.
        let p = mask_from_polygons(&[vec![1.0, 1.0, 3.0, 1.0, 3.0, 3.0, 1.0, 3.0]], 5, 5).unwrap();
        assert_eq!(p.area(), 4);
        assert!(p.get(1, 1) && p.get(2, 2) && !p.get(3, 3));
        // pycocotools encodes counts [1, 2, 3] as "123" offsets: check the
        // round trip of small counts (each a single character).
        assert_eq!(decode_coco_rle_string("123"), Some(vec![1, 2, 3]));
        assert_eq!(decode_coco_rle_string("1"), Some(vec![1]));
        assert_eq!(decode_coco_rle_string("\u{7f}"), None);
    }

    /// A tiny COCO file written here: one good annotation (polygon), one
    /// whose box lies outside the image, one with an empty mask, one whose
    /// image is missing, and an image without annotation (a negative).
    #[test]
    fn coco_reader_keeps_good_annotations_and_reports_bad_ones() {
        let dir = std::env::temp_dir().join(format!("sdhop-coco-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in ["a.png", "b.png", "c.png", "neg.png"] {
            image::RgbImage::new(40, 30).save(dir.join(name)).unwrap();
        }
        let json = serde_json::json!({
            "images": [
                {"id": 1, "file_name": "a.png", "width": 40, "height": 30},
                {"id": 2, "file_name": "b.png", "width": 40, "height": 30},
                {"id": 3, "file_name": "c.png", "width": 40, "height": 30},
                {"id": 4, "file_name": "missing.png", "width": 40, "height": 30},
                {"id": 5, "file_name": "neg.png", "width": 40, "height": 30}
            ],
            "categories": [{"id": 7, "name": "mug"}],
            "annotations": [
                {"image_id": 1, "category_id": 7, "bbox": [5, 5, 20, 15], "viewpoint": 1,
                 "segmentation": [[5, 5, 25, 5, 25, 20, 5, 20]]},
                {"image_id": 2, "category_id": 7, "bbox": [50, 5, 20, 15],
                 "segmentation": [[5, 5, 25, 5, 25, 20, 5, 20]]},
                {"image_id": 3, "category_id": 7, "bbox": [5, 5, 20, 15],
                 "segmentation": {"size": [30, 40], "counts": [1200]}},
                {"image_id": 4, "category_id": 7, "bbox": [5, 5, 20, 15],
                 "segmentation": [[5, 5, 25, 5, 25, 20, 5, 20]]}
            ]
        });
        let path = dir.join("ann.json");
        std::fs::write(&path, json.to_string()).unwrap();
        let loaded = load_coco(&path, &dir, "mug").unwrap();
        let positives: Vec<_> = loaded
            .samples
            .iter()
            .filter(|s| s.annotation.is_some())
            .collect();
        assert_eq!(positives.len(), 1);
        let a = positives[0].annotation.as_ref().unwrap();
        assert_eq!((a.viewpoint, a.visible.area()), (1, 20 * 15));
        assert_eq!(loaded.samples.len(), 2, "one positive and one negative");
        assert_eq!(loaded.skipped.len(), 3, "{:?}", loaded.skipped);
        assert!(loaded
            .skipped
            .iter()
            .any(|m| m.contains("b.png") && m.contains("outside")));
        assert!(loaded
            .skipped
            .iter()
            .any(|m| m.contains("c.png") && m.contains("empty")));
        assert!(loaded.skipped.iter().any(|m| m.contains("missing.png")));
        assert!(load_coco(&path, &dir, "teapot").is_err());
        std::fs::write(&path, "{not json").unwrap();
        assert!(matches!(
            load_coco(&path, &dir, "mug"),
            Err(DatasetError::Invalid { .. })
        ));
        std::fs::remove_dir_all(&dir).ok();
    }
}
