//! Shared setup of the bound-feasibility examples: a shipped CMU_KO8 model
//! and its development photographs.

use std::path::PathBuf;

use sdhop::model::Model;

/// `models/NAME.safetensors` and the sorted development photographs of
/// `NAME` (the first command-line argument, default cup; the second is
/// how many photographs to use, default 3).
pub fn model_and_images() -> (String, Model, Vec<PathBuf>, usize) {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or_else(|| "cup".into());
    let n_img: usize = args.get(2).and_then(|v| v.parse().ok()).unwrap_or(3);
    let model = Model::load(std::path::Path::new(&format!("models/{name}.safetensors")))
        .expect("a shipped model");
    let dir = format!("../shared/data/cmu_ko8/single/test/{name}");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("../shared/data/cmu_ko8")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
        .collect();
    files.sort();
    (name, model, files, n_img)
}

/// Cells of a box of `len` cells from `s` inside `[0, size)`.
pub fn overlap(s: isize, len: usize, size: usize) -> usize {
    ((s + len as isize).min(size as isize) - s.max(0)).max(0) as usize
}
