//! One signed-distance code for two number types: `f64` for sphere tracing and [`Dual`]
//! (forward-mode derivatives with respect to the three coordinates) for exact surface normals.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// The arithmetic the head's signed distance needs.
pub trait Scalar:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + Add<f64, Output = Self>
    + Sub<f64, Output = Self>
    + Mul<f64, Output = Self>
{
    /// A constant.
    fn cst(v: f64) -> Self;
    /// The value without derivatives.
    fn value(self) -> f64;
    fn sqrt(self) -> Self;
}

impl Scalar for f64 {
    fn cst(v: f64) -> Self {
        v
    }

    fn value(self) -> f64 {
        self
    }

    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
}

/// A value and its gradient with respect to a point's coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dual {
    pub v: f64,
    pub d: [f64; 3],
}

impl Dual {
    /// Coordinate `axis` of a point, as a variable.
    pub fn variable(v: f64, axis: usize) -> Dual {
        let mut d = [0.0; 3];
        d[axis] = 1.0;
        Dual { v, d }
    }

    /// A point's coordinates as variables.
    pub fn point(p: [f64; 3]) -> [Dual; 3] {
        std::array::from_fn(|k| Dual::variable(p[k], k))
    }
}

impl Scalar for Dual {
    fn cst(v: f64) -> Self {
        Dual { v, d: [0.0; 3] }
    }

    fn value(self) -> f64 {
        self.v
    }

    fn sqrt(self) -> Self {
        let s = self.v.max(0.0).sqrt();
        // The derivative of sqrt at 0 is infinite; a length of exactly zero has no direction,
        // so report a zero gradient rather than infinities.
        let k = if s > 0.0 { 0.5 / s } else { 0.0 };
        Dual {
            v: s,
            d: self.d.map(|g| g * k),
        }
    }
}

impl Add for Dual {
    type Output = Dual;
    fn add(self, o: Dual) -> Dual {
        Dual {
            v: self.v + o.v,
            d: std::array::from_fn(|k| self.d[k] + o.d[k]),
        }
    }
}

impl Sub for Dual {
    type Output = Dual;
    fn sub(self, o: Dual) -> Dual {
        Dual {
            v: self.v - o.v,
            d: std::array::from_fn(|k| self.d[k] - o.d[k]),
        }
    }
}

impl Mul for Dual {
    type Output = Dual;
    // The product rule adds.
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn mul(self, o: Dual) -> Dual {
        Dual {
            v: self.v * o.v,
            d: std::array::from_fn(|k| self.d[k] * o.v + self.v * o.d[k]),
        }
    }
}

impl Div for Dual {
    type Output = Dual;
    // The quotient rule subtracts and multiplies.
    #[allow(clippy::suspicious_arithmetic_impl)]
    fn div(self, o: Dual) -> Dual {
        let inv = 1.0 / o.v;
        Dual {
            v: self.v * inv,
            d: std::array::from_fn(|k| (self.d[k] - self.v * inv * o.d[k]) * inv),
        }
    }
}

impl Neg for Dual {
    type Output = Dual;
    fn neg(self) -> Dual {
        Dual {
            v: -self.v,
            d: self.d.map(|g| -g),
        }
    }
}

impl Add<f64> for Dual {
    type Output = Dual;
    fn add(self, c: f64) -> Dual {
        Dual {
            v: self.v + c,
            d: self.d,
        }
    }
}

impl Sub<f64> for Dual {
    type Output = Dual;
    fn sub(self, c: f64) -> Dual {
        Dual {
            v: self.v - c,
            d: self.d,
        }
    }
}

impl Mul<f64> for Dual {
    type Output = Dual;
    fn mul(self, c: f64) -> Dual {
        Dual {
            v: self.v * c,
            d: self.d.map(|g| g * c),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dual_derivatives_match_finite_differences() {
        // f(x, y, z) = sqrt(x^2 + y z) / (1 + z) - 2 x, at a generic point.
        fn f<S: Scalar>(p: [S; 3]) -> S {
            (p[0] * p[0] + p[1] * p[2]).sqrt() / (p[2] + 1.0) - p[0] * 2.0
        }
        let p = [0.7, -0.3, -1.9];
        let g = f(Dual::point(p));
        assert_eq!(g.v, f(p));
        let h = 1e-6;
        for k in 0..3 {
            let (mut a, mut b) = (p, p);
            a[k] += h;
            b[k] -= h;
            let fd = (f(a) - f(b)) / (2.0 * h);
            assert!((g.d[k] - fd).abs() < 1e-8, "axis {k}: {} vs {fd}", g.d[k]);
        }
    }
}
