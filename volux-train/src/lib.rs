//! Training VoLux-GAN (paper section 3.4): the losses ([`losses`]: non-saturating logistic
//! losses, lazy R1, the path loss, the shading discriminator's condition, loss weights) and
//! the staged schedule ([`schedule`]: stage 1 with progressive growing, stage 2 end to end,
//! which terms run).
//!
//! Still to come: optimisers, EMA, the training loop, checkpoints, sampling and metrics.

pub mod losses;
pub mod schedule;
