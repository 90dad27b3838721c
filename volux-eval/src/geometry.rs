//! Geometry check: do the accumulated normals `N` agree with the shape the depth map
//! describes? The normal of the rendered depth is the cross product of the central differences
//! of the surface points behind neighbouring pixels (turned to face the camera); the angle
//! between it and `N` is measured at interior pixels (the pixel and its four neighbours in the
//! foreground), at the volume's resolution where both are rendered.

use serde::Serialize;
use volux_model::pose::Pose;
use volux_model::ray_sampling::{CameraConfig, camera_basis};

use crate::image::{mean, median};
use crate::reprojection::{FOREGROUND, unproject};
use crate::views::Rendered;

/// Camera-space unit normals of a depth map's surface at interior pixels (`None` elsewhere).
pub fn depth_normals(
    camera: &CameraConfig,
    pose: Pose,
    side: usize,
    depth: &[f32],
    mask: &[f32],
) -> Vec<Option<[f64; 3]>> {
    let points = unproject(camera, pose, side, depth);
    let [right, up, back] = camera_basis(camera, pose);
    let inside = |x: usize, y: usize| mask[y * side + x] >= FOREGROUND;
    (0..side * side)
        .map(|i| {
            let (x, y) = (i % side, i / side);
            if x == 0 || y == 0 || x + 1 == side || y + 1 == side {
                return None;
            }
            let around = [(x, y), (x - 1, y), (x + 1, y), (x, y - 1), (x, y + 1)];
            if !around.iter().all(|&(x, y)| inside(x, y)) {
                return None;
            }
            let p = |x: usize, y: usize| points[y * side + x];
            let (l, r, t, b) = (p(x - 1, y), p(x + 1, y), p(x, y - 1), p(x, y + 1));
            let dx: [f64; 3] = std::array::from_fn(|k| r[k] - l[k]);
            let dy: [f64; 3] = std::array::from_fn(|k| b[k] - t[k]);
            let n = [
                dy[1] * dx[2] - dy[2] * dx[1],
                dy[2] * dx[0] - dy[0] * dx[2],
                dy[0] * dx[1] - dy[1] * dx[0],
            ];
            let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
            let len = dot(n, n).sqrt();
            if len < 1e-12 {
                return None;
            }
            let camera_space = [dot(n, right), dot(n, up), dot(n, back)].map(|v| v / len);
            // Face the camera (+z in camera space).
            Some(if camera_space[2] < 0.0 {
                camera_space.map(|v| -v)
            } else {
                camera_space
            })
        })
        .collect()
}

/// Angles in degrees between `normals` and the depth map's normals, at interior pixels where
/// the accumulated normal is not degenerate.
pub fn normal_angles(
    camera: &CameraConfig,
    pose: Pose,
    side: usize,
    normals: &[[f32; 3]],
    depth: &[f32],
    mask: &[f32],
) -> Vec<f64> {
    depth_normals(camera, pose, side, depth, mask)
        .iter()
        .zip(normals)
        .filter_map(|(d, n)| {
            let d = (*d)?;
            let n = n.map(f64::from);
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            (len > 1e-3).then(|| {
                let c = (d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) / len;
                c.clamp(-1.0, 1.0).acos().to_degrees()
            })
        })
        .collect()
}

/// [`normal_angles`] of a render's volume-resolution layers.
pub fn render_angles(camera: &CameraConfig, r: &Rendered) -> Vec<f64> {
    normal_angles(
        camera,
        r.pose,
        r.side_lo,
        &r.normals_lo,
        &r.depth_lo,
        &r.mask_lo,
    )
}

/// Summary of angular errors.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct GeometryScore {
    /// Interior pixels measured.
    pub pixels: usize,
    pub mean_degrees: f64,
    pub median_degrees: f64,
    /// Fraction of pixels within 10 degrees.
    pub within_10_degrees: f64,
}

impl GeometryScore {
    pub fn of(angles: &[f64]) -> GeometryScore {
        GeometryScore {
            pixels: angles.len(),
            mean_degrees: mean(angles),
            median_degrees: median(angles),
            within_10_degrees: if angles.is_empty() {
                0.0
            } else {
                angles.iter().filter(|&&a| a <= 10.0).count() as f64 / angles.len() as f64
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use volux_model::ray_sampling::camera_rays;

    /// Depth, normals and mask of a sphere of radius `r` at the origin, seen at `pose`.
    fn sphere(r: f64, pose: Pose, side: usize) -> (Vec<f32>, Vec<[f32; 3]>, Vec<f32>) {
        let camera = CameraConfig::new();
        let (origins, dirs) = camera_rays(&camera, pose, side, side);
        let [right, up, back] = camera_basis(&camera, pose);
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (mut depth, mut normals, mut mask) = (vec![], vec![], vec![]);
        for (o, d) in origins.iter().zip(&dirs) {
            let b = dot(*o, *d);
            let disc = b * b - (dot(*o, *o) - r * r);
            if disc > 0.0 {
                let t = -b - disc.sqrt();
                let p: [f64; 3] = std::array::from_fn(|k| o[k] + t * d[k]);
                let n = p.map(|v| v / r);
                depth.push(t as f32);
                normals.push([dot(n, right) as f32, dot(n, up) as f32, dot(n, back) as f32]);
                mask.push(1.0);
            } else {
                depth.push(camera.far as f32);
                normals.push([0.0; 3]);
                mask.push(0.0);
            }
        }
        (depth, normals, mask)
    }

    #[test]
    fn a_spheres_depth_gives_its_normals() {
        let camera = CameraConfig::new();
        for pose in [Pose::new(0.0, 0.0), Pose::new(0.3, 0.1)] {
            let (depth, normals, mask) = sphere(0.4, pose, 48);
            let angles = normal_angles(&camera, pose, 48, &normals, &depth, &mask);
            let score = GeometryScore::of(&angles);
            assert!(score.pixels > 500, "{score:?}");
            // Central differences of a sampled sphere: small errors, largest at the rim.
            assert!(score.median_degrees < 1.0, "{score:?}");
            assert!(score.within_10_degrees > 0.95, "{score:?}");
        }
    }

    #[test]
    fn normals_that_disagree_with_the_depth_are_caught() {
        let camera = CameraConfig::new();
        let (depth, _, mask) = sphere(0.4, Pose::new(0.0, 0.0), 48);
        // Every normal facing the camera: a flat shape's normals on a round depth.
        let flat = vec![[0.0f32, 0.0, 1.0]; depth.len()];
        let score = GeometryScore::of(&normal_angles(
            &camera,
            Pose::new(0.0, 0.0),
            48,
            &flat,
            &depth,
            &mask,
        ));
        assert!(score.mean_degrees > 20.0, "{score:?}");
    }
}
