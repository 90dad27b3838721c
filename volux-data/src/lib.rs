//! Training data for VoLux-GAN (paper appendix A): built-in synthetic relightable heads, folder
//! datasets, HDRI collections and relighting augmentation (pseudo ground truth), batched into
//! Burn tensors.
//!
//! Today:
//! - [`relighting`]: diffuse, specular and relit layers of an image's albedo, normals and mask
//!   under light maps at a yaw rotation;
//! - [`procedural_sky`]: procedural environments (sun and sky, overcast, studio area lights);
//! - [`hdri_collection`]: the environments a dataset draws from (the eight embedded maps,
//!   seeded procedural ones, folders of `.exr` / `.hdr`), each with a name and a content key,
//!   and the draw of an environment and a yaw;
//! - [`light_map_cache`]: light maps cached on disk, keyed by content and options;
//! - [`light_map_bank`]: the light maps of a whole collection in memory, built in parallel
//!   through the cache.
//!
//! The synthetic heads, folder datasets and batching follow.
//!
//! The dataset camera is the model's (`volux_model::ray_sampling`), so that pseudo ground
//! truth and generated images share one set of conventions.

pub mod hdri_collection;
pub mod light_map_bank;
pub mod light_map_cache;
pub mod procedural_sky;
pub mod relighting;
