//! `sdhop-train pose-eval`: pose refinement on real photographs in BOP
//! format (LM-O), the protocol of `lmo_pose.py` in process: IRLS and
//! OR-IRLS from seeded starts, the paper's Table 2 per object and overall,
//! rows for nearly unoccluded instances and for nearer and farther starts,
//! and a JSON report.

use super::*;
use crate::data::bop::Bop;
use crate::eval::bop_pose::{run, select, summarize, table, Cut, Outcome, Row, Selection};

#[derive(clap::Args)]
pub(crate) struct PoseEvalArgs {
    /// BOP dataset root (models/ and test/SCENE/), e.g. ../shared/data/lmo_dev.
    #[arg(long)]
    pub(crate) bop: PathBuf,
    /// Object ids (comma-separated; default every object of models_info.json).
    #[arg(long, value_delimiter = ',')]
    pub(crate) objects: Vec<u32>,
    /// Instances per object and row at most.
    #[arg(long, default_value_t = 25)]
    pub(crate) per_object: usize,
    /// visib_fract range of the occluded rows, "LO,HI".
    #[arg(long, default_value = "0.4,0.8")]
    pub(crate) visib: String,
    /// Largest |oracle_visib_fract - visib_fract| kept (the visible mask
    /// was rendered from annotated occluders only).
    #[arg(long, default_value_t = 0.10)]
    pub(crate) max_oracle_gap: f64,
    #[arg(long, default_value_t = 7)]
    pub(crate) seed: u64,
    /// Starts per instance, each about its own random axis (the first is
    /// the one of a single start; more narrow the figures' noise).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=100))]
    pub(crate) starts: u64,
    /// Only the main row (occluded, 5 degree / 10 mm starts).
    #[arg(long)]
    pub(crate) main_only: bool,
    /// One row only: the occluded instances from starts this far,
    /// "DEGREES,MM" (e.g. "0,0": started at the true pose, where a
    /// refinement should stay).
    #[arg(long)]
    pub(crate) start: Option<String>,
    /// Send each row's start distance as the request's start_uncertainty
    /// (as a client that knows how good its start is); default: the
    /// service's default uncertainty (5 degrees, 5% of the mesh's
    /// box diagonal).
    #[arg(long, conflicts_with = "start_uncertainty")]
    pub(crate) prior_from_start: bool,
    /// Send this start uncertainty with every request, "DEGREES,MM" (as a
    /// client that states its own; e.g. "5,20" is the translation prior
    /// that 5% of the box diagonal gave an object 2.5 times the size of
    /// the development objects)
    #[arg(long)]
    pub(crate) start_uncertainty: Option<String>,
    /// The requests' `max_iterations` (outer iterations per start; default:
    /// the service's).
    #[arg(long)]
    pub(crate) max_iterations: Option<usize>,
    /// Only the rows whose names start with these (comma-separated:
    /// `occluded`, `nearly`, `border`, `cropped`, `zoomed`, `large`).
    #[arg(long, value_delimiter = ',')]
    pub(crate) rows: Vec<String>,
    /// Write every outcome (with its answered pose) and summary as JSON here.
    #[arg(long)]
    pub(crate) report: Option<PathBuf>,
}

pub(crate) fn run_pose_eval(args: &PoseEvalArgs) -> Result<(), Failure> {
    let bop = Bop::load(&args.bop).map_err(Failure::input)?;
    let (lo, hi) = args
        .visib
        .split_once(',')
        .and_then(|(a, b)| Some((a.trim().parse().ok()?, b.trim().parse().ok()?)))
        .ok_or_else(|| Failure::input(format!("--visib {:?}: expected LO,HI", args.visib)))?;
    let objects = if args.objects.is_empty() {
        bop.models.keys().copied().collect()
    } else {
        args.objects.clone()
    };
    let mut meshes = std::collections::BTreeMap::new();
    for &obj in &objects {
        let path = bop.model_path(obj);
        let bytes =
            std::fs::read(&path).map_err(|e| Failure::io(format!("{}: {e}", path.display())))?;
        let mesh = crate::pose::Mesh::parse(&bytes)
            .map_err(|e| Failure::input(format!("{}: {e}", path.display())))?;
        meshes.insert(obj, mesh);
    }
    let sel = Selection {
        objects: objects.clone(),
        per_object: args.per_object,
        max_oracle_gap: args.max_oracle_gap,
        seed: args.seed,
        starts: args.starts as usize,
    };
    let uncertainty = args
        .start_uncertainty
        .as_deref()
        .map(|text| {
            parse_pair(text)
                .filter(|(d, mm)| *d >= 0.0 && *mm >= 0.0)
                .ok_or_else(|| {
                    Failure::input(format!("--start-uncertainty {text:?}: expected DEGREES,MM"))
                })
        })
        .transpose()?;
    let row = |name: &str, visib: (f64, f64), start_degrees: f64, start_mm: f64| Row {
        name: name.to_string(),
        visib,
        start_degrees,
        start_mm,
        prior_from_start: args.prior_from_start,
        uncertainty,
        cut: Cut::Any,
        min_diagonal: None,
        max_iterations: args.max_iterations,
    };
    let mut rows = vec![row("occluded, 5 deg / 10 mm starts", (lo, hi), 5.0, 10.0)];
    if let Some(text) = &args.start {
        let (d, mm) = parse_pair(text)
            .filter(|(d, mm)| *d >= 0.0 && *mm >= 0.0)
            .ok_or_else(|| Failure::input(format!("--start {text:?}: expected DEGREES,MM")))?;
        rows = vec![row(
            &format!("occluded, {d} deg / {mm} mm starts"),
            (lo, hi),
            d,
            mm,
        )];
    } else if !args.main_only {
        rows.push(row(
            "nearly unoccluded (visib >= 0.8), 5 deg / 10 mm",
            (0.8, 1.0),
            5.0,
            10.0,
        ));
        rows.push(row("occluded, 2.5 deg / 5 mm starts", (lo, hi), 2.5, 5.0));
        rows.push(row("occluded, 10 deg / 20 mm starts", (lo, hi), 10.0, 20.0));
    }
    if args.start.is_none() && !args.main_only {
        rows.extend(border_rows(&row("", (lo, hi), 5.0, 10.0)));
    }
    if !args.rows.is_empty() {
        rows.retain(|r| args.rows.iter().any(|k| r.name.starts_with(k.as_str())));
        if rows.is_empty() {
            return Err(Failure::input(format!(
                "--rows {:?}: no row starts so (rows: occluded, nearly, border, cropped, zoomed, large)",
                args.rows
            )));
        }
    }
    let mut report = Vec::new();
    for (ri, r) in rows.iter().enumerate() {
        let cases = select(&bop, r, &sel);
        let pb = progress_bar(cases.len() as u64, &r.name);
        let outcomes: Vec<Outcome> =
            run(&bop, r, &cases, &meshes, || pb.inc(1)).map_err(Failure::input)?;
        pb.finish_and_clear();
        if ri == 0 || r.cut != Cut::Any || r.min_diagonal.is_some() {
            for &obj in &objects {
                println!("{}", table(&format!("obj {obj}"), &outcomes, Some(obj)));
            }
        }
        println!(
            "{}",
            table(&format!("{}: all objects", r.name), &outcomes, None)
        );
        let summaries: Vec<_> = ["initial", "irls", "or_irls"]
            .iter()
            .filter_map(|m| summarize(&outcomes, m, None))
            .collect();
        report.push(serde_json::json!({
            "row": r, "summaries": summaries, "outcomes": outcomes,
        }));
    }
    if let Some(p) = &args.report {
        let doc = serde_json::json!({"selection": sel, "rows": report});
        let text = serde_json::to_string_pretty(&doc).map_err(Failure::io)?;
        std::fs::write(p, text).map_err(|e| Failure::io(format!("{}: {e}", p.display())))?;
    }
    Ok(())
}

/// The rows of objects cut by the image's border and of large objects,
/// from `base`'s starts and settings: photographed at the border (any
/// visibility of 0.3 and more: few are), development photographs cropped
/// so that 10-50% of a mostly visible object is cut away, development
/// photographs enlarged 2.5 times about the object (as a longer lens sees
/// it: large in the image, `base`'s visibility range) and objects whose
/// full extent's diagonal is 200 pixels or more (`base`'s visibility
/// range).
fn border_rows(base: &Row) -> Vec<Row> {
    vec![
        Row {
            name: "border, photographed (visib >= 0.3)".into(),
            visib: (0.3, 1.0),
            cut: Cut::Border,
            ..base.clone()
        },
        Row {
            name: "cropped: 10-50% cut by the border (visib >= 0.6)".into(),
            visib: (0.6, 1.0),
            cut: Cut::Cropped(0.1, 0.5),
            ..base.clone()
        },
        Row {
            name: "zoomed: enlarged 2.5x about the object".into(),
            cut: Cut::Zoomed(2.5),
            ..base.clone()
        },
        Row {
            name: "large: diagonal >= 200 px".into(),
            min_diagonal: Some(200.0),
            ..base.clone()
        },
    ]
}

/// Two finite numbers, "A,B".
fn parse_pair(text: &str) -> Option<(f64, f64)> {
    let (a, b) = text.split_once(',')?;
    let (a, b) = (a.trim().parse::<f64>().ok()?, b.trim().parse::<f64>().ok()?);
    (a.is_finite() && b.is_finite()).then_some((a, b))
}
