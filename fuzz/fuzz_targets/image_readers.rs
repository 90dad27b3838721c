//! EXR, Radiance HDR, PNG and JPEG decoding from bytes, then the checks an environment map
//! gets: any input is an image or an error, never a panic, an abort or an unbounded
//! allocation. The first byte picks the format (the reader goes by the file extension).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, bytes)) = data.split_first() else {
        return;
    };
    let name = ["map.exr", "map.hdr", "map.png", "map.jpg"][usize::from(pick % 4)];
    let path = Path::new(name);
    if volux_envmap::io::read_raw_bytes(bytes, path).is_ok() {
        // A decoded image still goes through the map's own checks (size, aspect, values).
        let _ = volux_envmap::io::load_bytes(bytes, path);
    }
});
