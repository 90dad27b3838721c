//! A folder dataset's `poses.csv` against three photos (`a`, `b`, `c`): every row checked, or
//! an error naming the file, line and column, never a panic.
#![no_main]

use std::collections::BTreeMap;
use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let photos: BTreeMap<String, ()> = ["a", "b", "c"].map(|s| (s.to_owned(), ())).into();
    if let Ok(poses) =
        volux_data::folder_dataset::parse_poses(text, Path::new("poses.csv"), &photos)
    {
        assert_eq!(poses.len(), 3, "every photo has its pose");
        assert!(
            poses.values().all(|p| p.is_finite()),
            "accepted poses are finite"
        );
    }
});
