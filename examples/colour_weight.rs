//! A model file with another colour weight, for a diagnosis: how much a
//! model's colour weight (chosen at training) moves its figures.
//!
//! `cargo run --release --example colour_weight -- IN.safetensors WEIGHT OUT.safetensors`

use sdhop::model::Model;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, weight, output] = args.as_slice() else {
        return Err("usage: colour_weight IN.safetensors WEIGHT OUT.safetensors".into());
    };
    let weight: f64 = weight.parse()?;
    if !(weight.is_finite() && weight >= 0.0) {
        return Err(format!("{weight}: a colour weight is a finite number >= 0").into());
    }
    let mut m = Model::load(&PathBuf::from(input))?;
    eprintln!(
        "{}: colour weight {} -> {weight}",
        m.meta.name, m.meta.detection.colour_weight
    );
    m.meta.detection.colour_weight = weight;
    m.save(&PathBuf::from(output))?;
    Ok(())
}
