//! What `colf-render` writes for one frame: the sRGB PNG, the segmentation mask and the EXR
//! with float colour plus each slot's compositor weight and ordering value.

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;

/// One rendered frame. Per-slot arrays are pixel-major with `1 + num_slots` entries per pixel:
/// entry 0 is the background, entry k + 1 is foreground slot k.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRender {
    pub width: u32,
    pub height: u32,
    pub num_slots: usize,
    /// Row-major RGB in [0, 1] (sRGB-encoded values, as the model is trained on 8-bit PNGs).
    pub rgb: Vec<f32>,
    /// Compositor weights; each pixel's entries sum to 1.
    pub weights: Vec<f32>,
    /// Ordering values, comparable across slots along a ray (see the model docs).
    pub ordering: Vec<f32>,
}

/// Each pixel's field with the largest compositor weight (`weights` holds `fields` per pixel:
/// 0 the background, k + 1 slot k; ties go to the lower field).
pub fn argmax_labels(weights: &[f32], fields: usize) -> Vec<u32> {
    weights
        .chunks_exact(fields)
        .map(|w| {
            let mut best = 0;
            for (i, &v) in w.iter().enumerate().skip(1) {
                if v > w[best] {
                    best = i;
                }
            }
            best as u32
        })
        .collect()
}

impl FrameRender {
    fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Checks that the arrays have the sizes the dimensions promise.
    pub fn validate(&self) -> Result<()> {
        let n = self.pixels();
        let per = 1 + self.num_slots;
        if self.rgb.len() != 3 * n
            || self.weights.len() != per * n
            || self.ordering.len() != per * n
        {
            bail!(
                "internal error: frame arrays do not match {}x{} with {} slots",
                self.width,
                self.height,
                self.num_slots
            );
        }
        Ok(())
    }

    /// Segmentation labels: 0 = background, k + 1 = slot k, by argmax of the compositor
    /// weights (ties go to the lower index, so to the background first).
    pub fn labels(&self) -> Vec<u32> {
        argmax_labels(&self.weights, 1 + self.num_slots)
    }

    /// The mask PNG: 8-bit grey labels (0 = background, k + 1 = slot k) while there are fewer
    /// than 255 slots, 16-bit grey beyond, so no label is ever clipped.
    pub fn mask_png(&self) -> Result<Vec<u8>> {
        self.validate()?;
        let labels = self.labels();
        if self.num_slots < 255 {
            let grey: Vec<u8> = labels.iter().map(|&l| l as u8).collect();
            return Ok(crate::image_io::encode_png_grey(
                self.width,
                self.height,
                &grey,
            ));
        }
        let grey: Vec<u16> = labels
            .iter()
            .map(|&l| l.min(u16::MAX as u32) as u16)
            .collect();
        let img =
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(self.width, self.height, grey)
                .ok_or_else(|| anyhow!("internal error: mask buffer size"))?;
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, image::ImageFormat::Png)
            .map_err(|e| anyhow!("PNG encoding failed: {e}"))?;
        Ok(bytes.into_inner())
    }

    /// The EXR bytes: `R`, `G`, `B` (float colour) and, per slot, `bg.weight` / `bg.order` for
    /// the background and `slotK.weight` / `slotK.order` for foreground slot K. Dotted names
    /// show up as layers (`slot3`) with channels `weight` and `order` in EXR viewers.
    pub fn exr_bytes(&self) -> Result<Vec<u8>> {
        self.validate()?;
        let mut planes = ExrPlanes::new(self.num_slots);
        planes.push(self);
        planes.into_exr(self.width, self.height)
    }
}

/// The float channels of an EXR, one plane per channel, gathered band by band (so a frame
/// written in bands holds each value once).
struct ExrPlanes {
    per: usize,
    /// R, G, B, then per entry (background, slot 0, …) its weight and its order.
    planes: Vec<Vec<f32>>,
}

impl ExrPlanes {
    fn new(num_slots: usize) -> ExrPlanes {
        let per = 1 + num_slots;
        ExrPlanes {
            per,
            planes: vec![Vec::new(); 3 + 2 * per],
        }
    }

    fn push(&mut self, band: &FrameRender) {
        let per = self.per;
        for (c, plane) in self.planes[..3].iter_mut().enumerate() {
            plane.extend(band.rgb.iter().skip(c).step_by(3));
        }
        for s in 0..per {
            self.planes[3 + 2 * s].extend(band.weights.iter().skip(s).step_by(per));
            self.planes[4 + 2 * s].extend(band.ordering.iter().skip(s).step_by(per));
        }
    }

    fn into_exr(self, width: u32, height: u32) -> Result<Vec<u8>> {
        use exr::prelude::*;
        let channels: Vec<AnyChannel<FlatSamples>> = self
            .planes
            .into_iter()
            .enumerate()
            .map(|(i, plane)| {
                let name = match i {
                    0 => "R".to_string(),
                    1 => "G".to_string(),
                    2 => "B".to_string(),
                    _ => {
                        let s = (i - 3) / 2;
                        let prefix = if s == 0 {
                            "bg".to_string()
                        } else {
                            format!("slot{}", s - 1)
                        };
                        let what = if (i - 3) % 2 == 0 { "weight" } else { "order" };
                        format!("{prefix}.{what}")
                    }
                };
                AnyChannel::new(name.as_str(), FlatSamples::F32(plane))
            })
            .collect();
        let layer = Layer::new(
            (width as usize, height as usize),
            LayerAttributes::named("colf"),
            // Blocks in increasing order: the compressor runs in parallel, and with the order
            // unspecified the blocks land in completion order (different bytes each run).
            Encoding {
                line_order: LineOrder::Increasing,
                ..Encoding::FAST_LOSSLESS
            },
            AnyChannels::sort(SmallVec::from_vec(channels)),
        );
        let mut buffer = std::io::Cursor::new(Vec::new());
        Image::from_layer(layer)
            .write()
            .to_buffered(&mut buffer)
            .map_err(|e| anyhow!("EXR encoding failed: {e}"))?;
        Ok(buffer.into_inner())
    }
}

/// An output file shared by a PNG stream writer (which owns its sink) and the code that
/// commits the file when the stream is done.
#[derive(Clone)]
struct SharedOutput(std::rc::Rc<std::cell::RefCell<crate::io::AtomicOutput>>);

impl std::io::Write for SharedOutput {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.borrow_mut().flush()
    }
}

/// A PNG written row by row into an output file.
struct PngRows {
    file: SharedOutput,
    stream: png::StreamWriter<'static, SharedOutput>,
    shown: String,
}

impl PngRows {
    fn create(
        path: &Path,
        w: u32,
        h: u32,
        colour: png::ColorType,
        depth: png::BitDepth,
    ) -> Result<PngRows> {
        let shown = path.display().to_string();
        let file = SharedOutput(std::rc::Rc::new(std::cell::RefCell::new(
            crate::io::AtomicOutput::create_in_folder(path)?,
        )));
        let mut encoder = png::Encoder::new(file.clone(), w, h);
        encoder.set_color(colour);
        encoder.set_depth(depth);
        encoder.set_compression(png::Compression::Balanced);
        encoder.set_filter(png::Filter::Adaptive);
        let stream = encoder
            .write_header()
            .and_then(|w| w.into_stream_writer())
            .map_err(|e| anyhow!("{shown}: write failed: {e}"))?;
        Ok(PngRows {
            file,
            stream,
            shown,
        })
    }

    fn write_rows(&mut self, bytes: &[u8]) -> Result<()> {
        use std::io::Write;
        self.stream
            .write_all(bytes)
            .map_err(|e| anyhow!("{}: write failed: {e}", self.shown))
    }

    fn commit(self) -> Result<()> {
        let PngRows {
            file,
            stream,
            shown,
        } = self;
        stream
            .finish()
            .map_err(|e| anyhow!("{shown}: write failed: {e}"))?;
        let file = std::rc::Rc::try_unwrap(file.0)
            .map_err(|_| anyhow!("internal error: {shown} is still being written"))?;
        file.into_inner().commit()
    }
}

/// The files of one frame (`S.png`, and `S.mask.png` and `S.exr` when asked), written as its
/// row bands arrive: the PNGs stream row by row, so their memory does not grow with the image;
/// the EXR's float channels are gathered and written whole at the end. Nothing replaces an
/// existing file until [`FrameFiles::commit`]; dropped before, every temporary file goes.
pub struct FrameFiles {
    width: u32,
    num_slots: usize,
    png: PngRows,
    mask: Option<PngRows>,
    exr: Option<(std::path::PathBuf, ExrPlanes, u32)>,
}

impl FrameFiles {
    /// Opens the files of a `width`×`height` frame with `num_slots` slots at `base` + `.png`,
    /// `.mask.png` (with `masks`) and `.exr` (with `exr`).
    pub fn create(
        dir: &Path,
        name: &str,
        (width, height): (u32, u32),
        num_slots: usize,
        masks: bool,
        exr: bool,
    ) -> Result<FrameFiles> {
        let png = PngRows::create(
            &dir.join(format!("{name}.png")),
            width,
            height,
            png::ColorType::Rgb,
            png::BitDepth::Eight,
        )?;
        let mask = masks
            .then(|| {
                let depth = if num_slots < 255 {
                    png::BitDepth::Eight
                } else {
                    png::BitDepth::Sixteen
                };
                PngRows::create(
                    &dir.join(format!("{name}.mask.png")),
                    width,
                    height,
                    png::ColorType::Grayscale,
                    depth,
                )
            })
            .transpose()?;
        let exr = exr.then(|| {
            (
                dir.join(format!("{name}.exr")),
                ExrPlanes::new(num_slots),
                0,
            )
        });
        Ok(FrameFiles {
            width,
            num_slots,
            png,
            mask,
            exr,
        })
    }

    /// Writes the next rows of the frame (a band as wide as the frame).
    pub fn write_band(&mut self, band: &FrameRender) -> Result<()> {
        band.validate()?;
        if band.width != self.width || band.num_slots != self.num_slots {
            bail!("internal error: a band does not match its frame");
        }
        let bytes: Vec<u8> = band
            .rgb
            .iter()
            .map(|&v| crate::image_io::to_u8(v))
            .collect();
        self.png.write_rows(&bytes)?;
        if let Some(mask) = &mut self.mask {
            let labels = band.labels();
            let bytes: Vec<u8> = if self.num_slots < 255 {
                labels.iter().map(|&l| l as u8).collect()
            } else {
                labels
                    .iter()
                    .flat_map(|&l| (l.min(u16::MAX as u32) as u16).to_be_bytes())
                    .collect()
            };
            mask.write_rows(&bytes)?;
        }
        if let Some((_, planes, rows)) = &mut self.exr {
            planes.push(band);
            *rows += band.height;
        }
        Ok(())
    }

    /// Finishes every file and puts them in place.
    pub fn commit(self) -> Result<()> {
        // The EXR is encoded before any file is renamed, so an encoding error leaves none.
        let width = self.width;
        let exr = match self.exr {
            Some((path, planes, rows)) => {
                let bytes = planes.into_exr(width, rows)?;
                let mut out = crate::io::AtomicOutput::create_in_folder(&path)?;
                std::io::Write::write_all(&mut out, &bytes)
                    .with_context(|| format!("{}: write failed", path.display()))?;
                Some(out)
            }
            None => None,
        };
        self.png.commit()?;
        if let Some(mask) = self.mask {
            mask.commit()?;
        }
        if let Some(out) = exr {
            out.commit()?;
        }
        Ok(())
    }
}

/// Reads the named float channels of an EXR file (for tests and tools): name → values.
pub fn read_exr_channels(path: &Path) -> Result<std::collections::BTreeMap<String, Vec<f32>>> {
    use exr::prelude::*;
    let image = read_first_flat_layer_from_file(path)
        .map_err(|e| anyhow!("{}: cannot read EXR: {e}", path.display()))?;
    Ok(image
        .layer_data
        .channel_data
        .list
        .iter()
        .map(|c| {
            let values = c.sample_data.values_as_f32().collect();
            (c.name.to_string(), values)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> FrameRender {
        // 2x1 image, 2 foreground slots.
        FrameRender {
            width: 2,
            height: 1,
            num_slots: 2,
            rgb: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
            weights: vec![0.2, 0.5, 0.3, 0.9, 0.05, 0.05],
            ordering: vec![1.0, 2.0, 3.0, -1.0, -2.0, -3.0],
        }
    }

    #[test]
    fn labels_are_argmax_with_background_zero() {
        assert_eq!(sample().labels(), vec![1, 0]);
    }

    #[test]
    fn exr_round_trip_by_channel_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.exr");
        std::fs::write(&path, sample().exr_bytes().unwrap()).unwrap();
        let ch = read_exr_channels(&path).unwrap();
        let names: Vec<&str> = ch.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            [
                "B",
                "G",
                "R",
                "bg.order",
                "bg.weight",
                "slot0.order",
                "slot0.weight",
                "slot1.order",
                "slot1.weight"
            ]
        );
        assert_eq!(ch["R"], vec![0.1, 0.4]);
        assert_eq!(ch["slot1.weight"], vec![0.3, 0.05]);
        assert_eq!(ch["bg.order"], vec![1.0, -1.0]);
    }

    #[test]
    fn exr_bytes_are_the_same_on_every_call() {
        // 300x200 with 3 slots: many tiles, compressed in parallel.
        let (w, h, per) = (300usize, 200usize, 4usize);
        let wave = |n: usize, k: f32| (0..n).map(|i| (i as f32 * k).sin()).collect::<Vec<_>>();
        let frame = FrameRender {
            width: w as u32,
            height: h as u32,
            num_slots: per - 1,
            rgb: wave(3 * w * h, 0.37),
            weights: wave(per * w * h, 0.11),
            ordering: wave(per * w * h, 0.05),
        };
        let first = frame.exr_bytes().unwrap();
        for _ in 0..5 {
            assert!(frame.exr_bytes().unwrap() == first, "EXR bytes differ");
        }
    }

    /// Rows `rows` of `f` as a band.
    fn band(f: &FrameRender, rows: std::ops::Range<usize>) -> FrameRender {
        let (w, per) = (f.width as usize, 1 + f.num_slots);
        FrameRender {
            width: f.width,
            height: rows.len() as u32,
            num_slots: f.num_slots,
            rgb: f.rgb[3 * w * rows.start..3 * w * rows.end].to_vec(),
            weights: f.weights[per * w * rows.start..per * w * rows.end].to_vec(),
            ordering: f.ordering[per * w * rows.start..per * w * rows.end].to_vec(),
        }
    }

    #[test]
    fn frames_written_in_bands_equal_frames_written_whole() {
        let (w, h, slots) = (7usize, 5usize, 2usize);
        let per = slots + 1;
        let wave = |n: usize, k: f32| (0..n).map(|i| (i as f32 * k).sin().abs()).collect();
        let whole = FrameRender {
            width: w as u32,
            height: h as u32,
            num_slots: slots,
            rgb: wave(3 * w * h, 0.37),
            weights: wave(per * w * h, 0.11),
            ordering: wave(per * w * h, 0.05),
        };
        let dir = tempfile::tempdir().unwrap();
        let mut files = FrameFiles::create(dir.path(), "f", (7, 5), slots, true, true).unwrap();
        for rows in [0..2, 2..3, 3..5] {
            files.write_band(&band(&whole, rows)).unwrap();
        }
        files.commit().unwrap();
        let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
        let rgb = crate::image_io::decode_rgb(&read("f.png"), "f.png").unwrap();
        let expected = crate::image_io::encode_png_rgb(7, 5, &whole.rgb);
        assert_eq!(rgb, crate::image_io::decode_rgb(&expected, "e").unwrap());
        let labels = crate::image_io::decode_labels(&read("f.mask.png"), "m").unwrap();
        assert_eq!(labels.2, whole.labels());
        assert_eq!(read("f.exr"), whole.exr_bytes().unwrap());
        // Dropped before commit: no file, no temporary file.
        let mut files = FrameFiles::create(dir.path(), "g", (7, 5), slots, true, true).unwrap();
        files.write_band(&band(&whole, 0..2)).unwrap();
        drop(files);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
    }

    #[test]
    fn mismatched_arrays_are_an_error() {
        let mut f = sample();
        f.weights.pop();
        assert!(f.exr_bytes().is_err());
    }
}
