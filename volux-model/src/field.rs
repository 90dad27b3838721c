//! The interface between a field and the renderer (EG3D keeps them apart the same way): a
//! [`Field`] gives densities and, when asked ([`FieldWants`]), normals and appearance at
//! points ([`FieldOutput`]). The renderer, the proposal sampler and the marcher know fields only
//! through it; the NeIIF ([`crate::neiif`]) and the analytic test fields
//! ([`crate::analytic`]) implement it.

use burn::tensor::Tensor;

/// Below this squared gradient norm the normal shrinks towards zero instead of dividing by
/// (almost) nothing: `n = -g / sqrt(|g|^2 + NORMAL_EPS2)`.
pub const NORMAL_EPS2: f64 = 1e-12;

/// Normals from density gradients `[.., .., 3]`: `-g / sqrt(|g|^2 + NORMAL_EPS2)`.
pub fn normals_from_gradient(g: Tensor<3>) -> Tensor<3> {
    let norm = g
        .clone()
        .powi_scalar(2)
        .sum_dim(2)
        .add_scalar(NORMAL_EPS2)
        .sqrt();
    g.neg() / norm
}

/// Which outputs a query needs; what is not needed is not computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FieldWants {
    /// Gradient of the density and normals (a reverse sweep through layers 1-4).
    pub normals: bool,
    /// Albedo, specular weights and features (layers 5-6 and the head).
    pub appearance: bool,
}

impl FieldWants {
    /// Everything.
    pub const ALL: Self = Self {
        normals: true,
        appearance: true,
    };
    /// Density only (layers 1-4 and the density head).
    pub const DENSITY: Self = Self {
        normals: false,
        appearance: false,
    };
}

/// What the field gives at `[batch, points]` positions.
#[derive(Clone, Debug)]
pub struct FieldOutput {
    /// `[batch, points]`, non-negative.
    pub sigma: Tensor<2>,
    /// `d sigma / dx`, `[batch, points, 3]`.
    pub grad_sigma: Option<Tensor<3>>,
    /// `-grad / |grad|` (guarded), `[batch, points, 3]`.
    pub normals: Option<Tensor<3>>,
    /// `[batch, points, 3]` in [0, 1].
    pub albedo: Option<Tensor<3>>,
    /// `[batch, points, specular_lobes]`, non-negative.
    pub specular_weights: Option<Tensor<3>>,
    /// The layer-6 output `f`, `[batch, points, width]`.
    pub features: Option<Tensor<3>>,
}

/// Anything that gives densities (and, when asked, normals and appearance) at points
/// `[batch, points, 3]`.
pub trait Field {
    fn query(&self, points: Tensor<3>, wants: FieldWants) -> FieldOutput;

    /// Densities alone, `[batch, points]`, for placing samples: no normals, no appearance
    /// and no autodiff (the result is a constant to any gradient; [`crate::proposal`]).
    fn density(&self, points: Tensor<3>) -> Tensor<2> {
        self.query(points.inner(), FieldWants::DENSITY)
            .sigma
            .inner()
    }
}
