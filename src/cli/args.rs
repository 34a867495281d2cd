//! Argument groups shared by several commands: the training settings
//! (`train`, `cv`) and the background photographs of the pose benchmark
//! (`pose-data`, `pose-bench`).

use super::*;

/// Every training setting; flags override the `--config` JSON file.
#[derive(clap::Args, Clone)]
pub(crate) struct TrainSettings {
    /// JSON file with any of the training settings (see `TrainParams` in
    /// the docs: c, k, template_scale, template, pyramid, segmentation,
    /// max_truncation, epsilon, max_passes, max_inner, init_locations,
    /// mining_passes, mining_budget, cache_size, positive_share, loss, seg_weight, hop,
    /// pairwise, occlusion, pair_mode, seed, background_regions, threshold).
    #[arg(long)]
    pub(crate) config: Option<PathBuf>,
    /// Regularisation constant C.
    #[arg(long)]
    pub(crate) c: Option<f64>,
    /// Standard clique size K of the higher-order potentials.
    #[arg(long)]
    pub(crate) k: Option<usize>,
    /// Template size as a fraction of the median training box.
    #[arg(long)]
    pub(crate) template_scale: Option<f64>,
    /// Template size in cells, ROWSxCOLS (overrides --template-scale).
    #[arg(long, value_parser = parse_template)]
    pub(crate) template: Option<[usize; 2]>,
    /// What a cell's vector is: `hog` (Felzenszwalb's HOG) or `cnn` (the
    /// pretrained EfficientNet-Lite0 backbone's cells, built in; see
    /// docs/training.md, "Learned cells"). Default: `cnn` for `train
    /// --coco`, `hog` for the CMU_KO8 routes and `mesh` (what won on the
    /// development data of each).
    #[arg(long, value_parser = FeatureKind::parse)]
    pub(crate) features: Option<FeatureKind>,
    /// Pyramid levels per octave.
    #[arg(long)]
    pub(crate) levels_per_octave: Option<u32>,
    /// Smallest pyramid scale.
    #[arg(long)]
    pub(crate) min_scale: Option<f32>,
    /// Largest pyramid scale (above 1: upsampled levels for small objects).
    #[arg(long)]
    pub(crate) max_scale: Option<f32>,
    /// Felzenszwalb-Huttenlocher k (segment size preference).
    #[arg(long)]
    pub(crate) seg_k: Option<f32>,
    /// Stopping tolerance of the cutting-plane algorithm.
    #[arg(long)]
    pub(crate) epsilon: Option<f64>,
    /// Full searches over every location, at most.
    #[arg(long)]
    pub(crate) max_passes: Option<usize>,
    /// Iterations over cached locations per full search, at most.
    #[arg(long)]
    pub(crate) max_inner: Option<usize>,
    /// Locations per image, in order of their bound, that a hard-example
    /// mining search reaches (default 300; `mesh --photos`: 1024).
    #[arg(long)]
    pub(crate) mining_budget: Option<usize>,
    /// First full searches that mine hard examples with a budget instead of
    /// being exact; a mining search that finds nothing is followed by an
    /// exact one, which decides convergence (default 0: every full search
    /// is exact; `mesh --photos`: every pass mines).
    #[arg(long)]
    pub(crate) mining_passes: Option<usize>,
    /// `mesh --photos`: check a mining search that finds nothing by an
    /// exact one before the training ends (slower; by default the mining
    /// search decides there).
    #[arg(long)]
    pub(crate) exact_check: bool,
    /// Most locations cached per image between full searches.
    #[arg(long)]
    pub(crate) cache_size: Option<usize>,
    /// Random seed (initial locations).
    #[arg(long)]
    pub(crate) seed: Option<u64>,
    /// Each positive photograph also trains as this many negative examples,
    /// one per region of a grid over it, away from its instances (its own
    /// clutter as hard negatives; 0: none). See docs/training.md.
    #[arg(long)]
    pub(crate) background_regions: Option<usize>,
    /// Loss: sd-hop (eq. 3) or gao (ablation).
    #[arg(long, value_enum)]
    pub(crate) loss: Option<LossKind>,
    /// Ablation: no higher-order potentials.
    #[arg(long)]
    pub(crate) no_hop: bool,
    /// Ablation: no pairwise term.
    #[arg(long)]
    pub(crate) no_pairwise: bool,
    /// Ablation: no occlusion reasoning (plain HOG templates: every cell
    /// visible, the loss compares boxes only).
    #[arg(long)]
    pub(crate) no_occlusion: bool,
    /// Ablation: pairwise terms only between neighbouring cells along an
    /// image edge, as Gao et al. 2011 (default: every 4-connected pair).
    #[arg(long)]
    pub(crate) edge_pairwise: bool,
    /// Detection threshold saved in the models (default -0.75; -1.0 for
    /// models trained without masked photographs, `train --sources` without
    /// `single`).
    #[arg(long, allow_negative_numbers = true)]
    pub(crate) threshold: Option<f64>,
    /// Images of each other object used as negatives.
    #[arg(long, default_value_t = 10)]
    pub(crate) other_negatives: usize,
    /// Negative scenes used (from negative/).
    #[arg(long, default_value_t = 100)]
    pub(crate) negative_scenes: usize,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub(crate) threads: Option<usize>,
}

impl TrainSettings {
    /// The settings: the `--config` file's, then the flags'. `features` is
    /// the route's feature kind, taken where neither names one.
    pub(crate) fn params(
        &self,
        features: FeatureKind,
    ) -> Result<(TrainParams, NegativeSet), Failure> {
        let mut p = match &self.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
                let json: serde_json::Value = serde_json::from_str(&text)
                    .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?;
                let named = json.pointer("/pyramid/features").is_some();
                let mut p: TrainParams = serde_json::from_value(json)
                    .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?;
                if !named {
                    p.pyramid.features = features;
                }
                p
            }
            None => {
                let mut p = TrainParams::default();
                p.pyramid.features = features;
                p
            }
        };
        if let Some(v) = self.c {
            p.c = v;
        }
        if let Some(v) = self.k {
            p.k = v;
        }
        if let Some(v) = self.template_scale {
            p.template_scale = v;
        }
        if self.template.is_some() {
            p.template = self.template;
        }
        if let Some(v) = self.features {
            p.pyramid.features = v;
        }
        if let Some(v) = self.levels_per_octave {
            p.pyramid.levels_per_octave = v;
        }
        if let Some(v) = self.min_scale {
            p.pyramid.min_scale = v;
        }
        if let Some(v) = self.max_scale {
            p.pyramid.max_scale = v;
        }
        if let Some(v) = self.seg_k {
            p.segmentation.k = v;
        }
        if let Some(v) = self.epsilon {
            p.epsilon = v;
        }
        if let Some(v) = self.max_passes {
            p.max_passes = v;
        }
        if let Some(v) = self.max_inner {
            p.max_inner = v;
        }
        if let Some(v) = self.mining_budget {
            p.mining_budget = v;
        }
        if let Some(v) = self.mining_passes {
            p.mining_passes = v;
        }
        if let Some(v) = self.cache_size {
            p.cache_size = v;
        }
        if let Some(v) = self.seed {
            p.seed = v;
        }
        if let Some(v) = self.background_regions {
            p.background_regions = v;
        }
        if let Some(v) = self.loss {
            p.loss = v;
        }
        if let Some(v) = self.threshold {
            p.threshold = v;
        }
        p.hop &= !self.no_hop;
        p.pairwise &= !self.no_pairwise;
        p.occlusion &= !self.no_occlusion;
        if self.edge_pairwise {
            p.pair_mode = PairwiseMode::Edges;
        }
        p.validate().map_err(Failure::input)?;
        if let Some(t) = self.threads {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build_global()
                .map_err(Failure::io)?;
        }
        let neg = NegativeSet {
            scenes: self.negative_scenes,
            per_other_object: self.other_negatives,
        };
        Ok((p, neg))
    }
}

pub(crate) fn parse_template(s: &str) -> Result<[usize; 2], String> {
    let (r, c) = s.split_once('x').ok_or("expected ROWSxCOLS")?;
    let r: usize = r.parse().map_err(|_| "bad rows")?;
    let c: usize = c.parse().map_err(|_| "bad cols")?;
    Ok([r, c])
}

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
