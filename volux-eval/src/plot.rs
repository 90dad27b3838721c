//! `volux plot`: a run's losses and light-evaluation scores (`metrics.jsonl`) against images
//! and against minutes, as PNG; or the scores of several runs against each other (A/B). Each quantity gets its own panel; a score's reference (the
//! dataset's floor or the data's own score) is drawn dashed in the score's colour.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

/// The font every label is drawn with (compiled in: plots need no installed fonts).
const FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

/// Why a run cannot be plotted.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("reading {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}, line {line}: not a metrics line", path.display())]
    Line {
        path: PathBuf,
        line: usize,
        #[source]
        source: serde_json::Error,
    },
    #[error("{}, line {line}: {message}", path.display())]
    Field {
        path: PathBuf,
        line: usize,
        message: String,
    },
    #[error("{} holds no metrics lines yet", path.display())]
    Empty { path: PathBuf },
    #[error(
        "{} has no evaluation lines to compare: train it with `[output] eval_kimg` set",
        run.display()
    )]
    NoEvaluations { run: PathBuf },
    #[error("the shipped font could not be loaded")]
    Font,
    #[error("drawing the plot")]
    Draw(#[source] volux_envmap::error::BoxError),
    #[error("creating {}", path.display())]
    CreateDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("writing {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: volux_envmap::EnvMapError,
    },
}

/// One logged point: where it was taken and its named values.
#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    pub kimg: f64,
    /// Absent in logs written before the run clock existed.
    pub minutes: Option<f64>,
    pub values: BTreeMap<String, f64>,
}

/// A run's log: the training lines (losses and `images_per_sec`) and the evaluation lines.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunMetrics {
    pub training: Vec<Point>,
    pub evals: Vec<Point>,
}

/// The finite numbers of a JSON object (`null`, the log's spelling of NaN, is left out).
fn numbers(object: &serde_json::Map<String, serde_json::Value>) -> BTreeMap<String, f64> {
    object
        .iter()
        .filter_map(|(k, v)| Some((k.clone(), v.as_f64().filter(|x| x.is_finite())?)))
        .collect()
}

impl RunMetrics {
    /// Parses `metrics.jsonl`; a line that is not a metrics line is an error naming it.
    pub fn read(path: &Path) -> Result<RunMetrics, PlotError> {
        let text = std::fs::read_to_string(path).map_err(|source| PlotError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut out = RunMetrics::default();
        for (i, line) in text.lines().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            let field = |message: &str| PlotError::Field {
                path: path.to_path_buf(),
                line: i + 1,
                message: message.into(),
            };
            let value: serde_json::Value =
                serde_json::from_str(line).map_err(|source| PlotError::Line {
                    path: path.to_path_buf(),
                    line: i + 1,
                    source,
                })?;
            let kimg = value
                .get("kimg")
                .and_then(serde_json::Value::as_f64)
                .filter(|k| k.is_finite())
                .ok_or_else(|| field("no finite \"kimg\""))?;
            let minutes = value.get("minutes").and_then(serde_json::Value::as_f64);
            if let Some(eval) = value.get("eval") {
                let eval = eval
                    .as_object()
                    .ok_or_else(|| field("\"eval\" is not an object"))?;
                out.evals.push(Point {
                    kimg,
                    minutes,
                    values: numbers(eval),
                });
            } else if let Some(losses) = value.get("losses") {
                let losses = losses
                    .as_object()
                    .ok_or_else(|| field("\"losses\" is not an object"))?;
                let mut values = numbers(losses);
                if let Some(rate) = value.get("images_per_sec").and_then(|v| v.as_f64()) {
                    values.insert("images_per_sec".into(), rate);
                }
                out.training.push(Point {
                    kimg,
                    minutes,
                    values,
                });
            } else {
                return Err(field("neither \"losses\" nor \"eval\""));
            }
        }
        if out.training.is_empty() && out.evals.is_empty() {
            return Err(PlotError::Empty {
                path: path.to_path_buf(),
            });
        }
        Ok(out)
    }

    /// Whether every line carries the run clock (a minutes axis can be drawn).
    pub fn has_minutes(&self) -> bool {
        self.training
            .iter()
            .chain(&self.evals)
            .all(|p| p.minutes.is_some())
    }
}

/// What the horizontal axis counts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum XAxis {
    Kimg,
    Minutes,
}

impl XAxis {
    pub fn label(self) -> &'static str {
        match self {
            XAxis::Kimg => "training images (thousands)",
            XAxis::Minutes => "wall-clock minutes",
        }
    }

    /// The file-name suffix.
    pub fn name(self) -> &'static str {
        match self {
            XAxis::Kimg => "kimg",
            XAxis::Minutes => "minutes",
        }
    }

    fn of(self, p: &Point) -> Option<f64> {
        match self {
            XAxis::Kimg => Some(p.kimg),
            XAxis::Minutes => p.minutes,
        }
    }
}

/// One line of a panel.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Drawn dashed: a reference, not a measurement.
    pub dashed: bool,
    /// Index into the palette (a score and its reference share one).
    pub colour: usize,
}

/// One quantity's panel.
#[derive(Clone, Debug, PartialEq)]
pub struct Panel {
    pub title: String,
    pub curves: Vec<Curve>,
}

/// `key`'s points along `axis`.
fn series(points: &[Point], key: &str, axis: XAxis) -> Vec<(f64, f64)> {
    points
        .iter()
        .filter_map(|p| Some((axis.of(p)?, *p.values.get(key)?)))
        .collect()
}

/// Every key of `points` that `keep` accepts, in order.
fn keys(points: &[Point], keep: impl Fn(&str) -> bool) -> Vec<String> {
    let mut all: Vec<String> = points
        .iter()
        .flat_map(|p| p.values.keys())
        .filter(|k| keep(k))
        .cloned()
        .collect();
    all.sort();
    all.dedup();
    all
}

/// A panel of the keys of `points` that `keep` accepts, each drawn solid, with the reference
/// `reference(key)` dashed beside it where the log has one.
fn panel(
    title: &str,
    points: &[Point],
    axis: XAxis,
    keep: impl Fn(&str) -> bool,
    reference: impl Fn(&str) -> Option<(String, String)>,
) -> Panel {
    let mut curves = Vec::new();
    for (colour, key) in keys(points, keep).into_iter().enumerate() {
        curves.push(Curve {
            points: series(points, &key, axis),
            name: key.clone(),
            dashed: false,
            colour,
        });
        if let Some((ref_key, name)) = reference(&key) {
            let points = series(points, &ref_key, axis);
            if !points.is_empty() {
                curves.push(Curve {
                    name,
                    points,
                    dashed: true,
                    colour,
                });
            }
        }
    }
    curves.retain(|c| !c.points.is_empty());
    Panel {
        title: title.into(),
        curves,
    }
}

/// The panels of a run along `axis`: losses by network, regularisers, throughput, and the
/// light evaluation's scores with their references. Panels with nothing to draw are left out.
pub fn panels(metrics: &RunMetrics, axis: XAxis) -> Vec<Panel> {
    let (t, e) = (&metrics.training, &metrics.evals);
    let none = |_: &str| None;
    let suffixed = |suffix: &'static str, label: &'static str| {
        move |k: &str| Some((format!("{k}{suffix}"), format!("{k} ({label})")))
    };
    let out = vec![
        panel(
            "Sample quality: SWD x1e3 (dashed: the data's floor)",
            e,
            axis,
            |k| k.starts_with("swd_") && !k.ends_with("_floor"),
            suffixed("_floor", "floor"),
        ),
        panel(
            "Multi-view albedo PSNR, dB (dashed: the data)",
            e,
            axis,
            |k| k == "multiview_albedo_psnr",
            suffixed("_data", "data"),
        ),
        panel(
            "Normals against depth, mean degrees (dashed: the data)",
            e,
            axis,
            |k| k == "normal_depth_degrees",
            suffixed("_data", "data"),
        ),
        panel(
            "Multi-view consistent fraction (dashed: the data)",
            e,
            axis,
            |k| k == "multiview_consistent",
            suffixed("_data", "data"),
        ),
        panel("Generator losses", t, axis, |k| k.starts_with("G_"), none),
        panel(
            "Discriminator losses",
            t,
            axis,
            |k| k.starts_with("D_"),
            none,
        ),
        panel(
            "Regularisers (R1, path length, density)",
            t,
            axis,
            |k| k.starts_with("R1_") || k == "path" || k == "density_reg",
            none,
        ),
        panel(
            "Throughput, images/s",
            t,
            axis,
            |k| k == "images_per_sec",
            none,
        ),
    ];
    out.into_iter().filter(|p| !p.curves.is_empty()).collect()
}

/// The light evaluation's scores of several runs along `axis`, one panel per score with one
/// curve per run (in the order given, named by its label) and the first run's reference
/// dashed, then every run's throughput: an A/B comparison at equal images or equal minutes.
pub fn compare_panels(runs: &[(String, RunMetrics)], axis: XAxis) -> Vec<Panel> {
    let reference_colour = runs.len();
    let mut scores: Vec<String> = runs
        .iter()
        .flat_map(|(_, m)| {
            keys(&m.evals, |k| {
                !k.ends_with("_floor") && !k.ends_with("_data")
            })
        })
        .collect();
    scores.sort();
    scores.dedup();
    let mut out = Vec::new();
    for key in scores {
        let mut curves: Vec<Curve> = runs
            .iter()
            .enumerate()
            .map(|(colour, (name, m))| Curve {
                name: name.clone(),
                points: series(&m.evals, &key, axis),
                dashed: false,
                colour,
            })
            .collect();
        if let Some((_, first)) = runs.first() {
            for (suffix, label) in [("_floor", "floor"), ("_data", "data")] {
                let points = series(&first.evals, &format!("{key}{suffix}"), axis);
                if !points.is_empty() {
                    curves.push(Curve {
                        name: label.into(),
                        points,
                        dashed: true,
                        colour: reference_colour,
                    });
                }
            }
        }
        curves.retain(|c| !c.points.is_empty());
        out.push(Panel { title: key, curves });
    }
    out.push(Panel {
        title: "images_per_sec".into(),
        curves: runs
            .iter()
            .enumerate()
            .map(|(colour, (name, m))| Curve {
                name: name.clone(),
                points: series(&m.training, "images_per_sec", axis),
                dashed: false,
                colour,
            })
            .filter(|c| !c.points.is_empty())
            .collect(),
    });
    out.into_iter().filter(|p| !p.curves.is_empty()).collect()
}

/// `[lo, hi]` with a margin, never empty.
fn padded(lo: f64, hi: f64) -> (f64, f64) {
    if !(lo.is_finite() && hi.is_finite()) {
        return (0.0, 1.0);
    }
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(1.0) {
        let d = (0.1 * hi.abs()).max(0.5);
        return (lo - d, hi + d);
    }
    (lo - 0.05 * span, hi + 0.05 * span)
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    padded(lo, hi)
}

fn draw_error<E: std::error::Error + Send + Sync + 'static>(e: E) -> PlotError {
    PlotError::Draw(Box::new(e))
}

fn register() -> Result<(), PlotError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok { Ok(()) } else { Err(PlotError::Font) }
}

/// Side of one panel, pixels.
pub const PANEL_WIDTH: usize = 700;
pub const PANEL_HEIGHT: usize = 380;

/// Draws `panels` two to a row under `title`; returns the image's width, height and pixels.
pub fn render(
    title: &str,
    panels: &[Panel],
    axis: XAxis,
) -> Result<(usize, usize, Vec<[u8; 3]>), PlotError> {
    register()?;
    let columns = panels.len().clamp(1, 2);
    let rows = panels.len().div_ceil(2).max(1);
    let header = 40;
    let (w, h) = (columns * PANEL_WIDTH, rows * PANEL_HEIGHT + header);
    let mut buffer = vec![0u8; w * h * 3];
    {
        let root =
            BitMapBackend::with_buffer(&mut buffer, (w as u32, h as u32)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_error)?;
        let (top, body) = root.split_vertically(header as u32);
        top.titled(title, (FAMILY, 22)).map_err(draw_error)?;
        let x_range = range(
            panels
                .iter()
                .flat_map(|p| &p.curves)
                .flat_map(|c| c.points.iter().map(|p| p.0)),
        );
        for (area, panel) in body.split_evenly((rows, columns)).iter().zip(panels) {
            let y_range = range(
                panel
                    .curves
                    .iter()
                    .flat_map(|c| c.points.iter().map(|p| p.1)),
            );
            let mut chart = ChartBuilder::on(area)
                .caption(&panel.title, (FAMILY, 16))
                .margin(10)
                .x_label_area_size(40)
                .y_label_area_size(60)
                .build_cartesian_2d(x_range.0..x_range.1, y_range.0..y_range.1)
                .map_err(draw_error)?;
            chart
                .configure_mesh()
                .x_desc(axis.label())
                .label_style((FAMILY, 12))
                .draw()
                .map_err(draw_error)?;
            for curve in &panel.curves {
                let colour = Palette99::pick(curve.colour).to_rgba();
                let style = colour.stroke_width(2);
                let points = curve.points.iter().copied();
                let drawn = if curve.dashed {
                    chart.draw_series(DashedLineSeries::new(points, 6, 4, style))
                } else {
                    chart.draw_series(LineSeries::new(points, style))
                }
                .map_err(draw_error)?;
                // The swatch is drawn the way its curve is: two dashes for a reference.
                let gap = if curve.dashed { 4 } else { 0 };
                drawn.label(curve.name.clone()).legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + PathElement::new(vec![(0, 0), (9 - gap, 0)], colour.stroke_width(2))
                        + PathElement::new(vec![(9 + gap, 0), (18, 0)], colour.stroke_width(2))
                });
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font((FAMILY, 12))
                .draw()
                .map_err(draw_error)?;
        }
        root.present().map_err(draw_error)?;
    }
    let pixels = buffer.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    Ok((w, h, pixels))
}

/// Plots the light evaluations of `runs` (label, run folder) against each other into `out`
/// (`compare-kimg.png`, and `compare-minutes.png` when every log carries the run clock);
/// returns the files written.
pub fn plot_runs(runs: &[(String, PathBuf)], out: &Path) -> Result<Vec<PathBuf>, PlotError> {
    let metrics = runs
        .iter()
        .map(|(name, run)| {
            let m = RunMetrics::read(&run.join(volux_train::run_folder::METRICS))?;
            if m.evals.is_empty() {
                return Err(PlotError::NoEvaluations { run: run.clone() });
            }
            Ok((name.clone(), m))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut axes = vec![XAxis::Kimg];
    if metrics.iter().all(|(_, m)| m.has_minutes()) {
        axes.push(XAxis::Minutes);
    }
    let names: Vec<&str> = runs.iter().map(|(n, _)| n.as_str()).collect();
    let title = format!("volux runs {}", names.join(" / "));
    write_plots(out, "compare", &axes, |axis| {
        render(&title, &compare_panels(&metrics, axis), axis)
    })
}

/// Renders one image per axis with `draw` and writes it to `out/<stem>-<axis>.png`.
fn write_plots(
    out: &Path,
    stem: &str,
    axes: &[XAxis],
    draw: impl Fn(XAxis) -> Result<(usize, usize, Vec<[u8; 3]>), PlotError>,
) -> Result<Vec<PathBuf>, PlotError> {
    std::fs::create_dir_all(out).map_err(|source| PlotError::CreateDir {
        path: out.to_path_buf(),
        source,
    })?;
    let mut written = Vec::new();
    for &axis in axes {
        let (w, h, pixels) = draw(axis)?;
        let path = out.join(format!("{stem}-{}.png", axis.name()));
        volux_envmap::io::save_png(&path, w, h, &pixels).map_err(|source| PlotError::Write {
            path: path.clone(),
            source,
        })?;
        written.push(path);
    }
    Ok(written)
}

/// Plots `run`'s `metrics.jsonl` into `out` (`curves-kimg.png`, and `curves-minutes.png`
/// when the log carries the run clock); returns the files written.
pub fn plot_run(run: &Path, out: &Path, title: &str) -> Result<Vec<PathBuf>, PlotError> {
    let metrics = RunMetrics::read(&run.join(volux_train::run_folder::METRICS))?;
    plot_metrics(&metrics, out, title)
}

/// [`plot_run`] for a log already read.
pub fn plot_metrics(
    metrics: &RunMetrics,
    out: &Path,
    title: &str,
) -> Result<Vec<PathBuf>, PlotError> {
    let mut axes = vec![XAxis::Kimg];
    if metrics.has_minutes() {
        axes.push(XAxis::Minutes);
    }
    write_plots(out, "curves", &axes, |axis| {
        render(title, &panels(metrics, axis), axis)
    })
}

#[cfg(test)]
mod tests;
