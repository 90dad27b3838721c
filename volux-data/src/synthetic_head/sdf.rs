//! Signed-distance primitives and smooth blends (the usual sphere-tracing toolkit), generic over
//! [`Scalar`] so that the same code gives distances and exact gradients.
//!
//! The ellipsoid and the tapered capsule are bounds rather than exact distances, and the smooth
//! blends shrink distances near seams; sphere tracing therefore takes slightly shortened steps
//! (see `render`).

use super::scalar::Scalar;

/// A point or vector of scalars.
pub type V3<S> = [S; 3];

/// `p - c` for a constant point `c`.
pub fn offset<S: Scalar>(p: V3<S>, c: [f64; 3]) -> V3<S> {
    [p[0] - c[0], p[1] - c[1], p[2] - c[2]]
}

pub fn dot<S: Scalar>(a: V3<S>, b: V3<S>) -> S {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn length<S: Scalar>(a: V3<S>) -> S {
    dot(a, a).sqrt()
}

/// The smaller by value (its derivatives come with it).
pub fn min<S: Scalar>(a: S, b: S) -> S {
    if a.value() <= b.value() { a } else { b }
}

/// The larger by value.
pub fn max<S: Scalar>(a: S, b: S) -> S {
    if a.value() >= b.value() { a } else { b }
}

/// `x` clamped to `[0, 1]`.
pub fn clamp01<S: Scalar>(x: S) -> S {
    max(min(x, S::cst(1.0)), S::cst(0.0))
}

/// Polynomial smooth minimum with blend radius `k`: equals `min(a, b)` where they differ by
/// more than `k`, and is at most `k / 4` below it.
pub fn smin<S: Scalar>(a: S, b: S, k: f64) -> S {
    let h = clamp01((b - a) * (0.5 / k) + 0.5);
    b + (a - b) * h - h * (-h + 1.0) * k
}

/// Smooth maximum (smooth intersection); `smax(a, -b, k)` carves `b` out of `a`.
pub fn smax<S: Scalar>(a: S, b: S, k: f64) -> S {
    -smin(-a, -b, k)
}

/// Sphere of radius `r` at `c`.
pub fn sphere<S: Scalar>(p: V3<S>, c: [f64; 3], r: f64) -> S {
    length(offset(p, c)) - r
}

/// Axis-aligned ellipsoid with radii `r` at `c` (Quilez's bound: exact on the surface, a close
/// under-estimate elsewhere).
pub fn ellipsoid<S: Scalar>(p: V3<S>, c: [f64; 3], r: [f64; 3]) -> S {
    let q = offset(p, c);
    let k0 = length([
        q[0] * (1.0 / r[0]),
        q[1] * (1.0 / r[1]),
        q[2] * (1.0 / r[2]),
    ]);
    let k1 = length([
        q[0] * (1.0 / (r[0] * r[0])),
        q[1] * (1.0 / (r[1] * r[1])),
        q[2] * (1.0 / (r[2] * r[2])),
    ]);
    // k1 vanishes only at the centre, deep inside: any negative value will do there.
    if k1.value() < 1e-12 {
        return S::cst(-r[0].min(r[1]).min(r[2]));
    }
    k0 * (k0 - 1.0) / k1
}

/// Capsule from `a` to `b` whose radius goes linearly from `ra` to `rb` (a bound for unequal
/// radii).
pub fn capsule<S: Scalar>(p: V3<S>, a: [f64; 3], b: [f64; 3], ra: f64, rb: f64) -> S {
    let pa = offset(p, a);
    let ba = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let bb = ba[0] * ba[0] + ba[1] * ba[1] + ba[2] * ba[2];
    let h = clamp01((pa[0] * ba[0] + pa[1] * ba[1] + pa[2] * ba[2]) * (1.0 / bb));
    let d = [pa[0] - h * ba[0], pa[1] - h * ba[1], pa[2] - h * ba[2]];
    length(d) - (h * (rb - ra) + ra)
}

/// Signed distance to the plane through `p0` with unit normal `n` (positive on `n`'s side).
pub fn plane<S: Scalar>(p: V3<S>, p0: [f64; 3], n: [f64; 3]) -> S {
    let q = offset(p, p0);
    q[0] * n[0] + q[1] * n[1] + q[2] * n[2]
}

#[cfg(test)]
mod tests {
    use super::super::scalar::Dual;
    use super::*;

    #[test]
    fn exact_primitives_are_distances() {
        // Sphere and capsule of equal radii are exact: |gradient| = 1 off the axis.
        let p = [0.3, -0.2, 0.5];
        let s = sphere(Dual::point(p), [0.1, 0.0, 0.1], 0.2);
        let want = (0.04f64 + 0.04 + 0.16).sqrt() - 0.2;
        assert!((s.v - want).abs() < 1e-15);
        assert!((length(s.d) - 1.0).abs() < 1e-12);
        let c = capsule(Dual::point(p), [0.0, -1.0, 0.0], [0.0, 1.0, 0.0], 0.1, 0.1);
        assert!((c.v - ((0.09f64 + 0.25).sqrt() - 0.1)).abs() < 1e-15);
        assert!((length(c.d) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn ellipsoid_bound_is_zero_on_the_surface_and_never_overestimates() {
        let r = [0.3, 0.2, 0.1];
        for i in 0..200 {
            let a = i as f64 * 0.731;
            let b = i as f64 * 0.377;
            let u = [a.cos() * b.sin(), b.cos(), a.sin() * b.sin()];
            let on = [u[0] * r[0], u[1] * r[1], u[2] * r[2]];
            assert!(ellipsoid(on, [0.0; 3], r).abs() < 1e-12);
            // A point at true distance 0.05 outside along the surface normal.
            let n = normalize([
                on[0] / (r[0] * r[0]),
                on[1] / (r[1] * r[1]),
                on[2] / (r[2] * r[2]),
            ]);
            let out = std::array::from_fn(|k| on[k] + 0.05 * n[k]);
            let d = ellipsoid(out, [0.0; 3], r);
            assert!(d <= 0.05 + 1e-9 && d > 0.02, "direction {i}: {d}");
        }
    }

    #[test]
    fn smooth_blends_stay_within_a_quarter_radius() {
        for i in 0..50 {
            let a = -0.2 + i as f64 * 0.01;
            let b = 0.05;
            let s = smin(a, b, 0.1);
            assert!(s <= a.min(b) + 1e-15 && s >= a.min(b) - 0.025 - 1e-15);
            let m = smax(a, b, 0.1);
            assert!(m >= a.max(b) - 1e-15 && m <= a.max(b) + 0.025 + 1e-15);
        }
        assert_eq!(smin(-1.0, 1.0, 0.1), -1.0);
    }

    fn normalize(v: [f64; 3]) -> [f64; 3] {
        let l = length(v);
        v.map(|c| c / l)
    }
}
