//! PNG charts of the experiments (plotters, bitmap backend, bundled font: no system fonts).

use crate::experiment::Scored;
use anyhow::{Result, anyhow};
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::Once;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

fn register_font() -> Result<()> {
    static ONCE: Once = Once::new();
    let mut res = Ok(());
    ONCE.call_once(|| {
        res = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
            .map_err(|_| anyhow!("the bundled font is not a valid TrueType font"));
    });
    res
}

const COLORS: [RGBColor; 4] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
];

/// Four panels (one per experiment): position RMS error sqrt(x² + y²) against the number of
/// particles, one line per updater.
pub fn paper_chart(path: &Path, results: &[Scored]) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, (1200, 900)).into_drawing_area();
    root.fill(&WHITE)?;
    let root = root.titled(
        "Position RMS error vs particles: EKF vs MLP updaters (3D point landmarks)",
        ("sans-serif", 22),
    )?;
    let mut experiments: Vec<&str> = Vec::new();
    for r in results {
        if !experiments.contains(&r.experiment.as_str()) {
            experiments.push(&r.experiment);
        }
    }
    let mut updaters: Vec<&str> = Vec::new();
    for r in results {
        if !updaters.contains(&r.updater.as_str()) {
            updaters.push(&r.updater);
        }
    }
    let pos = |r: &Scored| (r.rms_x * r.rms_x + r.rms_y * r.rms_y).sqrt();
    // Log scale: the errors of different updaters differ by orders of magnitude.
    let y_max = results.iter().map(pos).fold(0.0f64, f64::max).max(1e-3) * 1.5;
    let y_min = results
        .iter()
        .map(pos)
        .filter(|v| *v > 0.0)
        .fold(f64::INFINITY, f64::min)
        .min(y_max / 10.0)
        * 0.7;
    let n_max = results.iter().map(|r| r.particles).max().unwrap_or(1) as f64;
    for (panel, exp) in root.split_evenly((2, 2)).iter().zip(&experiments) {
        let mut chart = ChartBuilder::on(panel)
            .caption(format!("Experiment {exp}"), ("sans-serif", 16))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..n_max * 1.05, (y_min..y_max).log_scale())?;
        chart
            .configure_mesh()
            .x_desc("particles")
            .y_desc("position RMS error [m], log scale")
            .x_label_formatter(&|v| format!("{v:.0}"))
            .label_style(("sans-serif", 13))
            .draw()?;
        for (k, u) in updaters.iter().enumerate() {
            let color = COLORS[k % COLORS.len()];
            let mut pts: Vec<(f64, f64)> = results
                .iter()
                .filter(|r| r.experiment == *exp && r.updater == *u)
                .map(|r| (r.particles as f64, pos(r)))
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart
                .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))?
                .label(*u)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                });
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .position(SeriesLabelPosition::MiddleRight)
            .draw()?;
    }
    root.present()?;
    Ok(())
}
