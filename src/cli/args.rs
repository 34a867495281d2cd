//! Argument groups shared by several commands: the training settings
//! (`train`, `cv`) and the background photographs of the pose benchmark
//! (`pose-data`, `pose-bench`).

use super::*;

#[derive(clap::Args)]
pub(crate) struct PoseBackgrounds {
    /// Folder of background photographs (JPEG or PNG, resized to 640x480),
    /// e.g. the CMU_KO8 negatives.
    #[arg(long)]
    pub(crate) backgrounds: PathBuf,
    /// The first N backgrounds (by name) are for training; the benchmark
    /// renders over the others.
    #[arg(long, default_value_t = 50)]
    pub(crate) train_backgrounds: usize,
    /// Objects (default both: box, bottle).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<String>,
}

impl PoseBackgrounds {
    /// The chosen objects and the background files: training ones, then
    /// the benchmark's.
    #[allow(clippy::type_complexity)]
    pub(crate) fn load(
        &self,
    ) -> Result<
        (
            Vec<crate::eval::pose::BenchObject>,
            Vec<PathBuf>,
            Vec<PathBuf>,
        ),
        Failure,
    > {
        let mut objects = crate::eval::pose::objects();
        if !self.objects.is_empty() {
            for name in &self.objects {
                if !objects.iter().any(|o| o.name == name) {
                    return Err(Failure::input(format!(
                        "no benchmark object {name:?} (box, bottle)"
                    )));
                }
            }
            objects.retain(|o| self.objects.iter().any(|n| n == o.name));
        }
        let dir = &self.backgrounds;
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Failure::io(format!("{}: {e}", dir.display())))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension().and_then(|x| x.to_str()).is_some_and(|x| {
                    matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png")
                })
            })
            .collect();
        files.sort();
        if files.len() <= self.train_backgrounds {
            return Err(Failure::input(format!(
                "{}: {} images, more than --train-backgrounds {} are needed",
                dir.display(),
                files.len(),
                self.train_backgrounds
            )));
        }
        let test = files.split_off(self.train_backgrounds);
        Ok((objects, files, test))
    }
}

/// `--pixel-refine`: "off", or the weights
/// "SHAPE,CELLS,SEGMENTS,BIAS,SMOOTHNESS[,COLOUR]".
pub(crate) fn parse_pixel_refine(text: &str) -> Result<PixelRefine, Failure> {
    if text.trim() == "off" {
        return Ok(PixelRefine {
            enabled: false,
            ..PixelRefine::default()
        });
    }
    let v: Vec<f64> = text
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| Failure::input(format!("--pixel-refine {text:?}: {e}")))?;
    let (shape, cells, segments, bias, smoothness, colour) = match v[..] {
        [a, b, c, d, e] => (a, b, c, d, e, 0.0),
        [a, b, c, d, e, f] => (a, b, c, d, e, f),
        _ => {
            return Err(Failure::input(format!(
                "--pixel-refine {text:?}: expected off or SHAPE,CELLS,SEGMENTS,BIAS,SMOOTHNESS[,COLOUR]"
            )))
        }
    };
    let p = PixelRefine {
        enabled: true,
        shape,
        cells,
        segments,
        bias,
        smoothness,
        colour,
        ..PixelRefine::default()
    };
    p.validate()
        .map_err(|e| Failure::input(format!("--pixel-refine {text:?}: {e}")))?;
    Ok(p)
}
