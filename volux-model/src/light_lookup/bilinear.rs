//! The look-up's bilinear interpolation as one flex operation with a hand-written backward.
//!
//! Burn's `grid_sample_2d` on flex is built from tensor ops: corner indices, four gathers per
//! channel and their interpolation forward, scatter-adds backward, each pass allocating. The
//! look-up runs per sample and per light map (five maps, 65 536 samples per quickstart step),
//! so here it is one pass forward that reads four texels per channel and one pass backward
//! that gives `d/du` and `d/dv` from the same four texels. The maps are data (preconvolved
//! environments): no gradient flows to them.
//!
//! The interpolation is `grid_sample_2d` with `align_corners = true` and border padding at
//! padded pixel `x = u W + 0.5`, `y = v H + 0.5`, clamped to the padded map, where the
//! gradient with respect to a clamped coordinate is zero. [`sample_reference`] is that
//! `grid_sample_2d` call; both are tested against each other and against f64 central
//! differences in [`super`]'s tests.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::{
    BalancedCheckpointing, CheckpointStrategy, NoCheckpointing,
};
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::flex::FlexTensor;
use burn::backend::{Autodiff, Flex, GradientCheckpointingStrategy, TensorMetadata};
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{DType, DispatchTensor, Tensor};
use burn_dispatch::DispatchKindConversion;
use rayon::prelude::*;

use crate::flex_extension::{Route, autodiff_parts, contiguous, flex_tensor, route};

/// Points per parallel task.
const POINTS_PER_TASK: usize = 2048;

/// Bilinear samples `[batch, points, 3]` of the padded maps `[batch, 3, height + 2,
/// width + 2]` at `(u, v)` (`[batch, points, 1]` each), differentiable in `u` and `v`.
pub(crate) fn sample(padded: &Tensor<4>, u: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
    let f32s = [padded.dtype(), u.dtype(), v.dtype()] == [DType::F32; 3];
    if !f32s {
        return sample_reference(padded, u, v);
    }
    match route(&u.device()) {
        Route::Flex => {
            let (Ok(maps), Ok(u), Ok(v)) = (
                padded.clone().try_into_primitive::<Flex>(),
                u.try_into_primitive::<Flex>(),
                v.try_into_primitive::<Flex>(),
            ) else {
                unreachable!("a flex device holds flex tensors")
            };
            Tensor::from_primitive::<Flex>(forward_flex(&maps, &u, &v))
        }
        Route::Autodiff(GradientCheckpointingStrategy::Disabled) => {
            sample_autodiff::<NoCheckpointing>(padded, u, v)
        }
        Route::Autodiff(GradientCheckpointingStrategy::Balanced) => {
            sample_autodiff::<BalancedCheckpointing>(padded, u, v)
        }
        Route::Other => sample_reference(padded, u, v),
    }
}

/// [`sample`] by Burn's `grid_sample_2d`: the reference, and what other backends run.
pub(crate) fn sample_reference(padded: &Tensor<4>, u: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
    let [b, n, _] = u.dims();
    let [_, _, hp, wp] = padded.dims();
    let (w, h) = ((wp - 2) as f32, (hp - 2) as f32);
    let gx = (u.mul_scalar(w).add_scalar(0.5))
        .mul_scalar(2.0 / (w + 1.0))
        .sub_scalar(1.0);
    let gy = (v.mul_scalar(h).add_scalar(0.5))
        .mul_scalar(2.0 / (h + 1.0))
        .sub_scalar(1.0);
    let grid = Tensor::cat(vec![gx, gy], 2).reshape([b, n, 1, 2]);
    let options = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Border)
        .with_align_corners(true);
    let sampled = padded.clone().grid_sample_2d(grid, options); // [b, 3, n, 1]
    sampled.reshape([b, 3, n]).swap_dims(1, 2)
}

fn sample_autodiff<C>(padded: &Tensor<4>, u: Tensor<3>, v: Tensor<3>) -> Tensor<3>
where
    C: CheckpointStrategy,
    DispatchTensor: DispatchKindConversion<Autodiff<Flex, C>>,
{
    let (maps, _) = autodiff_parts::<C, 4>(padded.clone().detach());
    let (u, u_node) = autodiff_parts::<C, 3>(u);
    let (v, v_node) = autodiff_parts::<C, 3>(v);
    let out = forward_flex(&maps, &u, &v);
    let out = match SampleBackward
        .prepare::<C>([u_node, v_node])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => prep.finish(SampleState { maps, u, v }, out),
        OpsKind::UnTracked(prep) => prep.finish(out),
    };
    Tensor::from_primitive::<Autodiff<Flex, C>>(out)
}

#[derive(Debug)]
struct SampleBackward;

#[derive(Clone, Debug)]
struct SampleState {
    maps: FlexTensor,
    u: FlexTensor,
    v: FlexTensor,
}

impl Backward<Flex, 2> for SampleBackward {
    type State = SampleState;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [u_node, v_node] = ops.parents;
        let grad = grads.consume::<Flex>(&ops.node);
        if u_node.is_none() && v_node.is_none() {
            return;
        }
        let s = ops.state;
        let (grad_u, grad_v) = backward_flex(&s.maps, &s.u, &s.v, &grad);
        if let Some(node) = u_node {
            grads.register::<Flex>(node.id, grad_u);
        }
        if let Some(node) = v_node {
            grads.register::<Flex>(node.id, grad_v);
        }
    }
}

/// Where one point samples a padded map: the top-left texel's flat offset, the fractions,
/// and the coordinates' scale factors for the gradient (zero where clamped).
struct Corner {
    at: usize,
    fx: f32,
    fy: f32,
    dx: f32,
    dy: f32,
}

/// The padded map's size and the coordinate scales `W` and `H`.
#[derive(Clone, Copy)]
struct Layout {
    hp: usize,
    wp: usize,
}

impl Layout {
    fn corner(self, u: f32, v: f32) -> Corner {
        let (w, h) = ((self.wp - 2) as f32, (self.hp - 2) as f32);
        let (x, y) = (u * w + 0.5, v * h + 0.5);
        let (x_max, y_max) = ((self.wp - 1) as f32, (self.hp - 1) as f32);
        let dx = if (0.0..=x_max).contains(&x) { w } else { 0.0 };
        let dy = if (0.0..=y_max).contains(&y) { h } else { 0.0 };
        let (x, y) = (x.clamp(0.0, x_max), y.clamp(0.0, y_max));
        // A NaN coordinate casts to 0 and stays NaN in the fraction: the output is NaN.
        let x0 = (x.floor() as usize).min(self.wp - 2);
        let y0 = (y.floor() as usize).min(self.hp - 2);
        Corner {
            at: y0 * self.wp + x0,
            fx: x - x0 as f32,
            fy: y - y0 as f32,
            dx,
            dy,
        }
    }

    fn plane(self) -> usize {
        self.hp * self.wp
    }
}

/// `[batch, 3, hp, wp]` maps and `[batch, n, 1]` coordinates as slices and sizes.
fn shapes(maps: &FlexTensor, u: &FlexTensor) -> (usize, usize, Layout) {
    let m = maps.shape();
    let (b, n) = (u.shape()[0], u.shape()[1]);
    assert_eq!(m[0], b, "one map per batch element");
    assert_eq!(m[1], 3, "RGB maps");
    (
        b,
        n,
        Layout {
            hp: m.as_slice()[2],
            wp: m.as_slice()[3],
        },
    )
}

fn forward_flex(maps: &FlexTensor, u: &FlexTensor, v: &FlexTensor) -> FlexTensor {
    let (b, n, layout) = shapes(maps, u);
    let (maps, u, v) = (contiguous(maps), contiguous(u), contiguous(v));
    let mut out = vec![0.0f32; b * n * 3];
    out.par_chunks_mut(POINTS_PER_TASK * 3)
        .enumerate()
        .for_each(|(task, out)| {
            let first = task * POINTS_PER_TASK;
            for (k, rgb) in out.chunks_exact_mut(3).enumerate() {
                let point = first + k;
                let c = layout.corner(u[point], v[point]);
                let base = (point / n) * 3 * layout.plane() + c.at;
                for (channel, o) in rgb.iter_mut().enumerate() {
                    let t = &maps[base + channel * layout.plane()..];
                    let top = t[0] + c.fx * (t[1] - t[0]);
                    let bottom = t[layout.wp] + c.fx * (t[layout.wp + 1] - t[layout.wp]);
                    *o = top + c.fy * (bottom - top);
                }
            }
        });
    flex_tensor(out, vec![b, n, 3])
}

fn backward_flex(
    maps: &FlexTensor,
    u: &FlexTensor,
    v: &FlexTensor,
    grad: &FlexTensor,
) -> (FlexTensor, FlexTensor) {
    let (b, n, layout) = shapes(maps, u);
    let (maps, u, v, grad) = (
        contiguous(maps),
        contiguous(u),
        contiguous(v),
        contiguous(grad),
    );
    let mut grad_uv = vec![[0.0f32; 2]; b * n];
    grad_uv
        .par_chunks_mut(POINTS_PER_TASK)
        .enumerate()
        .for_each(|(task, out)| {
            let first = task * POINTS_PER_TASK;
            for (k, duv) in out.iter_mut().enumerate() {
                let point = first + k;
                let c = layout.corner(u[point], v[point]);
                let base = (point / n) * 3 * layout.plane() + c.at;
                let (mut gx, mut gy) = (0.0f32, 0.0f32);
                for channel in 0..3 {
                    let g = grad[point * 3 + channel];
                    let t = &maps[base + channel * layout.plane()..];
                    let (t00, t01) = (t[0], t[1]);
                    let (t10, t11) = (t[layout.wp], t[layout.wp + 1]);
                    let d_x = (1.0 - c.fy) * (t01 - t00) + c.fy * (t11 - t10);
                    let d_y = (1.0 - c.fx) * (t10 - t00) + c.fx * (t11 - t01);
                    gx += g * d_x;
                    gy += g * d_y;
                }
                *duv = [gx * c.dx, gy * c.dy];
            }
        });
    let (grad_u, grad_v) = grad_uv.into_iter().map(|[a, b]| (a, b)).unzip();
    (
        flex_tensor(grad_u, vec![b, n, 1]),
        flex_tensor(grad_v, vec![b, n, 1]),
    )
}
