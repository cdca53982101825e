//! Plots with `plotters`, PNG and SVG: the paper's Fig. 3 panels and a Fig. 4-style trajectory.
//!
//! Text is drawn with DejaVu Sans (`assets/DejaVuSans.ttf`, free licence in
//! `assets/DejaVuSans-LICENSE.txt`), compiled in and registered with plotters' `ab_glyph` font
//! registry on first use.

use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use skyherd_model::Task;
use thiserror::Error;

use crate::eval::ConfigResult;
use crate::scenario::HerderCount;
use crate::task::task_name;
use crate::world::World;

const FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

/// Why a plot could not be drawn or written.
#[derive(Debug, Error)]
pub enum PlotError {
    /// The drawing backend failed (file, encoding, font).
    #[error("plot {path}: {message}")]
    Draw {
        /// Output file.
        path: String,
        /// Backend message.
        message: String,
    },
    /// Nothing to plot.
    #[error("nothing to plot: {0}")]
    Empty(String),
}

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in and known to parse; a failure would only lose the labels.
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

/// Method colours, in report order.
const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// A viridis-like ramp for `t` in [0, 1] (dark blue -> green -> yellow).
pub(crate) fn time_colour(t: f64) -> RGBColor {
    const STOPS: [(f64, [f64; 3]); 5] = [
        (0.0, [68.0, 1.0, 84.0]),
        (0.25, [59.0, 82.0, 139.0]),
        (0.5, [33.0, 145.0, 140.0]),
        (0.75, [94.0, 201.0, 98.0]),
        (1.0, [253.0, 231.0, 37.0]),
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let k = STOPS.iter().position(|s| s.0 >= t).unwrap_or(4).max(1);
    let (t0, c0) = STOPS[k - 1];
    let (t1, c1) = STOPS[k];
    let f = (t - t0) / (t1 - t0);
    let mix = |i: usize| (c0[i] + f * (c1[i] - c0[i])).round() as u8;
    RGBColor(mix(0), mix(1), mix(2))
}

fn draw_err<E: std::fmt::Display>(path: &Path) -> impl Fn(E) -> PlotError + '_ {
    move |e| PlotError::Draw {
        path: path.display().to_string(),
        message: e.to_string(),
    }
}

/// Which metric a Fig. 3 panel shows.
#[derive(Clone, Copy)]
enum Metric {
    Success,
    Time,
    Path,
}

impl Metric {
    fn label(self) -> &'static str {
        match self {
            Metric::Success => "success rate (%)",
            Metric::Time => "completion time (s)",
            Metric::Path => "herder path length (m)",
        }
    }
    fn value(self, r: &ConfigResult) -> Option<f64> {
        match self {
            Metric::Success => Some(100.0 * r.success_rate),
            Metric::Time => r.mean_time_s,
            Metric::Path => r.mean_path_m,
        }
    }
}

fn fig3_panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    rows: &[&ConfigResult],
    methods: &[String],
) -> Result<(), String> {
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let root = root
        .titled(title, (FAMILY, 22))
        .map_err(|e| e.to_string())?;
    let panels = root.split_evenly((1, 3));
    let max_log = rows
        .iter()
        .map(|r| (r.config.targets as f64).log2())
        .fold(0.0, f64::max)
        .max(1.0);
    for (panel, metric) in panels
        .iter()
        .zip([Metric::Success, Metric::Time, Metric::Path])
    {
        let top = rows
            .iter()
            .filter_map(|r| metric.value(r))
            .fold(0.0, f64::max);
        let top = match metric {
            Metric::Success => 105.0,
            _ => (top * 1.1).max(1.0),
        };
        let mut chart = ChartBuilder::on(panel)
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(56)
            .build_cartesian_2d(-0.3..max_log + 0.3, 0.0..top)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .x_desc("targets N (log2)")
            .y_desc(metric.label())
            .x_label_formatter(&|x| format!("{}", 2f64.powf(x.round()) as u64))
            .label_style((FAMILY, 13))
            .axis_desc_style((FAMILY, 14))
            .draw()
            .map_err(|e| e.to_string())?;
        for (k, method) in methods.iter().enumerate() {
            let colour = PALETTE[k % PALETTE.len()];
            let mut pts: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| &r.config.method == method)
                .filter_map(|r| {
                    metric
                        .value(r)
                        .map(|v| ((r.config.targets as f64).log2(), v))
                })
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label(method.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                });
            chart
                .draw_series(pts.into_iter().map(|p| Circle::new(p, 3, colour.filled())))
                .map_err(|e| e.to_string())?;
        }
        if matches!(metric, Metric::Success) {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((FAMILY, 13))
                .position(SeriesLabelPosition::LowerLeft)
                .draw()
                .map_err(|e| e.to_string())?;
        }
    }
    root.present().map_err(|e| e.to_string())
}

/// Writes one Fig. 3 figure (success, time, path vs N, a line per method) per task and herder
/// setting found in `results`, as `fig3-<task>-m<setting>.{png,svg}` in `dir`. Returns the files.
pub fn fig3(results: &[ConfigResult], dir: &Path) -> Result<Vec<PathBuf>, PlotError> {
    register_font();
    if results.is_empty() {
        return Err(PlotError::Empty("no evaluation results".into()));
    }
    let mut methods: Vec<String> = Vec::new();
    let mut groups: Vec<(Task, HerderCount)> = Vec::new();
    for r in results {
        if !methods.contains(&r.config.method) {
            methods.push(r.config.method.clone());
        }
        let g = (r.config.task, r.config.herders.0);
        if !groups.contains(&g) {
            groups.push(g);
        }
    }
    let mut files = Vec::new();
    for (task, herders) in groups {
        let rows: Vec<&ConfigResult> = results
            .iter()
            .filter(|r| r.config.task == task && r.config.herders.0 == herders)
            .collect();
        let title = format!("{} task, M = {}", task_name(task), herders);
        let stem = format!("fig3-{}-m{}", task_name(task), herders);
        let png = dir.join(format!("{stem}.png"));
        let root = BitMapBackend::new(&png, (1500, 450)).into_drawing_area();
        fig3_panels(&root, &title, &rows, &methods).map_err(draw_err(&png))?;
        drop(root);
        files.push(png);
        let svg = dir.join(format!("{stem}.svg"));
        let root = SVGBackend::new(&svg, (1500, 450)).into_drawing_area();
        fig3_panels(&root, &title, &rows, &methods).map_err(draw_err(&svg))?;
        drop(root);
        files.push(svg);
    }
    Ok(files)
}

fn trajectory_panel<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    states: &[World],
) -> Result<(), String> {
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let first = &states[0];
    let last_step = states.last().map_or(1, |w| w.step).max(1) as f64;
    // Frame the episode: everything any object visited, plus the goal, squared up.
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    let mut grow = |p: [f64; 2]| {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    };
    for w in states {
        w.herders.iter().for_each(|h| grow([h[0], h[1]]));
        w.targets.iter().for_each(|&t| grow(t));
    }
    let g = first.goal;
    grow([g.center[0] - g.radius, g.center[1] - g.radius]);
    grow([g.center[0] + g.radius, g.center[1] + g.radius]);
    let span = (hi[0] - lo[0]).max(hi[1] - lo[1]) * 1.05;
    let mid = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    let (x0, x1) = (mid[0] - span / 2.0, mid[0] + span / 2.0);
    let (y0, y1) = (mid[1] - span / 2.0, mid[1] + span / 2.0);
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FAMILY, 20))
        .margin(14)
        .x_label_area_size(36)
        .y_label_area_size(48)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| e.to_string())?;
    chart
        .configure_mesh()
        .x_desc("x (m, east)")
        .y_desc("y (m, north)")
        .label_style((FAMILY, 13))
        .axis_desc_style((FAMILY, 14))
        .disable_mesh()
        .draw()
        .map_err(|e| e.to_string())?;
    let circle: Vec<(f64, f64)> = (0..=120)
        .map(|k| {
            let a = k as f64 / 120.0 * std::f64::consts::TAU;
            (
                g.center[0] + g.radius * a.cos(),
                g.center[1] + g.radius * a.sin(),
            )
        })
        .collect();
    chart
        .draw_series(LineSeries::new(circle, BLACK.stroke_width(2)))
        .map_err(|e| e.to_string())?
        .label("goal")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.stroke_width(2)));
    for w in states {
        let c = time_colour(w.step as f64 / last_step);
        chart
            .draw_series(
                w.targets
                    .iter()
                    .map(|&t| Circle::new((t[0], t[1]), 2, c.filled())),
            )
            .map_err(|e| e.to_string())?;
        chart
            .draw_series(
                w.herders
                    .iter()
                    .map(|h| TriangleMarker::new((h[0], h[1]), 4, c.filled())),
            )
            .map_err(|e| e.to_string())?;
    }
    let legend_c = time_colour(0.5);
    chart
        .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
        .map_err(|e| e.to_string())?
        .label("targets (dots)")
        .legend(move |(x, y)| Circle::new((x + 9, y), 3, legend_c.filled()));
    chart
        .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
        .map_err(|e| e.to_string())?
        .label(format!(
            "herders (triangles); colour: time 0 (purple) to {last_step:.0} steps (yellow)"
        ))
        .legend(move |(x, y)| TriangleMarker::new((x + 9, y), 4, legend_c.filled()));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FAMILY, 13))
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(|e| e.to_string())?;
    root.present().map_err(|e| e.to_string())
}

/// Writes a Fig. 4-style trajectory plot of an episode's states (x-y plane, colour by time) as
/// `<stem>.png` and `<stem>.svg`. Returns the files.
pub fn trajectory(states: &[World], title: &str, stem: &Path) -> Result<Vec<PathBuf>, PlotError> {
    register_font();
    if states.is_empty() {
        return Err(PlotError::Empty("no states in the trajectory".into()));
    }
    let png = stem.with_extension("png");
    let root = BitMapBackend::new(&png, (900, 900)).into_drawing_area();
    trajectory_panel(&root, title, states).map_err(draw_err(&png))?;
    drop(root);
    let svg = stem.with_extension("svg");
    let root = SVGBackend::new(&svg, (900, 900)).into_drawing_area();
    trajectory_panel(&root, title, states).map_err(draw_err(&svg))?;
    drop(root);
    Ok(vec![png, svg])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_colours_run_from_purple_to_yellow() {
        assert_eq!(time_colour(0.0), RGBColor(68, 1, 84));
        assert_eq!(time_colour(1.0), RGBColor(253, 231, 37));
        assert_eq!(time_colour(f64::NAN), RGBColor(68, 1, 84));
        let mid = time_colour(0.5);
        assert_eq!(mid, RGBColor(33, 145, 140));
    }
}
