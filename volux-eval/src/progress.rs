//! The light evaluation taken during training (`[output] eval_kimg`): a few of `volux eval`'s
//! measurements on a small fixed set, cheap enough to run every few hundred images, so that a
//! run's quality can be read against its images and minutes (`volux plot`).
//!
//! - Sample quality: the sliced Wasserstein distance of albedo, normals and relit image
//!   ([`crate::sample_quality`]) on `samples` latents against `samples` dataset images, both
//!   fixed for the whole run; the dataset's floor at the same count is measured once.
//! - Multi-view consistency: `views` latents rendered frontally and at `-yaw` and `+yaw`, side
//!   views warped into the frontal one ([`crate::reprojection`]); the albedo's PSNR and the
//!   consistent fraction over both sides.
//! - Geometry: the mean angle between the frontal views' accumulated normals and the normals
//!   of their depth ([`crate::geometry`]).
//!
//! On the built-in synthetic heads the multi-view and geometry scores of the data are measured
//! once too (`_data` keys). With few samples the distances sit above `volux eval`'s: compare a
//! run's curve with its own floor, not with an eval table.

use std::collections::BTreeMap;

use burn::tensor::Device;
use volux_data::dataset::SourceConfig;
use volux_envmap::LightMapSet;
use volux_model::generator::Generator;
use volux_model::pose::Pose;
use volux_model::ray_sampling::CameraConfig;
use volux_train::config::TrainConfig;
use volux_train::metrics::{BoxError, ProgressEvaluator};

use crate::evaluate::{EvalError, Heads, Model, Source};
use crate::geometry::{GeometryScore, render_angles};
use crate::reprojection::{DEFAULT_TOLERANCE, Reprojection, reproject};
use crate::sample_quality::{DataSets, distances, fake_sets};
use crate::swd::SwdOptions;

/// How much the light evaluation measures.
#[derive(Clone, Debug, PartialEq)]
pub struct ProgressOptions {
    /// Latents and dataset images of the sliced Wasserstein distance.
    pub samples: usize,
    /// Latents of the multi-view and geometry scores.
    pub views: usize,
    /// Side-view yaw, radians (both signs are measured).
    pub yaw: f64,
    /// Images per generator forward pass.
    pub batch: usize,
    /// Depth agreement of a consistent reprojection, world units.
    pub tolerance: f64,
    pub swd: SwdOptions,
}

impl ProgressOptions {
    /// `samples` for the distance, 8 latents (at most `samples`) at +-0.5 rad for the views.
    pub fn new(samples: usize) -> ProgressOptions {
        ProgressOptions {
            samples,
            views: samples.min(8),
            yaw: 0.5,
            batch: 8,
            tolerance: DEFAULT_TOLERANCE,
            swd: SwdOptions::default(),
        }
    }
}

/// Multi-view and geometry scores of one source.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewScores {
    /// PSNR of the side views' sRGB albedo warped into the frontal view.
    pub albedo_psnr: f64,
    /// Fraction of frontal foreground pixels that reproject consistently.
    pub consistent: f64,
    /// Mean angle between accumulated normals and depth normals, degrees.
    pub normal_depth_degrees: f64,
}

/// Renders latents (or heads) `seeds` frontally and at `-yaw` and `+yaw` under `lights`.
fn view_scores(
    source: &dyn Source,
    seeds: &[u64],
    options: &ProgressOptions,
    lights: &LightMapSet,
    camera: &CameraConfig,
) -> Result<ViewScores, EvalError> {
    let mut pairs = Reprojection::default();
    let mut angles = Vec::new();
    for chunk in seeds.chunks(options.batch) {
        let front = source.render(chunk, Pose::FRONTAL, lights, 0.0)?;
        for f in &front {
            angles.extend(render_angles(camera, f));
        }
        for yaw in [-options.yaw, options.yaw] {
            let side = source.render(chunk, Pose::new(yaw, 0.0), lights, 0.0)?;
            for (f, s) in front.iter().zip(&side) {
                pairs.merge(&reproject(f, s, camera, options.tolerance));
            }
        }
    }
    Ok(ViewScores {
        albedo_psnr: pairs.albedo.psnr(),
        consistent: pairs.consistent_fraction(),
        normal_depth_degrees: GeometryScore::of(&angles).mean_degrees,
    })
}

/// The light evaluation of one run: its fixed dataset draws and the data's scores, measured
/// once; [`ProgressEval::measure`] measures a generator against them.
pub struct ProgressEval {
    config: TrainConfig,
    device: Device,
    options: ProgressOptions,
    data: DataSets,
    /// The dataset's distance to itself per compared layer (x1e3, mean over levels).
    floor: Vec<f64>,
    /// The synthetic heads' view scores (`None` for folder datasets).
    data_views: Option<ViewScores>,
}

impl ProgressEval {
    /// Draws the fixed dataset sets of `config` and measures the data once. `device` is where
    /// the generators to measure live.
    pub fn new(
        config: &TrainConfig,
        device: Device,
        options: ProgressOptions,
    ) -> Result<ProgressEval, EvalError> {
        if options.samples < 2 || options.views == 0 || options.batch == 0 {
            return Err(EvalError::Options(format!(
                "the light evaluation needs at least 2 samples, 1 view and a batch of 1 (got {}, {}, {})",
                options.samples, options.views, options.batch
            )));
        }
        if !(options.yaw.is_finite() && options.yaw != 0.0 && options.yaw.abs() <= 1.5) {
            return Err(EvalError::Options(format!(
                "side-view yaw {} must be non-zero and within [-1.5, 1.5] rad",
                options.yaw
            )));
        }
        let data = DataSets::draw(config, options.samples, options.batch)?;
        let floor = data.floor(&options.swd)?.iter().map(|s| s.mean).collect();
        let g = config.generator();
        let data_views = match &config.data.source {
            SourceConfig::Synthetic { identities, .. } => {
                let heads = Heads {
                    identities: *identities,
                    side: g.output_resolution,
                    side_lo: g.volume_resolution,
                    background: config.data.background,
                };
                let seeds: Vec<u64> = (0..options.views as u64).collect();
                Some(view_scores(
                    &heads,
                    &seeds,
                    &options,
                    &data.lights[0],
                    &g.renderer.camera,
                )?)
            }
            SourceConfig::Folder { .. } => None,
        };
        Ok(ProgressEval {
            config: config.clone(),
            device,
            options,
            data,
            floor,
            data_views,
        })
    }

    /// The scores of generator `g`, by name: `swd_<layer>` and `swd_<layer>_floor` (x1e3),
    /// `multiview_albedo_psnr`, `multiview_consistent`, `normal_depth_degrees`, and the data's
    /// view scores with a `_data` suffix where they are known.
    pub fn measure(&self, g: &Generator) -> Result<BTreeMap<String, f64>, EvalError> {
        let o = &self.options;
        let fake = fake_sets(g, &self.device, &self.config, &self.data, 0, o.batch)?;
        let model = distances(&self.data.compared, &fake, &self.data.other, &o.swd)?;
        let mut scores = BTreeMap::new();
        for (k, c) in self.data.compared.iter().enumerate() {
            scores.insert(format!("swd_{}", c.name), model[k].mean);
            scores.insert(format!("swd_{}_floor", c.name), self.floor[k]);
        }
        let source = Model {
            g,
            device: &self.device,
            z_dim: self.config.generator().mapping.z_dim,
            background: self.config.data.background,
        };
        let seeds: Vec<u64> = (0..o.views as u64).collect();
        let views = view_scores(&source, &seeds, o, &self.data.lights[0], &g.renderer.camera)?;
        let mut put = |suffix: &str, v: &ViewScores| {
            scores.insert(format!("multiview_albedo_psnr{suffix}"), v.albedo_psnr);
            scores.insert(format!("multiview_consistent{suffix}"), v.consistent);
            scores.insert(
                format!("normal_depth_degrees{suffix}"),
                v.normal_depth_degrees,
            );
        };
        put("", &views);
        if let Some(d) = &self.data_views {
            put("_data", d);
        }
        Ok(scores)
    }
}

impl ProgressEvaluator for ProgressEval {
    fn measure(&mut self, ema: &Generator) -> Result<BTreeMap<String, f64>, BoxError> {
        Ok(ProgressEval::measure(self, ema)?)
    }
}
