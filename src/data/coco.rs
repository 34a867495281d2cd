//! A COCO-style JSON format for users' own objects: images, one category
//! per object, annotations with the full-extent `bbox` and the visible
//! `segmentation` (uncompressed or compressed RLE, or polygons).

use std::collections::HashMap;
use std::path::Path;

use serde::Deserialize;

use super::{check_box, invalid, Annotation, DatasetError, Loaded, Sample};
use crate::vision::mask::{CompressedRle, Mask};

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
    /// The full extent; may be left out where the segmentation is of an
    /// unoccluded view (the box is then the mask's tight box).
    #[serde(default)]
    bbox: Option<[f64; 4]>,
    /// The visible pixels; left out (or null, or `[]`) for a box-only
    /// annotation, whose visibility training imputes.
    #[serde(default)]
    segmentation: serde_json::Value,
    #[serde(default)]
    viewpoint: Option<usize>,
    /// COCO's "ignore" flag (1: a region neither positive nor negative).
    #[serde(default)]
    iscrowd: u8,
}

/// Decodes COCO's compressed RLE string (the LEB128-like text of
/// `pycocotools`' `rleToString`) into run lengths.
pub fn decode_coco_rle_string(s: &str) -> Option<Vec<u32>> {
    CompressedRle {
        size: [0, 0],
        counts: s.to_string(),
    }
    .decompress()
    .map(|r| r.counts)
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

/// The pixels of a box, clipped to the image (the start of a box-only
/// annotation's imputed visibility).
pub fn box_mask(b: (f64, f64, f64, f64), width: usize, height: usize) -> Mask {
    let mut m = Mask::new(width, height);
    let clip = |v: f64, hi: usize| v.round().clamp(0.0, hi as f64) as usize;
    let (x0, x1) = (clip(b.0, width), clip(b.0 + b.2, width));
    let (y0, y1) = (clip(b.1, height), clip(b.1 + b.3, height));
    for y in y0..y1 {
        for x in x0..x1 {
            m.set(x, y, true);
        }
    }
    m
}

/// Reads a COCO-style JSON file for one category: images with an annotation
/// of `category` are positives (the first annotation per image; further ones
/// are reported as skipped), every other image is a negative, except images
/// whose only annotations of `category` are `iscrowd` (ignored regions:
/// neither positive nor negative, reported as skipped). Image paths are
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
        let Some(all) = by_image.get(&img.id) else {
            out.samples.push(Sample {
                image: path,
                id,
                annotation: None,
            });
            continue;
        };
        let anns: Vec<&CocoAnnotation> = all.iter().copied().filter(|a| a.iscrowd == 0).collect();
        if anns.is_empty() {
            out.skipped.push(format!(
                "{}: only ignored (iscrowd) {category}: neither a positive nor a negative",
                path.display()
            ));
            continue;
        }
        for extra in &anns[1..] {
            out.skipped.push(format!(
                "{}: more than one {category} (only the first is used; bbox {:?})",
                path.display(),
                extra.bbox
            ));
        }
        let a = anns[0];
        let no_mask = match &a.segmentation {
            serde_json::Value::Null => true,
            serde_json::Value::Array(v) => v.is_empty(),
            _ => false,
        };
        let mask = if no_mask {
            None
        } else {
            match coco_mask(&a.segmentation, img.width, img.height) {
                Ok(m) if m.area() > 0 => Some(m),
                Ok(_) => {
                    out.skipped
                        .push(format!("{}: empty segmentation", path.display()));
                    continue;
                }
                Err(e) => {
                    out.skipped.push(format!("{}: {e}", path.display()));
                    continue;
                }
            }
        };
        let bbox = match (a.bbox, &mask) {
            (Some(b), _) => (b[0], b[1], b[2], b[3]),
            (None, Some(m)) => match m.tight_box() {
                Some((x0, y0, x1, y1)) => {
                    (x0 as f64, y0 as f64, (x1 - x0) as f64, (y1 - y0) as f64)
                }
                None => continue,
            },
            (None, None) => {
                out.skipped.push(format!(
                    "{}: annotation of {category} has neither a bbox nor a segmentation",
                    path.display()
                ));
                continue;
            }
        };
        if let Err(e) = check_box(&path, bbox, img.width, img.height) {
            out.skipped.push(e.to_string());
            continue;
        }
        let mask_known = mask.is_some();
        let visible = mask.unwrap_or_else(|| box_mask(bbox, img.width, img.height));
        out.samples.push(Sample {
            image: path,
            id,
            annotation: Some(Annotation {
                label: category.to_string(),
                bbox,
                visible,
                viewpoint: a.viewpoint.unwrap_or(0),
                mask_known,
            }),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
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
        for name in ["a.png", "b.png", "c.png", "neg.png", "crowd.png"] {
            image::RgbImage::new(40, 30).save(dir.join(name)).unwrap();
        }
        let json = serde_json::json!({
            "images": [
                {"id": 1, "file_name": "a.png", "width": 40, "height": 30},
                {"id": 2, "file_name": "b.png", "width": 40, "height": 30},
                {"id": 3, "file_name": "c.png", "width": 40, "height": 30},
                {"id": 4, "file_name": "missing.png", "width": 40, "height": 30},
                {"id": 5, "file_name": "neg.png", "width": 40, "height": 30},
                {"id": 6, "file_name": "crowd.png", "width": 40, "height": 30}
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
                 "segmentation": [[5, 5, 25, 5, 25, 20, 5, 20]]},
                {"image_id": 6, "category_id": 7, "bbox": [5, 5, 20, 15], "iscrowd": 1},
                {"image_id": 1, "category_id": 7, "bbox": [1, 1, 3, 3], "iscrowd": 1}
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
        assert_eq!(loaded.skipped.len(), 4, "{:?}", loaded.skipped);
        // An image with only an ignored instance is neither a positive nor
        // a negative; an ignored instance beside a real one changes nothing.
        assert!(loaded
            .skipped
            .iter()
            .any(|m| m.contains("crowd.png") && m.contains("iscrowd")));
        assert!(!loaded.samples.iter().any(|s| s.id == "crowd"));
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
