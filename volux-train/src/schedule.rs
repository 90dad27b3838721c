//! The staged schedule (paper section 3.4, "Implementation Details"): stage 1 trains the NeIIF
//! and the upsampler on albedo, geometry and the path loss while the upsampling blocks fade in
//! one after another; stage 2 trains everything end to end. Lengths are in images (kimg in the
//! config). Which loss terms run follows from the stage and the weights: a term whose weight
//! is 0 never runs.

use serde::{Deserialize, Serialize};

use crate::losses::LossWeights;

/// The paper's schedule ("Implementation Details"): 1M iterations of stage 1 and 500k more of
/// stage 2, at batch 24.
pub const PAPER_ITERATIONS: (u64, u64) = (1_000_000, 500_000);
/// The paper's batch.
pub const PAPER_BATCH: u64 = 24;

/// Stage lengths (`[schedule]` in a training config), in thousands of images.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScheduleConfig {
    pub stage1_kimg: f64,
    pub stage2_kimg: f64,
    /// Images over which each upsampling block fades in (within stage 1, one after another).
    pub fade_kimg: f64,
    /// Whether the high-resolution albedo discriminator grows with the upsampler: while a
    /// block fades in, its inputs (real and fake) have the ungrown resolutions faded out
    /// in the same way (PGGAN; see [`crate::progressive`]).
    pub fade_discriminator: bool,
    /// Positional-encoding octaves open from the start; the rest open coarse to fine (BARF),
    /// one after another, each over `octave_fade_kimg` from `octave_fade_start_kimg` on.
    /// Absent: every octave from the start (the paper).
    pub open_octaves: Option<usize>,
    pub octave_fade_start_kimg: f64,
    pub octave_fade_kimg: f64,
}

impl ScheduleConfig {
    /// The paper's schedule for `batch` images per step: its iterations times the batch.
    pub fn paper(batch: u64) -> ScheduleConfig {
        let kimg = |iterations: u64| (iterations * batch) as f64 / 1000.0;
        ScheduleConfig {
            stage1_kimg: kimg(PAPER_ITERATIONS.0),
            stage2_kimg: kimg(PAPER_ITERATIONS.1),
            // PGGAN's 600k images per fade-in.
            fade_kimg: 600.0,
            fade_discriminator: true,
            open_octaves: None,
            octave_fade_start_kimg: 0.0,
            octave_fade_kimg: 0.0,
        }
    }
}

impl Default for ScheduleConfig {
    /// The paper's: 24,000 + 12,000 kimg (1M + 500k iterations of 24 images).
    fn default() -> Self {
        ScheduleConfig::paper(PAPER_BATCH)
    }
}

/// Which part of training an image count falls in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Albedo, geometry and path losses; blocks fading in.
    One,
    /// Everything end to end.
    Two,
    /// Past both stages.
    Done,
}

/// The loss terms (and so discriminators and renders) a step runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct ActiveTerms {
    pub albedo: bool,
    pub geometry: bool,
    pub shading: bool,
    pub photo: bool,
    pub path: bool,
    /// The density regulariser (`[loss] density_reg`), in both stages.
    pub density: bool,
}

impl ActiveTerms {
    /// Whether the step needs the relit image (and so light-map look-ups and the U-Net).
    pub fn needs_relit(&self) -> bool {
        self.shading || self.photo
    }
}

impl ScheduleConfig {
    /// Checks lengths, naming the bad key: finite, non-negative, fade-in within stage 1, no
    /// more octaves open than the encoding has (`frequencies`).
    pub fn validate(&self, blocks: usize, frequencies: usize) -> Result<(), String> {
        for (key, v) in [
            ("stage1_kimg", self.stage1_kimg),
            ("stage2_kimg", self.stage2_kimg),
            ("fade_kimg", self.fade_kimg),
            ("octave_fade_start_kimg", self.octave_fade_start_kimg),
            ("octave_fade_kimg", self.octave_fade_kimg),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("schedule.{key} = {v} must be finite and >= 0"));
            }
        }
        if self.fade_kimg * blocks as f64 > self.stage1_kimg {
            return Err(format!(
                "schedule.fade_kimg = {} x {blocks} upsampling blocks is longer than stage1_kimg = {}",
                self.fade_kimg, self.stage1_kimg
            ));
        }
        if let Some(open) = self.open_octaves
            && open > frequencies
        {
            return Err(format!(
                "schedule.open_octaves = {open} is more than the encoding's {frequencies} octaves (model.frequencies)"
            ));
        }
        Ok(())
    }

    /// The positional encoding's window after `images` images, for an encoding of
    /// `frequencies` octaves: `None` (every octave open) without `open_octaves` or once all
    /// have opened, else the octaves open (fractional while one opens; BARF's `alpha`).
    pub fn octave_window(&self, images: u64, frequencies: usize) -> Option<f64> {
        let open = self.open_octaves? as f64;
        let closed = frequencies as f64 - open;
        let elapsed = images as f64 / 1000.0 - self.octave_fade_start_kimg;
        let opened = if elapsed < 0.0 {
            0.0
        } else if self.octave_fade_kimg == 0.0 {
            closed
        } else {
            (elapsed / self.octave_fade_kimg).min(closed)
        };
        (opened < closed).then_some(open + opened)
    }

    /// The stage after `images` images.
    pub fn stage(&self, images: u64) -> Stage {
        let kimg = images as f64 / 1000.0;
        if kimg < self.stage1_kimg {
            Stage::One
        } else if kimg < self.stage1_kimg + self.stage2_kimg {
            Stage::Two
        } else {
            Stage::Done
        }
    }

    /// Fade-in weight of each of `blocks` upsampling blocks after `images` images: block `b`
    /// ramps linearly from 0 to 1 over `[b, b + 1] * fade_kimg`; all are 1 from stage 2 on.
    pub fn fade(&self, images: u64, blocks: usize) -> Vec<f64> {
        let kimg = images as f64 / 1000.0;
        (0..blocks)
            .map(|b| {
                if self.stage(images) != Stage::One || self.fade_kimg == 0.0 {
                    1.0
                } else {
                    ((kimg - b as f64 * self.fade_kimg) / self.fade_kimg).clamp(0.0, 1.0)
                }
            })
            .collect()
    }

    /// The terms a step at `images` runs under `weights`.
    pub fn active(&self, images: u64, weights: &LossWeights) -> ActiveTerms {
        let stage = self.stage(images);
        let two = stage == Stage::Two;
        ActiveTerms {
            albedo: stage != Stage::Done && weights.albedo > 0.0,
            geometry: stage != Stage::Done && weights.geometry > 0.0,
            path: stage != Stage::Done && weights.path > 0.0,
            density: stage != Stage::Done && weights.density_reg > 0.0,
            shading: two && weights.shading > 0.0,
            photo: two && weights.photo > 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schedule() -> ScheduleConfig {
        ScheduleConfig {
            stage1_kimg: 10.0,
            stage2_kimg: 20.0,
            fade_kimg: 4.0,
            fade_discriminator: true,
            open_octaves: None,
            octave_fade_start_kimg: 0.0,
            octave_fade_kimg: 0.0,
        }
    }

    #[test]
    fn the_default_schedule_is_the_papers_iterations_at_its_batch() {
        let s = ScheduleConfig::default();
        // 1M and 500k iterations of 24 images, not 1M and 500k images.
        assert_eq!((s.stage1_kimg, s.stage2_kimg), (24_000.0, 12_000.0));
        assert_eq!(s.stage(999_999 * 24), Stage::One);
        assert_eq!(s.stage(1_000_000 * 24), Stage::Two);
        assert_eq!(s.stage(1_500_000 * 24), Stage::Done);
        assert!(s.fade_discriminator);
    }

    #[test]
    fn stages_follow_the_image_count() {
        let s = schedule();
        assert_eq!(s.stage(0), Stage::One);
        assert_eq!(s.stage(9_999), Stage::One);
        assert_eq!(s.stage(10_000), Stage::Two);
        assert_eq!(s.stage(29_999), Stage::Two);
        assert_eq!(s.stage(30_000), Stage::Done);
    }

    #[test]
    fn blocks_fade_in_one_after_another_during_stage_one() {
        let s = schedule();
        assert_eq!(s.fade(0, 2), [0.0, 0.0]);
        assert_eq!(s.fade(2_000, 2), [0.5, 0.0]);
        assert_eq!(s.fade(4_000, 2), [1.0, 0.0]);
        assert_eq!(s.fade(7_000, 2), [1.0, 0.75]);
        assert_eq!(s.fade(9_000, 2), [1.0, 1.0]);
        assert_eq!(s.fade(12_000, 2), [1.0, 1.0]);
        let instant = ScheduleConfig {
            fade_kimg: 0.0,
            ..s
        };
        assert_eq!(instant.fade(0, 1), [1.0]);
    }

    #[test]
    fn octaves_open_one_after_another_from_their_start() {
        let s = schedule();
        assert_eq!(s.octave_window(5_000, 6), None, "no open_octaves: all open");
        let s = ScheduleConfig {
            open_octaves: Some(4),
            octave_fade_start_kimg: 2.0,
            octave_fade_kimg: 1.5,
            ..s
        };
        assert_eq!(s.octave_window(0, 6), Some(4.0));
        assert_eq!(s.octave_window(2_000, 6), Some(4.0));
        assert_eq!(s.octave_window(2_750, 6), Some(4.5));
        assert_eq!(s.octave_window(3_500, 6), Some(5.0));
        assert_eq!(s.octave_window(4_250, 6), Some(5.5));
        assert_eq!(s.octave_window(5_000, 6), None, "all open");
        assert_eq!(s.octave_window(50_000, 6), None);
        assert_eq!(s.octave_window(0, 4), None, "nothing left to open");
        let instant = ScheduleConfig {
            octave_fade_kimg: 0.0,
            ..s
        };
        assert_eq!(instant.octave_window(1_999, 6), Some(4.0));
        assert_eq!(instant.octave_window(2_000, 6), None);
    }

    #[test]
    fn terms_follow_the_stage_and_zero_weights_run_nothing() {
        let s = schedule();
        let w = LossWeights::default();
        let one = s.active(0, &w);
        assert!(one.albedo && one.geometry && one.path && !one.shading && !one.photo);
        assert!(!one.needs_relit());
        let two = s.active(10_000, &w);
        assert!(two.albedo && two.geometry && two.path && two.shading && two.photo);
        let no_photo = LossWeights {
            photo: 0.0,
            geometry: 0.0,
            ..w
        };
        let t = s.active(10_000, &no_photo);
        assert!(!t.photo && !t.geometry && t.shading && t.needs_relit());
        let only_albedo = LossWeights {
            shading: 0.0,
            photo: 0.0,
            ..w
        };
        assert!(!s.active(15_000, &only_albedo).needs_relit());
        assert!(
            !one.density && !two.density,
            "no density regulariser unless asked"
        );
        let density = LossWeights {
            density_reg: 0.25,
            ..w
        };
        assert!(s.active(0, &density).density && s.active(10_000, &density).density);
        assert!(!s.active(30_000, &density).density);
        assert_eq!(s.active(30_000, &w), ActiveTerms::default());
    }

    #[test]
    fn configs_reject_unknown_keys_and_impossible_lengths() {
        let c: ScheduleConfig = toml::from_str("stage1_kimg = 5.0\nfade_kimg = 1.0").unwrap();
        assert_eq!((c.stage1_kimg, c.stage2_kimg), (5.0, 12_000.0));
        assert!(
            toml::from_str::<ScheduleConfig>("stage3_kimg = 1.0")
                .unwrap_err()
                .to_string()
                .contains("stage3_kimg")
        );
        assert!(c.validate(2, 4).is_ok());
        assert!(c.validate(6, 4).unwrap_err().contains("fade_kimg"));
        let bad = ScheduleConfig {
            stage2_kimg: f64::NAN,
            ..c
        };
        assert!(
            bad.validate(1, 4)
                .unwrap_err()
                .contains("schedule.stage2_kimg")
        );
        let c: ScheduleConfig = toml::from_str("open_octaves = 4\noctave_fade_kimg = 2.0").unwrap();
        assert!(c.validate(1, 5).is_ok());
        let e = c.validate(1, 3).unwrap_err();
        assert!(
            e.contains("schedule.open_octaves = 4") && e.contains("3"),
            "{e}"
        );
        let bad = ScheduleConfig {
            octave_fade_kimg: -1.0,
            ..c
        };
        assert!(
            bad.validate(1, 5)
                .unwrap_err()
                .contains("schedule.octave_fade_kimg")
        );
    }
}
