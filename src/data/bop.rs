//! The BOP layout (Hodaň et al.): `models/models_info.json` and
//! `models/obj_NNNNNN.ply`, and per scene `test/SSSSSS/` with
//! `scene_camera.json` (`cam_K`), `scene_gt.json` (`cam_R_m2c`,
//! `cam_t_m2c`, `obj_id`), `scene_gt_info.json` (`visib_fract`, and
//! `oracle_visib_fract` where the visible masks were rendered from the
//! annotated poses only), `rgb/NNNNNN.png` and
//! `mask_visib/NNNNNN_KKKKKK.png`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::{invalid, DatasetError};

/// An object of `models_info.json`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct ModelInfo {
    /// Diameter, mesh units (mm in BOP).
    pub diameter: f64,
    /// Discrete symmetries: 4x4 row-major object-frame transforms.
    #[serde(default)]
    pub symmetries_discrete: Vec<Vec<f64>>,
}

/// One annotated instance of one image.
#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    /// Its index in the image's list (the `KKKKKK` of its masks).
    pub k: usize,
    pub obj_id: u32,
    /// Camera-from-object rotation, row-major (BOP's may be up to 1% off
    /// orthonormal).
    pub rotation: [f64; 9],
    /// Camera-from-object translation, mesh units.
    pub translation: [f64; 3],
    pub visib_fract: f64,
    /// The visible fraction of `mask_visib` where it was rendered from
    /// the annotated poses only; `None` when not given.
    pub oracle_visib_fract: Option<f64>,
    /// The box `(x, y, w, h)` of the object's full extent (hidden parts
    /// included), `bbox_obj` of `scene_gt_info.json`; `None` when not given.
    pub bbox_obj: Option<[f64; 4]>,
}

/// BOP's names of the Linemod(-Occluded) objects by id, the labels their
/// detectors carry.
pub const LINEMOD_NAMES: [(u32, &str); 15] = [
    (1, "ape"),
    (2, "benchvise"),
    (3, "bowl"),
    (4, "camera"),
    (5, "can"),
    (6, "cat"),
    (7, "cup"),
    (8, "driller"),
    (9, "duck"),
    (10, "eggbox"),
    (11, "glue"),
    (12, "holepuncher"),
    (13, "iron"),
    (14, "lamp"),
    (15, "phone"),
];

/// One image: its intrinsics (`cam_K`, row-major) and instances.
#[derive(Clone, Debug, PartialEq)]
pub struct BopImage {
    pub scene: String,
    pub id: u32,
    pub cam_k: [f64; 9],
    pub instances: Vec<Instance>,
}

/// A BOP dataset's test scenes and models.
#[derive(Clone, Debug)]
pub struct Bop {
    pub root: PathBuf,
    pub models: BTreeMap<u32, ModelInfo>,
    /// Every image of every scene, in scene and id order.
    pub images: Vec<BopImage>,
}

#[derive(Deserialize)]
struct GtEntry {
    cam_r_m2c: Vec<f64>,
    cam_t_m2c: Vec<f64>,
    obj_id: u32,
}

#[derive(Deserialize)]
struct InfoEntry {
    visib_fract: f64,
    #[serde(default)]
    oracle_visib_fract: Option<f64>,
    #[serde(default)]
    bbox_obj: Option<[f64; 4]>,
}

#[derive(Deserialize)]
struct CameraEntry {
    #[serde(rename = "cam_K")]
    cam_k: Vec<f64>,
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| DatasetError::Io {
        path: path.to_path_buf(),
        source: e,
    })?;
    // BOP writes cam_R_m2c in that case; serde's field names are lower case.
    let text = text.replace("\"cam_R_m2c\"", "\"cam_r_m2c\"");
    serde_json::from_str(&text).map_err(|e| invalid(path, e.to_string()))
}

impl Bop {
    /// Reads `models/models_info.json` and every scene under `test/`.
    pub fn load(root: &Path) -> Result<Self, DatasetError> {
        let info: BTreeMap<String, ModelInfo> =
            read_json(&root.join("models").join("models_info.json"))?;
        let models = info
            .into_iter()
            .map(|(k, v)| {
                let id = k.parse().map_err(|_| {
                    invalid(
                        &root.join("models/models_info.json"),
                        format!("object id {k:?}"),
                    )
                })?;
                Ok((id, v))
            })
            .collect::<Result<BTreeMap<u32, ModelInfo>, DatasetError>>()?;
        let test = root.join("test");
        let mut scenes: Vec<PathBuf> = std::fs::read_dir(&test)
            .map_err(|e| DatasetError::Io {
                path: test.clone(),
                source: e,
            })?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("scene_gt.json").is_file())
            .collect();
        scenes.sort();
        let mut images = Vec::new();
        for dir in scenes {
            let scene = dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let gt: BTreeMap<String, Vec<GtEntry>> = read_json(&dir.join("scene_gt.json"))?;
            let info: BTreeMap<String, Vec<InfoEntry>> =
                read_json(&dir.join("scene_gt_info.json"))?;
            let cams: BTreeMap<String, CameraEntry> = read_json(&dir.join("scene_camera.json"))?;
            let bad = |msg: String| invalid(&dir, msg);
            let mut ids: Vec<(u32, &String)> = gt
                .keys()
                .map(|k| {
                    k.parse()
                        .map(|id| (id, k))
                        .map_err(|_| bad(format!("image id {k:?}")))
                })
                .collect::<Result<_, _>>()?;
            ids.sort();
            for (id, key) in ids {
                let cam = cams
                    .get(key)
                    .ok_or_else(|| bad(format!("image {key} has no camera")))?;
                let infos = info
                    .get(key)
                    .ok_or_else(|| bad(format!("image {key} has no gt info")))?;
                let cam_k: [f64; 9] = cam
                    .cam_k
                    .as_slice()
                    .try_into()
                    .map_err(|_| bad(format!("image {key}: cam_K is not 3x3")))?;
                let mut instances = Vec::new();
                for (k, (g, i)) in gt[key].iter().zip(infos).enumerate() {
                    let rotation: [f64; 9] = g
                        .cam_r_m2c
                        .as_slice()
                        .try_into()
                        .map_err(|_| bad(format!("image {key}, instance {k}: rotation")))?;
                    let translation: [f64; 3] = g
                        .cam_t_m2c
                        .as_slice()
                        .try_into()
                        .map_err(|_| bad(format!("image {key}, instance {k}: translation")))?;
                    instances.push(Instance {
                        k,
                        obj_id: g.obj_id,
                        rotation,
                        translation,
                        visib_fract: i.visib_fract,
                        oracle_visib_fract: i.oracle_visib_fract,
                        bbox_obj: i.bbox_obj,
                    });
                }
                images.push(BopImage {
                    scene: scene.clone(),
                    id,
                    cam_k,
                    instances,
                });
            }
        }
        Ok(Self {
            root: root.to_path_buf(),
            models,
            images,
        })
    }

    /// The photograph of an image.
    pub fn rgb_path(&self, image: &BopImage) -> PathBuf {
        self.root
            .join("test")
            .join(&image.scene)
            .join("rgb")
            .join(format!("{:06}.png", image.id))
    }

    /// The visible mask of instance `k` of an image.
    pub fn mask_visib_path(&self, image: &BopImage, k: usize) -> PathBuf {
        self.root
            .join("test")
            .join(&image.scene)
            .join("mask_visib")
            .join(format!("{:06}_{:06}.png", image.id, k))
    }

    /// The mesh of an object.
    pub fn model_path(&self, obj_id: u32) -> PathBuf {
        self.root
            .join("models")
            .join(format!("obj_{obj_id:06}.ply"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_a_small_scene() {
        let dir = std::env::temp_dir().join(format!("sdhop-bop-{}", std::process::id()));
        let scene = dir.join("test/000002");
        std::fs::create_dir_all(&scene).unwrap();
        std::fs::create_dir_all(dir.join("models")).unwrap();
        std::fs::write(
            dir.join("models/models_info.json"),
            r#"{"1": {"diameter": 102.1, "min_x": 0}, "11": {"diameter": 175.9,
               "symmetries_discrete": [[-1,0,0,0, 0,-1,0,0, 0,0,1,0, 0,0,0,1]]}}"#,
        )
        .unwrap();
        std::fs::write(
            scene.join("scene_gt.json"),
            r#"{"3": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [1,2,1000], "obj_id": 1}]}"#,
        )
        .unwrap();
        std::fs::write(
            scene.join("scene_gt_info.json"),
            r#"{"3": [{"visib_fract": 0.5, "oracle_visib_fract": 0.55, "bbox_obj": [1,2,3,4]}]}"#,
        )
        .unwrap();
        std::fs::write(
            scene.join("scene_camera.json"),
            r#"{"3": {"cam_K": [572,0,325,0,573,242,0,0,1], "depth_scale": 1.0}}"#,
        )
        .unwrap();
        let bop = Bop::load(&dir).unwrap();
        assert_eq!(bop.models.len(), 2);
        assert_eq!(bop.models[&11].symmetries_discrete.len(), 1);
        assert_eq!(bop.images.len(), 1);
        let im = &bop.images[0];
        assert_eq!((im.id, im.scene.as_str()), (3, "000002"));
        assert_eq!(im.instances[0].translation, [1.0, 2.0, 1000.0]);
        assert_eq!(im.instances[0].oracle_visib_fract, Some(0.55));
        assert!(bop
            .mask_visib_path(im, 0)
            .ends_with("test/000002/mask_visib/000003_000000.png"));
        std::fs::write(scene.join("scene_camera.json"), "{}").unwrap();
        assert!(Bop::load(&dir).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
