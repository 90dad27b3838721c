//! Multi-view consistency (the property of the paper's Table 1, measured without a
//! face-recognition network): a frontal view's foreground pixels are lifted to 3D with its
//! rendered depth, projected into a side view with the dataset camera, and compared with
//! what the side view shows there.
//!
//! A pixel reprojects consistently when it lands inside the side image, on the side view's
//! foreground (coverage at least 0.5 at all four pixels the look-up blends, so that no colour
//! is mixed with the background), and the side view's depth there agrees with the point's
//! distance from the side camera to within a tolerance; otherwise it is occluded, off-screen or
//! the geometry disagrees. The photometric errors (mean L1 and PSNR on sRGB values, peak 1) are
//! taken over consistent pixels only, for the albedo (sRGB-encoded) and the relit image.

use volux_envmap::Rgb;
use volux_envmap::io::linear_to_srgb;
use volux_model::pose::Pose;
use volux_model::ray_sampling::{CameraConfig, camera_basis, camera_position, camera_rays};

use crate::image::{ErrorSums, bilinear, bilinear1, neighbourhood_min};
use crate::views::Rendered;

/// Depth agreement in world units (the head spans about 1): about one volume pixel at the
/// head's distance for the small model's 32x32 volume.
pub const DEFAULT_TOLERANCE: f64 = 0.03;

/// Pixel coordinates `(x, y)` (integer values are pixel centres) of world point `p` in a
/// `side x side` image at `pose`, and its distance from the camera; `None` behind it.
pub fn project(
    camera: &CameraConfig,
    pose: Pose,
    side: usize,
    p: [f64; 3],
) -> Option<(f64, f64, f64)> {
    let o = camera_position(camera, pose);
    let [right, up, back] = camera_basis(camera, pose);
    let v: [f64; 3] = std::array::from_fn(|k| p[k] - o[k]);
    let dot = |a: [f64; 3]| a[0] * v[0] + a[1] * v[1] + a[2] * v[2];
    let (xc, yc, zc) = (dot(right), dot(up), -dot(back));
    if zc <= 1e-9 {
        return None;
    }
    let tan = (camera.fov_degrees.to_radians() / 2.0).tan();
    let s = side as f64;
    let x = ((xc / zc) / tan + 1.0) * s / 2.0 - 0.5;
    let y = (1.0 - (yc / zc) / tan) * s / 2.0 - 0.5;
    Some((x, y, dot(v).sqrt()))
}

/// The world point behind every pixel of a `side x side` depth map at `pose`.
pub fn unproject(camera: &CameraConfig, pose: Pose, side: usize, depth: &[f32]) -> Vec<[f64; 3]> {
    let (origins, dirs) = camera_rays(camera, pose, side, side);
    origins
        .iter()
        .zip(&dirs)
        .zip(depth)
        .map(|((o, d), &t)| std::array::from_fn(|k| o[k] + f64::from(t) * d[k]))
        .collect()
}

/// Coverage above which a pixel counts as foreground.
pub const FOREGROUND: f32 = 0.5;

/// One frontal-side pair's counts and error sums.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Reprojection {
    /// Frontal foreground pixels.
    pub foreground: usize,
    /// Of those, the ones that reproject consistently.
    pub consistent: usize,
    pub albedo: ErrorSums,
    pub relit: ErrorSums,
    /// Per frontal pixel: the albedo's mean absolute error where consistent, `None` elsewhere
    /// (for figures).
    pub error_map: Vec<Option<f32>>,
}

impl Reprojection {
    /// Consistent pixels over frontal foreground pixels (1 when there is no foreground).
    pub fn consistent_fraction(&self) -> f64 {
        if self.foreground == 0 {
            1.0
        } else {
            self.consistent as f64 / self.foreground as f64
        }
    }

    /// Adds another pair's counts and sums (not its error map).
    pub fn merge(&mut self, other: &Reprojection) {
        self.foreground += other.foreground;
        self.consistent += other.consistent;
        self.albedo.merge(&other.albedo);
        self.relit.merge(&other.relit);
    }
}

fn srgb(c: Rgb) -> Rgb {
    c.map(linear_to_srgb)
}

/// Warps `side_view` into `front` with `front`'s depth and compares (see the module notes).
pub fn reproject(
    front: &Rendered,
    side_view: &Rendered,
    camera: &CameraConfig,
    tolerance: f64,
) -> Reprojection {
    assert_eq!(front.side, side_view.side, "views of one size");
    let s = front.side;
    let points = unproject(camera, front.pose, s, &front.depth);
    let mut out = Reprojection {
        error_map: vec![None; s * s],
        ..Reprojection::default()
    };
    for (i, p) in points.iter().enumerate() {
        if front.mask[i] < FOREGROUND {
            continue;
        }
        out.foreground += 1;
        let Some((x, y, distance)) = project(camera, side_view.pose, s, *p) else {
            continue;
        };
        let (Some(m), Some(t)) = (
            neighbourhood_min(&side_view.mask, s, x, y),
            bilinear1(&side_view.depth, s, x, y),
        ) else {
            continue;
        };
        if m < FOREGROUND || (f64::from(t) - distance).abs() > tolerance {
            continue;
        }
        let (Some(a), Some(r)) = (
            bilinear(&side_view.albedo, s, x, y),
            bilinear(&side_view.relit, s, x, y),
        ) else {
            continue;
        };
        out.consistent += 1;
        let (fa, sa) = (srgb(front.albedo[i]), srgb(a));
        let mut one = ErrorSums::default();
        one.add(fa, sa);
        out.error_map[i] = Some(one.l1() as f32);
        out.albedo.merge(&one);
        out.relit.add(front.relit[i], r);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn projecting_a_pixel_ray_gives_the_pixel_back() {
        let camera = CameraConfig::new();
        for pose in [
            Pose::new(0.0, 0.0),
            Pose::new(0.4, -0.2),
            Pose::new(-0.5, 0.15),
        ] {
            let side = 16;
            let depth: Vec<f32> = (0..side * side).map(|i| 2.3 + 0.003 * i as f32).collect();
            let points = unproject(&camera, pose, side, &depth);
            for (i, p) in points.iter().enumerate() {
                let (x, y, t) = project(&camera, pose, side, *p).unwrap();
                assert!((x - (i % side) as f64).abs() < 1e-9, "{x} at {i}");
                assert!((y - (i / side) as f64).abs() < 1e-9, "{y} at {i}");
                assert!((t - f64::from(depth[i])).abs() < 1e-5, "{t} at {i}");
            }
        }
        // Behind the camera: no projection.
        assert_eq!(
            project(&camera, Pose::new(0.0, 0.0), 8, [0.0, 0.0, 5.0]),
            None
        );
    }
}
