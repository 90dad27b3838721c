//! `volux eval`: renders a generator's latents from several cameras and under several
//! environments, the same measurements on the synthetic dataset's exact renders, the sliced
//! Wasserstein distance against the training data, and figure strips.

use std::time::Instant;

use burn::tensor::Device;
use volux_data::contact_sheet::{self, ContactSheet};
use volux_data::dataset::{DataError, SourceConfig};
use volux_data::examples::ExamplesError;
use volux_data::relighting::RelightError;
use volux_data::synthetic_head::SyntheticHead;
use volux_envmap::{LightMapSet, Rgb};
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_model::ray_sampling::CameraConfig;
use volux_train::config::TrainConfig;
use volux_train::sampling::{self, SampleError};

use crate::geometry::{GeometryScore, render_angles};
use crate::image::ErrorSums;
use crate::relighting_consistency::{Invariance, ShadingScore, invariance, relit_against_shaded};
use crate::report::{EvalReport, InvarianceScore, MultiViewRow, Pair, ShadingRow, ViewScore};
use crate::reprojection::{DEFAULT_TOLERANCE, Reprojection, reproject};
use crate::sample_quality::sample_quality;
use crate::swd::{SwdError, SwdOptions};
use crate::views::{Rendered, render_model, render_synthetic};

/// An environment's light maps under a short name.
pub struct Environment {
    pub name: String,
    pub lights: LightMapSet,
}

/// What to measure and how much.
pub struct EvalOptions {
    /// Latents (seeds `first_seed ..`), synthetic heads and dataset images per measurement.
    pub samples: usize,
    pub first_seed: u64,
    /// Side-view yaws in radians (the frontal view is yaw 0).
    pub yaws: Vec<f64>,
    /// The multi-view test lights with the first; relighting compares all of them.
    pub environments: Vec<Environment>,
    /// Images per generator forward pass.
    pub batch: usize,
    /// Depth agreement of a consistent reprojection, world units.
    pub tolerance: f64,
    pub swd: SwdOptions,
    /// Latents shown in the figures.
    pub figure_rows: usize,
    /// Steps of the rotating-light figure.
    pub light_steps: usize,
}

impl EvalOptions {
    /// The defaults: 100 samples, side views at -0.5, -0.25, 0.25 and 0.5 rad.
    pub fn new(environments: Vec<Environment>) -> EvalOptions {
        EvalOptions {
            samples: 100,
            first_seed: 0,
            yaws: vec![-0.5, -0.25, 0.25, 0.5],
            environments,
            batch: 8,
            tolerance: DEFAULT_TOLERANCE,
            swd: SwdOptions::default(),
            figure_rows: 4,
            light_steps: 8,
        }
    }
}

/// Why an evaluation cannot run.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{0}")]
    Options(String),
    #[error("rendering the generator")]
    Sample(#[from] SampleError),
    #[error("relighting a synthetic head")]
    Relight(#[from] RelightError),
    #[error("dataset")]
    Data(#[from] DataError),
    #[error("dataset")]
    Examples(#[from] ExamplesError),
    #[error("sliced Wasserstein distance")]
    Swd(#[from] SwdError),
}

/// A named figure (written as `<name>.png`).
pub struct Figure {
    pub name: String,
    pub sheet: ContactSheet,
}

/// The report and its figures.
pub struct Evaluation {
    pub report: EvalReport,
    pub figures: Vec<Figure>,
}

/// Renders latents or heads: element `i` of a chunk at `pose`, under environment `env`
/// turned by `env_yaw`.
pub(crate) trait Source {
    fn render(
        &self,
        chunk: &[u64],
        pose: Pose,
        env: &LightMapSet,
        env_yaw: f64,
    ) -> Result<Vec<Rendered>, EvalError>;
}

pub(crate) struct Model<'a> {
    pub g: &'a Generator,
    pub device: &'a Device,
    pub z_dim: usize,
    pub background: Rgb,
}

impl Source for Model<'_> {
    fn render(
        &self,
        chunk: &[u64],
        pose: Pose,
        env: &LightMapSet,
        env_yaw: f64,
    ) -> Result<Vec<Rendered>, EvalError> {
        let z = sampling::latents(chunk, self.z_dim, self.device);
        let n = chunk.len();
        Ok(render_model(
            self.g,
            z,
            &vec![pose; n],
            &vec![env; n],
            &vec![env_yaw; n],
            self.background,
        )?)
    }
}

pub(crate) struct Heads {
    pub identities: u64,
    pub side: usize,
    pub side_lo: usize,
    pub background: Rgb,
}

impl Source for Heads {
    fn render(
        &self,
        chunk: &[u64],
        pose: Pose,
        env: &LightMapSet,
        env_yaw: f64,
    ) -> Result<Vec<Rendered>, EvalError> {
        chunk
            .iter()
            .map(|&seed| {
                let head = SyntheticHead::from_seed(seed % self.identities);
                Ok(render_synthetic(
                    &head,
                    pose,
                    self.side,
                    self.side_lo,
                    env,
                    env_yaw,
                    self.background,
                )?)
            })
            .collect()
    }
}

/// The multi-view, relighting and geometry measurements of one source.
#[derive(Default)]
struct Consistency {
    multiview: Vec<Reprojection>,
    invariance: Invariance,
    shading: Vec<ErrorSums>,
    angles: Vec<f64>,
    /// Per figure row: views at the sorted yaws (0 included), error maps per side yaw, and
    /// the frontal view under each environment.
    rows: Vec<FigureRow>,
}

struct FigureRow {
    views: Vec<Rendered>,
    errors: Vec<Vec<Option<f32>>>,
    lit: Vec<Rendered>,
}

fn measure(
    source: &dyn Source,
    options: &EvalOptions,
    camera: &CameraConfig,
    what: &str,
) -> Result<Consistency, EvalError> {
    let envs = &options.environments;
    let mut out = Consistency {
        multiview: vec![Reprojection::default(); options.yaws.len()],
        shading: vec![ErrorSums::default(); envs.len()],
        ..Consistency::default()
    };
    let seeds: Vec<u64> = (0..options.samples as u64)
        .map(|i| options.first_seed + i)
        .collect();
    let frontal = Pose::FRONTAL;
    for (c, chunk) in seeds.chunks(options.batch).enumerate() {
        tracing::info!(
            "{what}: samples {}..{} of {}",
            c * options.batch,
            c * options.batch + chunk.len(),
            seeds.len()
        );
        let front = source.render(chunk, frontal, &envs[0].lights, 0.0)?;
        let mut lit: Vec<Vec<Rendered>> = front.iter().map(|f| vec![f.clone()]).collect();
        for env in &envs[1..] {
            for (i, v) in source
                .render(chunk, frontal, &env.lights, 0.0)?
                .into_iter()
                .enumerate()
            {
                lit[i].push(v);
            }
        }
        for views in &lit {
            out.invariance.merge(&invariance(views));
            for (k, v) in views.iter().enumerate() {
                out.shading[k].merge(&relit_against_shaded(v));
            }
        }
        for f in &front {
            out.angles.extend(render_angles(camera, f));
        }
        let mut sides: Vec<Vec<Rendered>> = Vec::with_capacity(options.yaws.len());
        let mut errors: Vec<Vec<Vec<Option<f32>>>> = vec![Vec::new(); chunk.len()];
        for (j, &yaw) in options.yaws.iter().enumerate() {
            let side = source.render(chunk, Pose::new(yaw, 0.0), &envs[0].lights, 0.0)?;
            for (i, (f, s)) in front.iter().zip(&side).enumerate() {
                let r = reproject(f, s, camera, options.tolerance);
                out.multiview[j].merge(&r);
                errors[i].push(r.error_map);
                out.angles.extend(render_angles(camera, s));
            }
            sides.push(side);
        }
        for i in 0..chunk.len() {
            if out.rows.len() >= options.figure_rows {
                break;
            }
            let mut by_yaw: Vec<(f64, Rendered)> = options
                .yaws
                .iter()
                .zip(&sides)
                .map(|(&y, s)| (y, s[i].clone()))
                .collect();
            by_yaw.push((0.0, front[i].clone()));
            by_yaw.sort_by(|a, b| a.0.total_cmp(&b.0));
            out.rows.push(FigureRow {
                views: by_yaw.into_iter().map(|(_, v)| v).collect(),
                errors: std::mem::take(&mut errors[i]),
                lit: std::mem::take(&mut lit[i]),
            });
        }
    }
    Ok(out)
}

/// A camera-space normal map at the output size (blocks of the low-resolution map).
fn normal_tile(r: &Rendered) -> Vec<Rgb> {
    let f = r.side / r.side_lo;
    let s = r.side;
    let colours = contact_sheet::normal_colours(&r.normals_lo, &r.mask_lo);
    (0..s * s)
        .map(|p| colours[(p / s / f) * r.side_lo + (p % s) / f])
        .collect()
}

/// Reprojection error as grey (4x, clamped), inconsistent foreground red, background black.
fn error_tile(errors: &[Option<f32>], front: &Rendered) -> Vec<Rgb> {
    errors
        .iter()
        .zip(&front.mask)
        .map(|(e, &m)| match e {
            Some(e) => [(4.0 * e).min(1.0); 3],
            None if m >= crate::reprojection::FOREGROUND => [0.8, 0.1, 0.1],
            None => [0.0; 3],
        })
        .collect()
}

/// Rows: latents; columns: the relit image at each yaw, then the albedo's reprojection error
/// of each side view (see [`error_tile`]).
fn multiview_figure(rows: &[FigureRow], yaws: usize) -> Option<ContactSheet> {
    let first = rows.first()?;
    let s = first.views[0].side;
    let mut sheet = ContactSheet::new(s, s, 2 * yaws + 1, rows.len());
    for (r, row) in rows.iter().enumerate() {
        for (c, v) in row.views.iter().enumerate() {
            sheet.put(c, r, &v.relit);
        }
        let front = &row.lit[0];
        for (j, e) in row.errors.iter().enumerate() {
            sheet.put(yaws + 1 + j, r, &error_tile(e, front));
        }
    }
    Some(sheet)
}

/// Rows: latents; columns: albedo, normals, then relit and shaded under each environment.
fn relighting_figure(rows: &[FigureRow]) -> Option<ContactSheet> {
    let first = rows.first()?;
    let s = first.views[0].side;
    let envs = first.lit.len();
    let mut sheet = ContactSheet::new(s, s, 2 + 2 * envs, rows.len());
    for (r, row) in rows.iter().enumerate() {
        sheet.put(0, r, &contact_sheet::albedo_colours(&row.lit[0].albedo));
        sheet.put(1, r, &normal_tile(&row.lit[0]));
        for (k, v) in row.lit.iter().enumerate() {
            sheet.put(2 + k, r, &v.relit);
            sheet.put(2 + envs + k, r, &v.shaded);
        }
    }
    Some(sheet)
}

/// Rows: the first latents; columns: the first environment turned in equal steps.
fn rotating_light_figure(
    source: &dyn Source,
    options: &EvalOptions,
    seeds: &[u64],
) -> Result<Option<ContactSheet>, EvalError> {
    if seeds.is_empty() || options.light_steps == 0 {
        return Ok(None);
    }
    let mut columns = Vec::with_capacity(options.light_steps);
    for k in 0..options.light_steps {
        let yaw = std::f64::consts::TAU * k as f64 / options.light_steps as f64;
        columns.push(source.render(
            seeds,
            Pose::new(0.0, 0.0),
            &options.environments[0].lights,
            yaw,
        )?);
    }
    let s = columns[0][0].side;
    let mut sheet = ContactSheet::new(s, s, options.light_steps, seeds.len());
    for (c, col) in columns.iter().enumerate() {
        for (r, v) in col.iter().enumerate() {
            sheet.put(c, r, &v.relit);
        }
    }
    Ok(Some(sheet))
}

fn invariance_score(i: &Invariance) -> InvarianceScore {
    InvarianceScore {
        albedo_l1: i.albedo.l1(),
        albedo_max: i.albedo_max,
        normals_l1: i.normals.l1(),
    }
}

/// Runs every measurement on generator `g` (trained with `config`, having seen `images`
/// training images) and, for the built-in synthetic heads, on the data.
pub fn evaluate(
    g: &Generator,
    device: &Device,
    config: &TrainConfig,
    checkpoint: &str,
    images: u64,
    options: &EvalOptions,
) -> Result<Evaluation, EvalError> {
    let started = Instant::now();
    if options.samples == 0 || options.batch == 0 {
        return Err(EvalError::Options(
            "samples and batch must be at least 1".into(),
        ));
    }
    if options.environments.is_empty() {
        return Err(EvalError::Options(
            "at least one environment is needed".into(),
        ));
    }
    if let Some(y) = options
        .yaws
        .iter()
        .find(|y| !y.is_finite() || y.abs() > 1.5 || **y == 0.0)
    {
        return Err(EvalError::Options(format!(
            "side-view yaw {y} must be non-zero and within [-1.5, 1.5] rad"
        )));
    }
    let camera = g.renderer.camera.clone();
    let background = config.data.background;
    let z_dim = config.generator().mapping.z_dim;
    let model = Model {
        g,
        device,
        z_dim,
        background,
    };
    let measured = measure(&model, options, &camera, "model")?;
    let data = match &config.data.source {
        SourceConfig::Synthetic { identities, .. } => {
            let heads = Heads {
                identities: *identities,
                side: g.output_resolution(),
                side_lo: g.volume_resolution,
                background,
            };
            Some((measure(&heads, options, &camera, "synthetic heads")?, heads))
        }
        SourceConfig::Folder { .. } => None,
    };
    let swd = sample_quality(
        g,
        device,
        config,
        options.samples,
        options.first_seed,
        options.batch,
        &options.swd,
    )?;

    let multiview = options
        .yaws
        .iter()
        .enumerate()
        .map(|(j, &yaw)| MultiViewRow {
            yaw,
            scores: Pair {
                model: ViewScore::of(&measured.multiview[j]),
                data: data.as_ref().map(|(d, _)| ViewScore::of(&d.multiview[j])),
            },
        })
        .collect();
    let shading = options
        .environments
        .iter()
        .enumerate()
        .map(|(k, env)| ShadingRow {
            environment: env.name.clone(),
            scores: Pair {
                model: ShadingScore::of(&measured.shading[k]),
                data: data.as_ref().map(|(d, _)| ShadingScore::of(&d.shading[k])),
            },
        })
        .collect();

    let mut figures = Vec::new();
    let mut add = |name: &str, sheet: Option<ContactSheet>| {
        if let Some(sheet) = sheet {
            figures.push(Figure {
                name: name.into(),
                sheet,
            });
        }
    };
    let figure_seeds: Vec<u64> = (0..options.figure_rows.min(options.samples) as u64)
        .map(|i| options.first_seed + i)
        .collect();
    add(
        "multiview",
        multiview_figure(&measured.rows, options.yaws.len()),
    );
    add("relighting", relighting_figure(&measured.rows));
    add(
        "rotating-light",
        rotating_light_figure(&model, options, &figure_seeds)?,
    );
    if let Some((d, heads)) = &data {
        add(
            "multiview-data",
            multiview_figure(&d.rows, options.yaws.len()),
        );
        add(
            "rotating-light-data",
            rotating_light_figure(heads, options, &figure_seeds)?,
        );
    }

    let report = EvalReport {
        checkpoint: checkpoint.into(),
        images,
        samples: options.samples,
        first_seed: options.first_seed,
        tolerance: options.tolerance,
        environments: options
            .environments
            .iter()
            .map(|e| e.name.clone())
            .collect(),
        multiview,
        invariance: Pair {
            model: invariance_score(&measured.invariance),
            data: data.as_ref().map(|(d, _)| invariance_score(&d.invariance)),
        },
        shading,
        geometry: Pair {
            model: GeometryScore::of(&measured.angles),
            data: data.as_ref().map(|(d, _)| GeometryScore::of(&d.angles)),
        },
        swd,
        seconds: started.elapsed().as_secs_f64(),
    };
    Ok(Evaluation { report, figures })
}
