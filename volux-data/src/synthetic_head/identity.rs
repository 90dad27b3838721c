//! A head's identity: the shape and appearance parameters that one seed fixes.
//!
//! Lengths are in world units (the head fits the unit sphere, faces +z, +y up; 1 unit is about
//! 30 cm); colours are linear albedo. Every parameter is drawn uniformly from a range that keeps
//! the parts attached and the face plausible; the ranges are in [`HeadIdentity::from_seed`].

use volux_envmap::random::SplitMix64;

/// Shape and appearance of one synthetic head.
#[derive(Clone, Debug, PartialEq)]
pub struct HeadIdentity {
    /// Cranium ellipsoid radii (width, height, depth).
    pub skull_radii: [f64; 3],
    /// Lower face ellipsoid: half-width at the jaw, half-height, half-depth.
    pub jaw_radii: [f64; 3],
    /// Chin sphere radius and how far forward it sits.
    pub chin_radius: f64,
    pub chin_forward: f64,
    /// Cheekbone x offset and size.
    pub cheek_x: f64,
    pub cheek_size: f64,
    /// Eye centres at `(+-eye_x, eye_y)`, eyeball radius, and how deep the sockets are carved.
    pub eye_x: f64,
    pub eye_y: f64,
    pub eye_radius: f64,
    pub socket_depth: f64,
    /// Height of the brow ridge above the eyes and its prominence.
    pub brow_lift: f64,
    pub brow_prominence: f64,
    /// Nose: length from bridge to tip, projection of the tip, half-width of the wings.
    pub nose_length: f64,
    pub nose_projection: f64,
    pub nose_width: f64,
    /// Mouth height, half-width of the lips, lip fullness.
    pub mouth_y: f64,
    pub lip_width: f64,
    pub lip_fullness: f64,
    /// Ear half-height.
    pub ear_size: f64,
    pub neck_radius: f64,
    /// Hair cap thickness (0: bald) and hairline height at the forehead.
    pub hair_thickness: f64,
    pub hairline: f64,
    pub skin: [f64; 3],
    /// Strength of the cheeks' redness and of the skin's blotchy variation.
    pub redness: f64,
    pub blotchiness: f64,
    /// Scales the skin's specular weights (oily skin shines more).
    pub oiliness: f64,
    pub lips: [f64; 3],
    pub hair: [f64; 3],
    pub brows: [f64; 3],
    pub iris: [f64; 3],
    /// Seed of the skin and hair texture noise.
    pub texture_seed: u64,
}

/// Skin albedos from light to deep (linear RGB), interpolated by the identity's tone.
const SKIN_TONES: [[f64; 3]; 5] = [
    [0.72, 0.52, 0.42],
    [0.60, 0.41, 0.31],
    [0.45, 0.29, 0.20],
    [0.29, 0.17, 0.11],
    [0.15, 0.09, 0.06],
];

/// Natural hair colours (linear): black, dark brown, brown, blond, red, grey.
const HAIR_COLOURS: [[f64; 3]; 6] = [
    [0.018, 0.014, 0.012],
    [0.045, 0.026, 0.016],
    [0.11, 0.06, 0.03],
    [0.42, 0.30, 0.15],
    [0.30, 0.09, 0.035],
    [0.40, 0.39, 0.37],
];

/// Iris colours: brown, dark brown, hazel, green, blue, grey.
const IRIS_COLOURS: [[f64; 3]; 6] = [
    [0.10, 0.05, 0.02],
    [0.04, 0.02, 0.01],
    [0.18, 0.12, 0.04],
    [0.10, 0.16, 0.07],
    [0.08, 0.15, 0.28],
    [0.18, 0.20, 0.22],
];

impl HeadIdentity {
    /// The identity of `seed`: the same seed always gives the same head.
    pub fn from_seed(seed: u64) -> HeadIdentity {
        // Decorrelate neighbouring seeds before drawing.
        let mut rng = SplitMix64::new(seed ^ 0x5EED_4EAD_0FF0_0D00_u64);
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
        let skull_radii = [u(0.25, 0.29), u(0.29, 0.33), u(0.31, 0.35)];
        let jaw_radii = [u(0.18, 0.23), u(0.22, 0.26), u(0.2, 0.23)];
        let chin_radius = u(0.055, 0.08);
        let chin_forward = u(0.0, 0.02);
        let cheek_x = u(0.11, 0.14);
        let cheek_size = u(0.06, 0.085);
        let eye_x = u(0.095, 0.115);
        let eye_y = u(0.0, 0.04);
        let eye_radius = u(0.038, 0.045);
        let socket_depth = u(0.035, 0.055);
        let brow_lift = u(0.055, 0.075);
        let brow_prominence = u(0.02, 0.035);
        let nose_length = u(0.09, 0.13);
        let nose_projection = u(0.06, 0.1);
        let nose_width = u(0.025, 0.04);
        let mouth_y = u(-0.2, -0.17);
        let lip_width = u(0.045, 0.065);
        let lip_fullness = u(0.014, 0.024);
        let ear_size = u(0.06, 0.08);
        let neck_radius = u(0.11, 0.14);
        let bald = u(0.0, 1.0) < 0.08;
        let hair_thickness = if bald { 0.0 } else { u(0.015, 0.06) };
        let hairline = u(0.14, 0.24);
        let tone = u(0.0, 1.0) * (SKIN_TONES.len() - 1) as f64;
        let (i, f) = (tone.floor() as usize, tone.fract());
        let j = (i + 1).min(SKIN_TONES.len() - 1);
        let hue = [u(0.95, 1.05), u(0.95, 1.05), u(0.93, 1.07)];
        let skin: [f64; 3] =
            std::array::from_fn(|k| (SKIN_TONES[i][k] * (1.0 - f) + SKIN_TONES[j][k] * f) * hue[k]);
        let redness = u(0.0, 0.25);
        let blotchiness = u(0.03, 0.12);
        let oiliness = u(0.5, 1.6);
        let lip_tint = [u(0.85, 1.0), u(0.45, 0.65), u(0.5, 0.7)];
        let lips = std::array::from_fn(|k| skin[k] * lip_tint[k]);
        let pick = |x: f64, n: usize| ((x * n as f64) as usize).min(n - 1);
        let hair = HAIR_COLOURS[pick(u(0.0, 1.0), HAIR_COLOURS.len())];
        let hair_shade = u(0.8, 1.2);
        let hair = hair.map(|c| c * hair_shade);
        let brows = std::array::from_fn(|k| hair[k] * 0.7 + skin[k] * 0.1);
        let iris = IRIS_COLOURS[pick(u(0.0, 1.0), IRIS_COLOURS.len())];
        let texture_seed = rng.next_u64();
        HeadIdentity {
            skull_radii,
            jaw_radii,
            chin_radius,
            chin_forward,
            cheek_x,
            cheek_size,
            eye_x,
            eye_y,
            eye_radius,
            socket_depth,
            brow_lift,
            brow_prominence,
            nose_length,
            nose_projection,
            nose_width,
            mouth_y,
            lip_width,
            lip_fullness,
            ear_size,
            neck_radius,
            hair_thickness,
            hairline,
            skin,
            redness,
            blotchiness,
            oiliness,
            lips,
            hair,
            brows,
            iris,
            texture_seed,
        }
    }
}
