//! Files of a rendered scene: PNG images and masks, `transforms.json`, `scene.json`. Every file
//! is written atomically (temporary file + rename), so an interrupted run leaves no partial file.

use crate::io::write_in_folder;
use anyhow::{Context, Result};
use image::{ExtendedColorType, ImageEncoder};
use std::path::Path;

/// PNG bytes of an 8-bit image (`channels` = 1 grey or 3 RGB), row-major.
pub fn png_bytes(pixels: &[u8], w: u32, h: u32, channels: usize) -> Result<Vec<u8>> {
    let color = if channels == 1 {
        ExtendedColorType::L8
    } else {
        ExtendedColorType::Rgb8
    };
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(pixels, w, h, color)
        .context("PNG encoding failed")?;
    Ok(bytes)
}

/// Writes an 8-bit PNG atomically.
pub fn write_png(path: &Path, pixels: &[u8], w: u32, h: u32, channels: usize) -> Result<()> {
    let bytes = png_bytes(pixels, w, h, channels).with_context(|| path.display().to_string())?;
    write_in_folder(path, &bytes)
}

/// Writes pretty JSON (with a final newline) atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)
        .with_context(|| format!("{}: JSON encoding failed", path.display()))?;
    text.push('\n');
    write_in_folder(path, text.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let rgb: Vec<u8> = (0..4 * 3 * 3).map(|v| (v * 7) as u8).collect();
        let path = dir.path().join("a.png");
        write_png(&path, &rgb, 4, 3, 3).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (4, 3));
        assert_eq!(img.into_raw(), rgb);
        let mask = vec![0u8, 1, 2, 3, 4, 5];
        let path = dir.path().join("m.png");
        write_png(&path, &mask, 3, 2, 1).unwrap();
        let img = image::open(&path).unwrap();
        assert_eq!(img.color(), image::ColorType::L8);
        assert_eq!(img.to_luma8().into_raw(), mask);
    }
}
