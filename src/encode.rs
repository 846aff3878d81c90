//! Encoding: one image → a codes file's content (slots in world frames, masses, sources).

use crate::camera::{Frame, Intrinsics};
use crate::codes::{Codes, Slot};
use crate::image_io::RgbImage32;
use crate::model::Colf;
use crate::refine::{input_view_mse, refine_latents_on_views, RefineOptions, RefineReport};
use anyhow::{bail, Result};

pub use crate::model::config::{MAX_ENCODE_SLOTS, MAX_ENCODE_TRIES};

/// The latents and frames of `slots`, in order.
fn latents_and_frames(slots: &[Slot]) -> (Vec<Vec<f32>>, Vec<glam::DMat4>) {
    slots
        .iter()
        .map(|s| (s.latent.clone(), s.slot_to_world))
        .unzip()
}

/// Refines `slots` (latents and frames) and `background` against `views`, in place; see
/// [`refine_latents_on_views`].
pub fn refine_slots(
    model: &Colf,
    slots: &mut [Slot],
    background: &mut Vec<f32>,
    views: &[(&Frame, &RgbImage32)],
    opts: &RefineOptions,
) -> Result<RefineReport> {
    let (mut latents, mut frames) = latents_and_frames(slots);
    let report =
        refine_latents_on_views(model, &mut latents, background, &mut frames, views, opts)?;
    for ((slot, latent), frame) in slots.iter_mut().zip(latents).zip(frames) {
        slot.latent = latent;
        slot.slot_to_world = frame;
    }
    Ok(report)
}

/// How to encode one image.
#[derive(Clone, Debug)]
pub struct EncodeOptions {
    /// Foreground slots K.
    pub num_slots: usize,
    /// Drop slots whose attention mass is below this.
    pub prune_mass: Option<f64>,
    /// Seed of the slot noise.
    pub seed: u64,
    /// The image's camera (None: the image's camera frame is the world, see [`default_camera`]).
    /// Slots' frames are placed from it (`model::frames`).
    pub camera: Option<Frame>,
    /// Name recorded in `sources` as `NAME#k` (k = the slot's index before pruning).
    pub source: String,
    /// Encode this many times (slot noise seeds `seed`, `seed + 1`, …) and keep the encoding
    /// that reconstructs the image best (1: one pass).
    pub tries: usize,
    /// Test-time refinement of the kept slots' latents on this image (`steps: 0`: none).
    pub refine: RefineOptions,
}

/// The camera assumed for an image given without one: at the world origin in OpenGL axes
/// (so the image's camera frame is the world), with the clevr567 field of view (49.13°).
pub fn default_camera(w: u32, h: u32) -> Frame {
    Frame {
        file_path: None,
        intrinsics: Intrinsics::from_fov(w, h, 49.13),
        camera_to_world: glam::DMat4::IDENTITY,
    }
}

/// Encodes `image` with `model`.
pub fn encode_image(model: &Colf, image: &RgbImage32, opts: &EncodeOptions) -> Result<Codes> {
    Ok(encode_image_report(model, image, opts)?.0)
}

/// One pass of the encoder with slot noise `seed`: the kept slots (pruned by mass) in their
/// frames, and the background latent.
fn encode_once(
    model: &Colf,
    image: &RgbImage32,
    camera: &Frame,
    opts: &EncodeOptions,
    seed: u64,
) -> Result<(Vec<Slot>, Vec<f32>)> {
    let encoded = model.encode(
        &image.data,
        image.h as usize,
        image.w as usize,
        opts.num_slots,
        seed,
    )?;
    let frames = crate::model::frames::slot_frames(model.config(), camera, &encoded.fg_centroid);
    let slots = encoded
        .fg_latents
        .into_iter()
        .zip(encoded.slot_mass)
        .zip(frames)
        .enumerate()
        .filter(|(_, ((_, mass), _))| opts.prune_mass.is_none_or(|m| *mass as f64 >= m))
        .map(|(k, ((latent, mass), slot_to_world))| Slot {
            latent,
            slot_to_world,
            mass: mass.clamp(0.0, 1.0),
            source: format!("{}#{k}", opts.source),
        })
        .collect();
    Ok((slots, encoded.bg_latent))
}

/// Encodes `image` with `model`; also returns what refinement did, if it ran.
pub fn encode_image_report(
    model: &Colf,
    image: &RgbImage32,
    opts: &EncodeOptions,
) -> Result<(Codes, Option<RefineReport>)> {
    if opts.num_slots > MAX_ENCODE_SLOTS {
        bail!(
            "--slots {} is more than the {MAX_ENCODE_SLOTS} supported",
            opts.num_slots
        );
    }
    if !(1..=MAX_ENCODE_TRIES).contains(&opts.tries) {
        bail!("--tries {} is outside 1..={MAX_ENCODE_TRIES}", opts.tries);
    }
    if let Some(m) = opts.prune_mass {
        if !(0.0..=1.0).contains(&m) {
            bail!("--prune {m} is outside [0, 1]");
        }
    }
    let camera = opts
        .camera
        .clone()
        .unwrap_or_else(|| default_camera(image.w, image.h));
    let tries = opts.tries;
    let mut best: Option<(f64, Vec<Slot>, Vec<f32>)> = None;
    for t in 0..tries {
        let (slots, background) = encode_once(
            model,
            image,
            &camera,
            opts,
            opts.seed.wrapping_add(t as u64),
        )?;
        if tries == 1 {
            best = Some((0.0, slots, background));
            break;
        }
        let (latents, frames) = latents_and_frames(&slots);
        let error = input_view_mse(model, &latents, &background, &frames, &camera, image)?;
        if best.as_ref().is_none_or(|(e, _, _)| error < *e) {
            best = Some((error, slots, background));
        }
    }
    // Judged before refinement: refining every try and judging after it scored the same on the
    // 100 held-out scenes (26.86 dB with 4 tries and 50 steps) at 4× the time.
    let Some((_, mut slots, mut background)) = best else {
        bail!("no encoding was made");
    };
    let report = if opts.refine.steps > 0 {
        // After pruning: the kept slots learn to cover what the dropped ones rendered.
        let views = [(&camera, image)];
        Some(refine_slots(
            model,
            &mut slots,
            &mut background,
            &views,
            &opts.refine,
        )?)
    } else {
        None
    };
    Ok((
        Codes {
            slots,
            background,
            model: model.identity()?,
        },
        report,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Config;

    fn image(size: u32) -> RgbImage32 {
        let data = (0..3 * size * size)
            .map(|i| ((i * 37 % 101) as f32) / 100.0)
            .collect();
        RgbImage32 {
            w: size,
            h: size,
            data,
        }
    }

    fn options(seed: u64, tries: usize) -> EncodeOptions {
        EncodeOptions {
            num_slots: 3,
            prune_mass: None,
            seed,
            camera: None,
            source: "t".into(),
            tries,
            refine: RefineOptions::default(),
        }
    }

    #[test]
    fn tries_keep_the_encoding_that_reconstructs_best() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(16);
        let camera = default_camera(16, 16);
        let singles: Vec<(f64, Codes)> = (5..8)
            .map(|seed| {
                let codes = encode_image(&model, &img, &options(seed, 1)).unwrap();
                let (latents, frames) = latents_and_frames(&codes.slots);
                let error =
                    input_view_mse(&model, &latents, &codes.background, &frames, &camera, &img)
                        .unwrap();
                (error, codes)
            })
            .collect();
        let best = singles.iter().min_by(|a, b| a.0.total_cmp(&b.0)).unwrap();
        assert_eq!(encode_image(&model, &img, &options(5, 3)).unwrap(), best.1);
        // One try is the plain encoding.
        assert_eq!(
            encode_image(&model, &img, &options(5, 1)).unwrap(),
            singles[0].1
        );
    }

    #[test]
    fn absurd_tries_are_refused() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(8);
        for tries in [0, MAX_ENCODE_TRIES + 1] {
            let err = encode_image(&model, &img, &options(0, tries)).unwrap_err();
            assert!(err.to_string().contains("--tries"), "{err}");
        }
    }
}
