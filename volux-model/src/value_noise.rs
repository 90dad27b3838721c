//! Seeded 3D value noise: smooth, deterministic, in `[-1, 1]`. One home for two users: the
//! synthetic heads' skin and hair texture (volux-data) and the upsampler's surface-anchored
//! noise inputs ([`crate::upsampler_noise`]).

/// A lattice hash of integer coordinates and a seed, in `[-1, 1]`.
fn lattice(seed: u64, x: i64, y: i64, z: i64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 31;
    (h >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// Value noise at `p` (lattice spacing 1), quintic interpolation so that it is C2.
pub fn value_noise(seed: u64, p: [f64; 3]) -> f64 {
    let cell = p.map(|c| c.floor());
    let f = std::array::from_fn::<f64, 3, _>(|k| p[k] - cell[k]);
    let s = f.map(|t| t * t * t * (t * (t * 6.0 - 15.0) + 10.0));
    let [x0, y0, z0] = cell.map(|c| c as i64);
    let mut acc = 0.0;
    for corner in 0..8 {
        let (dx, dy, dz) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
        let w = (if dx == 1 { s[0] } else { 1.0 - s[0] })
            * (if dy == 1 { s[1] } else { 1.0 - s[1] })
            * (if dz == 1 { s[2] } else { 1.0 - s[2] });
        acc += w * lattice(seed, x0 + dx, y0 + dy, z0 + dz);
    }
    acc
}

/// Fractal sum of `octaves` octaves of value noise at base frequency `frequency`, normalised to
/// `[-1, 1]`.
pub fn fbm(seed: u64, p: [f64; 3], frequency: f64, octaves: u32) -> f64 {
    let (mut sum, mut norm, mut amp, mut freq) = (0.0, 0.0, 1.0, frequency);
    for o in 0..octaves {
        sum += amp * value_noise(seed.wrapping_add(u64::from(o)), p.map(|c| c * freq));
        norm += amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    sum / norm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_bounded_continuous_and_seeded() {
        let mut prev = value_noise(7, [0.0, 0.3, 0.1]);
        let mut spread = (f64::MAX, f64::MIN);
        for i in 1..4000 {
            let p = [i as f64 * 1e-3, 0.3, 0.1];
            let v = value_noise(7, p);
            assert!((-1.0..=1.0).contains(&v));
            assert!((v - prev).abs() < 5e-3, "jump at {i}");
            spread = (spread.0.min(v), spread.1.max(v));
            prev = v;
        }
        assert!(spread.1 - spread.0 > 0.5, "flat noise {spread:?}");
        assert_eq!(
            value_noise(3, [1.5, 2.5, 3.5]),
            value_noise(3, [1.5, 2.5, 3.5])
        );
        assert_ne!(
            value_noise(3, [1.5, 2.5, 3.5]),
            value_noise(4, [1.5, 2.5, 3.5])
        );
    }
}
