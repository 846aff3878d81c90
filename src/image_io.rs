//! PNG in and out for every stage: colour images as `f32` sRGB values in [0, 1], segmentation
//! masks as `u32` labels, and deterministic 8-bit encoders.
//!
//! Values are *sRGB-encoded* (8-bit value / 255), not linear light: that is what the model is
//! trained on and what the uORF metrics compare.

use crate::io::{display_name, read_input};
use anyhow::{anyhow, bail, Result};
use image::{DynamicImage, ImageFormat};
use std::collections::HashMap;

/// A decoded colour image: row-major, 3 interleaved channels (R, G, B) per pixel, values in
/// [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage32 {
    pub w: u32,
    pub h: u32,
    /// `3 * w * h` values, pixel `(x, y)` channel `c` at `3 * (y * w + x) + c`.
    pub data: Vec<f32>,
}

impl RgbImage32 {
    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.w as usize * self.h as usize
    }
}

/// Most pixels a PNG may hold to be decoded: 2^26 (8192²). The size is read from the header
/// and checked before any pixel is decoded, so a small file declaring a huge image (a
/// decompression bomb: 0.4 MB can hold 20000²) is refused at once.
pub const MAX_DECODE_PIXELS: u64 = 1 << 26;

/// Most bytes a PNG's decoded pixels may take: 512 MiB (8192² at 16-bit RGBA).
pub const MAX_DECODE_BYTES: u64 = 512 << 20;

/// Largest image `colf-encode` uses at its own resolution (1024²); a larger one is reduced to
/// the encoder's input size first (see [`decode_rgb_for_encoder`]).
pub const ENCODE_FULL_RES_PIXELS: u64 = 1 << 20;

/// The width and height a PNG's header declares (nothing is decoded), refused above
/// [`MAX_DECODE_PIXELS`].
pub fn png_dimensions(bytes: &[u8], name: &str) -> Result<(u32, u32)> {
    use image::ImageDecoder;
    let (w, h) = image::codecs::png::PngDecoder::new(std::io::Cursor::new(bytes))
        .map(|d| d.dimensions())
        .map_err(|e| {
            let why = e.to_string().replace('\n', " ");
            anyhow!("{name}: not a valid PNG image: {why}")
        })?;
    if w as u64 * h as u64 > MAX_DECODE_PIXELS {
        bail!(
            "{name}: the image is {w}x{h} pixels, more than the {MAX_DECODE_PIXELS} colf decodes"
        );
    }
    Ok((w, h))
}

/// Refuses a PLTE chunk whose length is not a whole number of RGB entries: the png crate
/// (0.18.1) panics expanding such a palette (found by `make fuzz`, docs/fuzzing.md).
pub fn check_png_palette(bytes: &[u8], name: &str) -> Result<()> {
    let mut at = 8usize;
    while let Some(head) = bytes.get(at..at + 8) {
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
        if &head[4..8] == b"PLTE" && !len.is_multiple_of(3) {
            bail!("{name}: not a valid PNG image: its palette (PLTE) of {len} bytes is not a whole number of RGB entries");
        }
        at = at.saturating_add(12).saturating_add(len);
    }
    Ok(())
}

/// Decodes PNG bytes within the decoding limits; `name` (a file name) prefixes every error.
fn decode_png(bytes: &[u8], name: &str) -> Result<DynamicImage> {
    use image::ImageDecoder;
    check_png_palette(bytes, name)?;
    // The png decoder's messages can span lines; the contract is one error line.
    let invalid = |e: image::ImageError| {
        let why = e.to_string().replace('\n', " ");
        anyhow!("{name}: not a valid PNG image: {why}")
    };
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    let decoder = image::codecs::png::PngDecoder::with_limits(std::io::Cursor::new(bytes), limits)
        .map_err(|e| match e {
            image::ImageError::Limits(_) => {
                anyhow!("{name}: the image is larger than the {MAX_DECODE_BYTES} bytes of pixels colf decodes")
            }
            e => invalid(e),
        })?;
    let (w, h) = decoder.dimensions();
    if w as u64 * h as u64 > MAX_DECODE_PIXELS {
        bail!(
            "{name}: the image is {w}x{h} pixels, more than the {MAX_DECODE_PIXELS} colf decodes"
        );
    }
    if decoder.total_bytes() > MAX_DECODE_BYTES {
        bail!(
            "{name}: the {w}x{h} image takes {} bytes decoded, more than the {MAX_DECODE_BYTES} colf decodes",
            decoder.total_bytes()
        );
    }
    DynamicImage::from_decoder(decoder).map_err(invalid)
}

/// Decodes a PNG into RGB values in [0, 1]: 8-bit values / 255, 16-bit values / 65535; grey is
/// replicated to the three channels; alpha is dropped (not composited).
pub fn decode_rgb(bytes: &[u8], name: &str) -> Result<RgbImage32> {
    let img = decode_png(bytes, name)?;
    let (w, h) = (img.width(), img.height());
    let data: Vec<f32> = match &img {
        DynamicImage::ImageLuma8(b) => grey_to_rgb(b.as_raw(), 1, |v| v as f32 / 255.0),
        DynamicImage::ImageLumaA8(b) => grey_to_rgb(b.as_raw(), 2, |v| v as f32 / 255.0),
        DynamicImage::ImageLuma16(b) => grey_to_rgb(b.as_raw(), 1, |v| v as f32 / 65535.0),
        DynamicImage::ImageLumaA16(b) => grey_to_rgb(b.as_raw(), 2, |v| v as f32 / 65535.0),
        DynamicImage::ImageRgb8(b) => b.as_raw().iter().map(|&v| v as f32 / 255.0).collect(),
        DynamicImage::ImageRgba8(b) => drop_alpha(b.as_raw(), |v| v as f32 / 255.0),
        DynamicImage::ImageRgb16(b) => b.as_raw().iter().map(|&v| v as f32 / 65535.0).collect(),
        DynamicImage::ImageRgba16(b) => drop_alpha(b.as_raw(), |v| v as f32 / 65535.0),
        other => bail!("{name}: unsupported PNG pixel format {:?}", other.color()),
    };
    Ok(RgbImage32 { w, h, data })
}

/// Decodes a PNG for an encoder whose input is `size`×`size`: images of at most
/// `full_res_pixels` pixels are decoded as they are ([`decode_rgb`]); larger ones are first
/// reduced to `size`×`size` on their 8/16-bit pixels (a triangle filter), so no full-size
/// float copy of a large photo is ever made.
pub fn decode_rgb_for_encoder(
    bytes: &[u8],
    name: &str,
    size: u32,
    full_res_pixels: u64,
) -> Result<RgbImage32> {
    let img = decode_png(bytes, name)?;
    if img.width() as u64 * img.height() as u64 <= full_res_pixels || size == 0 {
        drop(img);
        return decode_rgb(bytes, name);
    }
    let small = img.resize_exact(size, size, image::imageops::FilterType::Triangle);
    drop(img);
    let mut png = Vec::new();
    small
        .write_to(&mut std::io::Cursor::new(&mut png), ImageFormat::Png)
        .map_err(|e| anyhow!("{name}: cannot reduce the image: {e}"))?;
    decode_rgb(&png, name)
}

fn grey_to_rgb<T: Copy>(raw: &[T], stride: usize, to_f32: impl Fn(T) -> f32) -> Vec<f32> {
    raw.chunks_exact(stride)
        .flat_map(|px| [to_f32(px[0]); 3])
        .collect()
}

fn drop_alpha<T: Copy>(raw: &[T], to_f32: impl Fn(T) -> f32) -> Vec<f32> {
    raw.chunks_exact(4)
        .flat_map(|px| [to_f32(px[0]), to_f32(px[1]), to_f32(px[2])])
        .collect()
}

/// Reads a colour PNG file (`-`: stdin), see [`decode_rgb`].
pub fn read_rgb(path: &str) -> Result<RgbImage32> {
    decode_rgb(&read_input(path, true)?, display_name(path))
}

/// Decodes a segmentation mask PNG into `(w, h, labels)`, labels row-major.
///
/// Grey masks (8- or 16-bit, alpha ignored) give the grey value as the label (`0` =
/// background, the colf convention). Colour masks (RGB or RGBA, alpha ignored) give one label
/// per distinct colour: black is `0` and the other colours are numbered `1, 2, …` in the order
/// they first appear in the image (row-major), so the result is deterministic.
pub fn decode_labels(bytes: &[u8], name: &str) -> Result<(u32, u32, Vec<u32>)> {
    let img = decode_png(bytes, name)?;
    let (w, h) = (img.width(), img.height());
    let labels: Vec<u32> = match &img {
        DynamicImage::ImageLuma8(b) => b.as_raw().iter().map(|&v| v as u32).collect(),
        DynamicImage::ImageLumaA8(b) => b.as_raw().chunks_exact(2).map(|p| p[0] as u32).collect(),
        DynamicImage::ImageLuma16(b) => b.as_raw().iter().map(|&v| v as u32).collect(),
        DynamicImage::ImageLumaA16(b) => b.as_raw().chunks_exact(2).map(|p| p[0] as u32).collect(),
        DynamicImage::ImageRgb8(b) => colours_to_labels(b.as_raw(), 3),
        DynamicImage::ImageRgba8(b) => colours_to_labels(b.as_raw(), 4),
        DynamicImage::ImageRgb16(b) => colours_to_labels(b.as_raw(), 3),
        DynamicImage::ImageRgba16(b) => colours_to_labels(b.as_raw(), 4),
        other => bail!("{name}: unsupported mask pixel format {:?}", other.color()),
    };
    Ok((w, h, labels))
}

/// One label per distinct RGB colour (alpha, if `stride` is 4, ignored): black → 0, other
/// colours numbered from 1 by first appearance.
fn colours_to_labels<T: Copy + Eq + std::hash::Hash + Default>(
    raw: &[T],
    stride: usize,
) -> Vec<u32> {
    let black = [T::default(); 3];
    let mut table: HashMap<[T; 3], u32> = HashMap::new();
    table.insert(black, 0);
    raw.chunks_exact(stride)
        .map(|px| {
            let colour = [px[0], px[1], px[2]];
            let next = table.len() as u32;
            *table.entry(colour).or_insert(next)
        })
        .collect()
}

/// Reads a segmentation mask PNG file (`-`: stdin), see [`decode_labels`].
pub fn read_labels(path: &str) -> Result<(u32, u32, Vec<u32>)> {
    decode_labels(&read_input(path, true)?, display_name(path))
}

/// Encodes row-major interleaved RGB values in [0, 1] as an 8-bit sRGB PNG: each value is
/// clamped to [0, 1] and rounded to the nearest of 0..=255 (NaN becomes 0). Same input, same
/// bytes.
///
/// # Panics
/// If `rgb.len() != 3 * w * h` or a side is 0 (a caller bug, not bad input).
pub fn encode_png_rgb(w: u32, h: u32, rgb: &[f32]) -> Vec<u8> {
    assert_eq!(
        rgb.len(),
        3 * w as usize * h as usize,
        "encode_png_rgb: {w}x{h} needs {} values",
        3 * w as usize * h as usize
    );
    let bytes: Vec<u8> = rgb.iter().map(|&v| to_u8(v)).collect();
    encode(w, h, &bytes, image::ExtendedColorType::Rgb8)
}

/// Encodes row-major 8-bit grey values (e.g. mask labels) as a grey PNG.
///
/// # Panics
/// If `grey.len() != w * h` or a side is 0 (a caller bug, not bad input).
pub fn encode_png_grey(w: u32, h: u32, grey: &[u8]) -> Vec<u8> {
    assert_eq!(
        grey.len(),
        w as usize * h as usize,
        "encode_png_grey: {w}x{h} needs {} values",
        w as usize * h as usize
    );
    encode(w, h, grey, image::ExtendedColorType::L8)
}

/// Value in [0, 1] → nearest 8-bit value; NaN → 0 (a saturating cast).
pub fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

fn encode(w: u32, h: u32, bytes: &[u8], colour: image::ExtendedColorType) -> Vec<u8> {
    use image::ImageEncoder;
    assert!(w > 0 && h > 0, "cannot encode an empty {w}x{h} PNG");
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(bytes, w, h, colour)
        .expect("PNG encoding into memory cannot fail for a buffer of the right size");
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::ImageEncoder;

    #[test]
    fn rgb_round_trip_is_exact_on_8_bit_values() {
        let (w, h) = (5, 3);
        let rgb: Vec<f32> = (0..3 * w * h)
            .map(|i| (i * 17 % 256) as f32 / 255.0)
            .collect();
        let png = encode_png_rgb(w as u32, h as u32, &rgb);
        assert_eq!(
            png,
            encode_png_rgb(w as u32, h as u32, &rgb),
            "not deterministic"
        );
        let back = decode_rgb(&png, "t.png").unwrap();
        assert_eq!((back.w, back.h), (5, 3));
        assert_eq!(back.data, rgb);
    }

    #[test]
    fn encoding_clamps_and_rounds() {
        let png = encode_png_rgb(2, 1, &[-0.5, 1.5, f32::NAN, 0.5, 0.2, 1.0 / 510.0]);
        let back = decode_rgb(&png, "t.png").unwrap();
        let bytes: Vec<u8> = back
            .data
            .iter()
            .map(|v| (v * 255.0).round() as u8)
            .collect();
        // 0.5 * 255 = 127.5 rounds away from zero; 0.2 * 255 = 51; 0.5 / 255 * 255 → 1.
        assert_eq!(bytes, [0, 255, 0, 128, 51, 1]);
    }

    #[test]
    fn rgba_drops_alpha_and_grey_is_replicated() {
        let mut buf = Vec::new();
        image::codecs::png::PngEncoder::new(&mut buf)
            .write_image(&[10, 20, 30, 0], 1, 1, image::ExtendedColorType::Rgba8)
            .unwrap();
        assert_eq!(
            decode_rgb(&buf, "a.png").unwrap().data,
            [10.0 / 255.0, 20.0 / 255.0, 30.0 / 255.0]
        );
        let grey = encode_png_grey(2, 1, &[0, 255]);
        assert_eq!(
            decode_rgb(&grey, "g.png").unwrap().data,
            [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
        );
    }

    #[test]
    fn grey_masks_keep_values_and_colour_masks_are_numbered() {
        let grey = encode_png_grey(3, 1, &[0, 7, 3]);
        assert_eq!(
            decode_labels(&grey, "m.png").unwrap(),
            (3, 1, vec![0, 7, 3])
        );
        let colour = [0.2, 0.4, 0.6, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.2, 0.4, 0.6];
        let png = encode_png_rgb(4, 1, &colour);
        assert_eq!(
            decode_labels(&png, "m.png").unwrap(),
            (4, 1, vec![1, 0, 2, 1])
        );
    }

    #[test]
    fn corrupt_and_truncated_pngs_are_one_line_errors_naming_the_file() {
        let png = encode_png_rgb(8, 8, &[0.5; 192]);
        for bytes in [&png[..png.len() / 2], &b"not a png at all"[..], &[][..]] {
            let msg = format!("{:#}", decode_rgb(bytes, "broken.png").unwrap_err());
            assert!(
                msg.starts_with("broken.png: not a valid PNG image"),
                "{msg}"
            );
            assert!(!msg.contains('\n'), "{msg}");
            let msg = format!("{:#}", decode_labels(bytes, "broken.png").unwrap_err());
            assert!(
                msg.starts_with("broken.png: not a valid PNG image"),
                "{msg}"
            );
        }
    }

    /// A valid PNG of `w`×`h` black 8-bit grey pixels, compressed to almost nothing.
    fn huge_png(w: u32, h: u32) -> Vec<u8> {
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(
                &vec![0u8; w as usize * h as usize],
                w,
                h,
                image::ExtendedColorType::L8,
            )
            .unwrap();
        out
    }

    #[test]
    fn decompression_bombs_are_refused_before_decoding() {
        let bomb = huge_png(9000, 9000);
        assert!(bomb.len() < 1 << 20, "{}", bomb.len());
        let msg = format!("{:#}", decode_rgb(&bomb, "bomb.png").unwrap_err());
        assert!(
            msg.starts_with("bomb.png: the image is 9000x9000 pixels"),
            "{msg}"
        );
        let msg = format!("{:#}", decode_labels(&bomb, "bomb.png").unwrap_err());
        assert!(msg.contains("more than the 67108864"), "{msg}");
    }

    #[test]
    fn large_images_are_reduced_for_the_encoder_and_small_ones_kept() {
        let rgb: Vec<f32> = (0..3 * 40 * 30).map(|i| (i % 7) as f32 / 6.0).collect();
        let png = encode_png_rgb(40, 30, &rgb);
        let kept = decode_rgb_for_encoder(&png, "a.png", 16, 40 * 30).unwrap();
        assert_eq!(kept, decode_rgb(&png, "a.png").unwrap());
        let reduced = decode_rgb_for_encoder(&png, "a.png", 16, 100).unwrap();
        assert_eq!((reduced.w, reduced.h), (16, 16));
        assert_eq!(
            reduced,
            decode_rgb_for_encoder(&png, "a.png", 16, 100).unwrap()
        );
    }

    #[test]
    fn missing_file_is_named() {
        let msg = format!("{:#}", read_rgb("/no/such/image.png").unwrap_err());
        assert!(msg.contains("/no/such/image.png"), "{msg}");
    }
}
