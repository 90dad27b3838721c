//! glibc's allocator settings for training. A training step allocates and frees the same
//! large tensors (tens of MiB) over and over. By default glibc serves every block above its
//! mmap threshold with a fresh `mmap` and returns it on free, so each step pays the kernel for
//! zeroing those pages again: measured as 5.9 s of system time in a 5-step stage-2 benchmark
//! of the quickstart, and a 1.3x slower step (docs/performance.md). Keeping freed blocks in
//! the heap for reuse (no mmap, no trimming) removes that cost without raising the peak
//! memory, since the step's blocks are reused at the same sizes.
//!
//! A user who sets `MALLOC_MMAP_MAX_` or `MALLOC_TRIM_THRESHOLD_` keeps their own settings.

/// Applies the settings above (glibc only; elsewhere nothing to do).
pub fn tune_for_training() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let user_set = ["MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_"]
            .iter()
            .any(|k| std::env::var_os(k).is_some());
        if user_set {
            return;
        }
        // SAFETY: mallopt only changes allocator parameters; it is called once, at start-up,
        // before the program starts any thread.
        let ok = unsafe {
            libc::mallopt(libc::M_MMAP_MAX, 0) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX) == 1
        };
        if !ok {
            tracing::debug!("glibc refused the allocator settings; keeping its defaults");
        }
    }
}
