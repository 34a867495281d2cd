//! `sdhop-train pose-data`: renders the pose benchmark's objects over
//! training backgrounds as a COCO training set.

use super::*;

#[derive(clap::Args)]
pub(crate) struct PoseDataArgs {
    #[command(flatten)]
    pub(crate) bg: PoseBackgrounds,
    /// Training renders per object (a third unoccluded, the rest 10-60%
    /// hidden).
    #[arg(long, default_value_t = 360)]
    pub(crate) scenes: usize,
    /// Folder for `coco.json` and `images/`.
    #[arg(long, default_value = "out/pose-data")]
    pub(crate) out: PathBuf,
}

pub(crate) fn run_pose_data(args: &PoseDataArgs) -> Result<(), Failure> {
    use crate::eval::pose::{scene, BenchSettings};
    let (objects, train, _) = args.bg.load()?;
    let images_dir = args.out.join("images");
    std::fs::create_dir_all(&images_dir)
        .map_err(|e| Failure::io(format!("{}: {e}", images_dir.display())))?;
    let settings = BenchSettings::default();
    let mut images = Vec::new();
    let mut annotations = Vec::new();
    let categories: Vec<_> = objects
        .iter()
        .enumerate()
        .map(|(i, o)| serde_json::json!({"id": i + 1, "name": o.name}))
        .collect();
    let backgrounds: Vec<ColorImage> = train
        .iter()
        .map(|p| background_image(p))
        .collect::<Result<_, _>>()?;
    for (ci, object) in objects.iter().enumerate() {
        for i in 0..args.scenes {
            let occlusion = if i % 3 == 0 { (0.0, 0.0) } else { (0.1, 0.6) };
            let seed = 1_000_000 * (ci as u64 + 1) + i as u64;
            let bg = &backgrounds[i % backgrounds.len()];
            let s = scene(object, bg, occlusion, &settings, seed).map_err(Failure::input)?;
            let name = format!("{}_{i:04}.jpg", object.name);
            let path = images_dir.join(&name);
            s.scene
                .image
                .to_rgb8()
                .save(&path)
                .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
            let id = images.len() + 1;
            images.push(serde_json::json!({
                "id": id, "file_name": format!("images/{name}"), "width": 640, "height": 480
            }));
            let (x, y, w, h) = s.full_box;
            annotations.push(serde_json::json!({
                "id": annotations.len() + 1,
                "image_id": id,
                "category_id": ci + 1,
                "bbox": [x, y, w, h],
                "segmentation": s.scene.visible.to_rle(),
            }));
        }
    }
    // The training backgrounds themselves are the negatives, referred to
    // where they are (absolute paths): nothing third-party is copied.
    for p in &train {
        let abs =
            std::fs::canonicalize(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
        images.push(serde_json::json!({
            "id": images.len() + 1, "file_name": abs, "width": 640, "height": 480
        }));
    }
    let coco = serde_json::json!({
        "images": images, "categories": categories, "annotations": annotations,
        "info": {"description": "sdhop pose benchmark training renders", "settings": settings}
    });
    let path = args.out.join("coco.json");
    std::fs::write(&path, serde_json::to_string(&coco).map_err(Failure::io)?)
        .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
    println!(
        "{} renders of {} objects and {} negatives -> {}",
        annotations.len(),
        objects.len(),
        train.len(),
        path.display()
    );
    Ok(())
}
