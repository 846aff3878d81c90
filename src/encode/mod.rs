//! Encoding: one image → a codes file's content (slots in world frames, masses, sources).
//!
//! An encoding is a pipeline of four steps over one [`InputView`] (the image, its camera and
//! the world rays of its pixels, built once), each its own function:
//! 1. [`encode_once`]: one pass of the encoder and slot attention with a seeded slot noise;
//!    slots placed in world frames from the camera, and pruned by attention mass.
//! 2. [`best_of_tries`]: step 1 with `tries` seeds, keeping the encoding that renders the input
//!    view best.
//! 3. [`refine::refine_slots`]: test-time refinement of the latents and frame origins on the
//!    input view (`refine.steps`, none by default).
//! 4. [`redundant::drop_redundant_slots`]: the slots the view does not need dropped.
//!
//! Several views of one scene: [`multiview::encode_views`] runs steps 1–2 per view, matches
//! the views' slots into one per object, then steps 3–4 on all views at once.
//!
//! A model file may carry its own default encoding (its config's `inference`); the CLIs read
//! it and fill [`EncodeOptions`].

pub mod multiview;
pub mod redundant;
pub mod refine;
pub mod residual;
pub mod view;

use crate::camera::{Frame, Intrinsics};
use crate::codes::{Codes, Slot};
use crate::image_io::RgbImage32;
use crate::model::{Colf, Config};
use anyhow::{bail, Result};
pub use redundant::drop_redundant_slots;
use refine::{RefineOptions, RefineReport};
pub use view::InputView;

pub use crate::model::config::{MAX_ENCODE_SLOTS, MAX_ENCODE_TRIES};

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
    /// Drop slots the image does not need, as long as the input view's mean squared error
    /// grows by at most this in all (0: keep every slot); see [`drop_redundant_slots`].
    pub redundant_mse: f64,
    /// With several views: at most this many slots added where the views agree on an object
    /// no slot draws ([`residual::add_agreed_slots`]; 0: none). Not read for one view.
    pub agreed_slots: usize,
    /// With three views or more: before each later view's slots are matched, the slots kept so
    /// far are refined this many steps on the views already taken (0: none; see
    /// [`multiview::encode_views`]). Not read for one or two views.
    pub triangulate_steps: usize,
}

impl EncodeOptions {
    /// One pass of the encoder with `num_slots` slots, seed 0, nothing else (no camera: set
    /// `camera` and `source` for the image at hand).
    pub fn one_pass(num_slots: usize) -> EncodeOptions {
        EncodeOptions {
            num_slots,
            prune_mass: None,
            seed: 0,
            camera: None,
            source: String::new(),
            tries: 1,
            refine: RefineOptions::default(),
            redundant_mse: 0.0,
            agreed_slots: 0,
            triangulate_steps: 0,
        }
    }

    /// Refuses values no encoding can use; messages name the setting, the CLIs the flag.
    pub fn check(&self) -> Result<()> {
        if self.num_slots > MAX_ENCODE_SLOTS {
            bail!(
                "{} slots is more than the {MAX_ENCODE_SLOTS} supported",
                self.num_slots
            );
        }
        if !(1..=MAX_ENCODE_TRIES).contains(&self.tries) {
            bail!("{} tries is outside 1..={MAX_ENCODE_TRIES}", self.tries);
        }
        if let Some(m) = self.prune_mass {
            if !(0.0..=1.0).contains(&m) {
                bail!("a pruning mass of {m} is outside [0, 1]");
            }
        }
        if !(0.0..=1.0).contains(&self.redundant_mse) {
            bail!(
                "a redundant-slot budget of {} is outside [0, 1]",
                self.redundant_mse
            );
        }
        Ok(())
    }
}

/// The default of [`EncodeOptions::redundant_mse`]: removing slots may cost the input view at
/// most this mean squared error (0.14 dB at 32 dB; about one pixel of a small object wrongly
/// coloured at 64²). Chosen on the held-out scenes (`docs/refinement.md`).
pub const DEFAULT_REDUNDANT_MSE: f64 = 2e-5;

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
    opts.check()?;
    refine::check_mask(model, &opts.refine)?;
    let camera = opts
        .camera
        .clone()
        .unwrap_or_else(|| default_camera(image.w, image.h));
    let view = InputView::new(&camera, image);
    // 1–2. One pass per try, the best kept. Judged before refinement: refining every try and
    // judging after it scored the same on the held-out scenes at `tries` times the cost.
    // The working renders (judging tries and redundant slots, refinement) leave out the far
    // shadow lines and slots (`RefineOptions::reached_config`); the codes are exact.
    let reached = opts.refine.reached_config(model.config());
    let (mut slots, mut background) = best_of_tries(model, &view, opts, reached.as_ref())?;
    // 3. After pruning: the kept slots learn to cover what the dropped ones rendered.
    let report = if opts.refine.steps > 0 {
        Some(refine::refine_slots(
            model,
            &mut slots,
            &mut background,
            &[&view],
            &opts.refine,
        )?)
    } else {
        None
    };
    // 4. After refinement: dropping slots before it and refining the rest scored worse on the
    // held-out scenes (`docs/refinement.md`); after it, the survivors already draw the objects.
    let slots = drop_redundant_slots(
        model,
        slots,
        &background,
        &[&view],
        opts.redundant_mse,
        reached.as_ref(),
    )?;
    Ok((
        Codes {
            slots,
            background,
            model: model.identity()?,
        },
        report,
    ))
}

/// Step 2: [`encode_once`] with seeds `seed`, `seed + 1`, … (`tries` of them); the encoding
/// whose slots render the input view with the least error (rendered within `reached`'s bounds,
/// see [`InputView::mse`]).
pub fn best_of_tries(
    model: &Colf,
    view: &InputView,
    opts: &EncodeOptions,
    reached: Option<&Config>,
) -> Result<(Vec<Slot>, Vec<f32>)> {
    if opts.tries == 1 {
        return encode_once(model, view, opts, opts.seed);
    }
    let mut best: Option<(f64, Vec<Slot>, Vec<f32>)> = None;
    for t in 0..opts.tries {
        let (slots, background) = encode_once(model, view, opts, opts.seed.wrapping_add(t as u64))?;
        let (latents, frames) = latents_and_frames(&slots);
        let error = view.mse(model, &latents, &background, &frames, reached)?;
        if best.as_ref().is_none_or(|(e, _, _)| error < *e) {
            best = Some((error, slots, background));
        }
    }
    let Some((_, slots, background)) = best else {
        bail!("no encoding was made");
    };
    Ok((slots, background))
}

/// Step 1: one pass of the encoder with slot noise `seed`: the kept slots (pruned by mass) in
/// their frames, and the background latent.
pub fn encode_once(
    model: &Colf,
    view: &InputView,
    opts: &EncodeOptions,
    seed: u64,
) -> Result<(Vec<Slot>, Vec<f32>)> {
    let image = view.image;
    let objects = if model.config().frames_from_residual {
        Some(view.object_pixels(model)?)
    } else {
        None
    };
    let encoded = model.encode_within(
        &image.data,
        image.h as usize,
        image.w as usize,
        opts.num_slots,
        seed,
        objects,
    )?;
    let frames = crate::model::frames::slot_frames(
        model.config(),
        view.camera,
        &encoded.fg_centroid,
        &encoded.fg_bottom,
    );
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

/// The latents and frames of `slots`, in order.
pub(crate) fn latents_and_frames(slots: &[Slot]) -> (Vec<Vec<f32>>, Vec<glam::DMat4>) {
    slots
        .iter()
        .map(|s| (s.latent.clone(), s.slot_to_world))
        .unzip()
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
            redundant_mse: 0.0,
            agreed_slots: 0,
            triangulate_steps: 0,
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
                let error = InputView::new(&camera, &img)
                    .mse(&model, &latents, &codes.background, &frames, None)
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
    fn redundant_slots_are_dropped_within_the_error_budget() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(16);
        let camera = default_camera(16, 16);
        let view = InputView::new(&camera, &img);
        let mut opts = options(3, 1);
        opts.num_slots = 6;
        let Codes {
            slots: all,
            background,
            ..
        } = encode_image(&model, &img, &opts).unwrap();
        let error = |slots: &[Slot], background: &[f32]| {
            let (latents, frames) = latents_and_frames(slots);
            view.mse(&model, &latents, background, &frames, None)
                .unwrap()
        };
        let base = error(&all, &background);
        // No budget: every slot stays.
        let kept =
            drop_redundant_slots(&model, all.clone(), &background, &[&view], 0.0, None).unwrap();
        assert_eq!(kept, all);
        // Any budget: what is left renders the image within it, in the original order.
        for tolerance in [1e-5, 1e-3, 1e-2] {
            let kept =
                drop_redundant_slots(&model, all.clone(), &background, &[&view], tolerance, None)
                    .unwrap();
            assert!(error(&kept, &background) <= base + tolerance, "{tolerance}");
            let mut rest = all.iter();
            assert!(kept.iter().all(|k| rest.any(|s| s == k)), "order kept");
        }
        // A budget as large as any error: no slot is needed.
        let kept = drop_redundant_slots(&model, all, &background, &[&view], 1.0, None).unwrap();
        assert!(kept.is_empty());
    }

    #[test]
    fn an_absurd_redundancy_budget_is_refused() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let mut opts = options(0, 1);
        for budget in [-1e-3, 1.5, f64::NAN] {
            opts.redundant_mse = budget;
            let err = encode_image(&model, &image(8), &opts).unwrap_err();
            assert!(err.to_string().contains("redundant-slot budget"), "{err}");
        }
    }

    #[test]
    fn absurd_tries_are_refused() {
        let model = Colf::init(&Config::small(), 1).unwrap();
        let img = image(8);
        for tries in [0, MAX_ENCODE_TRIES + 1] {
            let err = encode_image(&model, &img, &options(0, tries)).unwrap_err();
            assert!(err.to_string().contains("tries"), "{err}");
        }
    }
}
