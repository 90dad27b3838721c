//! Evaluating a VoLux-GAN generator without a face-recognition network: the properties the
//! paper's Tables 1 and 2 measure (a face stays the same across camera poses and across
//! environment maps), measured directly from what the generator renders, plus a distribution
//! distance and a geometry check. Each measurement also runs on the built-in synthetic heads,
//! whose layers are exact, to show what a perfect score looks like.
//!
//! - [`reprojection`]: side views warped into the frontal view with the rendered depth.
//! - [`relighting_consistency`]: albedo and normals under different lights, relit against
//!   the physically shaded image.
//! - [`geometry`]: accumulated normals against the normals of the rendered depth.
//! - [`swd`]: sliced Wasserstein distance on Laplacian-pyramid patches (ProGAN);
//!   [`sample_quality`]: generated layers against two draws of the dataset.
//! - [`views`]: the layers the measurements read, from a generator or a synthetic head.
//! - [`evaluate`]: the whole evaluation and its figures; [`report`]: the JSON report and table.
//! - [`progress`]: the light evaluation taken during training (`[output] eval_kimg`);
//!   [`plot`]: a run's losses and scores against images and minutes, as PNG;
//!   [`run_page`]: one self-contained HTML page of a run (`volux report`).

pub mod evaluate;
pub mod geometry;
pub mod image;
pub mod plot;
pub mod progress;
pub mod relighting_consistency;
pub mod report;
pub mod reprojection;
pub mod run_page;
pub mod sample_quality;
pub mod swd;
pub mod views;
