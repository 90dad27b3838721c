//! The convolution's three products for one image by shifted matrix products over the
//! polyphase planes of the padded input, with no patch matrix (large planes).
//!
//! Split the zero-padded input `x_pad` (`hp x wp` per channel) by stride phase:
//! `phase[q_r, q_c][c, i', j'] = x_pad[c, i' s + q_r, j' s + q_c]`, planes of `wph =
//! ceil(wp / s)` columns. Tap `(u, v)` of output `(i, j)` reads `x_pad[c, i s + u, j s + v]`,
//! which is `phase[u % s, v % s][c, i + u / s, j + v / s]`: for all outputs at once, the
//! phase plane read from flat offset `(u / s) wph + v / s` with the outputs laid out at
//! `i wph + j`. So each tap is one product `W_uv [o, c] x window_uv [c, ho wph]` whose right
//! operand is a strided view of the planes themselves, accumulated into a `[o, ho wph]`
//! output of which the columns `j < wo` are the convolution and the `wph - wo` others are
//! discarded (they read across a row's end; nothing valid depends on them). The transposed
//! products give the adjoint (`window_uv += W_uv^T y'`, then the phases back into `x`) and
//! the weight gradient (`dW_uv^T += window_uv g'^T`), where `y'` and `g'` are the output or
//! its gradient spread to `ho wph` columns with zeros in the discarded ones.
//!
//! Against im2col + one product ([`super::patches`]) the `c k^2 x ho wo` patch matrix is
//! never written or read back (im2col and col2im were 14% of a discriminator step's
//! samples), and the planes, `k^2 / s^2` times smaller, stay in cache while the `k^2`
//! products read them; but `k^2` products with the inner dimension `c` lose to one with
//! `c k^2` once the patch matrix itself fits in cache (`kernels::Strategy`).

use std::mem::MaybeUninit;

use super::Shape;
use super::kernels::{View, matmul, rows, rows_out, tap_weight, tap_weight_t, transposed};

/// The polyphase layout of one image's padded input.
#[derive(Clone, Copy, Debug)]
pub(super) struct Phases {
    pub(super) s: Shape,
    /// Columns of a phase plane, `ceil(wp / stride)`.
    wph: usize,
    /// Rows of a phase plane, `ceil(hp / stride)`.
    hph: usize,
    /// Elements per channel of a phase plane: its rows plus the tail the last tap's window
    /// reads past the last row for the discarded columns.
    plane: usize,
}

impl Phases {
    pub(super) fn new(s: Shape) -> Self {
        let (st, p) = (s.geometry.stride, s.geometry.pad);
        let (hp, wp) = (s.h + 2 * p, s.w + 2 * p);
        let (hph, wph) = (hp.div_ceil(st), wp.div_ceil(st));
        let reach = (s.k - 1) / st;
        // The last tap's window ends at offset reach (wph + 1) + ho wph.
        let plane = (hph * wph).max(reach * (wph + 1) + s.ho * wph);
        Self { s, wph, hph, plane }
    }

    /// Output columns per image, `ho wph` (the discarded ones included).
    pub(super) fn columns(&self) -> usize {
        self.s.ho * self.wph
    }

    /// Elements of all phases of one image.
    pub(super) fn len(&self) -> usize {
        self.s.geometry.stride.pow(2) * self.s.c * self.plane
    }

    /// Whether some tap reads phase `(q_r, q_c)`.
    fn used(&self, q_r: usize, q_c: usize) -> bool {
        q_r < self.s.k && q_c < self.s.k
    }

    /// The window of tap `(u, v)`: `[c, ho wph]`, channels `plane` apart.
    fn window(&self, phases: *const f32, u: usize, v: usize) -> View {
        let st = self.s.geometry.stride;
        let q = (u % st) * st + v % st;
        let offset = q * self.s.c * self.plane + (u / st) * self.wph + v / st;
        View {
            // The offset stays inside the phases' allocation (`plane` holds the window's end).
            ptr: phases.wrapping_add(offset),
            row: self.plane as isize,
            col: 1,
        }
    }

    /// The input columns that land in column phase `q_c`: the first phase column written,
    /// the first input column, and how many (input columns `x0, x0 + st, ..` go to phase
    /// columns `j0, j0 + 1, ..`).
    fn column_run(&self, q_c: usize) -> (usize, usize, usize) {
        let (st, p, w) = (self.s.geometry.stride, self.s.geometry.pad, self.s.w);
        // Phase column j' holds padded column j' st + q_c, input column j' st + q_c - p.
        let j0 = p.saturating_sub(q_c).div_ceil(st);
        let x0 = j0 * st + q_c - p;
        let count = if x0 < w { (w - x0).div_ceil(st) } else { 0 };
        (j0, x0, count.min(self.wph.saturating_sub(j0)))
    }

    /// The input row behind phase row `ip` of row phase `q_r`, if it is not padding.
    fn input_row(&self, q_r: usize, ip: usize) -> Option<usize> {
        let (st, p) = (self.s.geometry.stride, self.s.geometry.pad);
        (ip * st + q_r).checked_sub(p).filter(|y| *y < self.s.h)
    }

    /// Writes image `x_b` (`[c, h, w]`) into `phases`: every element of the phases a tap
    /// reads is written, zero where it is padding.
    fn load(&self, x_b: &[f32], phases: &mut [f32]) {
        let (s, st) = (self.s, self.s.geometry.stride);
        for q_r in 0..st {
            for q_c in 0..st {
                if !self.used(q_r, q_c) {
                    continue;
                }
                let (j0, x0, count) = self.column_run(q_c);
                let q = q_r * st + q_c;
                for c in 0..s.c {
                    let start = (q * s.c + c) * self.plane;
                    let plane = &mut phases[start..start + self.plane];
                    plane.fill(0.0);
                    let channel = &x_b[c * s.h * s.w..(c + 1) * s.h * s.w];
                    for ip in 0..self.hph {
                        let Some(y) = self.input_row(q_r, ip) else {
                            continue;
                        };
                        if count == 0 {
                            continue;
                        }
                        let src = &channel[y * s.w + x0..(y + 1) * s.w];
                        let dst = &mut plane[ip * self.wph + j0..][..count];
                        if st == 1 {
                            dst.copy_from_slice(&src[..count]);
                        } else {
                            for (d, v) in dst.iter_mut().zip(src.iter().step_by(st)) {
                                *d = *v;
                            }
                        }
                    }
                }
            }
        }
    }

    /// The inverse of [`Self::load`] on the image's positions: `x_b[c, y, x]` from the phases
    /// (the padding is dropped). Positions in a phase no tap reads get zero.
    fn store(&self, phases: &[f32], x_b: &mut [MaybeUninit<f32>]) {
        let (s, st) = (self.s, self.s.geometry.stride);
        for q_r in 0..st {
            for q_c in 0..st {
                let (j0, x0, count) = self.column_run(q_c);
                let used = self.used(q_r, q_c);
                let q = q_r * st + q_c;
                for c in 0..s.c {
                    let plane = &phases[(q * s.c + c) * self.plane..][..self.plane];
                    let channel = &mut x_b[c * s.h * s.w..(c + 1) * s.h * s.w];
                    for ip in 0..self.hph {
                        let Some(y) = self.input_row(q_r, ip).filter(|_| count > 0) else {
                            continue;
                        };
                        let dst = &mut channel[y * s.w + x0..(y + 1) * s.w];
                        let src = &plane[ip * self.wph + j0..][..count];
                        for (d, v) in dst.iter_mut().step_by(st).zip(src) {
                            d.write(if used { *v } else { 0.0 });
                        }
                    }
                }
            }
        }
    }

    /// Zeroes the phases some tap reads or writes.
    fn clear_used(&self, phases: &mut [f32]) {
        let st = self.s.geometry.stride;
        let per_phase = self.s.c * self.plane;
        for (q, phase) in phases.chunks_exact_mut(per_phase).enumerate() {
            if self.used(q / st, q % st) {
                phase.fill(0.0);
            }
        }
    }

    /// `y_b` (`[o, ho, wo]`) spread to `[o, ho wph]` in `out`, zeros in the discarded columns.
    fn spread(&self, y_b: &[f32], out: &mut [f32]) {
        let (s, wph) = (self.s, self.wph);
        for (src, dst) in y_b.chunks_exact(s.wo).zip(out.chunks_exact_mut(wph)) {
            dst[..s.wo].copy_from_slice(src);
            dst[s.wo..].fill(0.0);
        }
    }

    /// The taps `(u, v)` in weight order.
    fn taps(&self) -> impl Iterator<Item = (usize, usize)> + use<> {
        let k = self.s.k;
        (0..k * k).map(move |t| (t / k, t % k))
    }
}

/// `y_b = conv(x_b)` for one image (`[o, ho, wo]`, written whole), in `scratch` of
/// [`Phases::len`] plus `o` [`Phases::columns`] elements.
pub(super) fn forward_image(
    x_b: &[f32],
    weight: &[f32],
    layout: &Phases,
    y_b: &mut [MaybeUninit<f32>],
    scratch: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (s, n) = (layout.s, layout.columns());
    let (phases, wide) = scratch.split_at_mut(layout.len());
    layout.load(x_b, phases);
    for (t, (u, v)) in layout.taps().enumerate() {
        // SAFETY: the tap's weight is `[o, c]` inside `weight`, its window `[c, n]` inside the
        // phases (`Phases::plane`), `wide` is `[o, n]`, written by the first tap.
        unsafe {
            matmul(
                rows_out(wide, n),
                t > 0,
                (s.o, s.c, n),
                tap_weight(weight, s, u, v),
                layout.window(phases.as_ptr(), u, v),
                parallelism,
            )
        };
    }
    for (dst, src) in y_b
        .chunks_exact_mut(s.wo)
        .zip(wide.chunks_exact(layout.wph))
    {
        for (d, v) in dst.iter_mut().zip(src) {
            d.write(*v);
        }
    }
}

/// `x_b = conv^T(y_b)` for one image (`[c, h, w]`, written whole), in `scratch` as for
/// [`forward_image`].
pub(super) fn adjoint_image(
    y_b: &[f32],
    weight: &[f32],
    layout: &Phases,
    x_b: &mut [MaybeUninit<f32>],
    scratch: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (s, n) = (layout.s, layout.columns());
    let (phases, wide) = scratch.split_at_mut(layout.len());
    layout.spread(y_b, wide);
    // The taps' windows overlap: every product adds onto zeroed phases (those no tap
    // writes are never read).
    layout.clear_used(phases);
    for (u, v) in layout.taps() {
        let window = layout.window(phases.as_mut_ptr(), u, v);
        // SAFETY: the tap's transposed weight is `[c, o]`, `wide` `[o, n]`, the window
        // `[c, n]` inside the (initialised) phases.
        unsafe {
            matmul(
                window,
                true,
                (s.c, s.o, n),
                tap_weight_t(weight, s, u, v),
                rows(wide, n),
                parallelism,
            )
        };
    }
    layout.store(phases, x_b);
}

/// `dW^T += conv-windows(x_b) g_b^T` for one image into `dw_t` (`[c k k, o]`), in `scratch`
/// as for [`forward_image`]: each tap's product `dW_uv^T += window_uv g'^T` has the long
/// inner dimension `ho wph` contiguous in the window.
pub(super) fn weight_gradient_image(
    x_b: &[f32],
    g_b: &[f32],
    layout: &Phases,
    dw_t: &mut [f32],
    scratch: &mut [f32],
    parallelism: gemm::Parallelism,
) {
    let (s, n) = (layout.s, layout.columns());
    let kk = s.k * s.k;
    let (phases, wide) = scratch.split_at_mut(layout.len());
    layout.load(x_b, phases);
    layout.spread(g_b, wide);
    for (u, v) in layout.taps() {
        // Rows `(c, u, v)` of `dw_t`: `c` at stride `k^2 o`.
        let dst = View {
            ptr: dw_t[(u * s.k + v) * s.o..].as_mut_ptr().cast_const(),
            row: (kk * s.o) as isize,
            col: 1,
        };
        // SAFETY: the window is `[c, n]` inside the phases, `wide^T` `[n, o]`, `dst` `[c, o]`
        // inside `dw_t`, initialised.
        unsafe {
            matmul(
                dst,
                true,
                (s.c, n, s.o),
                layout.window(phases.as_ptr(), u, v),
                transposed(wide, n),
                parallelism,
            )
        };
    }
}
