//! A checkpoint's `state.toml`: its fields and format version, and the config text it carries
//! as a resume would read it, or an error naming the file, never a panic.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let path = Path::new("state.toml");
    if let Ok(state) = volux_train::checkpoint::parse_state(text, path) {
        let _ =
            volux_train::config::TrainConfig::from_text(state.config.clone(), &state.config_path);
    }
});
