//! Directions and equirectangular texture coordinates (`docs/conventions.md`, "Directions and environment maps").
//!
//! `u` in `[0, 1)` runs with azimuth `phi = 2 pi u - pi` (so `u = 0.5` faces +z), `v` in
//! `[0, 1]` with polar angle `theta = pi v` from +y (so `v = 0` is straight up).

use std::f64::consts::PI;

/// A unit direction in world space (+y up, the face looks along +z).
pub type Dir = [f64; 3];

/// Direction of texture coordinates `(u, v)`.
pub fn uv_to_dir(u: f64, v: f64) -> Dir {
    let theta = PI * v;
    let phi = 2.0 * PI * u - PI;
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    [st * sp, ct, st * cp]
}

/// Texture coordinates `(u, v)` of a direction (need not be normalised, must be non-zero).
/// `u` is in `[0, 1)`; at the poles, where the azimuth is undefined, `u = 0.5`.
pub fn dir_to_uv(d: Dir) -> (f64, f64) {
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let y = (d[1] / len).clamp(-1.0, 1.0);
    let v = y.acos() / PI;
    let phi = d[0].atan2(d[2]);
    let mut u = (phi + PI) / (2.0 * PI);
    if u >= 1.0 {
        u -= 1.0;
    }
    (u, v)
}

/// Direction of the centre of texel `(x, y)` in a `width x height` map.
pub fn texel_dir(x: usize, y: usize, width: usize, height: usize) -> Dir {
    uv_to_dir(
        (x as f64 + 0.5) / width as f64,
        (y as f64 + 0.5) / height as f64,
    )
}

/// Exact solid angle of any texel in row `y` of a map with `width x height` texels:
/// `(2 pi / width) (cos theta_top - cos theta_bottom)`. The row sums to `4 pi` over the map.
pub fn row_solid_angle(y: usize, width: usize, height: usize) -> f64 {
    let t0 = PI * y as f64 / height as f64;
    let t1 = PI * (y + 1) as f64 / height as f64;
    2.0 * PI / width as f64 * (t0.cos() - t1.cos())
}

/// Rotation about +y by `angle` radians (right-handed: +z turns towards +x), which adds
/// `angle` to the azimuth and `angle / (2 pi)` to `u`.
pub fn rotate_yaw(d: Dir, angle: f64) -> Dir {
    let (s, c) = angle.sin_cos();
    [c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]]
}

/// Mirror reflection of the incoming ray direction `d` about the unit normal `n`:
/// `r = d - 2 (d.n) n`, the direction the specular light maps are indexed by.
pub fn reflect(d: Dir, n: Dir) -> Dir {
    let dn = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
    [
        d[0] - 2.0 * dn * n[0],
        d[1] - 2.0 * dn * n[1],
        d[2] - 2.0 * dn * n[2],
    ]
}

/// `d / |d|` (`d` must not be zero).
pub fn normalize(d: Dir) -> Dir {
    let len = dot(d, d).sqrt();
    d.map(|c| c / len)
}

/// Dot product.
pub fn dot(a: Dir, b: Dir) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalize_gives_unit_length_and_keeps_the_direction() {
        let n = normalize([3.0, -4.0, 12.0]);
        assert!((dot(n, n) - 1.0).abs() < 1e-15);
        assert!((n[0] - 3.0 / 13.0).abs() < 1e-15 && (n[2] - 12.0 / 13.0).abs() < 1e-15);
    }

    fn close(a: Dir, b: Dir, tol: f64) -> bool {
        (0..3).all(|i| (a[i] - b[i]).abs() <= tol)
    }

    #[test]
    fn axes_follow_design_conventions() {
        assert!(
            close(uv_to_dir(0.5, 0.5), [0.0, 0.0, 1.0], 1e-15),
            "centre faces +z"
        );
        assert!(
            close(uv_to_dir(0.75, 0.5), [1.0, 0.0, 0.0], 1e-15),
            "u = 3/4 is +x"
        );
        assert!(
            close(uv_to_dir(0.0, 0.5), [0.0, 0.0, -1.0], 1e-15),
            "seam is -z"
        );
        assert!(
            close(uv_to_dir(0.3, 0.0), [0.0, 1.0, 0.0], 1e-15),
            "v = 0 is up"
        );
        assert!(
            close(uv_to_dir(0.3, 1.0), [0.0, -1.0, 0.0], 1e-15),
            "v = 1 is down"
        );
    }

    #[test]
    fn round_trip_everywhere_including_seam_and_poles() {
        for j in 0..=64 {
            for i in 0..128 {
                let (u, v) = (i as f64 / 128.0, j as f64 / 64.0);
                let d = uv_to_dir(u, v);
                let (u2, v2) = dir_to_uv(d);
                assert!((v - v2).abs() < 1e-12, "v {v} -> {v2}");
                if j != 0 && j != 64 {
                    let du = (u - u2).abs();
                    assert!(du.min(1.0 - du) < 1e-12, "u {u} -> {u2} at v {v}");
                }
                assert!(close(uv_to_dir(u2, v2), d, 1e-12));
            }
        }
        // Just either side of the seam (-z) lands on either end of [0, 1).
        let (u_left, _) = dir_to_uv([-1e-9, 0.0, -1.0]);
        let (u_right, _) = dir_to_uv([1e-9, 0.0, -1.0]);
        assert!(u_left < 1e-9 && u_right > 1.0 - 1e-9 && u_right < 1.0);
        // Exactly on the seam and at the poles, u stays in [0, 1).
        assert!((0.0..1.0).contains(&dir_to_uv([0.0, 0.0, -1.0]).0));
        assert_eq!(dir_to_uv([0.0, 2.0, 0.0]), (0.5, 0.0));
        assert_eq!(dir_to_uv([0.0, -1.0, 0.0]), (0.5, 1.0));
    }

    #[test]
    fn solid_angles_sum_to_the_sphere() {
        for (w, h) in [(8, 4), (64, 32), (1024, 512)] {
            let total: f64 = (0..h).map(|y| w as f64 * row_solid_angle(y, w, h)).sum();
            assert!((total - 4.0 * PI).abs() < 1e-12, "{w}x{h}: {total}");
        }
    }

    #[test]
    fn yaw_rotation_shifts_u() {
        let d = uv_to_dir(0.2, 0.3);
        let r = rotate_yaw(d, 0.25 * 2.0 * PI);
        let (u, v) = dir_to_uv(r);
        assert!((u - 0.45).abs() < 1e-12 && (v - 0.3).abs() < 1e-12);
        assert!(close(
            rotate_yaw([0.0, 0.0, 1.0], PI / 2.0),
            [1.0, 0.0, 0.0],
            1e-15
        ));
    }

    #[test]
    fn reflection_about_normal() {
        let r = reflect([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]);
        assert!(close(r, [0.0, 0.0, 1.0], 1e-15));
        let s = 0.5f64.sqrt();
        let r = reflect([0.0, -s, -s], [0.0, 0.0, 1.0]);
        assert!(close(r, [0.0, -s, s], 1e-15));
    }
}
