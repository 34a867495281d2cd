//! Training photographs that the few given ones do not show, made from
//! them (issue 62): every boxed object is cut out with some of its real
//! surroundings and seen again at another size (a learned cell is not
//! scale-invariant: an object 40 pixels tall and one 150 pixels tall,
//! brought to the template's size, are different vectors), mirrored where
//! the object allows it, with colour and blur jitter, optionally pasted
//! onto another photograph's background (Cut, Paste and Learn, Dwibedi et
//! al., ICCV 2017) and partly covered by a pasted occluder.
//!
//! A crop is a training photograph of its own, its pyramid computed here
//! and kept in the [`PyramidCache`] under a name that is its source
//! photograph's path followed by [`CROP_MARK`]: the box-correction folds
//! train a crop only with its source photograph ([`source_photo`]).

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::views::{feathered, occluder_shape};
use super::{PyramidCache, TrainError, TrainParams};
use crate::data::{load_image, Annotation, Sample};
use crate::vision::image::ColorImage;
use crate::vision::mask::Mask;
use crate::vision::pyramid::FeaturePyramid;
use crate::vision::rng::SplitMix64;
use crate::vision::segment::gaussian_blur;

/// What a crop's path and id carry after its source photograph's.
pub const CROP_MARK: &str = "#crop";

/// How the photographs' objects are seen again; saved in the model's
/// provenance (`photo_augment`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PhotoAugment {
    /// Crops made from each box (0: none).
    pub per_box: usize,
    /// Range of the factor on the object's size, drawn log-uniformly; a
    /// crop is never made smaller than the smallest given box.
    pub scale: [f64; 2],
    /// Surroundings kept on each side of the box, as a fraction of its
    /// size (cut at the photograph's border).
    pub margin: f64,
    /// Mirror half of the crops (objects with a plane of symmetry).
    pub mirror: bool,
    /// Contrast and brightness within `1 +- jitter`, each channel's gain
    /// within `1 +- jitter / 2`.
    pub jitter: f64,
    /// Share of the crops blurred (a Gaussian of 0.5-1.5 pixels).
    pub blur: f64,
    /// Share of the crops whose object (its visible mask where known,
    /// its box otherwise, the outline feathered) is pasted onto a patch of
    /// another photograph away from that photograph's boxes.
    pub paste: f64,
    /// Share of the crops with a patch of another photograph pasted over
    /// part of the object (15-50% of the box's depth from one side).
    pub occluded: f64,
    pub seed: u64,
}

impl Default for PhotoAugment {
    fn default() -> Self {
        Self {
            per_box: 0,
            scale: [0.6, 1.8],
            margin: 0.5,
            mirror: true,
            jitter: 0.2,
            blur: 0.25,
            paste: 0.0,
            occluded: 0.0,
            seed: 11,
        }
    }
}

impl PhotoAugment {
    pub fn validate(&self) -> Result<(), TrainError> {
        let ok = self.per_box <= 16
            && self.scale[0] >= 0.25
            && self.scale[0] <= self.scale[1]
            && self.scale[1] <= 4.0
            && (0.0..=2.0).contains(&self.margin)
            && (0.0..=0.9).contains(&self.jitter)
            && [self.blur, self.paste, self.occluded]
                .iter()
                .all(|s| (0.0..=1.0).contains(s));
        if ok {
            Ok(())
        } else {
            Err(TrainError::NoData(
                "invalid photograph augmentation: per_box 0..16, scale MIN <= MAX in 0.25..4, margin 0..2, jitter 0..0.9, blur, paste and occluded shares 0..1".into(),
            ))
        }
    }
}

/// The photograph a crop was made from (`path` itself for a photograph).
pub fn source_photo(path: &Path) -> PathBuf {
    let s = path.to_string_lossy();
    match s.find(CROP_MARK) {
        Some(i) => PathBuf::from(&s[..i]),
        None => path.to_path_buf(),
    }
}

/// Whether `path` names a crop made here.
pub fn is_crop(path: &Path) -> bool {
    path.to_string_lossy().contains(CROP_MARK)
}

/// `samples` without the crops whose source photograph is not among them
/// (a box-correction fold that holds a photograph out trains none of its
/// crops).
pub fn with_their_photographs(samples: Vec<Sample>) -> Vec<Sample> {
    let photos: HashSet<PathBuf> = samples
        .iter()
        .filter(|s| !is_crop(&s.image))
        .map(|s| s.image.clone())
        .collect();
    samples
        .into_iter()
        .filter(|s| !is_crop(&s.image) || photos.contains(&source_photo(&s.image)))
        .collect()
}

/// One crop: its image and annotation.
pub struct Crop {
    pub image: ColorImage,
    pub annotation: Annotation,
}

/// A rectangle `(x0, y0, x1, y1)` in pixels.
type Rect = (f64, f64, f64, f64);

fn overlaps(a: Rect, b: Rect) -> bool {
    a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
}

/// The pixels of `img` inside `r` (whole pixels, inside the image).
fn cut(img: &ColorImage, r: (usize, usize, usize, usize)) -> Result<ColorImage, TrainError> {
    let (x0, y0, x1, y1) = r;
    let mut data = Vec::with_capacity((x1 - x0) * (y1 - y0) * 3);
    for y in y0..y1 {
        for x in x0..x1 {
            for c in 0..3 {
                data.push(img.get(x, y, c));
            }
        }
    }
    Ok(ColorImage::new(x1 - x0, y1 - y0, data)?)
}

/// `mask` inside `r`, resampled (nearest) to `w x h`.
fn cut_mask(mask: &Mask, r: (usize, usize, usize, usize), w: usize, h: usize) -> Mask {
    let (x0, y0, x1, y1) = r;
    let (sx, sy) = ((x1 - x0) as f64 / w as f64, (y1 - y0) as f64 / h as f64);
    let mut out = Mask::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let px = (x0 + ((x as f64 + 0.5) * sx) as usize).min(x1 - 1);
            let py = (y0 + ((y as f64 + 0.5) * sy) as usize).min(y1 - 1);
            if px < mask.width && py < mask.height && mask.get(px, py) {
                out.set(x, y, true);
            }
        }
    }
    out
}

/// The box `b` (pixels) as a mask of a `w x h` image.
fn box_mask(b: Rect, w: usize, h: usize) -> Mask {
    let mut m = Mask::new(w, h);
    let clip = |v: f64, hi: usize| (v.max(0.0) as usize).min(hi);
    for y in clip(b.1.floor(), h)..clip(b.3.ceil(), h) {
        for x in clip(b.0.floor(), w)..clip(b.2.ceil(), w) {
            m.set(x, y, true);
        }
    }
    m
}

/// A `w x h` patch of `bg` at a random place away from `avoid` (its
/// boxes of the object), at the photograph's own scale; `None` when ten
/// draws found no such place.
fn free_patch(
    bg: &ColorImage,
    avoid: &[Rect],
    w: usize,
    h: usize,
    rng: &mut SplitMix64,
) -> Option<ColorImage> {
    let (bw, bh) = (bg.width(), bg.height());
    if w > bw || h > bh {
        return None;
    }
    for _ in 0..10 {
        let x0 = rng.range_usize(0, bw - w + 1);
        let y0 = rng.range_usize(0, bh - h + 1);
        let r = (x0 as f64, y0 as f64, (x0 + w) as f64, (y0 + h) as f64);
        if !avoid.iter().any(|&a| overlaps(a, r)) {
            return cut(bg, (x0, y0, x0 + w, y0 + h)).ok();
        }
    }
    None
}

/// `top` over `bottom` by the weights `alpha` (0..1 per pixel).
fn blend(top: &mut [f32], bottom: &[f32], alpha: &[f32]) {
    for (i, &a) in alpha.iter().enumerate() {
        for c in 0..3 {
            let j = i * 3 + c;
            top[j] = a * top[j] + (1.0 - a) * bottom[j];
        }
    }
}

fn jitter(data: &mut [f32], j: f64, rng: &mut SplitMix64) {
    let contrast = rng.range_f64(1.0 - j, 1.0 + j) as f32;
    let bright = (rng.range_f64(-j, j) * 80.0) as f32;
    let gains: Vec<f32> = (0..3)
        .map(|_| rng.range_f64(1.0 - j / 2.0, 1.0 + j / 2.0) as f32)
        .collect();
    for (i, v) in data.iter_mut().enumerate() {
        *v = (((*v - 128.0) * contrast + 128.0 + bright) * gains[i % 3]).clamp(0.0, 255.0);
    }
}

/// Other photographs (with their boxes of the object) to paste onto.
pub struct Backdrops<'a> {
    pub images: &'a [(ColorImage, Vec<Rect>)],
}

/// One crop of the object annotated by `a` in `img` (see the module's
/// notes); `smallest` is the longer side of the smallest given box.
pub fn crop_object(
    img: &ColorImage,
    a: &Annotation,
    smallest: f64,
    p: &PhotoAugment,
    backdrops: &Backdrops,
    rng: &mut SplitMix64,
) -> Result<Crop, TrainError> {
    let (bx, by, bw, bh) = a.bbox;
    let (iw, ih) = (img.width(), img.height());
    let lo = p.scale[0].max(smallest / bw.max(bh).max(1.0));
    let scale = if lo >= p.scale[1] {
        lo
    } else {
        (rng.range_f64(lo.ln(), p.scale[1].ln())).exp()
    };
    let clip = |v: f64, hi: usize| (v.round().max(0.0) as usize).min(hi);
    let r = (
        clip(bx - p.margin * bw, iw),
        clip(by - p.margin * bh, ih),
        clip(bx + bw + p.margin * bw, iw),
        clip(by + bh + p.margin * bh, ih),
    );
    if r.2 <= r.0 + 1 || r.3 <= r.1 + 1 {
        return Err(TrainError::NoData("a box outside its photograph".into()));
    }
    let (cw, ch) = (r.2 - r.0, r.3 - r.1);
    let (w, h) = (
        ((cw as f64 * scale).round() as usize).max(8),
        ((ch as f64 * scale).round() as usize).max(8),
    );
    let (sx, sy) = (w as f64 / cw as f64, h as f64 / ch as f64);
    let mut image = cut(img, r)?.resize_smooth(w, h)?;
    let b = (
        (bx - r.0 as f64) * sx,
        (by - r.1 as f64) * sy,
        (bx + bw - r.0 as f64) * sx,
        (by + bh - r.1 as f64) * sy,
    );
    let mut visible = if a.mask_known {
        cut_mask(&a.visible, r, w, h)
    } else {
        box_mask(b, w, h)
    };
    let mut data = image.data().to_vec();
    if rng.next_f64() < p.paste && !backdrops.images.is_empty() {
        let (bg, avoid) = &backdrops.images[rng.range_usize(0, backdrops.images.len())];
        if let Some(patch) = free_patch(bg, avoid, w, h, rng) {
            blend(&mut data, patch.data(), &feathered(&visible));
        }
    }
    if rng.next_f64() < p.occluded && !backdrops.images.is_empty() {
        let (bg, avoid) = &backdrops.images[rng.range_usize(0, backdrops.images.len())];
        if let Some(patch) = free_patch(bg, avoid, w, h, rng) {
            let shape = occluder_shape(b, rng.range_f64(0.15, 0.5), w, h, rng);
            let mut over = patch.data().to_vec();
            blend(&mut over, &data, &feathered(&shape));
            data = over;
            for (v, s) in visible.data.iter_mut().zip(&shape.data) {
                if *s != 0 {
                    *v = 0;
                }
            }
        }
    }
    if p.jitter > 0.0 {
        jitter(&mut data, p.jitter, rng);
    }
    image = ColorImage::new(w, h, data)?;
    if rng.next_f64() < p.blur {
        image = gaussian_blur(&image, rng.range_f64(0.5, 1.5) as f32);
    }
    let mut bbox = (b.0, b.1, b.2 - b.0, b.3 - b.1);
    if p.mirror && rng.next_f64() < 0.5 {
        image = image.mirrored();
        visible = visible.mirrored();
        bbox.0 = w as f64 - bbox.0 - bbox.2;
    }
    Ok(Crop {
        image,
        annotation: Annotation {
            bbox,
            visible,
            ..a.clone()
        },
    })
}

/// `samples` followed by `p.per_box` crops of every annotated photograph
/// (not those in `skip`, nor mirror images), whose pyramids (with
/// `params`' settings) go into `cache`; the crops' paths
/// (which the caller keeps out of background examples and box-correction
/// folds that hold their photograph out) are returned beside.
pub fn with_crops(
    samples: &[Sample],
    p: &PhotoAugment,
    skip: &HashSet<PathBuf>,
    cache: &PyramidCache,
    params: &TrainParams,
    progress: &ProgressBar,
) -> Result<(Vec<Sample>, HashSet<PathBuf>), TrainError> {
    p.validate()?;
    // Photographs on disk only: not the renders, nor mirror images.
    let positives: Vec<&Sample> = samples
        .iter()
        .filter(|s| s.annotation.is_some() && !skip.contains(&s.image))
        .filter(|s| !s.image.to_string_lossy().contains('#'))
        .collect();
    if p.per_box == 0 || positives.is_empty() {
        return Ok((samples.to_vec(), HashSet::new()));
    }
    let smallest = positives
        .iter()
        .filter_map(|s| s.annotation.as_ref())
        .map(|a| a.bbox.2.max(a.bbox.3))
        .fold(f64::INFINITY, f64::min);
    let mut photos: Vec<PathBuf> = Vec::new();
    for s in &positives {
        if !photos.contains(&s.image) {
            photos.push(s.image.clone());
        }
    }
    let boxes_of = |path: &PathBuf| -> Vec<Rect> {
        positives
            .iter()
            .filter(|s| &s.image == path)
            .filter_map(|s| s.annotation.as_ref())
            .map(|a| (a.bbox.0, a.bbox.1, a.bbox.0 + a.bbox.2, a.bbox.1 + a.bbox.3))
            .collect()
    };
    let loaded: Vec<(ColorImage, Vec<Rect>)> = photos
        .par_iter()
        .map(|path| Ok((load_image(path)?, boxes_of(path))))
        .collect::<Result<_, TrainError>>()?;
    let backdrops = Backdrops { images: &loaded };
    progress.set_length((positives.len() * p.per_box) as u64);
    progress.set_position(0);
    let jobs: Vec<(usize, &Sample, usize)> = positives
        .iter()
        .enumerate()
        .flat_map(|(i, s)| (0..p.per_box).map(move |k| (i, *s, k)))
        .collect();
    let crops: Vec<Sample> = jobs
        .par_iter()
        .map(|&(i, s, k)| {
            let mut rng = SplitMix64::new(p.seed ^ ((i as u64) << 24) ^ (k as u64 + 1));
            let Some(a) = s.annotation.as_ref() else {
                return Ok(None);
            };
            let Some(at) = photos.iter().position(|q| *q == s.image) else {
                return Ok(None);
            };
            let crop = crop_object(&loaded[at].0, a, smallest, p, &backdrops, &mut rng)?;
            let name = format!("{CROP_MARK}{i}.{k}");
            let mut path = s.image.as_os_str().to_owned();
            path.push(&name);
            let path = PathBuf::from(path);
            let pyr = FeaturePyramid::build(&crop.image, &params.pyramid, &params.segmentation)?;
            cache.insert(path.clone(), pyr);
            progress.inc(1);
            Ok(Some(Sample {
                image: path,
                id: format!("{}{name}", s.id),
                annotation: Some(crop.annotation),
            }))
        })
        .collect::<Result<Vec<Option<Sample>>, TrainError>>()?
        .into_iter()
        .flatten()
        .collect();
    let paths = crops.iter().map(|s| s.image.clone()).collect();
    let mut out = samples.to_vec();
    out.extend(crops);
    Ok((out, paths))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photo(w: usize, h: usize) -> ColorImage {
        let data = (0..w * h * 3).map(|i| ((i * 7) % 251) as f32).collect();
        ColorImage::new(w, h, data).unwrap()
    }

    fn annotation(bbox: Rect, w: usize, h: usize, mask_known: bool) -> Annotation {
        let mut visible = Mask::new(w, h);
        // The left half of the box visible.
        for y in bbox.1 as usize..(bbox.1 + bbox.3) as usize {
            for x in bbox.0 as usize..(bbox.0 + bbox.2 / 2.0) as usize {
                visible.set(x, y, true);
            }
        }
        Annotation {
            label: "thing".into(),
            bbox,
            visible,
            viewpoint: 0,
            mask_known,
        }
    }

    /// A crop keeps its box on the object: the box scaled by the crop's
    /// factor, inside the crop, and (masked objects) the visible mask
    /// inside the box; a pasted occluder removes pixels from the mask
    /// and never adds any.
    #[test]
    fn a_crop_keeps_the_box_and_the_visible_pixels_consistent() {
        let img = photo(200, 150);
        let bg = (photo(200, 150), vec![(0.0, 0.0, 20.0, 20.0)]);
        let images = vec![bg];
        let backdrops = Backdrops { images: &images };
        for mask_known in [false, true] {
            let a = annotation((60.0, 40.0, 40.0, 30.0), 200, 150, mask_known);
            let p = PhotoAugment {
                per_box: 1,
                paste: 1.0,
                occluded: 1.0,
                blur: 0.5,
                ..PhotoAugment::default()
            };
            for seed in 0..20 {
                let mut rng = SplitMix64::new(seed);
                let c = crop_object(&img, &a, 10.0, &p, &backdrops, &mut rng).unwrap();
                let (x, y, w, h) = c.annotation.bbox;
                let (iw, ih) = (c.image.width() as f64, c.image.height() as f64);
                assert!(x >= -0.5 && y >= -0.5 && x + w <= iw + 0.5 && y + h <= ih + 0.5);
                // The same aspect, the size the crop's factor gives.
                let s = w / 40.0;
                assert!((h / 30.0 - s).abs() < 0.05, "aspect {w}x{h}");
                assert!((0.55..=1.85).contains(&s), "scale {s}");
                assert_eq!(c.image.width() as f64, (80.0 * s).round().max(8.0));
                assert_eq!(c.annotation.visible.width, c.image.width());
                // Every visible pixel lies in the box.
                let vis = &c.annotation.visible;
                let mut inside = 0;
                for py in 0..vis.height {
                    for px in 0..vis.width {
                        if vis.get(px, py) {
                            let (fx, fy) = (px as f64 + 0.5, py as f64 + 0.5);
                            assert!(fx >= x - 1.0 && fx <= x + w + 1.0);
                            assert!(fy >= y - 1.0 && fy <= y + h + 1.0);
                            inside += 1;
                        }
                    }
                }
                let full = if mask_known { w * h / 2.0 } else { w * h };
                assert!((inside as f64) <= full * 1.15 + 2.0 * (w + h));
                assert_eq!(c.annotation.mask_known, mask_known);
            }
        }
    }

    /// The smallest box bounds the crops' sizes from below.
    #[test]
    fn no_crop_is_smaller_than_the_smallest_box() {
        let img = photo(200, 150);
        let a = annotation((60.0, 40.0, 40.0, 30.0), 200, 150, false);
        let p = PhotoAugment {
            per_box: 1,
            scale: [0.3, 0.5],
            ..PhotoAugment::default()
        };
        let backdrops = Backdrops { images: &[] };
        let mut rng = SplitMix64::new(3);
        let c = crop_object(&img, &a, 36.0, &p, &backdrops, &mut rng).unwrap();
        assert!(c.annotation.bbox.2 >= 35.5, "{:?}", c.annotation.bbox);
    }

    #[test]
    fn a_crop_names_its_photograph() {
        let p = Path::new("a/b.png#crop3.1");
        assert!(is_crop(p));
        assert_eq!(source_photo(p), PathBuf::from("a/b.png"));
        assert_eq!(source_photo(Path::new("a/b.png")), PathBuf::from("a/b.png"));
        assert!(!is_crop(Path::new("a/b.png")));
    }

    #[test]
    fn a_fold_trains_no_crop_of_a_photograph_it_holds_out() {
        let s = |p: &str| Sample::negative(PathBuf::from(p));
        let fold = vec![
            s("a.png"),
            s("a.png#crop0.0"),
            s("a.png#crop0.1"),
            s("b.png#crop1.0"),
            s("c.png"),
        ];
        let kept: Vec<PathBuf> = with_their_photographs(fold)
            .into_iter()
            .map(|s| s.image)
            .collect();
        let want: Vec<PathBuf> = ["a.png", "a.png#crop0.0", "a.png#crop0.1", "c.png"]
            .iter()
            .map(PathBuf::from)
            .collect();
        assert_eq!(kept, want);
    }

    #[test]
    fn invalid_settings_are_refused() {
        for p in [
            PhotoAugment {
                scale: [2.0, 1.0],
                ..PhotoAugment::default()
            },
            PhotoAugment {
                paste: 1.5,
                ..PhotoAugment::default()
            },
        ] {
            assert!(p.validate().is_err());
        }
        assert!(PhotoAugment::default().validate().is_ok());
    }
}

#[cfg(test)]
mod provenance_tests {
    use super::*;

    /// The settings as the model's provenance records them read back as
    /// the same settings, and a provenance without some field reads it as
    /// its default.
    #[test]
    fn the_settings_round_trip_through_the_provenance() {
        let p = PhotoAugment {
            per_box: 3,
            scale: [0.5, 2.0],
            paste: 0.5,
            occluded: 0.25,
            mirror: false,
            ..PhotoAugment::default()
        };
        let mut prov = serde_json::Map::new();
        prov.insert("photo_augment".into(), serde_json::json!(p));
        let text = serde_json::to_string(&prov).unwrap();
        let back: serde_json::Value = serde_json::from_str(&text).unwrap();
        let q: PhotoAugment = serde_json::from_value(back["photo_augment"].clone()).unwrap();
        assert_eq!(p, q);
        let partial: PhotoAugment = serde_json::from_str(r#"{"per_box": 2}"#).unwrap();
        assert_eq!(partial.per_box, 2);
        assert_eq!(partial.scale, PhotoAugment::default().scale);
    }
}
