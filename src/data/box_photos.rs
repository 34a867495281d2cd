//! Box-only photographs of a scene: a COCO file whose annotations are
//! full-extent boxes without masks (what a user draws on a few photographs
//! of the place where the robot works), read strictly: a training run that
//! silently dropped a photograph or a box would train on less than its
//! user thinks, so every fault is an error that names it.
//!
//! `file_name`s are relative to the COCO file's own folder (as
//! `lmo_boxes_coco.py` writes them). A box may reach past the image's
//! border (it is the object's full extent), but not lie wholly outside it.
//! `iscrowd` annotations are ignore regions: neither positives nor places
//! for negatives.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::{check_box, invalid, DatasetError};

/// One photograph and the boxes of one category on it.
#[derive(Clone, Debug, PartialEq)]
pub struct BoxPhoto {
    /// The image file, resolved against the COCO file's folder.
    pub image: PathBuf,
    pub width: usize,
    pub height: usize,
    /// Full-extent boxes `(x, y, width, height)` of the category.
    pub boxes: Vec<(f64, f64, f64, f64)>,
    /// Boxes of the category to ignore (`iscrowd`: hardly visible).
    pub ignore: Vec<(f64, f64, f64, f64)>,
    /// Boxes of the other categories (objects that are not this one: hard
    /// negatives where they do not overlap a box of this one).
    pub others: Vec<(f64, f64, f64, f64)>,
}

/// The photographs of a box-only COCO file, for one category.
#[derive(Clone, Debug, PartialEq)]
pub struct BoxPhotos {
    pub category: String,
    /// Every photograph of the file, in its order (those without a box of
    /// the category are negatives).
    pub photos: Vec<BoxPhoto>,
}

impl BoxPhotos {
    /// The boxes of the category (not counting ignored ones).
    pub fn box_count(&self) -> usize {
        self.photos.iter().map(|p| p.boxes.len()).sum()
    }
}

#[derive(Deserialize)]
struct File {
    #[serde(default)]
    images: Vec<Image>,
    #[serde(default)]
    annotations: Vec<Ann>,
    #[serde(default)]
    categories: Vec<Category>,
}

#[derive(Deserialize)]
struct Image {
    id: u64,
    file_name: String,
    width: usize,
    height: usize,
}

#[derive(Deserialize)]
struct Ann {
    #[serde(default)]
    id: Option<u64>,
    image_id: u64,
    category_id: u64,
    bbox: [f64; 4],
    #[serde(default)]
    iscrowd: u8,
}

#[derive(Deserialize)]
struct Category {
    id: u64,
    name: String,
}

/// Reads `json`'s photographs and its boxes of `category`.
///
/// Errors (each naming the file, and the photograph or annotation): not
/// readable or not COCO JSON; no photographs; no category named so (the
/// names there are listed); no box of it; an annotation of an image id
/// that is not listed, or of a category id that is not; a photograph
/// listed twice; a missing or unreadable image file, or one whose size is
/// not the listed one; a degenerate box or one wholly outside its image.
pub fn load_box_photos(json: &Path, category: &str) -> Result<BoxPhotos, DatasetError> {
    let text = std::fs::read_to_string(json).map_err(|source| DatasetError::Io {
        path: json.to_path_buf(),
        source,
    })?;
    let file: File =
        serde_json::from_str(&text).map_err(|e| invalid(json, format!("not COCO JSON: {e}")))?;
    if file.images.is_empty() {
        return Err(invalid(json, "lists no photographs (\"images\" is empty)"));
    }
    let names: BTreeMap<u64, &str> = file
        .categories
        .iter()
        .map(|c| (c.id, c.name.as_str()))
        .collect();
    let cat = file
        .categories
        .iter()
        .find(|c| c.name == category)
        .ok_or_else(|| {
            let known: Vec<&str> = names.values().copied().collect();
            invalid(
                json,
                format!(
                    "no category named {category:?} (its categories: {})",
                    if known.is_empty() {
                        "none".to_string()
                    } else {
                        known.join(", ")
                    }
                ),
            )
        })?
        .id;
    let folder = json.parent().unwrap_or_else(|| Path::new("."));
    let mut index: HashMap<u64, usize> = HashMap::new();
    let mut photos = Vec::with_capacity(file.images.len());
    for im in &file.images {
        if im.file_name.trim().is_empty() {
            return Err(invalid(
                json,
                format!("image {} has an empty file_name", im.id),
            ));
        }
        let path = folder.join(&im.file_name);
        if index.insert(im.id, photos.len()).is_some() {
            return Err(invalid(json, format!("image id {} is listed twice", im.id)));
        }
        let (w, h) = image::image_dimensions(&path).map_err(|e| {
            invalid(
                json,
                format!(
                    "image {} ({:?}): cannot read {}: {e}",
                    im.id,
                    im.file_name,
                    path.display()
                ),
            )
        })?;
        if (w as usize, h as usize) != (im.width, im.height) {
            return Err(invalid(
                json,
                format!(
                    "image {} ({:?}) is {w}x{h}, listed as {}x{}",
                    im.id, im.file_name, im.width, im.height
                ),
            ));
        }
        photos.push(BoxPhoto {
            image: path,
            width: im.width,
            height: im.height,
            boxes: Vec::new(),
            ignore: Vec::new(),
            others: Vec::new(),
        });
    }
    for (n, a) in file.annotations.iter().enumerate() {
        let what = match a.id {
            Some(id) => format!("annotation {id}"),
            None => format!("annotation #{}", n + 1),
        };
        let Some(&i) = index.get(&a.image_id) else {
            return Err(invalid(
                json,
                format!("{what}: image id {} is not listed", a.image_id),
            ));
        };
        if !names.contains_key(&a.category_id) {
            return Err(invalid(
                json,
                format!("{what}: category id {} is not listed", a.category_id),
            ));
        }
        let p = &mut photos[i];
        let b = (a.bbox[0], a.bbox[1], a.bbox[2], a.bbox[3]);
        check_box(&p.image, b, p.width, p.height).map_err(|e| {
            let msg = match e {
                DatasetError::Invalid { msg, .. } => msg,
                other => other.to_string(),
            };
            invalid(json, format!("{what} ({}): {msg}", p.image.display()))
        })?;
        match (a.category_id == cat, a.iscrowd != 0) {
            (true, false) => p.boxes.push(b),
            (true, true) => p.ignore.push(b),
            (false, _) => p.others.push(b),
        }
    }
    let out = BoxPhotos {
        category: category.to_string(),
        photos,
    };
    if out.box_count() == 0 {
        return Err(invalid(
            json,
            format!("no box of {category:?} (other than ignored ones)"),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A folder with two 40x30 photographs and a COCO file `ann.json`
    /// beside them, its content given.
    fn fixture(tag: &str, json: serde_json::Value) -> (PathBuf, PathBuf) {
        let dir = std::env::temp_dir().join(format!("sdhop-boxes-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("rgb")).unwrap();
        for name in ["a.png", "b.png"] {
            image::RgbImage::new(40, 30)
                .save(dir.join("rgb").join(name))
                .unwrap();
        }
        let path = dir.join("ann.json");
        std::fs::write(&path, json.to_string()).unwrap();
        (dir, path)
    }

    fn good() -> serde_json::Value {
        serde_json::json!({
            "images": [
                {"id": 1, "file_name": "rgb/a.png", "width": 40, "height": 30},
                {"id": 2, "file_name": "rgb/b.png", "width": 40, "height": 30}
            ],
            "categories": [{"id": 1, "name": "ape"}, {"id": 6, "name": "cat"}],
            "annotations": [
                {"id": 1, "image_id": 1, "category_id": 1, "bbox": [-5, 2, 20, 15], "iscrowd": 0},
                {"id": 2, "image_id": 1, "category_id": 6, "bbox": [20, 5, 10, 10], "iscrowd": 0},
                {"id": 3, "image_id": 2, "category_id": 1, "bbox": [30, 20, 20, 15], "iscrowd": 1}
            ]
        })
    }

    fn error_of(tag: &str, json: serde_json::Value, category: &str) -> String {
        let (dir, path) = fixture(tag, json);
        let e = load_box_photos(&path, category).unwrap_err().to_string();
        std::fs::remove_dir_all(&dir).ok();
        e
    }

    #[test]
    fn boxes_ignore_regions_and_other_objects_are_read_relative_to_the_file() {
        let (dir, path) = fixture("good", good());
        let ape = load_box_photos(&path, "ape").unwrap();
        assert_eq!(ape.photos.len(), 2);
        assert_eq!(ape.photos[0].image, dir.join("rgb/a.png"));
        // A box past the border is the object's full extent: kept.
        assert_eq!(ape.photos[0].boxes, vec![(-5.0, 2.0, 20.0, 15.0)]);
        assert_eq!(ape.photos[0].others, vec![(20.0, 5.0, 10.0, 10.0)]);
        assert!(ape.photos[1].boxes.is_empty());
        assert_eq!(ape.photos[1].ignore.len(), 1);
        assert_eq!(ape.box_count(), 1);
        let cat = load_box_photos(&path, "cat").unwrap();
        assert_eq!(cat.photos[0].boxes, vec![(20.0, 5.0, 10.0, 10.0)]);
        assert_eq!(cat.photos[0].others.len(), 1);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn bad_files_are_refused_with_errors_that_name_the_fault() {
        let e = error_of("unknown", good(), "duck");
        assert!(e.contains("\"duck\"") && e.contains("ape, cat"), "{e}");
        let mut j = good();
        j["images"][1]["file_name"] = "rgb/missing.png".into();
        let e = error_of("missing", j, "ape");
        assert!(e.contains("missing.png") && e.contains("image 2"), "{e}");
        let mut j = good();
        j["images"][0]["file_name"] = "".into();
        assert!(error_of("empty-name", j, "ape").contains("empty file_name"));
        let mut j = good();
        j["images"][0]["width"] = 64.into();
        let e = error_of("size", j, "ape");
        assert!(e.contains("40x30") && e.contains("64x30"), "{e}");
        let mut j = good();
        j["annotations"][1]["bbox"] = serde_json::json!([45, 5, 10, 10]);
        let e = error_of("outside", j, "ape");
        assert!(e.contains("annotation 2") && e.contains("outside"), "{e}");
        let mut j = good();
        j["annotations"][0]["bbox"] = serde_json::json!([5, 5, 0, 10]);
        let e = error_of("degenerate", j, "ape");
        assert!(
            e.contains("annotation 1") && e.contains("degenerate"),
            "{e}"
        );
        let mut j = good();
        j["annotations"][0]["image_id"] = 9.into();
        assert!(error_of("no-image", j, "ape").contains("image id 9 is not listed"));
        let mut j = good();
        j["annotations"][0]["category_id"] = 3.into();
        assert!(error_of("no-cat", j, "ape").contains("category id 3 is not listed"));
        // Only an ignored box of the category: nothing to train on.
        let mut j = good();
        j["annotations"][0]["iscrowd"] = 1.into();
        assert!(error_of("crowd-only", j, "ape").contains("no box of \"ape\""));
        let mut j = good();
        j["images"][1]["id"] = 1.into();
        assert!(error_of("twice", j, "ape").contains("listed twice"));
    }

    #[test]
    fn an_empty_or_broken_file_is_refused() {
        let e = error_of("empty", serde_json::json!({}), "ape");
        assert!(e.contains("no photographs"), "{e}");
        let (dir, path) = fixture("broken", good());
        std::fs::write(&path, "").unwrap();
        let e = load_box_photos(&path, "ape").unwrap_err().to_string();
        assert!(e.contains("not COCO JSON"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
        let e = load_box_photos(Path::new("/nonexistent/boxes.json"), "ape").unwrap_err();
        assert!(matches!(e, DatasetError::Io { .. }));
    }
}
