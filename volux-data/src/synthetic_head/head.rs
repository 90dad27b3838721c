//! The head as a signed distance: smooth unions of ellipsoids, spheres and capsules (cranium,
//! jaw, chin, cheekbones, brow ridge, nose, lips, ears, neck), carved eye sockets with eyeballs,
//! and a hair cap; and the material (albedo, per-region specular weights, skin fraction) at a
//! surface point.

use super::identity::HeadIdentity;
use super::scalar::{Dual, Scalar};
use super::sdf::{V3, capsule, ellipsoid, min, offset, plane, smax, smin, sphere};
use volux_model::value_noise::fbm;

/// Everything in the head lies inside this sphere about the origin (the neck is cut by it).
pub const BOUNDING_RADIUS: f64 = 0.95;

/// Which part a surface point belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Region {
    Skin,
    Eye,
    Hair,
}

/// The surface material at a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    /// Linear albedo.
    pub albedo: [f64; 3],
    /// Weights of the Phong lobes 1, 16, 32, 64 in the specular layer.
    pub specular: [f64; 4],
    /// How much of the surface scatters light under it (skin 1, lips less, eyes and hair 0).
    pub skin: f64,
    pub region: Region,
}

/// Signed distances of the head's parts at a point.
#[derive(Clone, Copy, Debug)]
pub struct Parts<S> {
    pub skin: S,
    pub eyes: S,
    pub hair: S,
    pub lips: S,
    pub nose: S,
}

/// A synthetic head: an identity turned into placed primitives.
#[derive(Clone, Debug)]
pub struct SyntheticHead {
    identity: HeadIdentity,
    skull_centre: [f64; 3],
    jaw_centre: [f64; 3],
    chin_centre: [f64; 3],
    cheek_centres: [[f64; 3]; 2],
    cheek_radii: [f64; 3],
    eye_centres: [[f64; 3]; 2],
    socket_centres: [[f64; 3]; 2],
    socket_radii: [f64; 3],
    brow_ends: [[f64; 3]; 3],
    nose_bridge: [f64; 3],
    nose_tip: [f64; 3],
    nose_wings: [[f64; 3]; 2],
    lip_centres: [[f64; 3]; 2],
    lip_radii: [[f64; 3]; 2],
    slit_centre: [f64; 3],
    slit_radii: [f64; 3],
    ear_centres: [[f64; 3]; 2],
    ear_radii: [f64; 3],
    neck: [[f64; 3]; 2],
    hair_radii: [f64; 3],
    hair_plane: ([f64; 3], [f64; 3]),
}

impl SyntheticHead {
    pub fn new(identity: HeadIdentity) -> SyntheticHead {
        let id = &identity;
        let skull_centre = [0.0, 0.07, -0.03];
        let jaw_centre = [0.0, -0.11, 0.05];
        // Front (+z) of an ellipsoid at (x, y), or its centre's depth outside its silhouette.
        let front = |c: [f64; 3], r: [f64; 3], x: f64, y: f64| {
            let q = 1.0 - (x / r[0]).powi(2) - ((y - c[1]) / r[1]).powi(2);
            c[2] + r[2] * q.max(0.0).sqrt()
        };
        let face_front = |x: f64, y: f64| {
            front(skull_centre, id.skull_radii, x, y).max(front(jaw_centre, id.jaw_radii, x, y))
        };
        let chin_centre = [
            0.0,
            jaw_centre[1] - 0.85 * id.jaw_radii[1],
            jaw_centre[2] + 0.5 * id.jaw_radii[2] + id.chin_forward,
        ];
        let cheek_z = face_front(id.cheek_x, -0.04) - 0.7 * id.cheek_size;
        let cheek_centres = [[-id.cheek_x, -0.04, cheek_z], [id.cheek_x, -0.04, cheek_z]];
        let cheek_radii = [id.cheek_size, 0.8 * id.cheek_size, 0.8 * id.cheek_size];
        let eye_front = face_front(id.eye_x, id.eye_y);
        let eye_z = eye_front - 0.008 - id.eye_radius;
        let eye_centres = [[-id.eye_x, id.eye_y, eye_z], [id.eye_x, id.eye_y, eye_z]];
        let socket_z = eye_front + 0.01;
        let socket_centres = [
            [-id.eye_x, id.eye_y, socket_z],
            [id.eye_x, id.eye_y, socket_z],
        ];
        let socket_radii = [1.45 * id.eye_radius, 0.72 * id.eye_radius, id.socket_depth];
        let brow_y = id.eye_y + id.brow_lift;
        let brow_x = 1.3 * id.eye_x;
        let brow_point = |x: f64, y: f64| [x, y, face_front(x, y) - 0.7 * id.brow_prominence];
        let brow_ends = [
            brow_point(-brow_x, brow_y - 0.006),
            brow_point(0.0, brow_y),
            brow_point(brow_x, brow_y - 0.006),
        ];
        let nose_bridge = [0.0, id.eye_y - 0.005, face_front(0.0, id.eye_y) - 0.008];
        let tip_y = id.eye_y - id.nose_length;
        let nose_tip = [
            0.0,
            tip_y,
            face_front(0.0, tip_y) + id.nose_projection - 0.03,
        ];
        let nose_wings = [
            [-id.nose_width, tip_y - 0.008, nose_tip[2] - 0.045],
            [id.nose_width, tip_y - 0.008, nose_tip[2] - 0.045],
        ];
        let lip_z = face_front(0.0, id.mouth_y) - 0.012;
        let lip_centres = [
            [0.0, id.mouth_y + 0.8 * id.lip_fullness, lip_z],
            [0.0, id.mouth_y - 0.9 * id.lip_fullness, lip_z - 0.004],
        ];
        let lip_radii = [
            [id.lip_width, id.lip_fullness, 0.03],
            [0.9 * id.lip_width, 1.1 * id.lip_fullness, 0.03],
        ];
        let slit_centre = [0.0, id.mouth_y, lip_z + 0.03];
        let slit_radii = [1.05 * id.lip_width, 0.003, 0.03];
        let ear_x = id.skull_radii[0] - 0.005;
        let ear_centres = [
            [-ear_x, id.eye_y - 0.03, -0.02],
            [ear_x, id.eye_y - 0.03, -0.02],
        ];
        let ear_radii = [0.025, id.ear_size, 0.6 * id.ear_size];
        let neck = [[0.0, -0.15, -0.05], [0.0, -0.9, -0.09]];
        let hair_radii = id.skull_radii.map(|r| r + id.hair_thickness);
        // The hairline runs from the forehead down to the nape: a plane through the hairline's
        // front point tilted so that it reaches 0.15 below the origin at the back of the head.
        let hair_front = [0.0, id.hairline, face_front(0.0, id.hairline)];
        let back = [0.0, -0.15, skull_centre[2] - id.skull_radii[2]];
        let (dy, dz) = (hair_front[1] - back[1], hair_front[2] - back[2]);
        let len = (dy * dy + dz * dz).sqrt();
        let hair_plane = (hair_front, [0.0, dz / len, -dy / len]);
        SyntheticHead {
            skull_centre,
            jaw_centre,
            chin_centre,
            cheek_centres,
            cheek_radii,
            eye_centres,
            socket_centres,
            socket_radii,
            brow_ends,
            nose_bridge,
            nose_tip,
            nose_wings,
            lip_centres,
            lip_radii,
            slit_centre,
            slit_radii,
            ear_centres,
            ear_radii,
            neck,
            hair_radii,
            hair_plane,
            identity,
        }
    }

    /// The head of `seed`.
    pub fn from_seed(seed: u64) -> SyntheticHead {
        SyntheticHead::new(HeadIdentity::from_seed(seed))
    }

    pub fn identity(&self) -> &HeadIdentity {
        &self.identity
    }

    /// Signed distances of the parts at `p`.
    pub fn parts<S: Scalar>(&self, p: V3<S>) -> Parts<S> {
        let id = &self.identity;
        let mut skin = smin(
            ellipsoid(p, self.skull_centre, id.skull_radii),
            ellipsoid(p, self.jaw_centre, id.jaw_radii),
            0.1,
        );
        skin = smin(skin, sphere(p, self.chin_centre, id.chin_radius), 0.06);
        for c in self.cheek_centres {
            skin = smin(skin, ellipsoid(p, c, self.cheek_radii), 0.05);
        }
        for c in self.socket_centres {
            skin = smax(skin, -ellipsoid(p, c, self.socket_radii), 0.02);
        }
        for pair in self.brow_ends.windows(2) {
            let brow = capsule(p, pair[0], pair[1], id.brow_prominence, id.brow_prominence);
            skin = smin(skin, brow, 0.04);
        }
        let mut nose = capsule(p, self.nose_bridge, self.nose_tip, 0.012, 0.022);
        nose = smin(nose, sphere(p, self.nose_tip, 0.026), 0.02);
        for c in self.nose_wings {
            nose = smin(nose, sphere(p, c, 0.022), 0.02);
        }
        skin = smin(skin, nose, 0.025);
        let lips = min(
            ellipsoid(p, self.lip_centres[0], self.lip_radii[0]),
            ellipsoid(p, self.lip_centres[1], self.lip_radii[1]),
        );
        skin = smin(skin, lips, 0.015);
        skin = smax(
            skin,
            -ellipsoid(p, self.slit_centre, self.slit_radii),
            0.004,
        );
        for c in self.ear_centres {
            skin = smin(skin, ellipsoid(p, c, self.ear_radii), 0.02);
        }
        skin = smin(
            skin,
            capsule(
                p,
                self.neck[0],
                self.neck[1],
                id.neck_radius,
                id.neck_radius,
            ),
            0.08,
        );
        let eyes = min(
            sphere(p, self.eye_centres[0], id.eye_radius),
            sphere(p, self.eye_centres[1], id.eye_radius),
        );
        let hair = if id.hair_thickness > 0.0 {
            let shell = ellipsoid(p, self.skull_centre, self.hair_radii);
            smax(shell, -plane(p, self.hair_plane.0, self.hair_plane.1), 0.02)
        } else {
            S::cst(f64::INFINITY)
        };
        Parts {
            skin,
            eyes,
            hair,
            lips,
            nose,
        }
    }

    /// Signed distance of the whole head (a bound: sphere tracing steps by a fraction of it).
    pub fn distance<S: Scalar>(&self, p: V3<S>) -> S {
        let parts = self.parts(p);
        min(min(parts.skin, parts.eyes), parts.hair)
    }

    /// The exact gradient of [`Self::distance`] at `p` (forward-mode derivatives).
    pub fn gradient(&self, p: [f64; 3]) -> [f64; 3] {
        self.distance(Dual::point(p)).d
    }

    /// The material at surface point `p`.
    pub fn material(&self, p: [f64; 3]) -> Material {
        let id = &self.identity;
        let parts = self.parts(p);
        if parts.eyes <= parts.skin.min(parts.hair) {
            return self.eye_material(p);
        }
        if parts.hair < parts.skin {
            // Strands run roughly down the head: noise stretched along y.
            let strands = fbm(
                id.texture_seed ^ 0x4A1,
                [p[0] * 70.0, p[1] * 6.0, p[2] * 70.0],
                1.0,
                3,
            );
            let shade = 0.8 + 0.35 * strands;
            return Material {
                albedo: id.hair.map(|c| c * shade),
                specular: [0.0, 0.03, 0.015, 0.0],
                skin: 0.0,
                region: Region::Hair,
            };
        }
        let seed = id.texture_seed;
        let blotch = 1.0 + id.blotchiness * fbm(seed, p, 10.0, 3);
        let pores = 1.0 + 0.03 * fbm(seed ^ 0x9E37, p, 90.0, 2);
        let mut albedo = id.skin.map(|c| c * blotch * pores);
        // Redness on the cheeks and the nose tip.
        let bump = |c: [f64; 3], s: f64| {
            let q = offset(p, c);
            (-(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) / (2.0 * s * s)).exp()
        };
        let flush = id.redness
            * (bump(self.cheek_centres[0], 0.05)
                + bump(self.cheek_centres[1], 0.05)
                + 0.6 * bump(self.nose_tip, 0.03));
        albedo = [
            albedo[0] * (1.0 + 0.5 * flush),
            albedo[1] * (1.0 - 0.25 * flush),
            albedo[2] * (1.0 - 0.2 * flush),
        ];
        let oily = if p[1] > id.eye_y + id.brow_lift || parts.nose < 0.006 {
            1.6
        } else {
            1.0
        };
        let mut specular = [0.0, 0.06, 0.035, 0.012].map(|w| w * id.oiliness * oily);
        let mut skin = 1.0;
        // Lips: where the lip ellipsoids carry the surface.
        let lip = (1.0 - parts.lips / 0.006).clamp(0.0, 1.0);
        if lip > 0.0 {
            albedo = std::array::from_fn(|k| albedo[k] * (1.0 - lip) + id.lips[k] * lip);
            let wet = [0.0, 0.08, 0.08, 0.05];
            specular = std::array::from_fn(|k| specular[k] * (1.0 - lip) + wet[k] * lip);
            skin = 1.0 - 0.4 * lip;
        }
        // Eyebrows: a band just above the brow ridge's axis, on the front of the face.
        let brow = self.brow_weight(p);
        if brow > 0.0 {
            albedo = std::array::from_fn(|k| albedo[k] * (1.0 - brow) + id.brows[k] * brow);
            specular = specular.map(|w| w * (1.0 - 0.7 * brow));
        }
        Material {
            albedo,
            specular,
            skin,
            region: Region::Skin,
        }
    }

    /// Coverage of eyebrow hair at `p`, in `[0, 1]`.
    fn brow_weight(&self, p: [f64; 3]) -> f64 {
        let id = &self.identity;
        if p[2] < 0.1 || p[0].abs() < 0.025 {
            return 0.0;
        }
        let lift = [0.0, 0.6 * id.brow_prominence, 0.0];
        let mut d = f64::INFINITY;
        for pair in self.brow_ends.windows(2) {
            let a = std::array::from_fn(|k| pair[0][k] + lift[k]);
            let b = std::array::from_fn(|k| pair[1][k] + lift[k]);
            d = d.min(capsule(p, a, b, 0.0, 0.0));
        }
        let half_height = id.brow_prominence + 0.006;
        ((half_height - d) / 0.006).clamp(0.0, 1.0)
    }

    fn eye_material(&self, p: [f64; 3]) -> Material {
        let id = &self.identity;
        let c = if p[0] < 0.0 {
            self.eye_centres[0]
        } else {
            self.eye_centres[1]
        };
        let q = offset(p, c);
        let cos = q[2] / (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
        let angle = cos.clamp(-1.0, 1.0).acos();
        let albedo = if angle < 0.2 {
            [0.01, 0.01, 0.01]
        } else if angle < 0.5 {
            let limbus = ((angle - 0.42) / 0.08).clamp(0.0, 1.0);
            id.iris.map(|v| v * (1.0 - 0.7 * limbus))
        } else {
            [0.62, 0.58, 0.55]
        };
        Material {
            albedo,
            specular: [0.0, 0.0, 0.1, 0.7],
            skin: 0.0,
            region: Region::Eye,
        }
    }
}
