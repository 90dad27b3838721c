//! Training VoLux-GAN: losses, R1 and path regularisation, the staged schedule, optimisers,
//! EMA, checkpoints, sampling and metrics.
//!
//! Not implemented yet: this crate is an empty library so that the workspace has its final
//! shape and dependency direction (`volux-data`, `volux-model <- volux-train`).
