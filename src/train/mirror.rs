//! Mirrored copies of the training photographs: each annotated photograph
//! also trains as its mirror image (box and visible mask mirrored), DPM's
//! and most detectors' cheapest augmentation. An object seen from one side
//! and mirrored looks much like the object seen from the other side where
//! it has a plane of symmetry (animals, tools, kitchenware), so a few
//! photographs from one walk around a scene cover more of the views a
//! detector meets later.

use std::path::PathBuf;

use indicatif::ProgressBar;
use rayon::prelude::*;

use super::{PyramidCache, TrainError};
use crate::data::{load_image, Annotation, Sample};
use crate::vision::pyramid::{FeaturePyramid, PyramidParams};
use crate::vision::segment::SegmentParams;

/// What a mirrored photograph's path and id end with.
pub const MIRROR_SUFFIX: &str = "#mirrored";

/// The path under which the mirror image of `image` is cached.
pub fn mirror_path(image: &std::path::Path) -> PathBuf {
    let mut s = image.as_os_str().to_owned();
    s.push(MIRROR_SUFFIX);
    PathBuf::from(s)
}

/// `annotation` of a `width` pixels wide photograph, mirrored.
pub fn mirror_annotation(a: &Annotation, width: f64) -> Annotation {
    let (x, y, w, h) = a.bbox;
    Annotation {
        bbox: (width - x - w, y, w, h),
        visible: a.visible.mirrored(),
        ..a.clone()
    }
}

/// `samples` with every sample whose annotation passes `which` followed by
/// its mirror image, whose pyramid (with `pyramid` and `seg`) goes into
/// `cache`; the others (negatives among them) are kept as they are. Each
/// photograph is read and mirrored once however many instances it has.
pub fn with_mirrors(
    samples: &[Sample],
    which: impl Fn(&Annotation) -> bool,
    cache: &PyramidCache,
    pyramid: &PyramidParams,
    seg: &SegmentParams,
    progress: &ProgressBar,
) -> Result<Vec<Sample>, TrainError> {
    let mut photos: Vec<&PathBuf> = Vec::new();
    for s in samples
        .iter()
        .filter(|s| s.annotation.as_ref().is_some_and(&which))
    {
        if !photos.contains(&&s.image) {
            photos.push(&s.image);
        }
    }
    progress.set_length(photos.len() as u64);
    progress.set_position(0);
    let widths: Vec<(PathBuf, f64)> = photos
        .par_iter()
        .map(|p| {
            let img = load_image(p)?.mirrored();
            let pyr = FeaturePyramid::build(&img, pyramid, seg)?;
            let width = pyr.image_width as f64;
            cache.insert(mirror_path(p), pyr);
            progress.inc(1);
            Ok(((*p).clone(), width))
        })
        .collect::<Result<_, TrainError>>()?;
    let mut out = Vec::with_capacity(samples.len() + widths.len());
    for s in samples {
        out.push(s.clone());
        let Some(a) = s.annotation.as_ref().filter(|a| which(a)) else {
            continue;
        };
        let Some((_, width)) = widths.iter().find(|(p, _)| *p == s.image) else {
            continue;
        };
        out.push(Sample {
            image: mirror_path(&s.image),
            id: format!("{}{MIRROR_SUFFIX}", s.id),
            annotation: Some(mirror_annotation(a, *width)),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::mask::Mask;

    #[test]
    fn a_mirrored_annotation_mirrors_its_box_and_mask() {
        let mut visible = Mask::new(10, 4);
        for x in 1..4 {
            visible.set(x, 2, true);
        }
        let a = Annotation {
            label: "thing".into(),
            bbox: (1.0, 1.0, 3.0, 2.0),
            visible,
            viewpoint: 0,
            mask_known: false,
        };
        let m = mirror_annotation(&a, 10.0);
        assert_eq!(m.bbox, (6.0, 1.0, 3.0, 2.0));
        for x in 0..10 {
            assert_eq!(m.visible.get(x, 2), (6..9).contains(&x), "x {x}");
        }
        assert_eq!(m.label, "thing");
        assert!(!m.mask_known);
        // Twice is the identity.
        assert_eq!(mirror_annotation(&m, 10.0), a);
        assert_eq!(
            mirror_path(std::path::Path::new("a/b.png")),
            PathBuf::from("a/b.png#mirrored")
        );
    }
}
