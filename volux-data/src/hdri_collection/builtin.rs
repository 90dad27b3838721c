//! The eight CC0 Poly Haven maps shipped in `assets/hdri`, embedded in the binary so that an
//! installed `volux` needs no checkout.

use super::{HdriEntry, HdriSource};

/// One of the HDR maps embedded in the binary.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BuiltinHdri {
    /// Stable name (the file stem).
    pub name: &'static str,
    /// The path the map was embedded from, relative to the repository root; named in errors.
    pub path: &'static str,
    /// The OpenEXR file's bytes.
    pub bytes: &'static [u8],
}

macro_rules! builtin {
    ($name:literal) => {
        BuiltinHdri {
            name: $name,
            path: concat!("assets/hdri/", $name, ".exr"),
            bytes: include_bytes!(concat!("../../../assets/hdri/", $name, ".exr")),
        }
    };
}

/// The eight shipped CC0 maps (1024x512 OpenEXR; `assets/hdri/SOURCE.md`), in name order.
pub const BUILTIN_HDRIS: [BuiltinHdri; 8] = [
    builtin!("city"),
    builtin!("courtyard"),
    builtin!("forest"),
    builtin!("interior"),
    builtin!("night"),
    builtin!("studio"),
    builtin!("sunrise"),
    builtin!("sunset"),
];

/// Entries for the embedded maps.
pub fn builtin_entries() -> Vec<HdriEntry> {
    BUILTIN_HDRIS
        .iter()
        .map(|b| HdriEntry {
            name: b.name.to_string(),
            source: HdriSource::Builtin(*b),
        })
        .collect()
}
