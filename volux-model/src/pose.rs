//! A camera pose on the orbit around the head (docs/conventions.md, "World and camera").
//!
//! Radians everywhere inside the program; degrees appear only where a person types or reads
//! them (CLI flags, printed tables), converted at that edge.

/// Where the camera sits: `yaw` turns it about +y towards +x, `pitch` raises it (it then looks
/// down); `(0, 0)` is at +z looking along -z, at the face. Both in radians; the pitch lies
/// strictly between -pi/2 and pi/2.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    pub yaw: f64,
    pub pitch: f64,
}

impl Pose {
    /// The frontal view.
    pub const FRONTAL: Pose = Pose {
        yaw: 0.0,
        pitch: 0.0,
    };

    /// A pose from radians.
    pub const fn new(yaw: f64, pitch: f64) -> Pose {
        Pose { yaw, pitch }
    }

    /// A pose from degrees (what the CLI takes).
    pub fn from_degrees(yaw: f64, pitch: f64) -> Pose {
        Pose::new(yaw.to_radians(), pitch.to_radians())
    }

    /// Whether both angles are finite numbers.
    pub fn is_finite(self) -> bool {
        self.yaw.is_finite() && self.pitch.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degrees_convert_to_radians() {
        let p = Pose::from_degrees(90.0, -45.0);
        assert!((p.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-15);
        assert!((p.pitch + std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        assert_eq!(Pose::FRONTAL, Pose::new(0.0, 0.0));
        assert!(!Pose::new(f64::NAN, 0.0).is_finite());
    }
}
