//! Small helpers on row-major square images: bilinear look-up at continuous pixel coordinates
//! and the error statistics every measurement reports.

use volux_envmap::Rgb;

/// Bilinear look-up of a `side x side` row-major image at pixel coordinates `(x, y)`, where
/// integer coordinates are pixel centres. `None` outside the centres' hull.
pub fn bilinear<const C: usize>(img: &[[f32; C]], side: usize, x: f64, y: f64) -> Option<[f32; C]> {
    sample(side, x, y, |i| img[i])
}

/// [`bilinear`] of a one-channel image.
pub fn bilinear1(img: &[f32], side: usize, x: f64, y: f64) -> Option<f32> {
    sample(side, x, y, |i| [img[i]]).map(|[v]| v)
}

/// The smallest of the four pixels a bilinear look-up at `(x, y)` blends (`None` outside).
pub fn neighbourhood_min(img: &[f32], side: usize, x: f64, y: f64) -> Option<f32> {
    let max = side.saturating_sub(1) as f64;
    if !(0.0..=max).contains(&x) || !(0.0..=max).contains(&y) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(side - 1), (y0 + 1).min(side - 1));
    Some(
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .iter()
            .map(|&(x, y)| img[y * side + x])
            .fold(f32::INFINITY, f32::min),
    )
}

fn sample<const C: usize>(
    side: usize,
    x: f64,
    y: f64,
    at: impl Fn(usize) -> [f32; C],
) -> Option<[f32; C]> {
    let max = side.saturating_sub(1) as f64;
    if !(0.0..=max).contains(&x) || !(0.0..=max).contains(&y) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(side - 1), (y0 + 1).min(side - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let (a, b, c, d) = (
        at(y0 * side + x0),
        at(y0 * side + x1),
        at(y1 * side + x0),
        at(y1 * side + x1),
    );
    Some(std::array::from_fn(|k| {
        let top = a[k] + fx * (b[k] - a[k]);
        let bottom = c[k] + fx * (d[k] - c[k]);
        top + fy * (bottom - top)
    }))
}

/// Running sums of absolute and squared differences of values in `[0, 1]`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ErrorSums {
    pub count: usize,
    pub abs: f64,
    pub sq: f64,
}

impl ErrorSums {
    /// Adds the channel differences of one pixel.
    pub fn add(&mut self, a: Rgb, b: Rgb) {
        for k in 0..3 {
            let d = f64::from(a[k]) - f64::from(b[k]);
            self.abs += d.abs();
            self.sq += d * d;
            self.count += 1;
        }
    }

    pub fn merge(&mut self, other: &ErrorSums) {
        self.count += other.count;
        self.abs += other.abs;
        self.sq += other.sq;
    }

    /// Mean absolute difference (0 when empty).
    pub fn l1(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.abs / self.count as f64
        }
    }

    /// Peak signal-to-noise ratio for a peak of 1, capped at [`PSNR_CAP`] (identical images).
    pub fn psnr(&self) -> f64 {
        if self.count == 0 {
            return PSNR_CAP;
        }
        psnr_of_mse(self.sq / self.count as f64)
    }
}

/// The PSNR reported for (near) identical images: JSON has no infinity.
pub const PSNR_CAP: f64 = 99.0;

/// `10 log10(1 / mse)`, capped at [`PSNR_CAP`].
pub fn psnr_of_mse(mse: f64) -> f64 {
    if mse <= 0.0 {
        PSNR_CAP
    } else {
        (-10.0 * mse.log10()).min(PSNR_CAP)
    }
}

/// Mean of a list (0 when empty).
pub fn mean(values: &[f64]) -> f64 {
    if values.is_empty() {
        0.0
    } else {
        values.iter().sum::<f64>() / values.len() as f64
    }
}

pub use volux_train::metrics::median;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_hits_pixel_centres_and_interpolates_between() {
        let img: Vec<[f32; 1]> = (0..9).map(|v| [v as f32]).collect();
        assert_eq!(bilinear(&img, 3, 1.0, 2.0), Some([7.0]));
        assert_eq!(bilinear(&img, 3, 0.5, 0.0), Some([0.5]));
        assert_eq!(bilinear(&img, 3, 0.5, 0.5), Some([2.0]));
        assert_eq!(bilinear(&img, 3, 2.0, 2.0), Some([8.0]));
        assert_eq!(bilinear(&img, 3, 2.01, 1.0), None);
        assert_eq!(bilinear(&img, 3, -0.01, 1.0), None);
        let flat: Vec<f32> = (0..9).map(|v| v as f32).collect();
        assert_eq!(bilinear1(&flat, 3, 0.5, 0.5), Some(2.0));
        assert_eq!(neighbourhood_min(&flat, 3, 1.5, 0.5), Some(1.0));
        assert_eq!(neighbourhood_min(&flat, 3, 2.0, 2.0), Some(8.0));
        assert_eq!(neighbourhood_min(&flat, 3, 3.0, 2.0), None);
    }

    #[test]
    fn psnr_and_l1_of_known_differences() {
        let mut e = ErrorSums::default();
        e.add([0.1, 0.1, 0.1], [0.2, 0.2, 0.2]);
        assert!((e.l1() - 0.1).abs() < 1e-6);
        assert!((e.psnr() - 20.0).abs() < 1e-4);
        assert_eq!(ErrorSums::default().psnr(), PSNR_CAP);
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
    }
}
