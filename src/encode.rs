//! Encoding: one image → a codes file's content (slots in world frames, masses, sources).

use crate::codes::{Codes, Slot};
use crate::image_io::RgbImage32;
use crate::model::Colf;
use anyhow::{bail, Result};
use glam::DMat4;

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
    /// Camera-to-world of the image's camera: every slot's frame (identity without a camera).
    pub camera_to_world: DMat4,
    /// Name recorded in `sources` as `NAME#k` (k = the slot's index before pruning).
    pub source: String,
}

/// Encodes `image` with `model`.
pub fn encode_image(model: &Colf, image: &RgbImage32, opts: &EncodeOptions) -> Result<Codes> {
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
    let slots = encoded
        .fg_latents
        .into_iter()
        .zip(encoded.slot_mass)
        .enumerate()
        .filter(|(_, (_, mass))| opts.prune_mass.is_none_or(|m| *mass as f64 >= m))
        .map(|(k, (latent, mass))| Slot {
            latent,
            slot_to_world: opts.camera_to_world,
            mass: mass.clamp(0.0, 1.0),
            source: format!("{}#{k}", opts.source),
        })
        .collect();
    Ok(Codes {
        slots,
        background: encoded.bg_latent,
        model: model.identity()?,
    })
}
