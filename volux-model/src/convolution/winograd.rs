//! 3x3 convolutions of stride 1 by Winograd's minimal filtering `F(2x2, 3x3)` (Lavin and
//! Gray, "Fast Algorithms for Convolutional Neural Networks", 2016): each 2x2 block of outputs
//! is `Y = A^T [(G g G^T) . (B^T d B)] A` for the 4x4 input tile `d` under it and the 3x3
//! filter `g`, summed over input channels. Written per position `xi` of the 4x4 transformed
//! tile, the sum over channels is a matrix product:
//!
//! `M_xi [o, T] = U_xi [o, c] V_xi [c, T]`, with `U_xi = (G g G^T)_xi` (the filters,
//! transformed once per call) and `V_xi = (B^T d B)_xi` (the image's `T` tiles),
//!
//! so a layer is 16 products with the inner dimension `c` and `T = ceil(ho / 2) ceil(wo / 2)`
//! columns, `16 T` columns in all where the direct products ([`super::shifted`],
//! [`super::patches`]) have `9 ho wo`: 4/9 of their multiply-adds. The transforms add and
//! subtract only (and halve, in `G`); they cost `O((c + o) T)` against the products'
//! `O(o c T)`, and they are laid out so that each is arithmetic on runs as long as the image
//! has tiles ([`Tiles::input_tiles_here`]): written tile by tile, or a row of tiles at a time
//! (runs of 8-32), they took a third of the layer's time and lost to the direct products at
//! 64^2 and 32 channels. Each task takes its images one at a time: the tiles of several
//! images side by side made longer products whose operands no longer stayed in cache.
//!
//! The other two products follow from linearity. The adjoint of a stride-1 3x3 convolution
//! with padding `p` is the convolution of the output with the filters flipped and their
//! channels swapped, `W'[c, o, u, v] = W[o, c, 2 - u, 2 - v]`, padded by `2 - p`; it runs
//! through the same forward code. The weight gradient takes the transposes of `A` and `G`:
//! `dU_xi = sum over tiles of (A dY A^T)_xi (B^T d B)_xi` (again 16 products, inner dimension
//! `T`), then `dW = G^T dU G`.
//!
//! `F(2x2, 3x3)` is the variant with the smallest transform coefficients (0, +-1, +-1/2):
//! its rounding error stays within a small factor of the direct sum's (relative RMS 2.0e-7
//! against 1.2-3.0e-7 on a 32-channel layer, `tests::winograd_rounding_stays_near_the_direct_products`;
//! larger tiles, `F(4x4, 3x3)`, trade accuracy for 4x fewer products). Two differences from
//! the direct sum at the extremes: a NaN or infinity in the input reaches every output of the
//! tiles whose 4x4 input tile holds it (one ring of outputs more than its 3x3 windows), and
//! the input transform adds up to four inputs, so inputs within 4x of `f32::MAX` can overflow
//! where the direct products would not. Both end a training step the same way (its
//! non-finite guard).

use std::mem::MaybeUninit;

use super::kernels::{matmul, rows, rows_out, transposed};
use super::{ConvGeometry, Shape};
use crate::flex_extension::dispatch_simd;

/// Positions of a transformed tile.
const POSITIONS: usize = 16;

/// Whether a convolution can be taken this way: a 3x3 kernel, stride 1, and padding up to 2
/// (the adjoint pads by `2 - pad`).
pub(super) fn applies(s: Shape) -> bool {
    s.k == 3 && s.geometry.stride == 1 && s.geometry.pad <= 2
}

/// One direction's tiling: a stride-1 3x3 convolution from `cin` planes of `h x w`, padded
/// by `pad`, to `cout` planes of `ho x wo`, in tiles of 2x2 outputs.
#[derive(Clone, Copy, Debug)]
pub(super) struct Tiles {
    cin: usize,
    cout: usize,
    h: usize,
    w: usize,
    pad: usize,
    ho: usize,
    wo: usize,
    /// Tile rows and columns, `ceil(ho / 2)` and `ceil(wo / 2)`.
    th: usize,
    tw: usize,
}

impl Tiles {
    fn new(cin: usize, cout: usize, [h, w]: [usize; 2], pad: usize) -> Self {
        let g = ConvGeometry::new(1, pad);
        let (ho, wo) = (g.out_len(h, 3), g.out_len(w, 3));
        Self {
            cin,
            cout,
            h,
            w,
            pad,
            ho,
            wo,
            th: ho.div_ceil(2),
            tw: wo.div_ceil(2),
        }
    }

    /// The convolution `x -> y` of `s`.
    pub(super) fn forward(s: Shape) -> Self {
        Self::new(s.c, s.o, [s.h, s.w], s.geometry.pad)
    }

    /// Its adjoint `y -> x`, as the convolution with the flipped filters ([`filters`]).
    pub(super) fn adjoint(s: Shape) -> Self {
        Self::new(s.o, s.c, [s.ho, s.wo], 2 - s.geometry.pad)
    }

    /// Columns of one image's transformed tiles: tile `(i, j)` at `i (tw + 1) + j`, so that
    /// every input of every tile is a contiguous run of a quarter plane (see
    /// [`Self::input_tiles_here`]); column `tw` of each row of tiles is not a tile (its
    /// products are computed and dropped: `1 / tw` more columns).
    fn columns(&self) -> usize {
        self.th * (self.tw + 1)
    }

    /// [`Self::input_tiles_here`] compiled for the widest vectors the CPU has.
    fn input_tiles(&self, x_b: &[f32], v: &mut [f32], temp: &mut [f32]) {
        #[inline(always)]
        fn kernel((tiles, x_b, v, temp): (&Tiles, &[f32], &mut [f32], &mut [f32])) {
            tiles.input_tiles_here(x_b, v, temp)
        }
        dispatch_simd!(
            kernel,
            (self, x_b, v, temp),
            (&Tiles, &[f32], &mut [f32], &mut [f32]) => ()
        )
    }

    /// [`Self::output_tiles_here`] compiled for the widest vectors the CPU has.
    fn output_tiles(&self, m: &[f32], y_b: &mut [MaybeUninit<f32>], temp: &mut [f32]) {
        type Args<'a> = (
            &'a Tiles,
            &'a [f32],
            &'a mut [MaybeUninit<f32>],
            &'a mut [f32],
        );
        #[inline(always)]
        fn kernel((tiles, m, y_b, temp): Args<'_>) {
            tiles.output_tiles_here(m, y_b, temp)
        }
        dispatch_simd!(kernel, (self, m, y_b, temp), Args<'_> => ())
    }

    /// [`Self::output_gradient_tiles_here`] compiled for the widest vectors the CPU has.
    fn output_gradient_tiles(&self, g_b: &[f32], dm: &mut [f32], temp: &mut [f32]) {
        #[inline(always)]
        fn kernel((tiles, g_b, dm, temp): (&Tiles, &[f32], &mut [f32], &mut [f32])) {
            tiles.output_gradient_tiles_here(g_b, dm, temp)
        }
        dispatch_simd!(
            kernel,
            (self, g_b, dm, temp),
            (&Tiles, &[f32], &mut [f32], &mut [f32]) => ()
        )
    }

    /// Elements of one quarter plane of a padded input ([`Self::input_tiles_here`]): its
    /// rows, and one more element that the last window reads.
    fn quarter_len(&self) -> usize {
        (self.th + 1) * (self.tw + 1) + 1
    }

    /// Working space of the three transforms (`temp`), the largest of their needs.
    fn temp_len(&self) -> usize {
        let l = self.columns();
        (4 * self.quarter_len() + 4 * l).max(12 * l)
    }

    /// `V = B^T d B` of every tile of one image `x_b` (`[cin, h, w]`) into `v`, laid out
    /// `[16, cin, columns]` ([`Self::columns`]); padding reads as zero.
    ///
    /// Each channel's padded plane is split into its four quarter planes by row and column
    /// parity, `Q[pr, pc][i, j] = x_pad[2 i + pr, 2 j + pc]`, rows of `tw + 1`. Input `(a, b)`
    /// of tile `(i, j)` is `x_pad[2 i + a, 2 j + b] = Q[a % 2, b % 2][i + a / 2, j + b / 2]`:
    /// for all tiles at once, the quarter plane read from offset `(a / 2) (tw + 1) + b / 2`
    /// in the tiles' own layout. So both halves of the transform are arithmetic on runs of
    /// every tile of the image.
    #[inline(always)]
    fn input_tiles_here(&self, x_b: &[f32], v: &mut [f32], temp: &mut [f32]) {
        let (l, lane, q_len) = (self.columns(), self.tw + 1, self.quarter_len());
        // The four quarter planes, then B^T d for one row a of the transformed tile
        // (columns b = 0..4).
        let (quarters, e) = temp.split_at_mut(4 * q_len);
        let e = &mut e[..4 * l];
        for c in 0..self.cin {
            let plane = &x_b[c * self.h * self.w..(c + 1) * self.h * self.w];
            quarters.fill(0.0);
            for (y, src) in plane.chunks_exact(self.w).enumerate() {
                let r = y + self.pad;
                if r >= 2 * (self.th + 1) {
                    break;
                }
                let row = (r / 2) * lane;
                let (even, odd) = quarters[(r % 2) * 2 * q_len..][..2 * q_len].split_at_mut(q_len);
                // Padded column q holds input column q - pad; columns past 2 lane are read by
                // no tile.
                let src = &src[..src.len().min(2 * lane - self.pad)];
                let k0 = row + self.pad / 2;
                if self.pad.is_multiple_of(2) {
                    deinterleave(src, &mut even[k0..], &mut odd[k0..]);
                } else {
                    deinterleave(src, &mut odd[k0..], &mut even[k0 + 1..]);
                }
            }
            let d = |a: usize, b: usize| {
                let start = ((a % 2) * 2 + b % 2) * q_len + (a / 2) * lane + b / 2;
                &quarters[start..start + l]
            };
            for a in 0..4 {
                for b in 0..4 {
                    let out = &mut e[b * l..(b + 1) * l];
                    match a {
                        0 => combine(out, d(0, b), d(2, b), |x, y| x - y),
                        1 => combine(out, d(1, b), d(2, b), |x, y| x + y),
                        2 => combine(out, d(2, b), d(1, b), |x, y| x - y),
                        _ => combine(out, d(1, b), d(3, b), |x, y| x - y),
                    }
                }
                let e_b = |b: usize| &e[b * l..(b + 1) * l];
                let start = |b: usize| ((a * 4 + b) * self.cin + c) * l;
                combine(&mut v[start(0)..][..l], e_b(0), e_b(2), |x, y| x - y);
                combine(&mut v[start(1)..][..l], e_b(1), e_b(2), |x, y| x + y);
                combine(&mut v[start(2)..][..l], e_b(2), e_b(1), |x, y| x - y);
                combine(&mut v[start(3)..][..l], e_b(1), e_b(3), |x, y| x - y);
            }
        }
    }

    /// `Y = A^T M A` of every tile from `m` (`[16, cout, columns]`) into `y_b` (`[cout, ho,
    /// wo]`, every element written once: each output lies in exactly one tile), for all tiles
    /// at once as in [`Self::input_tiles_here`], then spread to the plane.
    #[inline(always)]
    fn output_tiles_here(&self, m: &[f32], y_b: &mut [MaybeUninit<f32>], temp: &mut [f32]) {
        let (l, lane) = (self.columns(), self.tw + 1);
        let plane_len = self.ho * self.wo;
        // A^T M: rows i = 0, 1 of column b at `(i 4 + b) l`; then the outputs (i, j) at
        // `(i 2 + j) l`.
        let (r, y) = temp[..12 * l].split_at_mut(8 * l);
        for o in 0..self.cout {
            let m_at = |a: usize, b: usize| &m[((a * 4 + b) * self.cout + o) * l..][..l];
            for b in 0..4 {
                let (m0, m1, m2, m3) = (m_at(0, b), m_at(1, b), m_at(2, b), m_at(3, b));
                let (r0, r1) = r.split_at_mut(4 * l);
                combine3(&mut r0[b * l..][..l], m0, m1, m2, |x, y, z| x + y + z);
                combine3(&mut r1[b * l..][..l], m1, m2, m3, |x, y, z| x - y - z);
            }
            for i in 0..2 {
                let row = |b: usize| &r[(i * 4 + b) * l..][..l];
                let (q0, q1, q2, q3) = (row(0), row(1), row(2), row(3));
                let (y0, y1) = y[i * 2 * l..(i + 1) * 2 * l].split_at_mut(l);
                combine3(y0, q0, q1, q2, |x, y, z| x + y + z);
                combine3(y1, q1, q2, q3, |x, y, z| x - y - z);
            }
            let plane = &mut y_b[o * plane_len..(o + 1) * plane_len];
            for (row, dst) in plane.chunks_exact_mut(self.wo).enumerate() {
                let (ti, i) = (row / 2, row % 2);
                let even = &y[(i * 2) * l + ti * lane..][..self.tw];
                let odd = &y[(i * 2 + 1) * l + ti * lane..][..self.tw];
                let mut pairs = dst.chunks_exact_mut(2);
                for (pair, (e, o)) in (&mut pairs).zip(even.iter().zip(odd.iter())) {
                    pair[0].write(*e);
                    pair[1].write(*o);
                }
                if let [last] = pairs.into_remainder() {
                    last.write(even[self.wo / 2]);
                }
            }
        }
    }

    /// `A dY A^T` of every 2x2 tile of one image's output gradient `g_b` (`[cout, ho, wo]`;
    /// outside the plane, and in the columns that are not tiles, zero) into `dm` (`[16, cout,
    /// columns]`), for all tiles at once as in [`Self::input_tiles_here`].
    #[inline(always)]
    fn output_gradient_tiles_here(&self, g_b: &[f32], dm: &mut [f32], temp: &mut [f32]) {
        let (l, lane) = (self.columns(), self.tw + 1);
        let plane_len = self.ho * self.wo;
        // The tiles' outputs (i, j) at `(i 2 + j) l`; then A dY down the columns: rows
        // a = 0..4 of column j at `(j 4 + a) l`.
        let (g, p) = temp[..12 * l].split_at_mut(4 * l);
        for o in 0..self.cout {
            let plane = &g_b[o * plane_len..(o + 1) * plane_len];
            g.fill(0.0);
            for (row, src) in plane.chunks_exact(self.wo).enumerate() {
                let (ti, i) = (row / 2, row % 2);
                let (even, odd) = g[i * 2 * l..(i + 1) * 2 * l].split_at_mut(l);
                deinterleave(src, &mut even[ti * lane..], &mut odd[ti * lane..]);
            }
            let g_at = |i: usize, j: usize| &g[(i * 2 + j) * l..][..l];
            for j in 0..2 {
                let (g0, g1) = (g_at(0, j), g_at(1, j));
                let col = &mut p[j * 4 * l..(j + 1) * 4 * l];
                let (p0, rest) = col.split_at_mut(l);
                let (p1, rest) = rest.split_at_mut(l);
                let (p2, p3) = rest.split_at_mut(l);
                p0.copy_from_slice(g0);
                combine(p1, g0, g1, |x, y| x + y);
                combine(p2, g0, g1, |x, y| x - y);
                combine(p3, g1, g1, |_, y| -y);
            }
            for a in 0..4 {
                let (q0, q1) = (&p[a * l..][..l], &p[(4 + a) * l..][..l]);
                let start = |b: usize| ((a * 4 + b) * self.cout + o) * l;
                dm[start(0)..][..l].copy_from_slice(q0);
                combine(&mut dm[start(1)..][..l], q0, q1, |x, y| x + y);
                combine(&mut dm[start(2)..][..l], q0, q1, |x, y| x - y);
                combine(&mut dm[start(3)..][..l], q1, q1, |_, y| -y);
            }
        }
    }
}

/// `even[k] = src[2 k]`, `odd[k] = src[2 k + 1]` for the elements `src` has (the
/// destinations hold at least that many).
#[inline(always)]
fn deinterleave(src: &[f32], even: &mut [f32], odd: &mut [f32]) {
    let mut pairs = src.chunks_exact(2);
    for ((pair, e), o) in (&mut pairs).zip(even.iter_mut()).zip(odd.iter_mut()) {
        *e = pair[0];
        *o = pair[1];
    }
    if let [last] = pairs.remainder() {
        even[src.len() / 2] = *last;
    }
}

/// `dst[j] = f(a[j], b[j])` (the runs have one length).
#[inline(always)]
fn combine(dst: &mut [f32], a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) {
    for ((d, x), y) in dst.iter_mut().zip(a).zip(b) {
        *d = f(*x, *y);
    }
}

/// `dst[j] = f(a[j], b[j], c[j])`.
#[inline(always)]
fn combine3(dst: &mut [f32], a: &[f32], b: &[f32], c: &[f32], f: impl Fn(f32, f32, f32) -> f32) {
    for (((d, x), y), z) in dst.iter_mut().zip(a).zip(b).zip(c) {
        *d = f(*x, *y, *z);
    }
}

/// `G g G^T` of a 3x3 filter `g(u, v)`: `G = [[1, 0, 0], [1/2, 1/2, 1/2], [1/2, -1/2, 1/2],
/// [0, 0, 1]]`.
fn filter_tile(g: impl Fn(usize, usize) -> f32) -> [[f32; 4]; 4] {
    let apply = |q: [f32; 3]| {
        [
            q[0],
            0.5 * (q[0] + q[1] + q[2]),
            0.5 * (q[0] - q[1] + q[2]),
            q[2],
        ]
    };
    // G g: each column of the filter; then G along each row of that.
    let columns = [0, 1, 2].map(|v| apply([g(0, v), g(1, v), g(2, v)]));
    [0, 1, 2, 3].map(|a| apply([columns[0][a], columns[1][a], columns[2][a]]))
}

/// The transformed filters `U` of a convolution's weight (`[o, c, 3, 3]`), laid out `[16,
/// cout, cin]` for the direction `tiles` describes: the forward filters, or (`adjoint`) the
/// flipped ones with the channels swapped.
pub(super) fn filters(weight: &[f32], s: Shape, adjoint: bool) -> Vec<f32> {
    let (cout, cin) = if adjoint { (s.c, s.o) } else { (s.o, s.c) };
    let mut u = vec![0.0f32; POSITIONS * cout * cin];
    for o in 0..s.o {
        for c in 0..s.c {
            let w = &weight[(o * s.c + c) * 9..][..9];
            let (tile, row, col) = if adjoint {
                (filter_tile(|a, b| w[(2 - a) * 3 + 2 - b]), c, o)
            } else {
                (filter_tile(|a, b| w[a * 3 + b]), o, c)
            };
            for (xi, value) in tile.iter().flatten().enumerate() {
                u[(xi * cout + row) * cin + col] = *value;
            }
        }
    }
    u
}

/// Scratch elements [`forward_image`] and [`weight_gradient_image`] need for one image of the
/// direction `tiles`: its transformed inputs and products, and the transforms' working space.
pub(super) fn scratch_len(tiles: &Tiles) -> usize {
    POSITIONS * (tiles.cin + tiles.cout) * tiles.columns() + tiles.temp_len()
}

/// `y_b = conv(x_b)` for one image of the direction `tiles` (`[cout, ho, wo]`, written whole)
/// with the filters `u` of [`filters`], in `scratch` of [`scratch_len`]. One image at a time:
/// the tiles of several images side by side made longer products, but ones whose operands
/// left the cache (5.8-5.9 against 4.9-5.2 ms at 16^2 and 128 channels, batch 8, one core).
pub(super) fn forward_image(
    x_b: &[f32],
    u: &[f32],
    tiles: &Tiles,
    y_b: &mut [MaybeUninit<f32>],
    scratch: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (cin, cout, t) = (tiles.cin, tiles.cout, tiles.columns());
    let (v, rest) = scratch.split_at_mut(POSITIONS * cin * t);
    let (m, temp) = rest.split_at_mut(POSITIONS * cout * t);
    tiles.input_tiles(x_b, v, temp);
    for xi in 0..POSITIONS {
        // SAFETY: `U_xi` is `[cout, cin]`, `V_xi` `[cin, t]`, `M_xi` `[cout, t]`, each inside
        // its buffer; `M_xi` is written whole.
        unsafe {
            matmul(
                rows_out(&mut m[xi * cout * t..][..cout * t], t),
                false,
                (cout, cin, t),
                rows(&u[xi * cout * cin..][..cout * cin], cin),
                rows(&v[xi * cin * t..][..cin * t], t),
                parallelism,
            )
        };
    }
    tiles.output_tiles(m, y_b, temp);
}

/// Elements of the weight gradient's accumulator `dU^T` (`[16, c, o]`) for the forward
/// direction `tiles`.
pub(super) fn gradient_len(tiles: &Tiles) -> usize {
    POSITIONS * tiles.cin * tiles.cout
}

/// `dU^T_xi += V_xi (A g_b A^T)_xi^T` for one image into `du_t` ([`gradient_len`]) of the
/// forward direction `tiles`, in `scratch` of [`scratch_len`].
pub(super) fn weight_gradient_image(
    x_b: &[f32],
    g_b: &[f32],
    tiles: &Tiles,
    du_t: &mut [f32],
    scratch: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (cin, cout, t) = (tiles.cin, tiles.cout, tiles.columns());
    let (v, rest) = scratch.split_at_mut(POSITIONS * cin * t);
    let (dm, temp) = rest.split_at_mut(POSITIONS * cout * t);
    tiles.input_tiles(x_b, v, temp);
    tiles.output_gradient_tiles(g_b, dm, temp);
    for xi in 0..POSITIONS {
        // SAFETY: `V_xi` is `[cin, t]`, `dM_xi^T` `[t, cout]`, the destination `[cin, cout]`
        // inside `du_t`, initialised.
        unsafe {
            matmul(
                rows_out(&mut du_t[xi * cin * cout..][..cin * cout], cout),
                true,
                (cin, t, cout),
                rows(&v[xi * cin * t..][..cin * t], t),
                transposed(&dm[xi * cout * t..][..cout * t], t),
                parallelism,
            )
        };
    }
}

/// `dW = G^T dU G` from the accumulated `du_t` (`[16, c, o]`): the weight gradient `[o, c, 3,
/// 3]`.
pub(super) fn filter_gradient(du_t: &[f32], s: Shape) -> Vec<f32> {
    // G^T q for q over one axis of the tile: [q0 + (q1 + q2) / 2, (q1 - q2) / 2,
    // (q1 + q2) / 2 + q3].
    let apply = |q: [f32; 4]| {
        [
            q[0] + 0.5 * (q[1] + q[2]),
            0.5 * (q[1] - q[2]),
            0.5 * (q[1] + q[2]) + q[3],
        ]
    };
    let mut dw = vec![0.0f32; s.o * s.c * 9];
    for o in 0..s.o {
        for c in 0..s.c {
            let at = |a: usize, b: usize| du_t[((a * 4 + b) * s.c + c) * s.o + o];
            // G^T dU: down each column, then along the rows.
            let columns = [0, 1, 2, 3].map(|b| apply([at(0, b), at(1, b), at(2, b), at(3, b)]));
            let w = &mut dw[(o * s.c + c) * 9..][..9];
            for (u, row) in w.chunks_exact_mut(3).enumerate() {
                let along = [columns[0][u], columns[1][u], columns[2][u], columns[3][u]];
                row.copy_from_slice(&apply(along));
            }
        }
    }
    dw
}
