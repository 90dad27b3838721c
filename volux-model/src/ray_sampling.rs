//! Camera rays and stratified samples along them (docs/conventions.md, "World and camera"; EG3D's set-up).
//!
//! A pinhole camera on a sphere of radius 2.7 looks at the origin with a vertical field of view
//! of 18.84 degrees; rays run from `t = 2.25` to `t = 3.3`. A [`Pose`]: yaw 0, pitch 0
//! sits at +z looking along -z (at the face), with +x to the right of the image and +y up;
//! positive yaw turns the camera about +y (right-handed, towards +x), positive pitch raises it
//! (it looks down). Pixel `(x, y)` counts from the top-left corner; rays go through pixel
//! centres. This file knows nothing of networks.

use burn::config::Config;
use burn::tensor::{Device, Distribution, Tensor, TensorData};
use volux_envmap::direction::normalize;

use crate::pose::Pose;

/// Camera intrinsics and ray bounds.
#[derive(Config, Debug, PartialEq)]
pub struct CameraConfig {
    /// Distance of the camera from the origin.
    #[config(default = 2.7)]
    pub radius: f64,
    /// Vertical field of view, degrees.
    #[config(default = 18.84)]
    pub fov_degrees: f64,
    /// Ray start.
    #[config(default = 2.25)]
    pub near: f64,
    /// Ray end.
    #[config(default = 3.3)]
    pub far: f64,
}

/// Camera position for a pose.
pub fn camera_position(config: &CameraConfig, pose: Pose) -> [f64; 3] {
    let (r, Pose { yaw, pitch }) = (config.radius, pose);
    [
        r * yaw.sin() * pitch.cos(),
        r * pitch.sin(),
        r * yaw.cos() * pitch.cos(),
    ]
}

/// The camera's axes in world space for a pose: `[right, up, back]` (image +x, image +y, and
/// the direction from the head towards the camera). Camera-space coordinates of a world
/// vector are its dot products with these, so a normal facing the camera is camera-space +z.
pub fn camera_basis(config: &CameraConfig, pose: Pose) -> [[f64; 3]; 3] {
    let back = normalize(camera_position(config, pose));
    let forward = back.map(|c| -c);
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let right = normalize(cross(forward, [0.0, 1.0, 0.0]));
    let up = cross(right, forward);
    [right, up, back]
}

/// Rays of a `width x height` image at `pose`: origins and unit directions,
/// `[height * width, 3]` each, row-major from the top-left pixel. Built in f64 on the host.
pub fn camera_rays(
    config: &CameraConfig,
    pose: Pose,
    width: usize,
    height: usize,
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let o = camera_position(config, pose);
    let [right, up, back] = camera_basis(config, pose);
    let forward = back.map(|c| -c);
    let tan = (config.fov_degrees.to_radians() / 2.0).tan();
    let aspect = width as f64 / height as f64;
    let mut dirs = Vec::with_capacity(width * height);
    for y in 0..height {
        for x in 0..width {
            let sx = (2.0 * (x as f64 + 0.5) / width as f64 - 1.0) * tan * aspect;
            let sy = (1.0 - 2.0 * (y as f64 + 0.5) / height as f64) * tan;
            dirs.push(normalize(std::array::from_fn(|k| {
                forward[k] + sx * right[k] + sy * up[k]
            })));
        }
    }
    (vec![o; width * height], dirs)
}

/// Rays of one `width x height` image per pose, on `device`: origins and unit directions,
/// `[poses, height * width, 3]` each (see [`camera_rays`]).
pub fn camera_ray_batch(
    config: &CameraConfig,
    poses: &[Pose],
    width: usize,
    height: usize,
    device: &Device,
) -> (Tensor<3>, Tensor<3>) {
    let r = width * height;
    let mut origins = Vec::with_capacity(poses.len() * r * 3);
    let mut dirs = Vec::with_capacity(poses.len() * r * 3);
    for &pose in poses {
        let (o, d) = camera_rays(config, pose, width, height);
        origins.extend(o.iter().flatten().map(|v| *v as f32));
        dirs.extend(d.iter().flatten().map(|v| *v as f32));
    }
    let shape = [poses.len(), r, 3];
    (
        Tensor::from_data(TensorData::new(origins, shape), device),
        Tensor::from_data(TensorData::new(dirs, shape), device),
    )
}

/// Stratified sample depths `[rays, samples]` between `near` and `far`, one per equal bin,
/// jittered uniformly inside it (`jitter = false`: bin centres), and the segment lengths
/// `delta` that compositing needs (each sample's distance to the next, the last to `far`).
pub fn stratified_samples(
    config: &CameraConfig,
    rays: usize,
    samples: usize,
    jitter: bool,
    device: &Device,
) -> (Tensor<2>, Tensor<2>) {
    assert!(samples >= 1, "at least one sample per ray");
    let bin = ((config.far - config.near) / samples as f64) as f32;
    let starts: Vec<f32> = (0..samples)
        .map(|i| (config.near + i as f64 * (config.far - config.near) / samples as f64) as f32)
        .collect();
    let starts = Tensor::<1>::from_data(TensorData::new(starts, [samples]), device)
        .reshape([1, samples])
        .expand([rays, samples]);
    let offset = if jitter {
        Tensor::<2>::random([rays, samples], Distribution::Uniform(0.0, 1.0), device)
    } else {
        Tensor::<2>::full([rays, samples], 0.5, device)
    };
    let t = starts + offset.mul_scalar(bin);
    let delta = segment_lengths(t.clone(), config.far);
    (t, delta)
}

/// Segment lengths of sorted depths `[rays, samples]`: each sample's distance to the next, the
/// last one's to `far`.
pub fn segment_lengths(t: Tensor<2>, far: f64) -> Tensor<2> {
    let [rays, samples] = t.dims();
    let end = Tensor::<2>::full([rays, 1], far as f32, &t.device());
    let next = if samples > 1 {
        Tensor::cat(vec![t.clone().narrow(1, 1, samples - 1), end], 1)
    } else {
        end
    };
    next - t
}

/// Share of the importance distribution spread uniformly over the ray, so that every bin keeps
/// a non-zero probability (empty rays, and surfaces the coarse pass missed).
pub const IMPORTANCE_UNIFORM_MIX: f64 = 1e-2;

/// Importance samples `[rays, count]` (NeRF's hierarchical sampling): coarse depths `t`
/// (`[rays, samples]`, sorted) and their compositing weights define a piecewise-constant
/// density over bins bounded by the midpoints between samples (and `near`, `far`); `count`
/// depths are drawn from it by inverse transform of stratified uniforms (`jitter = false`:
/// bin centres of the uniforms). The result is sorted and carries no gradient.
pub fn importance_samples(
    config: &CameraConfig,
    t: Tensor<2>,
    weights: Tensor<2>,
    count: usize,
    jitter: bool,
) -> Tensor<2> {
    let [rays, samples] = t.dims();
    let device = t.device();
    let t = t.detach();
    // Bin edges [rays, samples + 1].
    let (near, far) = ends(config, rays, &device);
    let edges = if samples > 1 {
        let mid =
            (t.clone().narrow(1, 0, samples - 1) + t.narrow(1, 1, samples - 1)).mul_scalar(0.5);
        Tensor::cat(vec![near, mid, far], 1)
    } else {
        Tensor::cat(vec![near, far], 1)
    };
    draw_from_bins(config, edges, weights, count, jitter)
}

/// Importance samples `[rays, count]` from bins that are the segments between sorted depths
/// `t` (`[rays, samples]`): the bins run `near..t_0, t_0..t_1, ..., t_last..far` and
/// `weights` (`[rays, samples + 1]`) are theirs. A surface crossed between two samples puts
/// its weight on the segment that holds it, so the draws bracket the surface; the midpoint
/// bins of [`importance_samples`] can miss it by half a bin. Sorted, no gradient.
pub fn segment_importance_samples(
    config: &CameraConfig,
    t: Tensor<2>,
    weights: Tensor<2>,
    count: usize,
    jitter: bool,
) -> Tensor<2> {
    draw_from_bins(
        config,
        segment_edges(config, t.detach()),
        weights,
        count,
        jitter,
    )
}

/// `near` and `far` as `[rays, 1]` columns.
fn ends(config: &CameraConfig, rays: usize, device: &Device) -> (Tensor<2>, Tensor<2>) {
    (
        Tensor::full([rays, 1], config.near as f32, device),
        Tensor::full([rays, 1], config.far as f32, device),
    )
}

/// The edges `near, t_0, ..., t_last, far` (`[rays, samples + 2]`) of the segments between
/// sorted depths `t` (`[rays, samples]`).
pub fn segment_edges(config: &CameraConfig, t: Tensor<2>) -> Tensor<2> {
    let (near, far) = ends(config, t.dims()[0], &t.device());
    Tensor::cat(vec![near, t, far], 1)
}

/// `count` sorted depths drawn by inverse transform of stratified uniforms from the
/// piecewise-constant density on bins `edges` (`[rays, bins + 1]`, from `near` to `far`)
/// whose masses are `weights` (`[rays, bins]`, non-negative, any scale), mixed with
/// [`IMPORTANCE_UNIFORM_MIX`] of the uniform density.
fn draw_from_bins(
    config: &CameraConfig,
    edges: Tensor<2>,
    weights: Tensor<2>,
    count: usize,
    jitter: bool,
) -> Tensor<2> {
    let [rays, bins] = weights.dims();
    let device = edges.device();
    let weights = weights.detach();
    let widths = edges.clone().narrow(1, 1, bins) - edges.clone().narrow(1, 0, bins);
    // Probability of each bin: the weights, mixed with a little of the uniform density.
    let total = weights.clone().sum_dim(1).add_scalar(1e-12);
    let length = (config.far - config.near) as f32;
    let prob = (weights / total).mul_scalar(1.0 - IMPORTANCE_UNIFORM_MIX)
        + widths
            .clone()
            .div_scalar(length)
            .mul_scalar(IMPORTANCE_UNIFORM_MIX);
    let cdf = Tensor::cat(
        vec![Tensor::zeros([rays, 1], &device), prob.clone().cumsum(1)],
        1,
    );
    // Stratified uniforms in (0, 1), sorted.
    let starts: Vec<f32> = (0..count).map(|i| i as f32 / count as f32).collect();
    let starts = Tensor::<1>::from_floats(starts.as_slice(), &device)
        .reshape([1, count])
        .expand([rays, count]);
    let offset = if jitter {
        Tensor::<2>::random([rays, count], Distribution::Uniform(0.0, 1.0), &device)
    } else {
        Tensor::<2>::full([rays, count], 0.5, &device)
    };
    let last = cdf.clone().narrow(1, bins, 1); // ~1, up to rounding
    let u = (starts + offset.div_scalar(count as f32)) * last;
    // Bin index: how many inner cdf values lie at or below u.
    let index = if bins > 1 {
        let inner = cdf.clone().narrow(1, 1, bins - 1);
        inner
            .reshape([rays, 1, bins - 1])
            .expand([rays, count, bins - 1])
            .lower_equal(
                u.clone()
                    .reshape([rays, count, 1])
                    .expand([rays, count, bins - 1]),
            )
            .int()
            .sum_dim(2)
            .reshape([rays, count])
    } else {
        Tensor::zeros([rays, count], &device)
    };
    let cdf_lo = cdf.gather(1, index.clone());
    let prob_at = prob.gather(1, index.clone());
    let edge_lo = edges.gather(1, index.clone());
    let width_at = widths.gather(1, index);
    let frac = ((u - cdf_lo) / prob_at.add_scalar(1e-12)).clamp(0.0, 1.0);
    edge_lo + frac * width_at
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::to_f32_vec;

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        (0..3).all(|k| (a[k] - b[k]).abs() < 1e-12)
    }

    #[test]
    fn frontal_camera_looks_along_minus_z_with_x_right_and_y_up() {
        let cfg = CameraConfig::new();
        let (o, d) = camera_rays(&cfg, Pose::new(0.0, 0.0), 2, 2);
        assert!(close(o[0], [0.0, 0.0, 2.7]));
        // Top-left pixel looks left (-x) and up (+y).
        assert!(d[0][0] < 0.0 && d[0][1] > 0.0 && d[0][2] < 0.0);
        assert!(d[3][0] > 0.0 && d[3][1] < 0.0);
        // The vertical field of view: rays through the top and bottom edges span 18.84 deg.
        let (_, col) = camera_rays(&cfg, Pose::new(0.0, 0.0), 1, 1000);
        let top = col[0][1].atan2(-col[0][2]);
        let bottom = col[999][1].atan2(-col[999][2]);
        assert!(((top - bottom).to_degrees() - 18.84).abs() < 0.05);
    }

    #[test]
    fn yaw_and_pitch_move_the_camera_around_the_head() {
        let cfg = CameraConfig::new();
        let p = camera_position(&cfg, Pose::new(std::f64::consts::FRAC_PI_2, 0.0));
        assert!(close(
            p,
            [2.7, 0.0, 2.7 * std::f64::consts::FRAC_PI_2.cos()]
        ));
        let p = camera_position(&cfg, Pose::new(0.0, 0.3));
        assert!(p[1] > 0.0);
        // The centre ray always passes through the origin.
        for (yaw, pitch) in [(0.4, -0.2), (-1.0, 0.5)] {
            let (o, d) = camera_rays(&cfg, Pose::new(yaw, pitch), 3, 3);
            let t = 2.7;
            let hit: [f64; 3] = std::array::from_fn(|k| o[4][k] + t * d[4][k]);
            assert!(hit.iter().all(|c| c.abs() < 1e-12), "{hit:?}");
        }
    }

    /// Weights of shape `[rays, bins]`, zero but for `value` at flat index `at`.
    fn one_weight(shape: [usize; 2], at: usize, value: f32, device: &Device) -> Tensor<2> {
        let mut w = vec![0.0f32; shape[0] * shape[1]];
        w[at] = value;
        Tensor::<1>::from_floats(w.as_slice(), device).reshape(shape)
    }

    #[test]
    fn importance_samples_follow_the_coarse_weights() {
        let device = Device::flex();
        let cfg = CameraConfig::new();
        let (t, _) = stratified_samples(&cfg, 2, 16, false, &device);
        // Ray 0: all weight in coarse sample 5; ray 1: no weight at all (an empty ray).
        let w = one_weight([2, 16], 5, 0.9, &device);
        let fine = importance_samples(&cfg, t.clone(), w, 64, false);
        assert_eq!(fine.dims(), [2, 64]);
        let fine = to_f32_vec(fine);
        let tv = to_f32_vec(t);
        let (lo, hi) = ((tv[4] + tv[5]) / 2.0, (tv[5] + tv[6]) / 2.0);
        let inside = fine[..64].iter().filter(|f| (lo..=hi).contains(*f)).count();
        // 99% of the probability sits in that bin: all but the uniform share's samples.
        assert!(inside >= 62, "{inside} of 64 in the heavy bin");
        for r in 0..2 {
            let row = &fine[r * 64..(r + 1) * 64];
            assert!(row.windows(2).all(|p| p[0] <= p[1]), "sorted");
            assert!(row.iter().all(|f| (2.25..=3.3).contains(f)));
        }
        // The empty ray gets uniform samples.
        let row = &fine[64..];
        for (i, f) in row.iter().enumerate() {
            let want = 2.25 + (i as f32 + 0.5) / 64.0 * 1.05;
            assert!((f - want).abs() < 1e-3, "{i}: {f} vs {want}");
        }
    }

    #[test]
    fn segment_importance_samples_fall_between_the_samples_that_bound_the_weight() {
        let device = Device::flex();
        let cfg = CameraConfig::new();
        let (t, _) = stratified_samples(&cfg, 1, 8, false, &device);
        // 9 segments: near..t0, t0..t1, ..., t7..far; all the weight on t2..t3.
        let w = one_weight([1, 9], 3, 0.7, &device);
        let fine = to_f32_vec(segment_importance_samples(&cfg, t.clone(), w, 32, false));
        let tv = to_f32_vec(t);
        let inside = fine.iter().filter(|f| (tv[2]..=tv[3]).contains(*f)).count();
        assert!(
            inside >= 31,
            "{inside} of 32 in the heavy segment: {fine:?}"
        );
        assert!(fine.windows(2).all(|p| p[0] <= p[1]), "sorted");
    }

    #[test]
    fn importance_samples_reproduce_a_smooth_distribution() {
        // Weights proportional to the bin widths of a linear ramp: the inverse transform of
        // stratified uniforms must land on the ramp's quantiles.
        let device = Device::flex();
        let cfg = CameraConfig::new();
        let (t, _) = stratified_samples(&cfg, 1, 200, false, &device);
        let w = t.clone().sub_scalar(2.25); // density ~ (t - near)
        let fine = to_f32_vec(importance_samples(&cfg, t, w, 10, false));
        for (i, f) in fine.iter().enumerate() {
            let q = (i as f64 + 0.5) / 10.0;
            // cdf(t) = ((t - near) / L)^2 for the pure ramp; the 1% uniform mix shifts it a bit.
            let want = 2.25 + 1.05 * q.sqrt();
            assert!((f64::from(*f) - want).abs() < 0.01, "{i}: {f} vs {want}");
        }
    }

    #[test]
    fn stratified_samples_cover_the_ray_in_order() {
        let device = Device::flex();
        let cfg = CameraConfig::new();
        let (t, delta) = stratified_samples(&cfg, 2, 1, false, &device);
        assert_eq!(t.dims(), [2, 1]);
        let d: Vec<f32> = to_f32_vec(delta);
        assert!(
            (d[0] - (3.3 - (2.25 + 3.3) / 2.0)).abs() < 1e-5,
            "one sample: {d:?}"
        );
        for jitter in [false, true] {
            let (t, delta) = stratified_samples(&cfg, 5, 12, jitter, &device);
            let t: Vec<f32> = to_f32_vec(t);
            let delta: Vec<f32> = to_f32_vec(delta);
            for r in 0..5 {
                let row = &t[r * 12..(r + 1) * 12];
                assert!(row.windows(2).all(|w| w[0] <= w[1]));
                assert!(row[0] >= 2.25 && row[11] <= 3.3);
                let sum: f32 = delta[r * 12..(r + 1) * 12].iter().sum();
                assert!((sum - (3.3 - row[0])).abs() < 1e-5);
                assert!(delta[r * 12..(r + 1) * 12].iter().all(|d| *d >= 0.0));
            }
        }
    }
}
