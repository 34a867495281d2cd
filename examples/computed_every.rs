//! A model file whose pyramid computes its cells every N levels (the
//! levels between resampled, `PyramidParams::computed_every`), for a
//! measurement: what the fast pyramid costs a model trained on every
//! level.
//!
//! `cargo run --release --example computed_every -- IN.safetensors N OUT.safetensors`

use sdhop::model::Model;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, every, output] = args.as_slice() else {
        return Err("usage: computed_every IN.safetensors N OUT.safetensors".into());
    };
    let every: u32 = every.parse()?;
    let mut m = Model::load(&PathBuf::from(input))?;
    eprintln!(
        "{}: computed every {} -> {every} level(s)",
        m.meta.name, m.meta.pyramid.computed_every
    );
    m.meta.pyramid.computed_every = every;
    m.meta.pyramid.validate()?;
    m.save(&PathBuf::from(output))?;
    Ok(())
}
