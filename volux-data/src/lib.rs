//! Training data for VoLux-GAN (paper appendix A): built-in synthetic relightable heads, folder
//! datasets, HDRI collections and relighting augmentation (pseudo ground truth), batched into
//! Burn tensors.
//!
//! - [`synthetic_head`]: the built-in dataset, procedural relightable heads (seeded
//!   identities, sphere-traced signed distances, exact normals, a photo with occlusion, soft
//!   shadows and subsurface softening);
//! - [`folder_dataset`]: a person's own photos with their albedo, normals, optional masks and
//!   poses, checked, decoded and written;
//! - [`relighting`]: diffuse, specular and relit layers of an image's albedo, normals and mask
//!   under light maps at a yaw rotation (the pseudo ground truth);
//! - [`procedural_sky`]: procedural environments (sun and sky, overcast, studio area lights);
//! - [`hdri_collection`]: the environments a dataset draws from (the eight embedded maps,
//!   seeded procedural ones, folders of `.exr` / `.hdr`), each with a name and a content key;
//! - [`light_map_cache`]: light maps cached on disk, keyed by content and options;
//! - [`light_map_bank`]: the light maps of a whole collection in memory, built in parallel
//!   through the cache;
//! - [`layers`]: the image layers of an example, described once (channels, resolution,
//!   range), and `Layers<T>`, one value per layer;
//!   [`training_sample`]: one example with every layer the discriminators see, in the
//!   generator's conventions; [`dataset`]: examples and batches as a pure function of their
//!   index; [`example_cache`]: examples rendered once into a sharded on-disk cache;
//!   [`examples`]: what training reads, live or from a cache that matches its config;
//!   [`batch`]: batches as Burn tensors and a prefetching loader;
//! - [`pose_distribution`], [`contact_sheet`]: camera poses, preview grids; [`config_file`]:
//!   why a TOML config cannot be used, naming the file; [`digest`]:
//!   SHA-256 keys and their hex form.
//!
//! The dataset camera is the model's (`volux_model::ray_sampling`), so that pseudo ground
//! truth and generated images share one set of conventions.

pub mod batch;
pub mod config_file;
pub mod contact_sheet;
pub mod dataset;
pub mod digest;
pub mod example_cache;
pub mod examples;
pub mod folder_dataset;
pub mod hdri_collection;
pub mod layers;
pub mod light_map_bank;
pub mod light_map_cache;
pub mod pose_distribution;
pub mod procedural_sky;
pub mod relighting;
pub mod resample;
pub mod synthetic_head;
pub mod training_sample;
