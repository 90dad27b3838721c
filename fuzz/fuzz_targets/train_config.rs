//! A training config's text (`[model]`, `[train]`, `[schedule]`, `[loss]`, `[output]` and
//! `[data]` with its source, lighting and caches): accepted and checked, or an error naming
//! the file and key, never a panic.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(config) =
        volux_train::config::TrainConfig::from_text(text.to_owned(), Path::new("fuzz.toml"))
    {
        // What training derives from an accepted config must not panic either.
        let _ = config.generator();
        let _ = config.blocks();
        let _ = config.resolved();
    }
});
