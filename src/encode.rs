//! Encoding: one image → a codes file's content (slots in world frames, masses, sources).

use crate::camera::{Frame, Intrinsics};
use crate::codes::{Codes, Slot};
use crate::image_io::RgbImage32;
use crate::model::Colf;
use crate::refine::{refine_latents, RefineOptions, RefineReport};
use anyhow::{bail, Result};

/// Largest slot count `colf-encode` accepts: slot attention runs with any K, but beyond this a
/// typo (`--slots 100000`) would only burn memory.
pub const MAX_ENCODE_SLOTS: usize = 1024;

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
    if let Some(m) = opts.prune_mass {
        if !(0.0..=1.0).contains(&m) {
            bail!("--prune {m} is outside [0, 1]");
        }
    }
    let encoded = model.encode(
        &image.data,
        image.h as usize,
        image.w as usize,
        opts.num_slots,
        opts.seed,
    )?;
    let camera = opts
        .camera
        .clone()
        .unwrap_or_else(|| default_camera(image.w, image.h));
    let frames = crate::model::frames::slot_frames(model.config(), &camera, &encoded.fg_centroid);
    let mut slots: Vec<Slot> = encoded
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
    let mut background = encoded.bg_latent;
    let report = if opts.refine.steps > 0 {
        // After pruning: the kept slots learn to cover what the dropped ones rendered.
        let mut latents: Vec<Vec<f32>> = slots.iter().map(|s| s.latent.clone()).collect();
        let frames: Vec<glam::DMat4> = slots.iter().map(|s| s.slot_to_world).collect();
        let report = refine_latents(
            model,
            &mut latents,
            &mut background,
            &frames,
            &camera,
            image,
            &opts.refine,
        )?;
        for (slot, latent) in slots.iter_mut().zip(latents) {
            slot.latent = latent;
        }
        Some(report)
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
