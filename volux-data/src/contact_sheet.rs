//! Contact sheets: grids of equally sized tiles (one sample per row, one layer per column) and
//! the conventional false colours of intrinsic layers, for previews and sample grids.

use volux_envmap::Rgb;
use volux_envmap::io::{linear_to_srgb, tonemap_pixel};

/// A grid of `columns x rows` tiles of `tile_width x tile_height` pixels, sRGB in `[0, 1]`.
#[derive(Clone, Debug, PartialEq)]
pub struct ContactSheet {
    tile_width: usize,
    tile_height: usize,
    columns: usize,
    rows: usize,
    pixels: Vec<Rgb>,
}

impl ContactSheet {
    /// A black sheet.
    pub fn new(tile_width: usize, tile_height: usize, columns: usize, rows: usize) -> Self {
        ContactSheet {
            tile_width,
            tile_height,
            columns,
            rows,
            pixels: vec![[0.0; 3]; tile_width * tile_height * columns * rows],
        }
    }

    pub fn width(&self) -> usize {
        self.tile_width * self.columns
    }

    pub fn height(&self) -> usize {
        self.tile_height * self.rows
    }

    /// Copies `tile` (row-major, the tile's size) into column `column` of row `row`.
    pub fn put(&mut self, column: usize, row: usize, tile: &[Rgb]) {
        assert!(
            column < self.columns && row < self.rows,
            "tile ({column}, {row}) off the sheet"
        );
        assert_eq!(tile.len(), self.tile_width * self.tile_height, "tile size");
        let width = self.width();
        for y in 0..self.tile_height {
            let start = (row * self.tile_height + y) * width + column * self.tile_width;
            self.pixels[start..start + self.tile_width]
                .copy_from_slice(&tile[y * self.tile_width..(y + 1) * self.tile_width]);
        }
    }

    /// 8-bit sRGB pixels, row-major.
    pub fn to_u8(&self) -> Vec<[u8; 3]> {
        self.pixels
            .iter()
            .map(|c| c.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
            .collect()
    }
}

/// Linear albedo as sRGB.
pub fn albedo_colours(albedo: &[Rgb]) -> Vec<Rgb> {
    albedo.iter().map(|a| a.map(linear_to_srgb)).collect()
}

/// Unit normals as `(n + 1) / 2`, times the mask (black background).
pub fn normal_colours(normals: &[[f32; 3]], mask: &[f32]) -> Vec<Rgb> {
    normals
        .iter()
        .zip(mask)
        .map(|(n, m)| n.map(|c| (c + 1.0) * 0.5 * m))
        .collect()
}

/// A scalar layer as grey, mapping `[lo, hi]` to `[0, 1]` (`lo > hi` inverts).
pub fn grey(values: &[f32], lo: f32, hi: f32) -> Vec<Rgb> {
    values
        .iter()
        .map(|v| [((v - lo) / (hi - lo)).clamp(0.0, 1.0); 3])
        .collect()
}

/// Linear HDR shading tone-mapped with the generator's curve at `exposure`.
pub fn shading_colours(shading: &[Rgb], exposure: f32) -> Vec<Rgb> {
    shading
        .iter()
        .map(|c| tonemap_pixel(*c, exposure))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_land_where_asked() {
        let mut sheet = ContactSheet::new(2, 3, 3, 2);
        let tile: Vec<Rgb> = (0..6).map(|i| [i as f32 / 10.0; 3]).collect();
        sheet.put(2, 1, &tile);
        let px = sheet.to_u8();
        assert_eq!((sheet.width(), sheet.height()), (6, 6));
        // Row 1 of the tile sits at sheet row 3 + 1, columns 4..6.
        assert_eq!(px[4 * 6 + 4], [51; 3]);
        assert_eq!(px[4 * 6 + 5], [77; 3]);
        assert_eq!(px[4 * 6 + 3], [0; 3]);
        assert_eq!(grey(&[2.25, 3.3], 3.3, 2.25), vec![[1.0; 3], [0.0; 3]]);
    }
}
