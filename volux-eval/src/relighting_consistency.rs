//! Relighting consistency (the property of the paper's Table 2): one latent under several
//! environment maps. The albedo and normals must not change with the light; the relit image is
//! compared with the physically shaded `tonemap(A D + S)`, which shows how far the relighting
//! network strays from the Phong image it refines.

use serde::Serialize;

use crate::image::ErrorSums;
use crate::views::Rendered;

/// Changes of the intrinsic layers between lightings of one latent.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Invariance {
    /// Albedo differences from the first lighting (linear values).
    pub albedo: ErrorSums,
    /// Largest albedo channel difference.
    pub albedo_max: f64,
    /// Normal component differences from the first lighting.
    pub normals: ErrorSums,
}

impl Invariance {
    pub fn merge(&mut self, other: &Invariance) {
        self.albedo.merge(&other.albedo);
        self.albedo_max = self.albedo_max.max(other.albedo_max);
        self.normals.merge(&other.normals);
    }
}

/// Compares renders of one latent at one pose under different lightings with the first.
pub fn invariance(views: &[Rendered]) -> Invariance {
    let mut out = Invariance::default();
    let Some(first) = views.first() else {
        return out;
    };
    for v in &views[1..] {
        for (a, b) in v.albedo.iter().zip(&first.albedo) {
            out.albedo.add(*a, *b);
            for k in 0..3 {
                out.albedo_max = out.albedo_max.max(f64::from((a[k] - b[k]).abs()));
            }
        }
        for (a, b) in v.normals_lo.iter().zip(&first.normals_lo) {
            out.normals.add(*a, *b);
        }
    }
    out
}

/// The relit image against the physically shaded one, over every pixel.
pub fn relit_against_shaded(view: &Rendered) -> ErrorSums {
    let mut e = ErrorSums::default();
    for (a, b) in view.relit.iter().zip(&view.shaded) {
        e.add(*a, *b);
    }
    e
}

/// One environment's row: relit against shaded.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ShadingScore {
    pub psnr: f64,
    pub l1: f64,
}

impl ShadingScore {
    pub fn of(e: &ErrorSums) -> ShadingScore {
        ShadingScore {
            psnr: e.psnr(),
            l1: e.l1(),
        }
    }
}

#[cfg(test)]
mod tests {
    use volux_model::pose::Pose;

    use super::*;

    fn view(albedo: f32, normal: f32, relit: f32, shaded: f32) -> Rendered {
        Rendered {
            pose: Pose::new(0.0, 0.0),
            side: 2,
            albedo: vec![[albedo; 3]; 4],
            relit: vec![[relit; 3]; 4],
            shaded: vec![[shaded; 3]; 4],
            depth: vec![2.5; 4],
            mask: vec![1.0; 4],
            side_lo: 1,
            normals_lo: vec![[0.0, 0.0, normal]],
            depth_lo: vec![2.5],
            mask_lo: vec![1.0],
        }
    }

    #[test]
    fn unchanged_layers_score_zero_and_changes_are_measured() {
        let same = invariance(&[view(0.5, 1.0, 0.2, 0.2), view(0.5, 1.0, 0.9, 0.9)]);
        assert_eq!(
            (same.albedo.l1(), same.albedo_max, same.normals.l1()),
            (0.0, 0.0, 0.0)
        );
        let moved = invariance(&[view(0.5, 1.0, 0.2, 0.2), view(0.6, 0.7, 0.2, 0.2)]);
        assert!((moved.albedo.l1() - 0.1).abs() < 1e-6);
        assert!((moved.albedo_max - 0.1).abs() < 1e-6);
        assert!((moved.normals.l1() - 0.1).abs() < 1e-6);
        let s = ShadingScore::of(&relit_against_shaded(&view(0.5, 1.0, 0.3, 0.2)));
        assert!(
            (s.psnr - 20.0).abs() < 1e-3 && (s.l1 - 0.1).abs() < 1e-6,
            "{s:?}"
        );
    }
}
