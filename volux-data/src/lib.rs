//! Training data for VoLux-GAN: built-in synthetic relightable heads, folder datasets, HDRI
//! collections and relighting augmentation (pseudo ground truth), batched into Burn tensors.
//!
//! Not implemented yet: this crate is an empty library so that the workspace has its final
//! shape and dependency direction (`volux-envmap <- volux-data <- volux-train`).
