//! `sdhop-train pose`: refines an object's pose from an image and its
//! mesh; prints the JSON of `POST /pose`.

use super::*;

#[derive(clap::Args)]
pub(crate) struct PoseArgs {
    /// The image (PNG or JPEG).
    #[arg(long)]
    pub(crate) image: PathBuf,
    /// The object's mesh (OBJ or PLY), in the units of the translation.
    #[arg(long)]
    pub(crate) mesh: PathBuf,
    /// JSON parameters: {"intrinsics": {"fx", "fy", "cx", "cy"},
    /// "initial_pose": {"rotation": [[3x3]], "translation": [x, y, z]},
    /// "model": NAME, "mask": "detect" | "provided" | "none",
    /// "max_iterations": N}; the pose is camera-from-object. Without
    /// "initial_pose", "model" (a detector trained from the mesh) gives
    /// the start poses.
    #[arg(long)]
    pub(crate) params: PathBuf,
    /// Visibility mask (PNG, non-zero = visible) for "mask": "provided".
    #[arg(long)]
    pub(crate) mask: Option<PathBuf>,
    /// Folder of detector models for "mask": "detect" or a request
    /// without "initial_pose".
    #[arg(long, default_value = "models")]
    pub(crate) models_dir: PathBuf,
    /// Largest image, in pixels.
    #[arg(long, default_value_t = DEFAULT_MAX_PIXELS)]
    pub(crate) max_pixels: usize,
}

pub(crate) fn run_pose(args: &PoseArgs) -> Result<(), Failure> {
    use crate::pose::api::{estimate, mask_from_image, MaskSource, PoseParams};
    let img = read_image(&args.image, args.max_pixels)?;
    let read =
        |p: &Path| std::fs::read(p).map_err(|e| Failure::io(format!("{}: {e}", p.display())));
    let mesh = crate::pose::Mesh::parse(&read(&args.mesh)?)
        .map_err(|e| Failure::input(format!("{}: {e}", args.mesh.display())))?;
    let params: PoseParams = serde_json::from_slice(&read(&args.params)?)
        .map_err(|e| Failure::input(format!("{}: {e}", args.params.display())))?;
    let mask = match &args.mask {
        Some(p) => {
            let m = image::load_from_memory(&read(p)?)
                .map_err(|e| Failure::input(format!("{}: {e}", p.display())))?;
            Some(mask_from_image(&m))
        }
        None => None,
    };
    let models = if params.mask == Some(MaskSource::Detect) || params.initial_pose.is_none() {
        model_paths(&args.models_dir)?
            .iter()
            .map(|p| Model::load(p).map_err(|e| Failure::input(format!("{}: {e}", p.display()))))
            .collect::<Result<Vec<_>, _>>()?
    } else {
        Vec::new()
    };
    let refs: Vec<&Model> = models.iter().collect();
    let resp = estimate(&img, &mesh, &params, mask, &refs).map_err(Failure::input)?;
    println!(
        "{}",
        serde_json::to_string_pretty(&resp).map_err(Failure::io)?
    );
    Ok(())
}
