//! Error against run time of the renderer's samples per ray: for each sample count (stratified
//! only, and with as many importance samples again under the left and the midpoint rule), the
//! relative RMS error of the accumulated albedo,
//! normals, diffuse and specular maps against a 1024-sample stratified reference, and the wall
//! time of the render, on random NeIIFs (fog-like, as a generator is at initialisation) and on
//! soft spheres (hard surfaces, the stiff case). Beside them, layouts whose importance samples
//! are placed by density-only [`crate::proposal`] passes, so that their cost can be set
//! against the plain counts' in the same sitting. `volux model sampling-report` prints it;
//! docs/model.md records it.

use crate::pose::Pose;
use std::time::Instant;

use burn::tensor::{Device, Distribution, Tensor};

use crate::analytic::SoftSphere;
use crate::backend::to_f32_vec;
use crate::field::Field;
use crate::light_lookup::Lighting;
use crate::neiif::{LatentField, NeiifConfig};
use crate::ray_sampling::camera_ray_batch;
use crate::volume_rendering::{RenderOutput, RenderWants, RendererConfig, render};

/// What the report measures.
#[derive(Clone, Debug)]
pub struct SamplingSettings {
    /// Image side (rays = side^2).
    pub side: usize,
    /// Stratified sample counts to measure.
    pub counts: Vec<usize>,
    /// Samples of the reference (stratified, no importance).
    pub reference: usize,
    /// Random NeIIFs to average over.
    pub random_fields: usize,
    /// Rays per render call (bounds memory).
    pub chunk: usize,
    /// Layouts with density-only proposal passes to measure (midpoint rule).
    pub layouts: Vec<ProposalLayout>,
}

/// Samples per ray of a renderer whose importance samples are placed by proposal passes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProposalLayout {
    /// Full stratified samples, composited with the importance ones (may be 0).
    pub stratified: usize,
    /// Density-only stratified samples.
    pub proposal: usize,
    /// Density-only samples drawn from the proposal's weights.
    pub refine: usize,
    /// Full samples drawn from the density-only samples' weights.
    pub importance: usize,
}

impl ProposalLayout {
    /// The renderer's configuration for this layout (midpoint rule).
    pub fn renderer(&self) -> RendererConfig {
        RendererConfig::new()
            .with_stratified(self.stratified)
            .with_proposal(self.proposal)
            .with_refine(self.refine)
            .with_importance(self.importance)
    }
}

impl std::str::FromStr for ProposalLayout {
    type Err = String;

    /// `S:P:R:I`: stratified, proposal, refine and importance samples per ray.
    fn from_str(s: &str) -> Result<Self, String> {
        let parts: Vec<usize> = s
            .split(':')
            .map(|p| p.trim().parse::<usize>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("layout {s:?}: {e} (expected S:P:R:I, e.g. 0:32:16:12)"))?;
        let [stratified, proposal, refine, importance] = parts[..] else {
            return Err(format!(
                "layout {s:?}: expected four counts S:P:R:I (stratified, proposal, refine, importance)"
            ));
        };
        let layout = Self {
            stratified,
            proposal,
            refine,
            importance,
        };
        if proposal == 0 {
            return Err(format!(
                "layout {s:?}: the proposal count P must be at least 1"
            ));
        }
        layout
            .renderer()
            .check_samples()
            .map_err(|e| format!("layout {s:?}: {e}"))?;
        if [stratified, proposal, refine, importance]
            .iter()
            .any(|&n| n > MAX_LAYOUT_SAMPLES)
        {
            return Err(format!(
                "layout {s:?}: at most {MAX_LAYOUT_SAMPLES} samples of each kind"
            ));
        }
        Ok(layout)
    }
}

/// The most samples of one kind a report layout may ask for.
pub const MAX_LAYOUT_SAMPLES: usize = 1024;

impl Default for SamplingSettings {
    fn default() -> Self {
        Self {
            side: 32,
            counts: vec![8, 16, 32, 64],
            reference: 1024,
            random_fields: 2,
            chunk: 256,
            layouts: DEFAULT_LAYOUTS
                .iter()
                .map(|l| l.parse().expect("valid default layout"))
                .collect(),
        }
    }
}

/// The proposal layouts the report measures by default, `S:P:R:I`.
pub const DEFAULT_LAYOUTS: [&str; 5] = [
    "0:16:0:13",
    "0:16:8:12",
    "0:16:4:14",
    "0:32:16:12",
    "8:16:0:8",
];

/// One line of the report.
#[derive(Clone, Debug)]
pub struct SamplingRow {
    pub scene: String,
    pub stratified: usize,
    pub importance: usize,
    /// Density-only proposal and refine samples (0, 0: EG3D's two passes).
    pub proposal: usize,
    pub refine: usize,
    /// Midpoint rule (else the left rule).
    pub midpoint: bool,
    /// Wall time of one render of the image (forward only), milliseconds.
    pub ms: f64,
    /// Relative RMS error of `[A, N, D, S]` against the reference.
    pub error: [f64; 4],
}

/// The maps the report compares, read back.
struct Maps([Vec<f32>; 4]);

fn render_chunked(
    cfg: &RendererConfig,
    field: &impl Field,
    side: usize,
    lighting: &Lighting,
    chunk: usize,
    device: &Device,
) -> Maps {
    let (o, d) = camera_ray_batch(&cfg.camera, &[Pose::new(0.3, -0.1)], side, side, device);
    let rays = side * side;
    let mut maps: [Vec<f32>; 4] = Default::default();
    let mut start = 0;
    while start < rays {
        let n = chunk.min(rays - start);
        let out: RenderOutput = render(
            cfg,
            field,
            o.clone().narrow(1, start, n),
            d.clone().narrow(1, start, n),
            Some(lighting),
            RenderWants {
                albedo: true,
                normals: true,
                shading: true,
                features: false,
                depth: false,
            },
            false,
        );
        for (m, t) in maps.iter_mut().zip([
            out.albedo.expect("asked"),
            out.normals.expect("asked"),
            out.diffuse.expect("asked"),
            out.specular.expect("asked"),
        ]) {
            m.extend(to_f32_vec(t));
        }
        start += n;
    }
    Maps(maps)
}

fn relative_rms(got: &[f32], want: &[f32]) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (g, w) in got.iter().zip(want) {
        num += (f64::from(*g) - f64::from(*w)).powi(2);
        den += f64::from(*w).powi(2);
    }
    (num / den.max(1e-30)).sqrt()
}

fn measure_scene(
    scene: &str,
    field: &impl Field,
    lighting: &Lighting,
    settings: &SamplingSettings,
    device: &Device,
    rows: &mut Vec<SamplingRow>,
) {
    let reference_cfg = RendererConfig::new()
        .with_stratified(settings.reference)
        .with_importance(0);
    let reference = render_chunked(
        &reference_cfg,
        field,
        settings.side,
        lighting,
        settings.chunk,
        device,
    );
    let plain = settings.counts.iter().flat_map(|&count| {
        [(0, true), (count, false), (count, true)].map(|(importance, midpoint)| {
            RendererConfig::new()
                .with_stratified(count)
                .with_importance(importance)
                .with_midpoint(midpoint)
        })
    });
    let proposed = settings.layouts.iter().map(ProposalLayout::renderer);
    for cfg in plain.chain(proposed) {
        let start = Instant::now();
        let got = render_chunked(&cfg, field, settings.side, lighting, settings.chunk, device);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let error = std::array::from_fn(|k| relative_rms(&got.0[k], &reference.0[k]));
        rows.push(SamplingRow {
            scene: scene.to_string(),
            stratified: cfg.stratified,
            importance: cfg.importance,
            proposal: cfg.proposal,
            refine: cfg.refine,
            midpoint: cfg.midpoint,
            ms,
            error,
        });
    }
}

/// Runs the report under `lighting` (batch 1, exponents matching 4 specular lobes).
pub fn run(settings: &SamplingSettings, lighting: &Lighting, device: &Device) -> Vec<SamplingRow> {
    let mut rows = Vec::new();
    let lobes = lighting.maps.len();
    for seed in 0..settings.random_fields {
        device.seed(seed as u64);
        let net = NeiifConfig::new()
            .with_w_dim(64)
            .with_width(64)
            .with_head_width(64)
            .with_specular_lobes(lobes)
            .init(device);
        let w = Tensor::<2>::random([1, 64], Distribution::Normal(0.0, 1.0), device);
        let field = LatentField { field: &net, w };
        let name = format!("random NeIIF {seed} (width 64)");
        measure_scene(&name, &field, lighting, settings, device, &mut rows);
    }
    for (name, softness, peak) in [
        ("soft sphere (softness 0.01, peak 60)", 0.01, 60.0),
        ("hard sphere (softness 0.001, peak 1e4)", 0.001, 1e4),
    ] {
        let sphere = SoftSphere {
            radius: 0.3,
            softness,
            peak,
            albedo: [0.8, 0.5, 0.3],
            specular_weights: (0..lobes).map(|i| 0.2 / (i + 1) as f32).collect(),
        };
        measure_scene(name, &sphere, lighting, settings, device, &mut rows);
    }
    rows
}

/// The report as a Markdown table.
pub fn to_markdown(rows: &[SamplingRow]) -> String {
    let mut s = String::from(
        "| scene | stratified | proposal + refine | importance | rule | ms | A rel RMS | N rel RMS | D rel RMS | S rel RMS |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let proposal = if r.proposal > 0 {
            format!("{} + {}", r.proposal, r.refine)
        } else {
            "-".to_string()
        };
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {:.0} | {:.2e} | {:.2e} | {:.2e} | {:.2e} |\n",
            r.scene,
            r.stratified,
            proposal,
            r.importance,
            if r.midpoint { "midpoint" } else { "left" },
            r.ms,
            r.error[0],
            r.error[1],
            r.error[2],
            r.error[3]
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light_lookup::LightMapBatch;
    use volux_envmap::LightMap;

    #[test]
    fn error_falls_with_more_samples_on_a_sphere() {
        let device = Device::flex();
        let maps: Vec<LightMap> = [1u32, 16]
            .iter()
            .map(|&n| {
                let texels = (0..32 * 16)
                    .map(|i| [1.0 + (i % 32) as f32 / 32.0, 1.0, 0.5])
                    .collect();
                LightMap::new(n, 32, 16, texels)
            })
            .collect();
        let lighting = Lighting::new(
            maps.iter()
                .map(|m| LightMapBatch::new(&[m], &device).unwrap())
                .collect(),
            None,
        )
        .unwrap();
        let settings = SamplingSettings {
            side: 8,
            counts: vec![4, 32],
            reference: 256,
            random_fields: 1,
            chunk: 64,
            layouts: vec!["0:16:8:4".parse().unwrap()],
        };
        let rows = run(&settings, &lighting, &device);
        assert_eq!(rows.len(), 3 * 7);
        for scene in rows.chunks(7) {
            // [4, 4+4 left, 4+4 mid, 32, ...]: 32 stratified beats 4 on every map that 4 gets
            // wrong (a hard sphere's constant albedo is exact, to rounding, with any count).
            for k in (0..4).filter(|&k| scene[0].error[k] > 1e-5) {
                assert!(
                    scene[3].error[k] < scene[0].error[k],
                    "{}: map {k}: {:?} vs {:?}",
                    scene[0].scene,
                    scene[3].error,
                    scene[0].error
                );
            }
        }
        // On the hard sphere, 4 full samples placed by density-only passes get the normals
        // and the diffuse shading better than 4 + 4 full samples do.
        let hard = &rows[14..21];
        assert_eq!((hard[6].proposal, hard[6].importance), (16, 4));
        for k in [1, 2] {
            assert!(
                hard[6].error[k] < hard[2].error[k],
                "{:?} vs {:?}",
                hard[6],
                hard[2]
            );
        }
        assert!(to_markdown(&rows).lines().count() == 2 + rows.len());
    }

    #[test]
    fn layouts_parse_and_bad_ones_are_named() {
        let l: ProposalLayout = "4:32:16:8".parse().unwrap();
        assert_eq!(
            (l.stratified, l.proposal, l.refine, l.importance),
            (4, 32, 16, 8)
        );
        for (bad, says) in [
            ("32:16:8", "four counts"),
            ("0:x:0:8", "\"0:x:0:8\""),
            ("0:0:0:8", "proposal count"),
            ("0:32:0:0", "stratified and importance are both 0"),
            ("4:32:0:0", "importance = 0"),
            ("0:32:0:5000", "at most 1024"),
        ] {
            let e = bad.parse::<ProposalLayout>().unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
