//! Contact sheets: PNGs tiled in a grid, label masks shown in colour, so a run's inputs, novel
//! views, masks and edits can be seen side by side in one picture.

use crate::image_io::{decode_labels, decode_rgb, RgbImage32};
use anyhow::{bail, Result};

/// A distinct colour per label (label 0, the background, is black). The first colours are
/// well separated; beyond them hues follow the golden angle.
pub fn label_color(label: u32) -> [f32; 3] {
    const FIXED: [[f32; 3]; 10] = [
        [0.0, 0.0, 0.0],
        [0.90, 0.10, 0.29],
        [0.24, 0.71, 0.29],
        [1.00, 0.88, 0.10],
        [0.00, 0.51, 0.78],
        [0.96, 0.51, 0.19],
        [0.57, 0.12, 0.71],
        [0.27, 0.94, 0.94],
        [0.94, 0.20, 0.90],
        [0.82, 0.96, 0.24],
    ];
    if let Some(c) = FIXED.get(label as usize) {
        return *c;
    }
    let hue = (label as f32 * 137.508).rem_euclid(360.0) / 60.0;
    let x = 1.0 - (hue % 2.0 - 1.0).abs();
    match hue as u32 {
        0 => [1.0, x, 0.0],
        1 => [x, 1.0, 0.0],
        2 => [0.0, 1.0, x],
        3 => [0.0, x, 1.0],
        4 => [x, 0.0, 1.0],
        _ => [1.0, 0.0, x],
    }
}

/// A tile: an RGB image, from a PNG, or a label mask shown in colour.
pub fn load_tile(bytes: &[u8], name: &str, as_labels: bool) -> Result<RgbImage32> {
    if !as_labels {
        return decode_rgb(bytes, name);
    }
    let (w, h, labels) = decode_labels(bytes, name)?;
    Ok(RgbImage32 {
        w,
        h,
        data: labels.iter().flat_map(|&l| label_color(l)).collect(),
    })
}

/// Most pixels a contact sheet (or one enlarged tile) may have: 2^26 (8192²), about 800 MB of
/// working memory; more is a typo (`--gap 2147483648`) rather than a picture.
pub const MAX_SHEET_PIXELS: u64 = 1 << 26;

/// `image` enlarged `factor` times by pixel replication (so small renders and label masks stay
/// crisp on a sheet). `name` (the file) prefixes the error for a result above
/// [`MAX_SHEET_PIXELS`].
pub fn enlarge(image: &RgbImage32, factor: u32, name: &str) -> Result<RgbImage32> {
    let (w, h) = (
        image.w as u64 * factor as u64,
        image.h as u64 * factor as u64,
    );
    if w * h > MAX_SHEET_PIXELS {
        bail!(
            "{name}: enlarged {factor} times the tile would be {w}x{h} pixels, more than the {MAX_SHEET_PIXELS} a sheet may have"
        );
    }
    let (w, h) = (w as u32, h as u32);
    let mut data = Vec::with_capacity(3 * (w * h) as usize);
    for y in 0..h {
        let row = (y / factor) * image.w;
        for x in 0..w {
            let at = 3 * (row + x / factor) as usize;
            data.extend_from_slice(&image.data[at..at + 3]);
        }
    }
    Ok(RgbImage32 { w, h, data })
}

/// Tiles `tiles` row-major into `cols` columns with `gap` pixels of white between them; tiles of
/// different sizes are placed top-left in cells of the largest size. `None` leaves a cell empty.
pub fn tile(tiles: &[Option<RgbImage32>], cols: usize, gap: u32) -> Result<RgbImage32> {
    let sizes: Vec<Option<(u32, u32)>> = tiles
        .iter()
        .map(|t| t.as_ref().map(|t| (t.w, t.h)))
        .collect();
    let (w, h, cell_w, cell_h) = sheet_size(&sizes, cols, gap, 1)?;
    let mut data = vec![1.0f32; 3 * (w * h) as usize];
    for (i, t) in tiles.iter().enumerate() {
        let Some(t) = t else { continue };
        let x0 = gap + (i % cols) as u32 * (cell_w + gap);
        let y0 = gap + (i / cols) as u32 * (cell_h + gap);
        for y in 0..t.h {
            let src = &t.data[(3 * y * t.w) as usize..(3 * (y + 1) * t.w) as usize];
            let at = (3 * ((y0 + y) * w + x0)) as usize;
            data[at..at + src.len()].copy_from_slice(src);
        }
    }
    Ok(RgbImage32 { w, h, data })
}

/// The size `(w, h, cell_w, cell_h)` of the sheet of tiles of sizes `sizes` (`None`: an empty
/// cell) enlarged `scale` times, in `cols` columns with `gap` pixels between them; refused
/// above [`MAX_SHEET_PIXELS`]. Checked from the PNG headers before any tile is decoded.
pub fn sheet_size(
    sizes: &[Option<(u32, u32)>],
    cols: usize,
    gap: u32,
    scale: u32,
) -> Result<(u32, u32, u32, u32)> {
    if cols == 0 || sizes.is_empty() {
        bail!("a contact sheet needs at least one tile and one column");
    }
    let cell = |side: fn(&(u32, u32)) -> u32| {
        sizes.iter().flatten().map(side).max().unwrap_or(1) as u64 * scale as u64
    };
    let (cell_w, cell_h) = (cell(|s| s.0), cell(|s| s.1));
    if cell_w * cell_h > MAX_SHEET_PIXELS {
        bail!(
            "a tile enlarged {scale} times would be {cell_w}x{cell_h} pixels, more than the {MAX_SHEET_PIXELS} a sheet may have"
        );
    }
    let (cell_w, cell_h) = (cell_w as u32, cell_h as u32);
    let rows = sizes.len().div_ceil(cols);
    // In u128: no product of a usize count and a u32 size can overflow it, so the size check
    // sees the true size whatever the flags.
    let side = |n: usize, cell: u32| n as u128 * cell as u128 + (n as u128 + 1) * gap as u128;
    let (w, h) = (side(cols, cell_w), side(rows, cell_h));
    if w * h > MAX_SHEET_PIXELS as u128 {
        bail!(
            "the contact sheet would be {w}x{h} pixels, more than the {MAX_SHEET_PIXELS} it may have (fewer columns, a smaller gap or scale)"
        );
    }
    Ok((w as u32, h as u32, cell_w, cell_h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_land_in_their_cells() {
        let red = RgbImage32 {
            w: 2,
            h: 1,
            data: vec![1.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        };
        let sheet = tile(&[Some(red.clone()), None, Some(red)], 2, 1).unwrap();
        assert_eq!((sheet.w, sheet.h), (7, 5));
        let px = |x: u32, y: u32| &sheet.data[(3 * (y * sheet.w + x)) as usize..][..3];
        assert_eq!(px(1, 1), &[1.0, 0.0, 0.0]); // first tile
        assert_eq!(px(4, 1), &[1.0, 1.0, 1.0]); // empty cell
        assert_eq!(px(1, 3), &[1.0, 0.0, 0.0]); // third tile, second row
        assert_eq!(px(0, 0), &[1.0, 1.0, 1.0]); // gap
    }

    #[test]
    fn enlarging_replicates_pixels() {
        let image = RgbImage32 {
            w: 2,
            h: 1,
            data: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        };
        let big = enlarge(&image, 3, "t.png").unwrap();
        assert_eq!((big.w, big.h), (6, 3));
        let px = |x: u32, y: u32| &big.data[(3 * (y * big.w + x)) as usize..][..3];
        assert_eq!(px(2, 2), &[1.0, 0.0, 0.0]);
        assert_eq!(px(3, 0), &[0.0, 0.0, 1.0]);
        assert_eq!(enlarge(&image, 1, "t.png").unwrap().data, image.data);
    }

    #[test]
    fn absurd_columns_and_gaps_are_errors_not_panics() {
        let red = Some(RgbImage32 {
            w: 2,
            h: 2,
            data: vec![1.0; 12],
        });
        for (tiles, cols, gap) in [
            (1, 1, 2_147_483_648u32),
            (6, 4_294_967_297usize, 0),
            (2, 4_294_967_297, 4),
            (2, usize::MAX, u32::MAX),
            (1, 1, u32::MAX),
        ] {
            let msg = format!(
                "{:#}",
                tile(&vec![red.clone(); tiles], cols, gap).unwrap_err()
            );
            assert!(msg.contains("more than the"), "{msg}");
        }
        let big = RgbImage32 {
            w: 1024,
            h: 512,
            data: vec![0.0; 3 * 1024 * 512],
        };
        let msg = format!("{:#}", enlarge(&big, 16, "big.png").unwrap_err());
        assert!(msg.starts_with("big.png: "), "{msg}");
    }

    #[test]
    fn label_colours_are_distinct() {
        let colours: Vec<[f32; 3]> = (0..40).map(label_color).collect();
        for i in 0..colours.len() {
            for j in 0..i {
                assert_ne!(colours[i], colours[j], "labels {i} and {j}");
            }
        }
        assert_eq!(label_color(0), [0.0; 3]);
    }
}
