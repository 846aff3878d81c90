//! What `colf-render` writes for one frame: the sRGB PNG, the segmentation mask and the EXR
//! with float colour plus each slot's compositor weight and ordering value.

use anyhow::{anyhow, bail, Result};
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
        let per = 1 + self.num_slots;
        self.weights
            .chunks_exact(per)
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
        use exr::prelude::*;
        self.validate()?;
        let n = self.pixels();
        let per = 1 + self.num_slots;
        let mut channels: Vec<AnyChannel<FlatSamples>> = ["R", "G", "B"]
            .iter()
            .enumerate()
            .map(|(c, name)| {
                let v: Vec<f32> = (0..n).map(|p| self.rgb[3 * p + c]).collect();
                AnyChannel::new(*name, FlatSamples::F32(v))
            })
            .collect();
        for s in 0..per {
            let prefix = if s == 0 {
                "bg".to_string()
            } else {
                format!("slot{}", s - 1)
            };
            let weight: Vec<f32> = (0..n).map(|p| self.weights[per * p + s]).collect();
            let order: Vec<f32> = (0..n).map(|p| self.ordering[per * p + s]).collect();
            channels.push(AnyChannel::new(
                format!("{prefix}.weight").as_str(),
                FlatSamples::F32(weight),
            ));
            channels.push(AnyChannel::new(
                format!("{prefix}.order").as_str(),
                FlatSamples::F32(order),
            ));
        }
        let layer = Layer::new(
            (self.width as usize, self.height as usize),
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

    #[test]
    fn mismatched_arrays_are_an_error() {
        let mut f = sample();
        f.weights.pop();
        assert!(f.exr_bytes().is_err());
    }
}
