//! The cameras the fakes are rendered from. A 3D-aware GAN learns 3D consistency only if its
//! fakes are seen from many viewpoints: pi-GAN, StyleNeRF and VoLux-GAN draw the camera from a
//! prior, EG3D conditions on the dataset's poses and swaps them between images. Photo
//! collections such as CelebA or FFHQ have no pose labels (a folder dataset without
//! `poses.csv` gives every photo the pose `(0, 0)`), so rendering the fakes at the reals'
//! poses would render them only frontally there.

use serde::{Deserialize, Serialize};
use volux_data::pose_distribution::PoseDistribution;
use volux_envmap::random::SplitMix64;
use volux_model::pose::Pose;

/// Where the fakes' cameras come from (`[train] fake_poses`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FakePoses {
    /// The real batch's poses when the dataset has poses, else the prior.
    #[default]
    Auto,
    /// Element `i` of the fakes at the pose of real `i`.
    Dataset,
    /// Drawn from `[train.pose_prior]`.
    Prior,
    /// The real batch's poses, shifted by one element (EG3D's pose swapping): each fake is
    /// seen from a dataset pose, but not its own real's.
    Swap,
}

impl FakePoses {
    /// What `Auto` means for a dataset with (or without) poses.
    pub fn resolve(self, dataset_has_poses: bool) -> FakePoses {
        match self {
            FakePoses::Auto if dataset_has_poses => FakePoses::Dataset,
            FakePoses::Auto => FakePoses::Prior,
            other => other,
        }
    }

    /// The fakes' poses for a batch whose reals have `real_poses`, drawing from `prior` with
    /// `rng` when the mode asks for it. `self` must be resolved (see [`FakePoses::resolve`]).
    pub fn poses(
        self,
        real_poses: &[Pose],
        prior: &PoseDistribution,
        rng: &mut SplitMix64,
    ) -> Vec<Pose> {
        match self {
            FakePoses::Dataset => real_poses.to_vec(),
            FakePoses::Prior => real_poses.iter().map(|_| prior.sample(rng)).collect(),
            FakePoses::Swap => {
                let mut poses = real_poses.to_vec();
                let shift = 1.min(poses.len());
                poses.rotate_left(shift);
                poses
            }
            FakePoses::Auto => unreachable!("FakePoses::poses on an unresolved mode"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_uses_the_datasets_poses_only_when_it_has_them() {
        assert_eq!(FakePoses::Auto.resolve(true), FakePoses::Dataset);
        assert_eq!(FakePoses::Auto.resolve(false), FakePoses::Prior);
        assert_eq!(FakePoses::Swap.resolve(false), FakePoses::Swap);
        assert_eq!(FakePoses::Dataset.resolve(false), FakePoses::Dataset);
    }

    #[test]
    fn each_mode_gives_its_poses() {
        let reals = [
            Pose::new(0.1, 0.0),
            Pose::new(0.2, 0.05),
            Pose::new(0.3, -0.05),
        ];
        let prior = PoseDistribution::default();
        let mut rng = SplitMix64::new(3);
        assert_eq!(FakePoses::Dataset.poses(&reals, &prior, &mut rng), reals);
        assert_eq!(
            FakePoses::Swap.poses(&reals, &prior, &mut rng),
            [reals[1], reals[2], reals[0]]
        );
        assert!(FakePoses::Swap.poses(&[], &prior, &mut rng).is_empty());
        // The prior's draws: as many as reals, spread like the prior, reproducible.
        let frontal = vec![Pose::FRONTAL; 4000];
        let drawn = FakePoses::Prior.poses(&frontal, &prior, &mut SplitMix64::new(9));
        assert_eq!(drawn.len(), frontal.len());
        let sd = |f: fn(&Pose) -> f64| {
            let mean = drawn.iter().map(f).sum::<f64>() / drawn.len() as f64;
            (drawn.iter().map(|p| (f(p) - mean).powi(2)).sum::<f64>() / drawn.len() as f64).sqrt()
        };
        let (yaw_sd, pitch_sd) = (sd(|p| p.yaw), sd(|p| p.pitch));
        assert!((yaw_sd - 0.3).abs() < 0.02, "yaw sd {yaw_sd}");
        assert!((pitch_sd - 0.155).abs() < 0.01, "pitch sd {pitch_sd}");
        assert_eq!(
            drawn,
            FakePoses::Prior.poses(&frontal, &prior, &mut SplitMix64::new(9))
        );
    }
}
