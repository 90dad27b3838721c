//! Pseudo ground truth for photos (docs/data.md, "Pseudo ground truth from photos"): an
//! intrinsic estimator trained on the synthetic heads, and `volux data pseudo-gt`, which turns
//! a folder of photos into a complete folder dataset with its albedo, normals and masks.

pub mod augmentation;
pub mod error;
pub mod estimator;
pub mod objective;
pub mod photo_folder;
pub mod sheets;
pub mod synthetic_pairs;
pub mod training;
pub mod weights;

pub use error::PseudoGtError;
