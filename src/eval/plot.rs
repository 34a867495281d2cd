//! Recall-FPPI plot: one panel per object with our curves (per-object and
//! cross-object protocols) beside the published Hsiao & Hebert curves.

use std::path::Path;
use std::sync::OnceLock;

use plotters::prelude::*;

use super::{ObjectScore, GRID};

/// Errors of plotting.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("plot: {0}")]
    Draw(String),
    #[error("{0}: {1}")]
    Io(String, String),
}

fn draw_err(e: impl std::fmt::Display) -> PlotError {
    PlotError::Draw(e.to_string())
}

/// Registers a TrueType font for labels (`SDHOP_FONT`, else DejaVu Sans or
/// Liberation Sans where the system has them). Without one the plot is drawn
/// without text.
fn font_available() -> bool {
    static FONT: OnceLock<bool> = OnceLock::new();
    *FONT.get_or_init(|| {
        let candidates = [
            std::env::var("SDHOP_FONT").unwrap_or_default(),
            "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf".into(),
            "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf".into(),
        ];
        for c in candidates.iter().filter(|c| !c.is_empty()) {
            if let Ok(bytes) = std::fs::read(c) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        false
    })
}

/// Reads a published curve file: rows `fppi r1 r2 r3 r4`.
fn read_published(path: &Path) -> Vec<Vec<(f64, f64)>> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Vec::new();
    };
    let rows: Vec<Vec<f64>> = text
        .lines()
        .map(|l| {
            l.split_whitespace()
                .filter_map(|v| v.parse().ok())
                .collect()
        })
        .filter(|r: &Vec<f64>| r.len() >= 2)
        .collect();
    let cols = rows.iter().map(|r| r.len()).min().unwrap_or(0);
    (1..cols)
        .map(|c| rows.iter().map(|r| (r[0], r[c])).collect())
        .collect()
}

/// A recall (0 to 1) against FPPI (0 to 1) chart on `panel` with its
/// caption and axes (a bare grid without a font).
fn recall_panel<'a, 'b>(
    panel: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    caption: &str,
    x_desc: &str,
    text: bool,
) -> Result<
    ChartContext<
        'a,
        BitMapBackend<'b>,
        Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
    >,
    PlotError,
> {
    let mut builder = ChartBuilder::on(panel);
    builder.margin(8);
    if text {
        builder
            .caption(caption, ("sans-serif", 15))
            .x_label_area_size(28)
            .y_label_area_size(34);
    }
    let mut chart = builder
        .build_cartesian_2d(0.0..1.0f64, 0.0..1.0f64)
        .map_err(draw_err)?;
    if text {
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc("recall")
            .label_style(("sans-serif", 11))
            .draw()
            .map_err(draw_err)?;
    } else {
        chart
            .configure_mesh()
            .disable_x_mesh()
            .disable_y_mesh()
            .draw()
            .map_err(draw_err)?;
    }
    Ok(chart)
}

const PUBLISHED: [&str; 4] = ["LINE2D", "rLINE2D", "rLINE2D+OPP", "rLINE2D+OCLP"];

/// Draws the panels into a PNG at `out`. `published_dir` holds
/// `<object>.txt` curves (missing files are left out).
pub fn recall_fppi_png(
    scores: &[ObjectScore],
    published_dir: &Path,
    out: &Path,
) -> Result<(), PlotError> {
    let text = font_available();
    let cols = 4usize;
    let rows = scores.len().div_ceil(cols).max(1);
    let (pw, ph) = (360u32, 300u32);
    let (w, h) = (pw * cols as u32, ph * rows as u32);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let panels = root.split_evenly((rows, cols));
        let grey = [
            RGBColor(190, 190, 190),
            RGBColor(160, 160, 160),
            RGBColor(120, 120, 120),
            RGBColor(230, 140, 40),
        ];
        for (panel, s) in panels.iter().zip(scores) {
            let caption = format!("{} AUC {:.3} / cross {:.3}", s.object, s.auc, s.auc_cross);
            let mut chart = recall_panel(panel, &caption, "FPPI", text)?;
            let published = read_published(&published_dir.join(format!("{}.txt", s.object)));
            for (i, curve) in published.iter().enumerate() {
                let color = grey[i.min(3)];
                let series = chart
                    .draw_series(LineSeries::new(
                        curve.iter().copied(),
                        color.stroke_width(2),
                    ))
                    .map_err(draw_err)?;
                if text {
                    series
                        .label(PUBLISHED.get(i).copied().unwrap_or("published"))
                        .legend(move |(x, y)| {
                            PathElement::new([(x, y), (x + 14, y)], color.stroke_width(3))
                        });
                }
            }
            let ours = |c: &[f64]| -> Vec<(f64, f64)> {
                c.iter()
                    .enumerate()
                    .map(|(g, &r)| (g as f64 / (GRID - 1) as f64, r))
                    .collect()
            };
            let blue = RGBColor(20, 70, 200);
            let red = RGBColor(200, 30, 30);
            let a = chart
                .draw_series(LineSeries::new(ours(&s.curve), blue.stroke_width(3)))
                .map_err(draw_err)?;
            if text {
                a.label("SD-HOP").legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 14, y)], blue.stroke_width(3))
                });
            }
            let b = chart
                .draw_series(LineSeries::new(ours(&s.curve_cross), red.stroke_width(2)))
                .map_err(draw_err)?;
            if text {
                b.label("SD-HOP cross-object").legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 14, y)], red.stroke_width(3))
                });
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::LowerRight)
                    .label_font(("sans-serif", 10))
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .draw()
                    .map_err(draw_err)?;
            }
        }
        root.present().map_err(draw_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| PlotError::Draw("buffer size".into()))?;
    img.save(out)
        .map_err(|e| PlotError::Io(out.display().to_string(), e.to_string()))
}

/// The recall-FPPI curve points of each object of one variant.
pub type VariantCurves = (String, Vec<(String, Vec<(f64, f64)>)>);

/// Recall against FPPI (0 to 1) of several variants (ablations) of the
/// same objects: one panel per object, one line per variant, the AUCs in
/// the legend. `variants[v] = (name, [(object, curve points)])`.
pub fn variants_png(variants: &[VariantCurves], out: &Path) -> Result<(), PlotError> {
    let text = font_available();
    // Every variant's objects, in the order they first appear.
    let mut objects: Vec<&String> = Vec::new();
    for (n, _) in variants.iter().flat_map(|(_, o)| o) {
        if !objects.contains(&n) {
            objects.push(n);
        }
    }
    let cols = objects.len().clamp(1, 4);
    let rows = objects.len().div_ceil(cols).max(1);
    let (pw, ph) = (360u32, 300u32);
    let (w, h) = (pw * cols as u32, ph * rows as u32);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    let colours = [
        RGBColor(20, 70, 200),
        RGBColor(200, 30, 30),
        RGBColor(40, 150, 60),
        RGBColor(230, 140, 40),
        RGBColor(120, 120, 120),
    ];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let panels = root.split_evenly((rows, cols));
        for (panel, object) in panels.iter().zip(&objects) {
            let mut chart = recall_panel(panel, object, "false positives per image", text)?;
            for (v, (name, curves)) in variants.iter().enumerate() {
                let Some((_, pts)) = curves.iter().find(|(n, _)| n == *object) else {
                    continue;
                };
                // The step function, cut at FPPI 1.
                let mut steps: Vec<(f64, f64)> = Vec::with_capacity(pts.len() * 2);
                let mut last_r = 0.0;
                for &(f, r) in pts {
                    if f > 1.0 {
                        steps.push((1.0, last_r));
                        break;
                    }
                    steps.push((f, last_r));
                    steps.push((f, r));
                    last_r = r;
                }
                if steps.last().is_some_and(|p| p.0 < 1.0) {
                    steps.push((1.0, last_r));
                }
                let colour = colours[v % colours.len()];
                let area: f64 = steps.windows(2).map(|w| (w[1].0 - w[0].0) * w[0].1).sum();
                let series = chart
                    .draw_series(LineSeries::new(steps, colour.stroke_width(2)))
                    .map_err(draw_err)?;
                if text {
                    series
                        .label(format!("{name} AUC {area:.3}"))
                        .legend(move |(x, y)| {
                            PathElement::new([(x, y), (x + 14, y)], colour.stroke_width(3))
                        });
                }
            }
            if text {
                chart
                    .configure_series_labels()
                    .position(SeriesLabelPosition::UpperLeft)
                    .label_font(("sans-serif", 11))
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .draw()
                    .map_err(draw_err)?;
            }
        }
        root.present().map_err(draw_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| PlotError::Draw("buffer size".into()))?;
    img.save(out)
        .map_err(|e| PlotError::Io(out.display().to_string(), e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both plots write a PNG with a panel per object (4 per row).
    #[test]
    fn plots_write_a_panel_per_object() {
        let dir = std::env::temp_dir().join(format!("sdhop-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let curve = vec![(0.0, 0.0), (0.0, 0.5), (0.4, 0.5), (1.2, 0.8)];
        let objects: Vec<(String, Vec<(f64, f64)>)> = ["ape", "cat", "duck", "glue", "can"]
            .iter()
            .map(|o| (o.to_string(), curve.clone()))
            .collect();
        // An object only the second variant has still gets its panel.
        let variants = vec![
            ("sdhop".to_string(), objects[..4].to_vec()),
            ("plain".to_string(), objects),
        ];
        let out = dir.join("variants.png");
        variants_png(&variants, &out).unwrap();
        let img = image::open(&out).unwrap();
        assert_eq!((img.width(), img.height()), (4 * 360, 2 * 300));
        let scores: Vec<ObjectScore> = ["cup", "pitcher"]
            .iter()
            .map(|o| ObjectScore {
                object: o.to_string(),
                curve: vec![0.5; GRID],
                curve_cross: vec![0.4; GRID],
                ..ObjectScore::default()
            })
            .collect();
        let out = dir.join("recall.png");
        recall_fppi_png(&scores, &dir, &out).unwrap();
        let img = image::open(&out).unwrap();
        assert_eq!((img.width(), img.height()), (4 * 360, 300));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
