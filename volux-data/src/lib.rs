//! Training data for VoLux-GAN (paper appendix A): built-in synthetic relightable heads, folder
//! datasets, HDRI collections and relighting augmentation (pseudo ground truth), batched into
//! Burn tensors.
//!
//! Today: the relighting augmentation ([`relighting`]): diffuse, specular and relit layers of
//! an image's albedo, normals and mask under light maps at a yaw rotation; procedural
//! environments for the built-in HDRI collection ([`procedural_sky`]: sun and sky, overcast,
//! studio area lights); folder datasets ([`folder_dataset`]: a person's own photos with their
//! albedo, normals, optional masks and poses, checked, decoded and written). The synthetic
//! heads, HDRI collections, cache and batching follow.
//!
//! The dataset camera is the model's (`volux_model::ray_sampling`), so that pseudo ground
//! truth and generated images share one set of conventions.

pub mod batch;
pub mod contact_sheet;
pub mod dataset;
pub mod example_cache;
pub mod folder_dataset;
pub mod pose_distribution;
pub mod procedural_sky;
pub mod relighting;
pub mod synthetic_head;
pub mod training_sample;
