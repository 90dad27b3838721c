//! The convolution's three products over a batch (forward, adjoint, weight gradient): the
//! images in parallel (one thread each) or, for fewer images than threads, one after another
//! with each product on every thread; each image by the strategy its shape runs fastest
//! with ([`Strategy`]), in the thread's scratch buffer, into outputs that are not zeroed first.

use std::cell::Cell;
use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::Shape;
use super::patches;
use super::shifted::{self, Phases};
use super::winograd::{self, Tiles};
use crate::flex_extension::{with_scratch, written_by};

/// How one image's products are taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Strategy {
    /// A 1x1 kernel with stride 1 and no padding: the image is its own patch matrix.
    Pointwise,
    /// im2col and one product ([`patches`]): small planes, whose patch matrix stays in cache.
    Patches,
    /// `k^2` shifted products over the polyphase planes ([`shifted`]): large planes, where
    /// writing and reading a patch matrix `k^2 / s^2` times the input cost more than the
    /// products. Alone on one core (batch 8, the small discriminators' layers, 2026-12-06)
    /// it took 8.1 against 11.7-12.1 ms forward at 64^2 and 32 channels, 5.9-6.0 against
    /// 7.5 ms at 32^2 and 64, 4.2 against 5.2-5.4 ms for the stride-2 layer on 65^2 planes,
    /// but 5.9-6.0 against 5.5 ms at 16^2 and 128 and 1.7 against 1.5 ms at 8^2.
    Shifted,
    /// Winograd's `F(2x2, 3x3)` ([`winograd`]): 3x3 kernels of stride 1, 4/9 of the
    /// multiply-adds of the direct products.
    Winograd,
}

/// Output positions per image from which [`Strategy::Shifted`] is taken.
const SHIFTED_FROM: usize = 512;

/// Output positions per image and channels (in and out) from which [`Strategy::Winograd`]
/// is taken where it applies. Alone on one core (batch 8, 2026-12-07, the machine shared
/// with a training run), forward + backward against the direct products: 18.2-19.1 against
/// 22.9-24.8 ms at 64^2 and 32 channels, 14.2-15.4 against 21.4-22.9 ms at 32^2 and 64,
/// 14.5-17.2 against 21.5-23.4 ms at 16^2 and 128; but 7.2-7.4 against 5.8 ms at 8^2 (4
/// tiles a row: short products, and a fifth of their columns are not tiles). Narrower
/// layers were not measured.
const WINOGRAD_FROM: usize = 256;
const WINOGRAD_CHANNELS: usize = 32;

thread_local! {
    /// A strategy forced on the convolutions this thread starts (0: none), for tests that
    /// run each strategy on every shape ([`forced::each`]). Per thread, so that the other
    /// tests running meanwhile keep their shapes' own choices (and bit-for-bit results).
    static FORCED: Cell<u8> = const { Cell::new(0) };
}

impl Strategy {
    fn of(s: Shape) -> Self {
        if s.pointwise() {
            return Strategy::Pointwise;
        }
        match FORCED.get() {
            1 => return Strategy::Patches,
            2 => return Strategy::Shifted,
            3 if winograd::applies(s) => return Strategy::Winograd,
            _ => {}
        }
        if winograd::applies(s) && s.ho * s.wo >= WINOGRAD_FROM && s.c.min(s.o) >= WINOGRAD_CHANNELS
        {
            return Strategy::Winograd;
        }
        // A strided 1x1 kernel reads a quarter of the input or less: nothing to reuse.
        if s.k > 1 && s.ho * s.wo >= SHIFTED_FROM {
            Strategy::Shifted
        } else {
            Strategy::Patches
        }
    }

    /// Scratch elements one image of a direct strategy needs (`layout`: the shape's
    /// polyphase layout; Winograd's depend on the direction, [`winograd::scratch_len`]).
    fn scratch_len(self, s: Shape, layout: &Phases) -> usize {
        match self {
            Strategy::Pointwise | Strategy::Winograd => 0,
            Strategy::Patches => patches::scratch_len(s),
            Strategy::Shifted => layout.len() + s.o * layout.columns(),
        }
    }
}

/// Runs `f` with each non-pointwise strategy forced on every convolution this thread starts,
/// in turn (Winograd where it applies, the shape's own choice elsewhere). The strategy is
/// chosen on the calling thread (the backward pass's too), so the forcing reaches every
/// convolution `f` runs and no other test's.
#[cfg(test)]
pub(super) mod forced {
    use super::{FORCED, Strategy};

    pub(crate) fn each(mut f: impl FnMut(Strategy)) {
        for (code, strategy) in [
            (1, Strategy::Patches),
            (2, Strategy::Shifted),
            (3, Strategy::Winograd),
        ] {
            FORCED.set(code);
            f(strategy);
        }
        FORCED.set(0);
    }
}

/// Whether each image's products run on one thread (images in parallel) or on all of them.
fn images_in_parallel(batch: usize) -> bool {
    batch >= rayon::current_num_threads()
}

fn gemm_parallelism(images_in_parallel: bool) -> gemm::Parallelism {
    if images_in_parallel {
        gemm::Parallelism::None
    } else {
        gemm::Parallelism::Rayon(0)
    }
}

/// A matrix view for [`matmul`]: element `(i, j)` at `ptr[i * row + j * col]`.
#[derive(Clone, Copy)]
pub(super) struct View {
    pub(super) ptr: *const f32,
    pub(super) row: isize,
    pub(super) col: isize,
}

/// A row-major matrix of `cols` columns.
pub(super) fn rows(m: &[f32], cols: usize) -> View {
    View {
        ptr: m.as_ptr(),
        row: cols as isize,
        col: 1,
    }
}

/// A row-major destination of `cols` columns.
pub(super) fn rows_out(m: &mut [f32], cols: usize) -> View {
    View {
        ptr: m.as_mut_ptr().cast_const(),
        row: cols as isize,
        col: 1,
    }
}

/// A row-major destination of `cols` columns in possibly uninitialised storage.
pub(super) fn rows_uninit(m: &mut [MaybeUninit<f32>], cols: usize) -> View {
    View {
        ptr: m.as_mut_ptr().cast::<f32>().cast_const(),
        row: cols as isize,
        col: 1,
    }
}

/// The transpose of a row-major matrix of `cols` columns: element `(i, j)` at `m[j cols + i]`.
pub(super) fn transposed(m: &[f32], cols: usize) -> View {
    View {
        ptr: m.as_ptr(),
        row: 1,
        col: cols as isize,
    }
}

/// Tap `(u, v)` of the weight, `[o, c]`: element `(o, c)` at `weight[(o c + c) k^2 + u k + v]`.
pub(super) fn tap_weight(weight: &[f32], s: Shape, u: usize, v: usize) -> View {
    let kk = (s.k * s.k) as isize;
    View {
        ptr: weight[u * s.k + v..].as_ptr(),
        row: s.c as isize * kk,
        col: kk,
    }
}

/// The same tap transposed, `[c, o]`.
pub(super) fn tap_weight_t(weight: &[f32], s: Shape, u: usize, v: usize) -> View {
    let w = tap_weight(weight, s, u, v);
    View {
        ptr: w.ptr,
        row: w.col,
        col: w.row,
    }
}

/// `dst = [dst +] a (m x k) b (k x n)`; without `accumulate` every element of `dst` is
/// written and none read.
///
/// # Safety
/// `a` and `b` must address `m x k` and `k x n` valid elements, `dst` `m x n` writable
/// elements (initialised if `accumulate`) that nothing else touches meanwhile.
pub(super) unsafe fn matmul(
    dst: View,
    accumulate: bool,
    (m, k, n): (usize, usize, usize),
    a: View,
    b: View,
    parallelism: gemm::Parallelism,
) {
    if m == 0 || n == 0 {
        return;
    }
    // SAFETY: the caller guarantees the views. With `k = 0` and no accumulation gemm writes
    // zeros.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.ptr.cast_mut(),
            dst.col,
            dst.row,
            accumulate,
            a.ptr,
            a.col,
            a.row,
            b.ptr,
            b.col,
            b.row,
            if accumulate { 1.0 } else { 0.0 },
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

/// The batch's outputs, `out_len` per image, from its inputs, `in_len` per image: `image`
/// writes each image's output whole from its input, with the parallelism its products get
/// (the images in parallel on one thread each, or one after another on every thread).
///
/// # Safety
/// `image` must initialise every element of the output block it is given.
unsafe fn map_images(
    batch: usize,
    (input, in_len): (&[f32], usize),
    out_len: usize,
    image: impl Fn(&mut [MaybeUninit<f32>], &[f32], gemm::Parallelism) + Send + Sync,
) -> Vec<f32> {
    let len = batch * out_len;
    if len == 0 {
        return Vec::new();
    }
    let parallel = images_in_parallel(batch);
    let p = gemm_parallelism(parallel);
    let pair = |(out, x): (&mut [MaybeUninit<f32>], &[f32])| image(out, x, p);
    let fill = |out: &mut [MaybeUninit<f32>]| {
        if parallel {
            out.par_chunks_mut(out_len)
                .zip(input.par_chunks(in_len))
                .for_each(pair);
        } else {
            out.chunks_mut(out_len)
                .zip(input.chunks(in_len))
                .for_each(pair);
        }
    };
    // SAFETY: the `batch` output blocks pair up with the `batch` input blocks (a zero
    // `in_len` panics in `chunks` before any output is used), and the caller's `image`
    // writes each block whole.
    unsafe { written_by(len, fill) }
}

/// `y = conv(x, W)` for every image: `[batch, o, ho, wo]`.
pub(super) fn forward(x: &[f32], weight: &[f32], s: Shape) -> Vec<f32> {
    let strategy = Strategy::of(s);
    let layout = Phases::new(s);
    let winograd = (strategy == Strategy::Winograd)
        .then(|| (Tiles::forward(s), winograd::filters(weight, s, false)));
    let image = |y_b: &mut [MaybeUninit<f32>], x_b: &[f32], p| match strategy {
        // SAFETY: `weight` is `[o, c]`, `x_b` `[c, h w]`, `y_b` `[o, h w]`, written whole.
        Strategy::Pointwise => unsafe {
            let n = s.ho * s.wo;
            matmul(
                rows_uninit(y_b, n),
                false,
                (s.o, s.c, n),
                rows(weight, s.c),
                rows(x_b, n),
                p,
            )
        },
        Strategy::Patches => with_scratch(strategy.scratch_len(s, &layout), |col| {
            patches::forward_image(x_b, weight, s, y_b, col, p)
        }),
        Strategy::Shifted => with_scratch(strategy.scratch_len(s, &layout), |scratch| {
            shifted::forward_image(x_b, weight, &layout, y_b, scratch, p)
        }),
        Strategy::Winograd => {
            let (tiles, u) = winograd.as_ref().expect("transformed above");
            with_scratch(winograd::scratch_len(tiles), |scratch| {
                winograd::forward_image(x_b, u, tiles, y_b, scratch, p)
            })
        }
    };
    // SAFETY: every strategy writes each image's `[o, ho, wo]` block whole.
    unsafe { map_images(s.batch, (x, s.x_len()), s.y_len(), image) }
}

/// `x = conv^T(y, W)` for every image: `[batch, c, h, w]`.
pub(super) fn adjoint(y: &[f32], weight: &[f32], s: Shape) -> Vec<f32> {
    let strategy = Strategy::of(s);
    let layout = Phases::new(s);
    // The adjoint is the forward convolution with the flipped filters.
    let winograd = (strategy == Strategy::Winograd)
        .then(|| (Tiles::adjoint(s), winograd::filters(weight, s, true)));
    let image = |x_b: &mut [MaybeUninit<f32>], y_b: &[f32], p| match strategy {
        // SAFETY: `W^T` is `[c, o]`, `y_b` `[o, h w]`, `x_b` `[c, h w]`, written whole.
        Strategy::Pointwise => unsafe {
            let n = s.h * s.w;
            matmul(
                rows_uninit(x_b, n),
                false,
                (s.c, s.o, n),
                tap_weight_t(weight, s, 0, 0),
                rows(y_b, n),
                p,
            )
        },
        Strategy::Patches => with_scratch(strategy.scratch_len(s, &layout), |col| {
            patches::adjoint_image(y_b, weight, s, x_b, col, p)
        }),
        Strategy::Shifted => with_scratch(strategy.scratch_len(s, &layout), |scratch| {
            shifted::adjoint_image(y_b, weight, &layout, x_b, scratch, p)
        }),
        Strategy::Winograd => {
            let (tiles, u) = winograd.as_ref().expect("transformed above");
            with_scratch(winograd::scratch_len(tiles), |scratch| {
                winograd::forward_image(y_b, u, tiles, x_b, scratch, p)
            })
        }
    };
    // SAFETY: every strategy writes each image's `[c, h, w]` block whole.
    unsafe { map_images(s.batch, (y, s.y_len()), s.x_len(), image) }
}

/// `dW = sum_b g_b col(x_b)^T`, `[o, c, k, k]`, for inputs `x` and output gradients `g`:
/// the direct strategies sum into a `[c k k, o]` buffer (the orientation the products run
/// fast in, see [`patches::weight_gradient_image`]), transposed once at the end; Winograd
/// sums in its transformed domain and transforms back ([`winograd::filter_gradient`]).
pub(super) fn weight_gradient(x: &[f32], g: &[f32], s: Shape) -> Vec<f32> {
    let patch = s.patch();
    let strategy = Strategy::of(s);
    let layout = Phases::new(s);
    let tiles = (strategy == Strategy::Winograd).then(|| Tiles::forward(s));
    let len = tiles.as_ref().map_or(s.o * patch, winograd::gradient_len);
    let sum = sum_over_images((x, g), s, len, |acc, x_b, g_b, p| match strategy {
        // SAFETY: `x_b` is `[c, h w]`, `g_b^T` `[h w, o]`, `acc` `[c, o]`, initialised.
        Strategy::Pointwise => unsafe {
            let n = s.h * s.w;
            matmul(
                rows_out(acc, s.o),
                true,
                (s.c, n, s.o),
                rows(x_b, n),
                transposed(g_b, n),
                p,
            )
        },
        Strategy::Patches => with_scratch(strategy.scratch_len(s, &layout), |col| {
            patches::weight_gradient_image(x_b, g_b, s, acc, col, p)
        }),
        Strategy::Shifted => with_scratch(strategy.scratch_len(s, &layout), |scratch| {
            shifted::weight_gradient_image(x_b, g_b, &layout, acc, scratch, p)
        }),
        Strategy::Winograd => {
            let tiles = tiles.as_ref().expect("tiled above");
            with_scratch(winograd::scratch_len(tiles), |scratch| {
                winograd::weight_gradient_image(x_b, g_b, tiles, acc, scratch, p)
            })
        }
    });
    if strategy == Strategy::Winograd {
        return winograd::filter_gradient(&sum, s);
    }
    // `[patch, o] -> [o, patch]`.
    let mut dw = vec![0.0f32; sum.len()];
    for (r, row) in sum.chunks_exact(s.o).enumerate() {
        for (o, v) in row.iter().enumerate() {
            dw[o * patch + r] = *v;
        }
    }
    dw
}

/// `sum_b image(x_b, g_b)` over the batch (`x`: `[batch, c, h, w]`, `g`: `[batch, o, ho,
/// wo]`), each call adding onto an accumulator of `len` elements that starts at zero: each
/// worker takes a share of the images into its own accumulator, and the partial sums are
/// added at the end.
fn sum_over_images(
    (x, g): (&[f32], &[f32]),
    s: Shape,
    len: usize,
    image: impl Fn(&mut [f32], &[f32], &[f32], gemm::Parallelism) + Sync,
) -> Vec<f32> {
    let parallel = images_in_parallel(s.batch);
    let p = gemm_parallelism(parallel);
    let shares = if parallel {
        rayon::current_num_threads().min(s.batch)
    } else {
        1
    };
    let per_share = s.batch.div_ceil(shares.max(1)).max(1);
    let share = |images: std::ops::Range<usize>| -> Vec<f32> {
        let mut acc = vec![0.0f32; len];
        for b in images {
            let x_b = &x[b * s.x_len()..(b + 1) * s.x_len()];
            let g_b = &g[b * s.y_len()..(b + 1) * s.y_len()];
            image(&mut acc, x_b, g_b, p);
        }
        acc
    };
    let ranges: Vec<_> = (0..s.batch)
        .step_by(per_share)
        .map(|start| start..(start + per_share).min(s.batch))
        .collect();
    let partials: Vec<Vec<f32>> = if parallel {
        ranges.into_par_iter().map(share).collect()
    } else {
        ranges.into_iter().map(share).collect()
    };
    let mut partials = partials.into_iter();
    let mut sum = partials.next().unwrap_or_else(|| vec![0.0; len]);
    for p in partials {
        for (t, v) in sum.iter_mut().zip(p) {
            *t += v;
        }
    }
    sum
}
