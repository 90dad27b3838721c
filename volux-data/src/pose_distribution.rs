//! The distribution training poses are drawn from (docs/conventions.md, "World and camera"): independent
//! Gaussians on yaw and pitch, pi-GAN's CelebA values by default, truncated at three standard
//! deviations so that no draw looks at the back of the head.

use volux_envmap::random::SplitMix64;
use volux_model::pose::Pose;

use crate::folder_dataset::MAX_YAW;

/// Gaussian yaw and pitch, radians.
#[derive(Clone, Copy, Debug, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PoseDistribution {
    pub yaw_mean: f64,
    pub yaw_sd: f64,
    pub pitch_mean: f64,
    pub pitch_sd: f64,
}

impl Default for PoseDistribution {
    fn default() -> Self {
        PoseDistribution {
            yaw_mean: 0.0,
            yaw_sd: 0.3,
            pitch_mean: 0.0,
            pitch_sd: 0.155,
        }
    }
}

/// Draws beyond this many standard deviations are redrawn.
const TRUNCATION: f64 = 3.0;

impl PoseDistribution {
    /// One draw.
    pub fn sample(&self, rng: &mut SplitMix64) -> Pose {
        Pose::new(
            self.yaw_mean + self.yaw_sd * truncated_normal(rng),
            self.pitch_mean + self.pitch_sd * truncated_normal(rng),
        )
    }

    /// Checks that the values are finite, the deviations non-negative and every draw (within
    /// the truncation) a pose `poses.csv` accepts: a yaw within `[-2 pi, 2 pi]`
    /// ([`MAX_YAW`]) and a pitch strictly between `-pi/2` and `pi/2` (past it the camera turns
    /// over; a deviation of 1e308 overflowed the draws to infinity). Names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        let fields = [
            ("yaw_mean", self.yaw_mean),
            ("yaw_sd", self.yaw_sd),
            ("pitch_mean", self.pitch_mean),
            ("pitch_sd", self.pitch_sd),
        ];
        for (name, v) in fields {
            if !v.is_finite() || (name.ends_with("_sd") && v < 0.0) {
                return Err(format!(
                    "{name} = {v:?} must be finite{}",
                    if name.ends_with("_sd") {
                        " and >= 0"
                    } else {
                        ""
                    }
                ));
            }
        }
        let yaw_reach = self.yaw_mean.abs() + TRUNCATION * self.yaw_sd;
        if yaw_reach > MAX_YAW {
            return Err(format!(
                "yaw_mean = {:?} and yaw_sd = {:?} draw yaws up to {yaw_reach:.4e} radians ({TRUNCATION} sd): every draw must lie within [-2 pi, 2 pi]",
                self.yaw_mean, self.yaw_sd
            ));
        }
        let pitch_reach = self.pitch_mean.abs() + TRUNCATION * self.pitch_sd;
        if pitch_reach >= std::f64::consts::FRAC_PI_2 {
            return Err(format!(
                "pitch_mean = {:?} and pitch_sd = {:?} draw pitches up to {pitch_reach:.4e} radians ({TRUNCATION} sd): every draw must lie strictly between -pi/2 and pi/2",
                self.pitch_mean, self.pitch_sd
            ));
        }
        Ok(())
    }
}

/// A standard normal draw (Box-Muller) redrawn until within [`TRUNCATION`].
pub fn truncated_normal(rng: &mut SplitMix64) -> f64 {
    loop {
        let u1 = 1.0 - rng.next_f64();
        let u2 = rng.next_f64();
        let z = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        if z.abs() <= TRUNCATION {
            return z;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_have_the_configured_moments() {
        let dist = PoseDistribution {
            yaw_mean: 0.1,
            ..PoseDistribution::default()
        };
        let mut rng = SplitMix64::new(5);
        let n = 40_000;
        let draws: Vec<Pose> = (0..n).map(|_| dist.sample(&mut rng)).collect();
        let mean = |f: &dyn Fn(&Pose) -> f64| draws.iter().map(f).sum::<f64>() / n as f64;
        let (my, mp) = (mean(&|d| d.yaw), mean(&|d| d.pitch));
        let sy = mean(&|d| (d.yaw - my).powi(2)).sqrt();
        let sp = mean(&|d| (d.pitch - mp).powi(2)).sqrt();
        assert!(
            (my - 0.1).abs() < 0.01 && mp.abs() < 0.005,
            "means {my} {mp}"
        );
        // Truncation at 3 sd removes 0.27% of the mass and shrinks the sd by about 1.4%.
        assert!((sy / 0.3 - 0.986).abs() < 0.015, "yaw sd {sy}");
        assert!((sp / 0.155 - 0.986).abs() < 0.015, "pitch sd {sp}");
        assert!(draws.iter().all(|d| (d.yaw - 0.1).abs() <= 0.9 + 1e-12));
        assert!(
            PoseDistribution {
                pitch_sd: -1.0,
                ..dist
            }
            .validate()
            .unwrap_err()
            .contains("pitch_sd")
        );
        // Draws past the camera's range (1e308 overflowed them to infinity) are refused.
        for (bad, key) in [
            (
                PoseDistribution {
                    pitch_sd: 1e308,
                    ..dist
                },
                "pitch_sd = 1e308 draw",
            ),
            (
                PoseDistribution {
                    pitch_mean: 1.5,
                    ..dist
                },
                "pitch_mean = 1.5",
            ),
            (
                PoseDistribution {
                    yaw_mean: 1e300,
                    ..dist
                },
                "yaw_mean = 1e300 and",
            ),
        ] {
            let e = bad.validate().unwrap_err();
            assert!(e.contains(key) && e.contains("every draw"), "{e}");
        }
    }
}
