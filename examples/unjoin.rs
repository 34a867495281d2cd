//! Splits the models an earlier `sdhop-train join` wrote back into the two
//! it joined: the single-pose base (its own components, its detection
//! threshold from its cross-validation, colour weight 0) and the added
//! view components (their offset taken back out of their bias, the
//! provenance `join` kept for them). A model that was not joined is its
//! own base. With these, `sdhop-train join --recorded DIR` can choose
//! again from the figures the earlier check recorded, without the hour
//! of training and scoring the check took.
//!
//! `cargo run --release --example unjoin -- JOINED_DIR BASE_OUT ADD_OUT`
//!
//! The added model's component count is its provenance's
//! `multiview.components` (the views+boxes route's record); the split is
//! checked by joining the two again at the recorded offset, which must
//! give the joined model's components back exactly.

use sdhop::model::{model_paths, Model};
use std::path::PathBuf;

fn provenance_without(m: &serde_json::Value, keys: &[&str]) -> serde_json::Value {
    let mut p = m.clone();
    if let Some(o) = p.as_object_mut() {
        for k in keys {
            o.remove(*k);
        }
    }
    p
}

fn split(m: &Model) -> Result<(Model, Option<Model>), String> {
    let name = &m.meta.name;
    let drop = ["joined", "join_check", "join_set", "join_cost"];
    let Some(j) = m.meta.provenance.get("joined") else {
        let mut base = m.clone();
        base.meta.provenance = provenance_without(&m.meta.provenance, &drop);
        return Ok((base, None));
    };
    let offset = j["offset"]
        .as_f64()
        .ok_or(format!("{name}: no joined offset"))?;
    let added = j["provenance"]["multiview"]["components"]
        .as_array()
        .map(Vec::len)
        .ok_or(format!(
            "{name}: the added model's component count is not recorded"
        ))?;
    let n = m.views.len();
    let k = n
        .checked_sub(added)
        .filter(|&k| k > 0)
        .ok_or(format!("{name}: {n} components, {added} added"))?;
    let threshold = m.meta.provenance["cross_validation"]["threshold"]
        .as_f64()
        .ok_or(format!("{name}: no cross-validated threshold"))?;
    let mut meta = m.meta.clone();
    meta.viewpoints.truncate(k);
    meta.detection.threshold = threshold;
    meta.detection.colour_weight = 0.0;
    meta.provenance = provenance_without(&m.meta.provenance, &drop);
    let base = Model::new(meta, m.views[..k].to_vec())
        .and_then(|b| b.with_shapes(m.shapes[..k].to_vec()))
        .map_err(|e| format!("{name}: {e}"))?;
    let mut meta = m.meta.clone();
    meta.viewpoints.drain(..k);
    meta.provenance = j["provenance"].clone();
    let views = m.views[k..]
        .iter()
        .map(|w| {
            let mut w = w.clone();
            w.bias += offset as f32;
            w
        })
        .collect();
    let add = Model::new(meta, views)
        .and_then(|a| a.with_shapes(m.shapes[k..].to_vec()))
        .map_err(|e| format!("{name}: {e}"))?;
    let again = base
        .joined(&add, offset)
        .map_err(|e| format!("{name}: {e}"))?;
    if again.views != m.views || again.shapes.len() != m.shapes.len() {
        return Err(format!(
            "{name}: joining the split again does not give the model back"
        ));
    }
    Ok((base, Some(add)))
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [dir, base_out, add_out] = &args[..] else {
        return Err("usage: unjoin JOINED_DIR BASE_OUT ADD_OUT".into());
    };
    let (base_out, add_out) = (PathBuf::from(base_out), PathBuf::from(add_out));
    for d in [&base_out, &add_out] {
        std::fs::create_dir_all(d).map_err(|e| format!("{}: {e}", d.display()))?;
    }
    for path in model_paths(&PathBuf::from(dir)).map_err(|e| e.to_string())? {
        let m = Model::load(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        let (base, add) = split(&m)?;
        let file = format!("{}.safetensors", m.meta.name);
        base.save(&base_out.join(&file))
            .map_err(|e| e.to_string())?;
        match add {
            Some(a) => {
                a.save(&add_out.join(&file)).map_err(|e| e.to_string())?;
                println!(
                    "{}: {} + {} component(s)",
                    m.meta.name,
                    base.views.len(),
                    a.views.len()
                );
            }
            None => println!(
                "{}: not joined, {} component(s)",
                m.meta.name,
                base.views.len()
            ),
        }
    }
    Ok(())
}
