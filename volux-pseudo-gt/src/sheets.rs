//! Contact sheets of estimates: the dataset's (`contact_sheet.png`: photo, albedo, normals,
//! mask) and the evaluation's (the same beside the true layers of held-out heads).

use std::path::Path;

use volux_data::contact_sheet::{self, ContactSheet};
use volux_envmap::{Rgb, io};

use crate::augmentation::Augmented;
use crate::error::PseudoGtError;
use crate::estimator::Estimate;

/// Albedo, normals and mask as false-colour tiles.
fn layer_tiles(albedo: &[Rgb], normals: &[[f32; 3]], mask: &[f32]) -> [Vec<Rgb>; 3] {
    [
        contact_sheet::albedo_colours(albedo),
        contact_sheet::normal_colours(normals, mask),
        contact_sheet::grey(mask, 0.0, 1.0),
    ]
}

fn save(path: &Path, sheet: &ContactSheet) -> Result<(), PseudoGtError> {
    io::save_png(path, sheet.width(), sheet.height(), &sheet.to_u8())?;
    Ok(())
}

/// Rows of `side x side` photos and their estimates; columns photo, albedo, normals, mask.
/// Nothing is written for no rows.
pub fn save_estimates(
    path: &Path,
    side: usize,
    rows: &[(&[Rgb], &Estimate)],
) -> Result<(), PseudoGtError> {
    if rows.is_empty() {
        return Ok(());
    }
    let mut sheet = ContactSheet::new(side, side, 4, rows.len());
    for (row, (photo, e)) in rows.iter().enumerate() {
        sheet.put(0, row, photo);
        for (k, tile) in layer_tiles(&e.albedo, &e.normals, &e.mask)
            .iter()
            .enumerate()
        {
            sheet.put(1 + k, row, tile);
        }
    }
    save(path, &sheet)
}

/// Rows of held-out inputs and their estimates; columns photo, then albedo, normals and mask,
/// each estimated and true side by side. Nothing is written for no rows.
pub fn save_comparison(path: &Path, rows: &[(&Augmented, &Estimate)]) -> Result<(), PseudoGtError> {
    let Some((first, _)) = rows.first() else {
        return Ok(());
    };
    let side = first.side;
    let mut sheet = ContactSheet::new(side, side, 7, rows.len());
    for (row, (truth, e)) in rows.iter().enumerate() {
        sheet.put(0, row, &truth.photo);
        let ours = layer_tiles(&e.albedo, &e.normals, &e.mask);
        let theirs = layer_tiles(&truth.albedo, &truth.normals, &truth.mask);
        for k in 0..3 {
            sheet.put(1 + 2 * k, row, &ours[k]);
            sheet.put(2 + 2 * k, row, &theirs[k]);
        }
    }
    save(path, &sheet)
}
