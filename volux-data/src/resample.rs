//! Square images on the host: centre crops and resizing, the one home of image resampling
//! outside Burn. [`area_downsample`] is the data pipeline's integer box filter (output to
//! volume resolution); [`resize`] takes any ratio: downsizing averages the exact area each
//! output pixel covers (a box filter with fractional weights, so any ratio keeps the image's
//! mean), enlarging interpolates bilinearly between pixel centres, edges clamped. Images are
//! row-major with `N` values per pixel.

/// The largest centred square of a `width x height` image, and its side.
pub fn centre_crop<const N: usize>(
    texels: &[[f32; N]],
    width: usize,
    height: usize,
) -> (Vec<[f32; N]>, usize) {
    let side = width.min(height);
    let (x0, y0) = ((width - side) / 2, (height - side) / 2);
    let out = (0..side)
        .flat_map(|y| {
            let row = (y0 + y) * width + x0;
            texels[row..row + side].iter().copied()
        })
        .collect();
    (out, side)
}

/// `texels` (`from x from`) resized to `to x to`: area averaging when `to <= from`, bilinear
/// otherwise.
pub fn resize<const N: usize>(texels: &[[f32; N]], from: usize, to: usize) -> Vec<[f32; N]> {
    debug_assert_eq!(texels.len(), from * from);
    if to == from {
        return texels.to_vec();
    }
    if to < from {
        resize_area(texels, from, to)
    } else {
        resize_bilinear(texels, from, to)
    }
}

/// The input pixels output pixel `i` of `to` covers along one axis, with their weights (the
/// covered length, in input pixels), summing to `from / to`.
fn coverage(i: usize, from: usize, to: usize) -> Vec<(usize, f64)> {
    let scale = from as f64 / to as f64;
    let (a, b) = (i as f64 * scale, (i + 1) as f64 * scale);
    let first = a.floor() as usize;
    let last = (b.ceil() as usize).min(from);
    (first..last)
        .map(|k| (k, (b.min((k + 1) as f64) - a.max(k as f64)).max(0.0)))
        .filter(|&(_, w)| w > 0.0)
        .collect()
}

fn resize_area<const N: usize>(texels: &[[f32; N]], from: usize, to: usize) -> Vec<[f32; N]> {
    let spans: Vec<Vec<(usize, f64)>> = (0..to).map(|i| coverage(i, from, to)).collect();
    let norm = (to as f64 / from as f64).powi(2);
    let mut out = Vec::with_capacity(to * to);
    for ys in &spans {
        for xs in &spans {
            let mut sum = [0.0f64; N];
            for &(y, wy) in ys {
                for &(x, wx) in xs {
                    let t = &texels[y * from + x];
                    for c in 0..N {
                        sum[c] += wy * wx * f64::from(t[c]);
                    }
                }
            }
            out.push(sum.map(|v| (v * norm) as f32));
        }
    }
    out
}

fn resize_bilinear<const N: usize>(texels: &[[f32; N]], from: usize, to: usize) -> Vec<[f32; N]> {
    let scale = from as f64 / to as f64;
    let taps: Vec<(usize, usize, f64)> = (0..to)
        .map(|i| {
            let p = ((i as f64 + 0.5) * scale - 0.5).clamp(0.0, (from - 1) as f64);
            let k = (p.floor() as usize).min(from - 1);
            (k, (k + 1).min(from - 1), p - k as f64)
        })
        .collect();
    let mut out = Vec::with_capacity(to * to);
    for &(y0, y1, fy) in &taps {
        for &(x0, x1, fx) in &taps {
            let at = |y: usize, x: usize| &texels[y * from + x];
            out.push(std::array::from_fn(|c| {
                let top = f64::from(at(y0, x0)[c]) * (1.0 - fx) + f64::from(at(y0, x1)[c]) * fx;
                let bottom = f64::from(at(y1, x0)[c]) * (1.0 - fx) + f64::from(at(y1, x1)[c]) * fx;
                (top * (1.0 - fy) + bottom * fy) as f32
            }));
        }
    }
    out
}

/// Box-filter downsampling of a square `side x side` layer by `factor`.
pub fn area_downsample(layer: &[[f32; 3]], side: usize, factor: usize) -> Vec<[f32; 3]> {
    let lo = side / factor;
    let scale = 1.0 / (factor * factor) as f32;
    let mut out = vec![[0.0f32; 3]; lo * lo];
    for y in 0..lo * factor {
        for x in 0..lo * factor {
            let o = &mut out[(y / factor) * lo + x / factor];
            let v = layer[y * side + x];
            for k in 0..3 {
                o[k] += v[k] * scale;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(side: usize) -> Vec<[f32; 2]> {
        (0..side * side)
            .map(|i| [(i % side) as f32, ((i / side) * (i % 7)) as f32])
            .collect()
    }

    #[test]
    fn integer_factors_average_blocks() {
        let src = ramp(12);
        let got = resize(&src, 12, 4);
        for (i, g) in got.iter().enumerate() {
            let (oy, ox) = (i / 4, i % 4);
            for c in 0..2 {
                let mut sum = 0.0;
                for y in 0..3 {
                    for x in 0..3 {
                        sum += src[(oy * 3 + y) * 12 + ox * 3 + x][c];
                    }
                }
                assert!((g[c] - sum / 9.0).abs() < 1e-4, "{i} {c}");
            }
        }
    }

    #[test]
    fn any_ratio_keeps_the_mean() {
        for (from, to) in [(37, 16), (100, 64), (65, 64), (257, 3)] {
            let src = ramp(from);
            let got = resize(&src, from, to);
            for c in 0..2 {
                let a: f64 =
                    src.iter().map(|t| f64::from(t[c])).sum::<f64>() / (from * from) as f64;
                let b: f64 = got.iter().map(|t| f64::from(t[c])).sum::<f64>() / (to * to) as f64;
                assert!(
                    (a - b).abs() < 1e-4 * a.abs().max(1.0),
                    "{from}->{to}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn enlarging_interpolates_and_keeps_constants() {
        let flat = vec![[0.25f32; 3]; 9];
        assert!(resize(&flat, 3, 10).iter().all(|t| *t == [0.25; 3]));
        // A horizontal ramp 0, 1 enlarged 2x: centres at -0.25 and 0.25 clamp, 0.75 ... .
        let src = vec![[0.0f32], [1.0], [0.0], [1.0]];
        let got = resize(&src, 2, 4);
        let row: Vec<f32> = got[..4].iter().map(|t| t[0]).collect();
        assert_eq!(row, vec![0.0, 0.25, 0.75, 1.0]);
    }

    #[test]
    fn crops_keep_the_centre() {
        let src: Vec<[f32; 1]> = (0..12).map(|i| [i as f32]).collect();
        let (wide, side) = centre_crop(&src, 4, 3);
        assert_eq!(side, 3);
        assert_eq!(
            wide.iter().map(|t| t[0]).collect::<Vec<_>>(),
            vec![0.0, 1.0, 2.0, 4.0, 5.0, 6.0, 8.0, 9.0, 10.0]
        );
        let (tall, side) = centre_crop(&src, 2, 6);
        assert_eq!(side, 2);
        assert_eq!(
            tall.iter().map(|t| t[0]).collect::<Vec<_>>(),
            vec![4.0, 5.0, 6.0, 7.0]
        );
    }

    #[test]
    fn area_downsampling_averages_blocks() {
        let layer: Vec<[f32; 3]> = (0..16).map(|i| [i as f32, 1.0, -(i as f32)]).collect();
        let lo = area_downsample(&layer, 4, 2);
        assert_eq!(lo.len(), 4);
        // Block (0, 0): pixels 0, 1, 4, 5.
        assert_eq!(lo[0], [2.5, 1.0, -2.5]);
        assert_eq!(lo[3], [12.5, 1.0, -12.5]);
        // The integer box filter is `resize`'s area path at an integer ratio.
        let image: Vec<[f32; 3]> = (0..36)
            .map(|i| [(i * i % 11) as f32, 0.5, i as f32])
            .collect();
        for (a, b) in area_downsample(&image, 6, 3)
            .iter()
            .zip(resize(&image, 6, 2))
        {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-5, "{a:?} {b:?}");
            }
        }
    }
}
