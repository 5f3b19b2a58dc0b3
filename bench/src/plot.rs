//! Plots of `kairos bench sim`, `kairos bench live` and `kairos demo` results, as PNG and SVG,
//! with plotters.

use std::path::Path;
use std::sync::Once;

use anyhow::{Context, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::sim::experiment::{Experiment, Report};
use crate::sim::stats::ecdf;

/// DejaVu Sans (Bitstream Vera licence, see assets/fonts/): the bitmap backend needs a font.
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
const FAMILY: &str = "kairos-sans";

const PANEL_W: u32 = 480;
const PANEL_H: u32 = 340;

struct Point {
    x: f64,
    lo: f64,
    mid: f64,
    hi: f64,
}

struct Series {
    label: String,
    color: RGBColor,
    points: Vec<Point>,
    /// Draw P25–P95 bars.
    bars: bool,
}

struct Panel {
    title: String,
    x_desc: String,
    y_desc: String,
    /// Category labels for x = 0, 1, 2, ... (otherwise numeric).
    x_labels: Option<Vec<String>>,
    series: Vec<Series>,
    /// Fixed y range (for CDFs).
    y_range: Option<(f64, f64)>,
    /// Where the legend goes.
    legend: SeriesLabelPosition,
}

fn color(key: &str, fallback: usize) -> RGBColor {
    match key {
        "fifo" => RGBColor(120, 120, 120),
        "autellix" => RGBColor(230, 126, 34),
        "kairos" | "edge" | "intra-longest" => RGBColor(31, 119, 180),
        "kairos-static" => RGBColor(140, 190, 230),
        "fifo-dynamic" => RGBColor(50, 50, 50),
        "autellix-dynamic" => RGBColor(150, 80, 20),
        "srw" | "hybrid" => RGBColor(44, 160, 44),
        "srw-hint" => RGBColor(148, 103, 189),
        "cloud" | "intra-fifo" => RGBColor(214, 39, 40),
        _ => {
            // Series 0–3 of most plots take the named colours above, so from index 4 on the
            // fallbacks differ from them and from each other (all ten entries are distinct).
            const PALETTE: [RGBColor; 10] = [
                RGBColor(23, 190, 207),
                RGBColor(188, 189, 34),
                RGBColor(227, 119, 194),
                RGBColor(140, 86, 75),
                RGBColor(214, 39, 40),
                RGBColor(148, 103, 189),
                RGBColor(0, 0, 0),
                RGBColor(255, 152, 150),
                RGBColor(0, 128, 128),
                RGBColor(255, 187, 120),
            ];
            PALETTE[fallback % PALETTE.len()]
        }
    }
}

/// Panels of an x-sweep experiment, one per workload, for the variants in `keys` (all when
/// empty).
fn sweep_panels(
    report: &Report<'_>,
    experiment: Experiment,
    x_desc: &str,
    keys: &[&str],
) -> Vec<Panel> {
    let mut panels = Vec::new();
    for (wi, w) in report.workloads.iter().enumerate() {
        let variants = report.variants(wi, experiment);
        if variants.is_empty() {
            continue;
        }
        let xs = report.xs(wi, experiment);
        let mut series = Vec::new();
        for (vi, v) in variants.iter().enumerate() {
            if !keys.is_empty() && !keys.contains(&v.key.as_str()) {
                continue;
            }
            let points = xs
                .iter()
                .filter_map(|&x| {
                    report.find(wi, experiment, x, &v.key).map(|r| Point {
                        x,
                        lo: r.summary.p25,
                        mid: r.summary.mean,
                        hi: r.summary.p95,
                    })
                })
                .collect();
            series.push(Series {
                label: v.label.clone(),
                color: color(&v.key, vi),
                points,
                bars: true,
            });
        }
        panels.push(Panel {
            title: w.title.clone(),
            x_desc: x_desc.to_string(),
            y_desc: "E2E latency (s)".into(),
            x_labels: None,
            series,
            y_range: None,
            legend: SeriesLabelPosition::UpperLeft,
        });
    }
    panels
}

/// One panel per workload with one point per variant at the peak (the ablations).
fn category_panels(report: &Report<'_>, experiment: Experiment, x_desc: &str) -> Vec<Panel> {
    let mut panels = Vec::new();
    for (wi, w) in report.workloads.iter().enumerate() {
        let variants = report.variants(wi, experiment);
        let Some(&x) = report.xs(wi, experiment).last() else {
            continue;
        };
        let mut points = Vec::new();
        let mut labels = Vec::new();
        for (i, v) in variants.iter().enumerate() {
            if let Some(r) = report.find(wi, experiment, x, &v.key) {
                points.push(Point {
                    x: i as f64,
                    lo: r.summary.p25,
                    mid: r.summary.mean,
                    hi: r.summary.p95,
                });
                labels.push(v.label.clone());
            }
        }
        panels.push(Panel {
            title: format!("{} @ {x} tasks/s", w.title),
            x_desc: x_desc.to_string(),
            y_desc: "E2E latency (s)".into(),
            x_labels: Some(labels),
            series: vec![Series {
                label: "avg (bars P25–P95)".into(),
                color: color("kairos", 0),
                points,
                bars: true,
            }],
            y_range: None,
            legend: SeriesLabelPosition::UpperLeft,
        });
    }
    panels
}

fn cdf_panels(report: &Report<'_>, keys: &[&str]) -> Vec<Panel> {
    let mut panels = Vec::new();
    for (wi, w) in report.workloads.iter().enumerate() {
        let Some(&peak) = report.xs(wi, Experiment::Online).last() else {
            continue;
        };
        let mut series = Vec::new();
        for (vi, v) in report.variants(wi, Experiment::Online).iter().enumerate() {
            if !keys.contains(&v.key.as_str()) {
                continue;
            }
            if let Some(r) = report.find(wi, Experiment::Online, peak, &v.key) {
                series.push(Series {
                    label: v.label.clone(),
                    color: color(&v.key, vi),
                    points: ecdf(&r.latencies, 200)
                        .into_iter()
                        .map(|(x, y)| Point {
                            x,
                            lo: y,
                            mid: y,
                            hi: y,
                        })
                        .collect(),
                    bars: false,
                });
            }
        }
        panels.push(Panel {
            title: format!("{} @ {peak} tasks/s", w.title),
            x_desc: "E2E latency (s)".into(),
            y_desc: "CDF".into(),
            x_labels: None,
            series,
            y_range: Some((0.0, 1.0)),
            legend: SeriesLabelPosition::LowerRight,
        });
    }
    panels
}

/// The scale experiment, one panel per workload: a decision's CPU time against the fleet size
/// (mean, bars from the median to P99).
fn scale_panels(report: &Report<'_>) -> Vec<Panel> {
    let mut panels = Vec::new();
    for (wi, w) in report.workloads.iter().enumerate() {
        let runs = report.scale_runs(wi);
        let points: Vec<Point> = runs
            .iter()
            .filter(|r| r.decision_cpu_us.n > 0)
            .map(|r| Point {
                x: r.robots as f64,
                lo: r.decision_cpu_us.p50,
                mid: r.decision_cpu_us.mean,
                hi: r.decision_cpu_us.p99,
            })
            .collect();
        if points.is_empty() {
            continue;
        }
        panels.push(Panel {
            title: w.title.clone(),
            x_desc: "robots".into(),
            y_desc: "decision CPU time (µs)".into(),
            x_labels: None,
            series: vec![Series {
                label: "mean (bars P50–P99)".into(),
                color: color("kairos", 0),
                points,
                bars: true,
            }],
            y_range: None,
            legend: SeriesLabelPosition::UpperLeft,
        });
    }
    panels
}

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, p: &Panel) -> anyhow::Result<()> {
    let all = p.series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for pt in all {
        x0 = x0.min(pt.x);
        x1 = x1.max(pt.x);
        y1 = y1.max(pt.hi).max(pt.mid);
    }
    if !x0.is_finite() {
        return Ok(());
    }
    let pad = if p.x_labels.is_some() {
        0.5
    } else {
        ((x1 - x0) * 0.06).max(1e-3)
    };
    let (ylo, yhi) = p.y_range.unwrap_or((0.0, (y1 * 1.08).max(1e-3)));
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, (FAMILY, 17))
        .margin(8)
        .x_label_area_size(34)
        .y_label_area_size(46)
        .build_cartesian_2d((x0 - pad)..(x1 + pad), ylo..yhi)
        .map_err(err)?;
    let labels = p.x_labels.clone();
    let x_fmt = move |x: &f64| match &labels {
        Some(l) => {
            let i = x.round();
            if (x - i).abs() < 1e-6 && i >= 0.0 {
                l.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        }
        None => {
            // Shortest decimal form, without binary-fraction noise (0.30000000000000004).
            let v = (x * 1e6).round() / 1e6;
            format!("{v}")
        }
    };
    let n_labels = p.x_labels.as_ref().map_or(6, |l| l.len() * 4 + 1);
    chart
        .configure_mesh()
        .x_desc(p.x_desc.as_str())
        .y_desc(p.y_desc.as_str())
        .x_labels(n_labels)
        .x_label_formatter(&x_fmt)
        .y_label_formatter(&|y: &f64| {
            if p.y_range.is_some() {
                format!("{y:.1}")
            } else {
                format!("{y:.0}")
            }
        })
        .label_style((FAMILY, 12))
        .axis_desc_style((FAMILY, 13))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(err)?;
    let n = p.series.len().max(1) as f64;
    let spread = if p.x_labels.is_some() {
        0.0
    } else {
        (x1 - x0).max(1e-3) * 0.012
    };
    for (si, s) in p.series.iter().enumerate() {
        let dx = (si as f64 - (n - 1.0) / 2.0) * spread;
        let style = ShapeStyle::from(&s.color).stroke_width(2);
        let line: Vec<(f64, f64)> = s.points.iter().map(|pt| (pt.x + dx, pt.mid)).collect();
        let legend_color = s.color;
        if p.x_labels.is_none() {
            chart
                .draw_series(LineSeries::new(line.clone(), style))
                .map_err(err)?
                .label(s.label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], legend_color.stroke_width(2))
                });
        }
        if s.bars {
            chart
                .draw_series(s.points.iter().map(|pt| {
                    ErrorBar::new_vertical(
                        pt.x + dx,
                        pt.lo,
                        pt.mid,
                        pt.hi,
                        s.color.stroke_width(1),
                        6,
                    )
                }))
                .map_err(err)?;
            chart
                .draw_series(
                    line.iter()
                        .map(|&(x, y)| Circle::new((x, y), 3, s.color.filled())),
                )
                .map_err(err)?;
        }
    }
    if p.x_labels.is_none() && p.series.len() > 1 {
        chart
            .configure_series_labels()
            .label_font((FAMILY, 11))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .position(p.legend.clone())
            .draw()
            .map_err(err)?;
    }
    Ok(())
}

fn draw_grid<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    panels: &[Panel],
) -> anyhow::Result<()> {
    root.fill(&WHITE).map_err(err)?;
    let cols = panels.len().clamp(1, 3);
    let rows = panels.len().div_ceil(cols).max(1);
    for (area, panel) in root.split_evenly((rows, cols)).iter().zip(panels) {
        draw_panel(area, panel)?;
    }
    root.present().map_err(err)?;
    Ok(())
}

fn render(out: &Path, name: &str, panels: &[Panel]) -> anyhow::Result<()> {
    if panels.is_empty() {
        return Ok(());
    }
    let cols = panels.len().clamp(1, 3) as u32;
    let rows = panels.len().div_ceil(cols as usize).max(1) as u32;
    let size = (PANEL_W * cols, PANEL_H * rows);
    let png = out.join(format!("{name}.png"));
    draw_grid(BitMapBackend::new(&png, size).into_drawing_area(), panels)
        .with_context(|| format!("drawing {}", png.display()))?;
    let svg = out.join(format!("{name}.svg"));
    draw_grid(SVGBackend::new(&svg, size).into_drawing_area(), panels)
        .with_context(|| format!("drawing {}", svg.display()))?;
    Ok(())
}

fn register_font() -> anyhow::Result<()> {
    static REGISTER: Once = Once::new();
    let mut registered = Ok(());
    REGISTER.call_once(|| {
        registered = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT)
            .map_err(|_| anyhow!("the embedded font is not a valid TrueType file"));
    });
    registered
}

/// One system of a [`comparison`] plot.
pub struct Compared<'a> {
    /// Its key (picks the colour, as in the simulator's plots: `fifo`, `autellix`, `kairos`, `srw`).
    pub key: &'a str,
    /// Its label.
    pub label: &'a str,
    /// Its latency summary, seconds.
    pub summary: &'a kairos_core::stats::Summary,
    /// Every task's latency, seconds.
    pub latencies: &'a [f64],
}

/// Two panels into `out/<name>.png` (and `.svg`): each system's average end-to-end latency with
/// P25–P95 bars, and the latency CDFs. Returns the PNG's path.
pub fn comparison(
    out: &Path,
    name: &str,
    title: &str,
    systems: &[Compared<'_>],
) -> anyhow::Result<std::path::PathBuf> {
    register_font()?;
    let bars = Panel {
        title: title.to_string(),
        x_desc: "scheduler".into(),
        y_desc: "E2E latency (s)".into(),
        x_labels: Some(systems.iter().map(|s| s.label.to_string()).collect()),
        series: vec![Series {
            label: "avg (bars P25–P95)".into(),
            color: color("kairos", 0),
            points: systems
                .iter()
                .enumerate()
                .map(|(i, s)| Point {
                    x: i as f64,
                    lo: s.summary.p25,
                    mid: s.summary.mean,
                    hi: s.summary.p95,
                })
                .collect(),
            bars: true,
        }],
        y_range: None,
        legend: SeriesLabelPosition::UpperLeft,
    };
    let cdf = Panel {
        title: "task latency CDF".into(),
        x_desc: "E2E latency (s)".into(),
        y_desc: "CDF".into(),
        x_labels: None,
        series: systems
            .iter()
            .enumerate()
            .map(|(i, s)| Series {
                label: s.label.to_string(),
                color: color(s.key, i),
                points: ecdf(s.latencies, 200)
                    .into_iter()
                    .map(|(x, y)| Point {
                        x,
                        lo: y,
                        mid: y,
                        hi: y,
                    })
                    .collect(),
                bars: false,
            })
            .collect(),
        y_range: Some((0.0, 1.0)),
        legend: SeriesLabelPosition::LowerRight,
    };
    render(out, name, &[bars, cdf])?;
    Ok(out.join(format!("{name}.png")))
}

/// Every plot the report has data for, into `out`.
pub fn all(report: &Report<'_>, out: &Path) -> anyhow::Result<()> {
    register_font()?;
    // The paper's systems and ours, plus whatever the user asked for (`--policy`, plugins).
    let mut main = vec!["fifo", "autellix", "kairos", "srw", "srw-hint"];
    for j in report.jobs.iter().filter(|j| j.variant.user) {
        if !main.contains(&j.variant.key.as_str()) {
            main.push(&j.variant.key);
        }
    }
    render(
        out,
        "online",
        &sweep_panels(report, Experiment::Online, "arrival rate (tasks/s)", &main),
    )?;
    render(
        out,
        "fleet",
        &sweep_panels(report, Experiment::Fleet, "robots", &[]),
    )?;
    render(
        out,
        "hybrid",
        &sweep_panels(report, Experiment::Hybrid, "arrival rate (tasks/s)", &[]),
    )?;
    render(
        out,
        "buckets",
        &category_panels(report, Experiment::Buckets, "wait-ratio buckets"),
    )?;
    render(
        out,
        "intra",
        &category_panels(report, Experiment::Intra, "intra-bucket order"),
    )?;
    render(out, "cdf", &cdf_panels(report, &main))?;
    render(out, "scale", &scale_panels(report))?;
    Ok(())
}

/// One policy family of a [`pareto`] plot: its points `(mean horizon, success, CI low, CI high)`.
pub struct ParetoSeries<'a> {
    /// Its name (`static`, `threshold`, a plugin's).
    pub label: &'a str,
    /// Its points, in the order to join them.
    pub points: Vec<(f64, f64, f64, f64)>,
}

/// Success rate against mean executed horizon, one line per policy family with 95% CI bars,
/// into `out/<name>.png` (and `.svg`). Returns the PNG's path.
pub fn pareto(
    out: &Path,
    name: &str,
    title: &str,
    families: &[ParetoSeries<'_>],
) -> anyhow::Result<std::path::PathBuf> {
    register_font()?;
    let keys = ["fifo", "kairos", "srw", "autellix"];
    let panel = Panel {
        title: title.to_string(),
        x_desc: "mean executed horizon (actions)".into(),
        y_desc: "success rate".into(),
        x_labels: None,
        series: families
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let mut points: Vec<Point> = f
                    .points
                    .iter()
                    .map(|&(x, mid, lo, hi)| Point { x, lo, mid, hi })
                    .collect();
                points.sort_by(|a, b| a.x.total_cmp(&b.x));
                Series {
                    label: f.label.to_string(),
                    color: color(keys.get(i).copied().unwrap_or(""), i),
                    points,
                    bars: true,
                }
            })
            .collect(),
        y_range: Some((0.0, 1.0)),
        // Success falls as the horizon grows, so the upper right (long horizons at high
        // success, where no policy gets) is the one corner that no family's points reach.
        legend: SeriesLabelPosition::UpperRight,
    };
    render(out, name, &[panel])?;
    Ok(out.join(format!("{name}.png")))
}

/// One panel of [`success_panels`]: its title and its lines.
pub struct SuccessPanel<'a> {
    /// The panel's title (a task).
    pub title: String,
    /// One line per series (an execution strategy), points `(x, success, CI low, CI high)`.
    pub series: Vec<ParetoSeries<'a>>,
}

/// Success rate against `x_desc` (a delay), one panel per entry of `panels`, one line per
/// series with 95% CI bars, into `out/<name>.png` (and `.svg`). Returns the PNG's path.
pub fn success_panels(
    out: &Path,
    name: &str,
    x_desc: &str,
    panels: &[SuccessPanel<'_>],
) -> anyhow::Result<std::path::PathBuf> {
    register_font()?;
    let panels: Vec<Panel> = panels
        .iter()
        .map(|p| Panel {
            title: p.title.clone(),
            x_desc: x_desc.to_string(),
            y_desc: "success rate".into(),
            x_labels: None,
            series: p
                .series
                .iter()
                .enumerate()
                .map(|(i, f)| {
                    let mut points: Vec<Point> = f
                        .points
                        .iter()
                        .map(|&(x, mid, lo, hi)| Point { x, lo, mid, hi })
                        .collect();
                    points.sort_by(|a, b| a.x.total_cmp(&b.x));
                    Series {
                        label: f.label.to_string(),
                        color: color("", i),
                        points,
                        bars: true,
                    }
                })
                .collect(),
            y_range: Some((0.0, 1.0)),
            // Success falls as the delay grows: the upper right is where no line reaches.
            legend: SeriesLabelPosition::UpperRight,
        })
        .collect();
    render(out, name, &panels)?;
    Ok(out.join(format!("{name}.png")))
}
