//! The evaluation's results: one serialisable report (written as JSON) and its terminal table.

use std::fmt::Write as _;

use serde::Serialize;

use crate::geometry::GeometryScore;
use crate::relighting_consistency::ShadingScore;
use crate::reprojection::Reprojection;
use crate::swd::Swd;

/// A measurement of the generator and, where the truth is known, of the dataset itself.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Pair<T> {
    pub model: T,
    pub data: Option<T>,
}

impl<T> Pair<T> {
    /// `("model", model)`, then `("data", data)` when there is one.
    pub fn rows(&self) -> impl Iterator<Item = (&'static str, &T)> {
        std::iter::once(("model", &self.model)).chain(self.data.iter().map(|d| ("data", d)))
    }
}

/// Photometric agreement of a side view warped into the frontal view.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ViewScore {
    /// PSNR (peak 1) and mean L1 of the sRGB-encoded albedo over consistent pixels.
    pub albedo_psnr: f64,
    pub albedo_l1: f64,
    /// The same for the relit image.
    pub relit_psnr: f64,
    pub relit_l1: f64,
    /// Fraction of frontal foreground pixels that reproject consistently.
    pub consistent: f64,
}

impl ViewScore {
    pub fn of(r: &Reprojection) -> ViewScore {
        ViewScore {
            albedo_psnr: r.albedo.psnr(),
            albedo_l1: r.albedo.l1(),
            relit_psnr: r.relit.psnr(),
            relit_l1: r.relit.l1(),
            consistent: r.consistent_fraction(),
        }
    }
}

/// One side-view yaw (radians) of the multi-view table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MultiViewRow {
    pub yaw: f64,
    #[serde(flatten)]
    pub scores: Pair<ViewScore>,
}

/// How much the intrinsic layers move when only the light changes.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct InvarianceScore {
    /// Mean and largest absolute albedo difference (linear).
    pub albedo_l1: f64,
    pub albedo_max: f64,
    /// Mean absolute difference of normal components.
    pub normals_l1: f64,
}

/// One environment's relit-against-shaded comparison.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ShadingRow {
    pub environment: String,
    #[serde(flatten)]
    pub scores: Pair<ShadingScore>,
}

/// Sliced Wasserstein distance of one layer: generated against the dataset, and the dataset
/// against another draw of itself (the floor a perfect generator reaches).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SwdRow {
    pub layer: String,
    pub model: Swd,
    pub data: Swd,
    /// The data brought down to the volume's resolution and back up, against the data: what a
    /// perfect volume scores when nothing adds detail above its rays (layers compared above
    /// the volume's resolution only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_through_volume: Option<Swd>,
}

/// Everything `volux eval` measured.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EvalReport {
    pub checkpoint: String,
    /// Training images the checkpoint had seen.
    pub images: u64,
    pub samples: usize,
    pub first_seed: u64,
    /// Depth agreement of the multi-view test, world units.
    pub tolerance: f64,
    pub environments: Vec<String>,
    pub multiview: Vec<MultiViewRow>,
    pub invariance: Pair<InvarianceScore>,
    pub shading: Vec<ShadingRow>,
    pub geometry: Pair<GeometryScore>,
    pub swd: Vec<SwdRow>,
    pub seconds: f64,
}

fn percent(v: f64) -> String {
    format!("{:.1}%", 100.0 * v)
}

impl EvalReport {
    /// The report as aligned plain-text tables.
    pub fn to_table(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "Multi-view consistency: {} samples, side views warped into the frontal view (depth tolerance {})",
            self.samples, self.tolerance
        );
        let _ = writeln!(
            s,
            "  {:>6}  {:<6} {:>12} {:>10} {:>11} {:>9} {:>11}",
            "yaw", "", "albedo PSNR", "albedo L1", "relit PSNR", "relit L1", "consistent"
        );
        for row in &self.multiview {
            for (source, v) in row.scores.rows() {
                let _ = writeln!(
                    s,
                    "  {:>6.2}  {:<6} {:>12.2} {:>10.4} {:>11.2} {:>9.4} {:>11}",
                    row.yaw,
                    source,
                    v.albedo_psnr,
                    v.albedo_l1,
                    v.relit_psnr,
                    v.relit_l1,
                    percent(v.consistent)
                );
            }
        }
        let _ = writeln!(
            s,
            "\nRelighting consistency: the same latents under {}",
            self.environments.join(", ")
        );
        let _ = writeln!(
            s,
            "  {:<6} {:>10} {:>11} {:>11}",
            "", "albedo L1", "albedo max", "normals L1"
        );
        for (source, v) in self.invariance.rows() {
            let _ = writeln!(
                s,
                "  {:<6} {:>10.2e} {:>11.2e} {:>11.2e}",
                source, v.albedo_l1, v.albedo_max, v.normals_l1
            );
        }
        let _ = writeln!(s, "  relit against tonemap(A D + S):");
        let _ = writeln!(
            s,
            "  {:<12} {:<6} {:>6} {:>8}",
            "environment", "", "PSNR", "L1"
        );
        for row in &self.shading {
            for (source, v) in row.scores.rows() {
                let _ = writeln!(
                    s,
                    "  {:<12} {:<6} {:>6.2} {:>8.4}",
                    row.environment, source, v.psnr, v.l1
                );
            }
        }
        let _ = writeln!(
            s,
            "\nGeometry: accumulated normals against the normals of the rendered depth"
        );
        let _ = writeln!(
            s,
            "  {:<6} {:>8} {:>10} {:>12} {:>8}",
            "", "pixels", "mean deg", "median deg", "<= 10"
        );
        for (source, v) in self.geometry.rows() {
            let _ = writeln!(
                s,
                "  {:<6} {:>8} {:>10.2} {:>12.2} {:>8}",
                source,
                v.pixels,
                v.mean_degrees,
                v.median_degrees,
                percent(v.within_10_degrees)
            );
        }
        let _ = writeln!(
            s,
            "\nSliced Wasserstein distance x1e3 (Laplacian levels, finest first; data = dataset against another draw of itself)"
        );
        for row in &self.swd {
            let levels = |w: &Swd| {
                w.sides
                    .iter()
                    .zip(&w.levels)
                    .map(|(side, v)| format!("{side}: {v:.1}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            let _ = writeln!(
                s,
                "  {:<8} model {:>7.1}  ({})",
                row.layer,
                row.model.mean,
                levels(&row.model)
            );
            let _ = writeln!(
                s,
                "  {:<8} data  {:>7.1}  ({})",
                "",
                row.data.mean,
                levels(&row.data)
            );
            if let Some(through) = &row.data_through_volume {
                let _ = writeln!(
                    s,
                    "  {:<8} data through the volume's resolution {:.1}  ({})",
                    "",
                    through.mean,
                    levels(through)
                );
            }
        }
        let _ = writeln!(s, "\n{:.1} s", self.seconds);
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pair_lists_the_data_row_only_when_there_is_one() {
        let both = Pair {
            model: 1,
            data: Some(2),
        };
        assert_eq!(
            both.rows().collect::<Vec<_>>(),
            vec![("model", &1), ("data", &2)]
        );
        let model = Pair {
            model: 1,
            data: None,
        };
        assert_eq!(model.rows().collect::<Vec<_>>(), vec![("model", &1)]);
    }
}
