//! Test-time refinement of slot latents: the encoder's slots are an amortised guess, made in one
//! pass for any scene; a few Adam steps on the latents (and, gently, on the slot frames'
//! origins; the model's weights fixed) then lower the input view's colour error for this
//! scene. Only the input image is used, so novel views are still predictions; the decoder,
//! trained on many views of many scenes, is the prior that keeps a refined latent a 3-D object
//! (how far that holds is measured in `docs/refinement.md`).
//!
//! Each step renders a seeded random subset of the input view's pixels (all of them when the
//! image has no more than `rays` pixels), so a step costs one training step's decoder pass on
//! one view, and the result is the same for the same inputs.

use super::latents_and_frames;
use super::view::InputView;
use crate::camera::Frame;
use crate::codes::Slot;
use crate::image_io::RgbImage32;
use crate::metrics::psnr_from_mse;
use crate::model::decode_kernel::RayMotion;
use crate::model::rays::MovingRays;
use crate::model::{Colf, ColfNet, Config, HostRays, RayBatch, SceneRays};
use crate::optim::{Adam, AdamConfig};
use anyhow::{bail, Context, Result};
use candle_core::{CpuStorage, CustomOp2, Layout, Shape, Tensor, Var};
use glam::{DMat4, DVec3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use std::sync::Arc;

/// How to refine (serialised as is into colf-eval's JSON, so a refined score says how it was
/// made).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct RefineOptions {
    /// Adam steps (0: no refinement).
    pub steps: usize,
    /// Adam's learning rate on the latents.
    pub lr: f64,
    /// Pixels rendered per step (all of them when the image has fewer).
    pub rays: usize,
    /// Weight of the pull toward the encoder's latents, λ·mean((z − z₀)²): keeps a latent near
    /// what the decoder was trained on.
    pub anchor_weight: f64,
    /// Adam's learning rate on the slots' frame origins (world units; 0: frames fixed).
    pub frame_lr: f64,
    /// A slot's light field is evaluated only on the pixels near where its compositor weight or
    /// its shadow exceeds this ([`Support`]; 0: every slot on every pixel). Elsewhere it
    /// neither draws nor receives gradient: most slots matter on a small part of the image.
    pub support: f64,
    /// For a model whose slots cast shadows along the light and that sets no `shadow_reach` of
    /// its own: during refinement, a slot's shadow line farther than this from its frame origin
    /// is not evaluated (world units; 0: every line). Half of a step's light-field evaluations
    /// are shadow lines, and far ones carry almost no shadow (`docs/speed.md`). A one-image
    /// encoding judges its tries and redundant slots the same way (`reached_config`); the codes
    /// are rendered with the model's own shadows.
    pub shadow_reach: f64,
    /// For a light-field model that sets no `slot_reach` of its own: during refinement, a slot
    /// is left out of the pixels whose ray passes farther than this from its frame origin
    /// (frame units; 0: every slot on every pixel), as `Config::slot_reach` does. A one-image
    /// encoding judges its tries and redundant slots the same way (`reached_config`); the codes
    /// are rendered with the model's own slots.
    pub slot_reach: f64,
    /// For a model with a static background (`Config::static_background`): weight of the
    /// compositor's mask loss against each view's object proposals (those pixels the
    /// background's render does not explain, grouped into objects; `--proposals-against` in
    /// training), objects matched to slots view by view, as the trainer's `--mask-weight`
    /// (0: colour alone). The colour loss alone lets the background keep an object's pixels
    /// that look like it (a dark car's wheels on a dark road). Not serialised when 0.
    #[serde(skip_serializing_if = "crate::model::config::is_zero")]
    pub mask_weight: f64,
    /// With `mask_weight`: proposal pixels left unsure within this many pixels of an object
    /// are counted to it, as the trainer's `--mask-claim`. Not serialised when 0.
    #[serde(skip_serializing_if = "crate::model::config::is_zero_count")]
    pub mask_claim: usize,
    /// With `mask_weight`: match each view's objects to slots and ask each object's pixels of
    /// its slot, as training does; without, an object's pixels ask only that some slot draw
    /// them (the background none), and the colour loss says which. Not serialised when false.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub mask_match: bool,
    /// Seed of the pixel subsets.
    pub seed: u64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        RefineOptions {
            steps: 0,
            lr: 0.01,
            rays: 1024,
            anchor_weight: 0.0,
            frame_lr: 0.003,
            support: DEFAULT_SUPPORT,
            shadow_reach: DEFAULT_REFINE_SHADOW_REACH,
            slot_reach: DEFAULT_REFINE_SLOT_REACH,
            mask_weight: 0.0,
            mask_claim: 0,
            mask_match: false,
            seed: 0,
        }
    }
}

/// The default of [`RefineOptions::support`]: off. With the bundled models an unused slot still
/// takes a compositor weight of 10⁻³–10⁻² on most pixels, so a support only pays at thresholds
/// that change the renders; measured in `docs/speed.md`.
pub const DEFAULT_SUPPORT: f64 = 0.0;

/// The default of [`RefineOptions::shadow_reach`], world units. Measured with the bundled model
/// on the 100 held-out analytic 128² scenes (`docs/speed.md`): 3 units cost 0.0025 dB and
/// 0.0024 FG-ARI and save 18 % of the default encoding's CPU time; 5 units change nothing
/// (+0.0001 dB) and save 11 %.
pub const DEFAULT_REFINE_SHADOW_REACH: f64 = 3.0;

/// The default of [`RefineOptions::slot_reach`], frame units. Measured with the bundled model
/// on the 100 held-out analytic 128² scenes (`docs/speed.md`): 3 units give +0.014 dB and
/// −0.0002 FG-ARI for 1.6× less CPU time in the default encoding (in refinement alone; with
/// the tries and redundant slots judged within it too, +0.007 dB and −0.0016 FG-ARI, 1.8×).
pub const DEFAULT_REFINE_SLOT_REACH: f64 = 3.0;

impl RefineOptions {
    /// The model's config `cfg` with this refinement's reaches (`shadow_reach`, `slot_reach`)
    /// where it sets none of its own; None when neither applies (the model is used as it is).
    /// An encoding's working renders — refinement, and judging its tries and its redundant
    /// slots — use it; its codes are rendered with the model's own config.
    pub fn reached_config(&self, cfg: &Config) -> Option<Config> {
        let add_shadow_reach =
            self.shadow_reach > 0.0 && cfg.shadow_light.is_some() && cfg.shadow_reach == 0.0;
        let add_slot_reach = self.slot_reach > 0.0 && cfg.slot_reach == 0.0 && !cfg.is_volumetric();
        (add_shadow_reach || add_slot_reach).then(|| {
            let mut reached = cfg.clone();
            if add_shadow_reach {
                reached.shadow_reach = self.shadow_reach;
            }
            if add_slot_reach {
                reached.slot_reach = self.slot_reach;
            }
            reached
        })
    }
}

/// Steps between two computations of the slots' supports (latents and frames move little
/// in that many steps).
const SUPPORT_EVERY: usize = 10;

/// What a refinement did: the input view's PSNR (on the rendered subsets) at the first and the
/// last step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineReport {
    pub steps: usize,
    pub first_psnr: f64,
    pub last_psnr: f64,
}

/// Refines `fg_latents` (and the background latent, unless the model fixes it to zero; and the
/// frame origins in `slot_to_world` when `opts.frame_lr > 0`) so that the slots render `image`
/// as seen by `camera`. Returns the report; the latents and frames are replaced only if every
/// refined value is finite.
///
/// Frame origins enter the rays' encoding on the host (`RayBatch::new`), outside the autodiff
/// graph; each step therefore linearises the encoding around the current origins (a forward
/// difference of `FRAME_STEP` world units per axis) and takes the gradient through that
/// linearisation, which at the current origins is the true gradient.
pub fn refine_latents(
    model: &Colf,
    fg_latents: &mut [Vec<f32>],
    bg_latent: &mut Vec<f32>,
    slot_to_world: &mut [DMat4],
    camera: &Frame,
    image: &RgbImage32,
    opts: &RefineOptions,
) -> Result<RefineReport> {
    let view = InputView::new(camera, image);
    refine_latents_on_views(model, fg_latents, bg_latent, slot_to_world, &[&view], opts)
}

/// Refines `slots` (latents and frames) and `background` against `views`, in place; see
/// [`refine_latents`].
pub fn refine_slots(
    model: &Colf,
    slots: &mut [Slot],
    background: &mut Vec<f32>,
    views: &[&InputView],
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

/// [`refine_latents`] against several views of the scene at once: each step draws its pixels
/// from all of them.
pub fn refine_latents_on_views(
    model: &Colf,
    fg_latents: &mut [Vec<f32>],
    bg_latent: &mut Vec<f32>,
    slot_to_world: &mut [DMat4],
    views: &[&InputView],
    opts: &RefineOptions,
) -> Result<RefineReport> {
    // 1. Options and model checked; nothing to do without steps or slots.
    check(model, views, opts)?;
    if opts.steps == 0 || fg_latents.is_empty() {
        return Ok(RefineReport {
            steps: 0,
            first_psnr: f64::NAN,
            last_psnr: f64::NAN,
        });
    }
    // 2. The pixels of every view, which the steps draw from, and their object proposals
    //    when a mask loss asks for them.
    let pixels = Pixels::gather(views);
    let proposals = (opts.mask_weight > 0.0)
        .then(|| PixelProposals::gather(model, views, opts.mask_claim))
        .transpose()?;
    // 3. The variables (latents, frame offsets) and their optimisers.
    let mut refinement = Refinement::new(
        model,
        fg_latents,
        bg_latent,
        slot_to_world,
        opts.reached_config(model.config()),
    )?;
    // 4. The steps: a seeded draw of pixels, the decoder, Adam.
    let n = pixels.origins.len();
    let per_step = opts.rays.min(n);
    let move_frames = opts.frame_lr > 0.0;
    // Every pixel once and fixed frames: one batch for all steps.
    let fixed = (per_step == n && !move_frames)
        .then(|| pixels.batch(model, slot_to_world, None))
        .transpose()?;
    let mut rng = StdRng::seed_from_u64(opts.seed);
    let (mut first, mut last) = (f64::NAN, f64::NAN);
    let mut support: Option<Support> = None;
    let every_pixel: Vec<usize> = (0..n).collect();
    for step in 0..opts.steps {
        let drawn;
        let drawn_pick;
        let (rays, target, pick) = match &fixed {
            Some(b) => (&b.0, &b.1, &every_pixel),
            None => {
                drawn_pick = if per_step == n {
                    every_pixel.clone()
                } else {
                    (0..per_step).map(|_| rng.random_range(0..n)).collect()
                };
                drawn = if move_frames {
                    pixels.linearised_batch(
                        model,
                        &refinement.frames,
                        &refinement.offset,
                        &drawn_pick,
                    )?
                } else {
                    pixels.batch(model, &refinement.frames, Some(&drawn_pick))?
                };
                (&drawn.0, &drawn.1, &drawn_pick)
            }
        };
        if opts.support > 0.0 && step % SUPPORT_EVERY == 0 {
            support = Some(refinement.support(model, &pixels, opts.support)?);
        }
        let fields = support.as_ref().map(|s| s.fields_of(pick));
        let mask = proposals.as_ref().map(|p| p.of(pick));
        // A non-finite gradient: keep what the last good step gave.
        let Some(mse) = refinement.step(rays, target, opts, fields, mask)? else {
            break;
        };
        if step == 0 {
            first = psnr_from_mse(mse.max(1e-12));
        }
        last = psnr_from_mse(mse.max(1e-12));
    }
    // 5. The result, kept only if every value is finite.
    refinement.write_back(fg_latents, bg_latent, slot_to_world)?;
    Ok(RefineReport {
        steps: opts.steps,
        first_psnr: first,
        last_psnr: last,
    })
}

/// Refuses options no refinement can use, and models it does not apply to.
fn check(model: &Colf, views: &[&InputView], opts: &RefineOptions) -> Result<()> {
    if !(opts.lr.is_finite() && opts.lr > 0.0 && opts.lr <= MAX_LEARNING_RATE) {
        bail!(
            "refinement learning rate must be in (0, {MAX_LEARNING_RATE}], not {}",
            opts.lr
        );
    }
    if !(opts.anchor_weight.is_finite() && opts.anchor_weight >= 0.0) {
        bail!(
            "refinement anchor weight must be a number ≥ 0, not {}",
            opts.anchor_weight
        );
    }
    if opts.rays == 0 {
        bail!("refinement needs at least 1 ray a step");
    }
    if !(opts.shadow_reach.is_finite() && opts.shadow_reach >= 0.0) {
        bail!(
            "refinement shadow reach must be a distance ≥ 0, not {}",
            opts.shadow_reach
        );
    }
    if !(opts.slot_reach.is_finite() && opts.slot_reach >= 0.0) {
        bail!(
            "refinement slot reach must be a distance ≥ 0, not {}",
            opts.slot_reach
        );
    }
    if !(opts.frame_lr.is_finite() && opts.frame_lr >= 0.0 && opts.frame_lr <= MAX_LEARNING_RATE) {
        bail!(
            "refinement frame learning rate must be in [0, {MAX_LEARNING_RATE}], not {}",
            opts.frame_lr
        );
    }
    if views.iter().all(|v| v.image.data.is_empty()) {
        bail!("refinement needs at least one view with pixels");
    }
    check_mask(model, opts)?;
    if model.model().light_field().is_none() {
        bail!("refinement applies to light-field models, not the volumetric baseline");
    }
    Ok(())
}

/// Refuses a mask loss ([`RefineOptions::mask_weight`]) that is negative or that `model` cannot
/// have: its proposals are made against a static background's render. Encodings call it before
/// any work.
pub fn check_mask(model: &Colf, opts: &RefineOptions) -> Result<()> {
    if !(opts.mask_weight.is_finite() && opts.mask_weight >= 0.0) {
        bail!(
            "refinement mask weight must be a number ≥ 0, not {}",
            opts.mask_weight
        );
    }
    if opts.mask_weight > 0.0 && opts.steps > 0 && !model.config().static_background {
        bail!("refinement's mask loss needs a model with a static background (its proposals are made against that background's render); this model reads its background from the image");
    }
    Ok(())
}

/// The largest learning rate refinement accepts (the same bound as a model config's).
pub const MAX_LEARNING_RATE: f64 = crate::model::config::MAX_REFINE_LR;

/// The rays and colours of every pixel of the views, in order (public for the fitting examples,
/// `examples/capacity_fit`).
pub struct Pixels {
    pub origins: Vec<DVec3>,
    pub dirs: Vec<DVec3>,
    pub rgb: Vec<f32>,
    /// Each view's first pixel, width and height (its pixels are row-major from there).
    pub views: Vec<(usize, usize, usize)>,
}

impl Pixels {
    pub fn gather(views: &[&InputView]) -> Pixels {
        let mut pixels = Pixels {
            origins: Vec::new(),
            dirs: Vec::new(),
            rgb: Vec::new(),
            views: Vec::new(),
        };
        for view in views {
            let (w, h) = (view.image.w as usize, view.image.h as usize);
            pixels.views.push((pixels.origins.len(), w, h));
            pixels.origins.extend_from_slice(&view.origins);
            pixels.dirs.extend_from_slice(&view.dirs);
            pixels.rgb.extend_from_slice(&view.image.data);
        }
        pixels
    }
}

/// The object proposals of every pixel of the views, in [`Pixels`]' order, with the view each
/// pixel belongs to (proposal ids are local to a view).
struct PixelProposals {
    ids: Vec<u8>,
    views: Vec<usize>,
}

impl PixelProposals {
    /// Each view's proposals against `model`'s background ([`InputView::proposal_ids`]), unsure
    /// pixels within `claim` pixels of an object counted to it.
    fn gather(model: &Colf, views: &[&InputView], claim: usize) -> Result<PixelProposals> {
        let (mut ids, mut of_view) = (Vec::new(), Vec::new());
        for (v, view) in views.iter().enumerate() {
            let (w, h) = (view.image.w as usize, view.image.h as usize);
            let claimed = crate::proposals::claim_edges(view.proposal_ids(model)?, w, h, claim);
            of_view.extend(std::iter::repeat_n(v, claimed.len()));
            ids.extend(claimed);
        }
        Ok(PixelProposals {
            ids,
            views: of_view,
        })
    }

    /// The ids and views of the pixels `pick`.
    fn of(&self, pick: &[usize]) -> (Vec<u8>, Vec<usize>) {
        pick.iter().map(|&p| (self.ids[p], self.views[p])).unzip()
    }
}

/// The refined variables: the latents as candle `Var`s with Adam, and the frames on the host,
/// moved by a zero-read offset `Var` with an Adam of its own.
struct Refinement<'a> {
    /// The model's network, with `RefineOptions::shadow_reach` and `slot_reach` applied.
    net: std::borrow::Cow<'a, ColfNet>,
    fg0: Tensor,
    fg: Var,
    bg: Var,
    adam: Adam,
    frames: Vec<DMat4>,
    /// The frame origins' offsets from `frames` (foreground slots; axis-major [3, K]), always
    /// zero when read: each step's update is moved into `frames`.
    offset: Var,
    frame_adam: Adam,
}

impl<'a> Refinement<'a> {
    fn new(
        model: &'a Colf,
        fg_latents: &[Vec<f32>],
        bg_latent: &[f32],
        slot_to_world: &[DMat4],
        reached: Option<Config>,
    ) -> Result<Refinement<'a>> {
        let cfg = model.config();
        let net = match reached {
            Some(reached) => {
                let mut net = model.model().clone();
                net.cfg = reached;
                std::borrow::Cow::Owned(net)
            }
            None => std::borrow::Cow::Borrowed(model.model()),
        };
        let (k, d) = (fg_latents.len(), cfg.slot_dim);
        let dev = model.device();
        let fg0 = Tensor::from_vec(
            fg_latents.iter().flatten().copied().collect::<Vec<f32>>(),
            (1, k, d),
            dev,
        )?;
        let fg = Var::from_tensor(&fg0)?;
        let bg = Var::from_tensor(&Tensor::from_vec(bg_latent.to_vec(), (1, d), dev)?)?;
        let mut params = vec![("fg".to_string(), fg.clone())];
        if !cfg.zero_background {
            params.push(("bg".to_string(), bg.clone()));
        }
        let unclipped = AdamConfig {
            clip_norm: None,
            ..AdamConfig::default()
        };
        let offset = Var::zeros((3, k), candle_core::DType::F32, dev)?;
        Ok(Refinement {
            net,
            fg0,
            fg,
            bg,
            adam: Adam::new(params, unclipped)?,
            frames: slot_to_world.to_vec(),
            frame_adam: Adam::new(vec![("offset".to_string(), offset.clone())], unclipped)?,
            offset,
        })
    }

    /// One Adam step on `rays` against `target`: the step's colour MSE, or None when a
    /// gradient was not finite (nothing was changed then).
    fn step(
        &mut self,
        rays: &RayBatch,
        target: &Tensor,
        opts: &RefineOptions,
        support: Option<Vec<Vec<u32>>>,
        mask: Option<(Vec<u8>, Vec<usize>)>,
    ) -> Result<Option<f64>> {
        let fields = self.net.prepare(self.fg.as_tensor(), self.bg.as_tensor())?;
        let decoded = match support {
            Some(support) => self.net.decode_with_support(&fields, rays, support)?,
            None => self.net.decode(&fields, rays)?,
        };
        let mse = (&decoded.rgb - target)?.sqr()?.mean_all()?;
        let mse_value = mse.to_scalar::<f32>()? as f64;
        let mut loss = mse;
        if opts.anchor_weight > 0.0 {
            let pull = (self.fg.as_tensor() - &self.fg0)?.sqr()?.mean_all()?;
            loss = (loss + (pull * opts.anchor_weight)?)?;
        }
        if let Some((ids, views)) = mask {
            let ce = if opts.mask_match {
                Some(crate::train::trainer::proposal_mask_loss(
                    &decoded.log_weights,
                    &ids,
                    &views,
                )?)
            } else {
                crate::train::trainer::proposal_foreground_loss(&decoded.log_weights, &ids)?
            };
            if let Some(ce) = ce {
                loss = (loss + (ce * opts.mask_weight)?)?;
            }
        }
        let grads = loss.backward()?;
        if self.adam.step(&grads, opts.lr).is_err() {
            return Ok(None);
        }
        if opts.frame_lr > 0.0 {
            if self.frame_adam.step(&grads, opts.frame_lr).is_err() {
                return Ok(None);
            }
            let moved = self.offset.as_tensor().to_vec2::<f32>()?;
            for (slot, frame) in self.frames.iter_mut().enumerate() {
                let delta = DVec3::new(
                    moved[0][slot] as f64,
                    moved[1][slot] as f64,
                    moved[2][slot] as f64,
                );
                frame.w_axis += delta.extend(0.0);
            }
            self.offset.set(&self.offset.as_tensor().zeros_like()?)?;
        }
        Ok(Some(mse_value))
    }

    /// Where each slot matters now ([`Support`]): the compositor weights and shadows of the
    /// current latents and frames on every [`SUPPORT_CELL`]-th pixel of each view (both ways),
    /// a slot active on a pixel when it exceeds `eps` on a sample of the 3×3 cells around it.
    fn support(&self, model: &Colf, pixels: &Pixels, eps: f64) -> Result<Support> {
        let c = SUPPORT_CELL;
        // The samples: the centre pixel of every c×c cell of every view.
        let mut samples = Vec::new();
        let mut cells = Vec::new(); // per view: first sample, cells across, cells down
        for &(first, w, h) in &pixels.views {
            let (cw, ch) = (w.div_ceil(c), h.div_ceil(c));
            cells.push((samples.len(), cw, ch));
            for cy in 0..ch {
                for cx in 0..cw {
                    let (x, y) = ((cx * c + c / 2).min(w - 1), (cy * c + c / 2).min(h - 1));
                    samples.push(first + y * w + x);
                }
            }
        }
        let (rays, _) = pixels.batch(model, &self.frames, Some(&samples))?;
        let fields = self.net.prepare(self.fg.as_tensor(), self.bg.as_tensor())?;
        let decoded = self.net.decode(&fields, &rays)?;
        let s = rays.fields;
        let weights = decoded.weights.flatten_all()?.to_vec1::<f32>()?;
        let shadow = match &decoded.shadow {
            Some(t) => t.flatten_all()?.to_vec1::<f32>()?,
            None => vec![0.0; weights.len()],
        };
        let eps = eps as f32;
        let hot = |sample: usize, field: usize| {
            weights[sample * s + field] > eps || shadow[sample * s + field] > eps
        };
        let n = pixels.origins.len();
        let mut active = vec![vec![false; n]; s];
        for ((first, w, h), (first_sample, cw, ch)) in pixels.views.iter().zip(&cells) {
            for y in 0..*h {
                for x in 0..*w {
                    let (cx, cy) = (x / c, y / c);
                    for (field, pixels_active) in active.iter_mut().enumerate().skip(1) {
                        let near = (cy.saturating_sub(1)..=(cy + 1).min(ch - 1)).any(|ny| {
                            (cx.saturating_sub(1)..=(cx + 1).min(cw - 1))
                                .any(|nx| hot(first_sample + ny * cw + nx, field))
                        });
                        pixels_active[first + y * w + x] = near;
                    }
                }
            }
        }
        Ok(Support { active })
    }

    /// Writes the refined values back, if every one is finite.
    fn write_back(
        &self,
        fg_latents: &mut [Vec<f32>],
        bg_latent: &mut Vec<f32>,
        slot_to_world: &mut [DMat4],
    ) -> Result<()> {
        let refined_fg = self.fg.as_tensor().squeeze(0)?.to_vec2::<f32>()?;
        let refined_bg = self.bg.as_tensor().squeeze(0)?.to_vec1::<f32>()?;
        let finite = refined_fg
            .iter()
            .flatten()
            .chain(&refined_bg)
            .all(|v| v.is_finite())
            && self.frames.iter().all(|f| f.is_finite());
        if finite {
            slot_to_world.copy_from_slice(&self.frames);
            for (dst, src) in fg_latents.iter_mut().zip(refined_fg) {
                *dst = src;
            }
            *bg_latent = refined_bg;
        }
        Ok(())
    }
}

impl Pixels {
    /// The rays of the pixels `pick` encoded as a function of the foreground frame origins'
    /// offsets `offset` [3, K] (zero at the call): coordinates, shadow lines and ordering shifts
    /// at `frames`, plus their derivatives along each world axis (`HostRays::frame_derivatives`)
    /// times the offsets ([`Linearised`]), so gradients reach `offset`. Returns the batch and the target
    /// colours [1, R, 3].
    fn linearised_batch(
        &self,
        model: &Colf,
        frames: &[DMat4],
        offset: &Var,
        pick: &[usize],
    ) -> Result<(RayBatch, Tensor)> {
        let explicit = model.model().reference_decoder;
        self.linearised_batch_as(model, frames, offset, pick, explicit)
    }

    /// [`Pixels::linearised_batch`] as [`MovingRays`] for the decode kernel, or (`explicit`)
    /// as tensors that are candle functions of the offsets, for candle's autograd.
    fn linearised_batch_as(
        &self,
        model: &Colf,
        frames: &[DMat4],
        offset: &Var,
        pick: &[usize],
        explicit: bool,
    ) -> Result<(RayBatch, Tensor)> {
        let cfg = model.config();
        let dev = model.device();
        let (at, target) = self.host_batch(model, frames, pick)?;
        let (s, r) = (at.fields, at.rays);
        let o: Vec<DVec3> = pick.iter().map(|&p| self.origins[p]).collect();
        let d: Vec<DVec3> = pick.iter().map(|&p| self.dirs[p]).collect();
        let scene = [SceneRays {
            slot_to_world: frames,
            origins: &o,
            dirs: &d,
        }];
        let (mut d_shift, mut background_follows) = (Vec::new(), Vec::new());
        for axis in 0..3 {
            let (shift, follows) = at.shift_derivatives(cfg, &scene, axis)?;
            d_shift.push(shift);
            background_follows = follows;
        }
        let batch = at.into_batch(cfg, dev)?;
        let offset = offset.as_tensor();
        // Coordinates and shadow lines move with the frames (the lines' ground flags do not).
        let moving = MovingLines::new(cfg, frames, r)?;
        let shift = Linearised::new(d_shift, FieldLayout::Minor { background_follows }, s);
        if !explicit {
            let motion = FrameMotion {
                lines: moving,
                shift,
            };
            let motion = Some(MovingRays {
                offsets: offset.clone(),
                motion: Arc::new(motion),
            });
            return Ok((RayBatch { motion, ..batch }, target));
        }
        // The explicit form, for candle's autograd through the reference decoder.
        let coords = batch.coords.apply_op2(offset, moving.clone())?;
        let shadow_lines = match batch.shadow_lines {
            Some((lines, on_ground)) => Some((lines.apply_op2(offset, moving)?, on_ground)),
            None => None,
        };
        let shift = batch.shift.apply_op2(offset, shift)?;
        Ok((
            RayBatch {
                coords,
                shadow_lines,
                shift,
                ..batch
            },
            target,
        ))
    }

    /// The encoded rays (on the host) and target colours [1, R, 3] of the pixels `pick`.
    fn host_batch(
        &self,
        model: &Colf,
        slot_to_world: &[DMat4],
        pick: &[usize],
    ) -> Result<(HostRays, Tensor)> {
        let o: Vec<DVec3> = pick.iter().map(|&p| self.origins[p]).collect();
        let d: Vec<DVec3> = pick.iter().map(|&p| self.dirs[p]).collect();
        let t: Vec<f32> = pick
            .iter()
            .flat_map(|&p| self.rgb[3 * p..3 * p + 3].iter().copied())
            .collect();
        let rays = HostRays::new(
            model.config(),
            &[SceneRays {
                slot_to_world,
                origins: &o,
                dirs: &d,
            }],
        )
        .context("encoding the input view's rays")?;
        let target = Tensor::from_vec(t, (1, pick.len(), 3), model.device())?;
        Ok((rays, target))
    }

    /// The encoded rays and target colours [1, R, 3] of the pixels `pick` (all when `None`).
    pub fn batch(
        &self,
        model: &Colf,
        slot_to_world: &[DMat4],
        pick: Option<&[usize]>,
    ) -> Result<(RayBatch, Tensor)> {
        let (origins, dirs, rgb) = (&self.origins, &self.dirs, &self.rgb);
        let all: Vec<usize>;
        let pick = match pick {
            Some(p) => p,
            None => {
                all = (0..origins.len()).collect();
                &all
            }
        };
        let o: Vec<DVec3> = pick.iter().map(|&p| origins[p]).collect();
        let d: Vec<DVec3> = pick.iter().map(|&p| dirs[p]).collect();
        let t: Vec<f32> = pick
            .iter()
            .flat_map(|&p| rgb[3 * p..3 * p + 3].iter().copied())
            .collect();
        let rays = RayBatch::new(
            model.config(),
            &[SceneRays {
                slot_to_world,
                origins: &o,
                dirs: &d,
            }],
            model.device(),
        )
        .context("encoding the input view's rays")?;
        let target = Tensor::from_vec(t, (1, pick.len(), 3), model.device())?;
        Ok((rays, target))
    }
}

/// Side of the pixel cells whose centre samples a slot's support (`Refinement::support`).
const SUPPORT_CELL: usize = 4;

/// Per field (background first), the input view's pixels on which it is evaluated.
struct Support {
    /// [S][pixels]; the background's row is unused (it is evaluated everywhere).
    active: Vec<Vec<bool>>,
}

impl Support {
    /// For the drawn pixels `pick` (a step's rays, in order), each field's rays as the decode
    /// kernel takes them: indices into `pick`, the background's all of them.
    fn fields_of(&self, pick: &[usize]) -> Vec<Vec<u32>> {
        self.active
            .iter()
            .enumerate()
            .map(|(field, active)| {
                (0..pick.len() as u32)
                    .filter(|&i| field == 0 || active[pick[i as usize]])
                    .collect()
            })
            .collect()
    }
}

/// How a linearised tensor's elements belong to fields (field 0, the background, never moves).
#[derive(Clone, Debug)]
enum FieldLayout {
    /// [S, R, in]: field-major blocks of `per_field` values (coordinates, shadow lines): the
    /// reference [`MovingLines`] is tested against.
    #[cfg_attr(not(test), allow(dead_code))]
    Major { per_field: usize },
    /// [1, R, S]: the field is the last index (ordering shifts). The background's shift of ray
    /// r moves with field `background_follows[r]` (`FrameDerivatives`; 0 = with none).
    Minor { background_follows: Vec<u32> },
}

/// x + Σ_axis ∂x/∂axis · offset[axis, field − 1] for a value x at the current frames, its
/// derivatives along the three world axes, and the foreground frame
/// origins' offsets [3, K] (the second input); the backward gives the offsets' gradient. One
/// pass over the values, where the same as candle ops took about a dozen passes and most of a
/// refinement step's time.
#[derive(Debug)]
struct Linearised {
    derivatives: Vec<Vec<f32>>,
    layout: FieldLayout,
    fields: usize,
}

impl Linearised {
    fn new(derivatives: Vec<Vec<f32>>, layout: FieldLayout, fields: usize) -> Linearised {
        Linearised {
            derivatives,
            layout,
            fields,
        }
    }

    /// The field whose frame offset moves element `i` (0: none).
    fn field(&self, i: usize) -> usize {
        match &self.layout {
            FieldLayout::Major { per_field } => i / per_field,
            FieldLayout::Minor { background_follows } => match i % self.fields {
                0 => background_follows[i / self.fields] as usize,
                f => f,
            },
        }
    }
}

fn cpu_f32<'a>(s: &'a CpuStorage, l: &Layout) -> candle_core::Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("linearised rays: f32 contiguous inputs expected"),
    }
}

impl CustomOp2 for Linearised {
    fn name(&self) -> &'static str {
        "colf-linearised-rays"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        os: &CpuStorage,
        ol: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, offset) = (cpu_f32(xs, xl)?, cpu_f32(os, ol)?);
        let k = self.fields - 1;
        if offset.len() != 3 * k || self.derivatives.iter().any(|d| d.len() != x.len()) {
            candle_core::bail!("linearised rays: sizes do not match");
        }
        let mut out = x.to_vec();
        for (axis, d) in self.derivatives.iter().enumerate() {
            let row = &offset[axis * k..(axis + 1) * k];
            if row.iter().all(|v| *v == 0.0) {
                continue;
            }
            for (i, (o, dv)) in out.iter_mut().zip(d).enumerate() {
                let f = self.field(i);
                if f > 0 {
                    *o += dv * row[f - 1];
                }
            }
        }
        Ok((CpuStorage::F32(out), xl.shape().clone()))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        offset: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let g = grad.flatten_all()?.to_vec1::<f32>()?;
        let d_offset: Vec<f32> = self.contract(&g).into_iter().map(|v| v as f32).collect();
        Ok((
            None,
            Some(Tensor::from_vec(d_offset, offset.shape(), offset.device())?),
        ))
    }
}

impl Linearised {
    /// The offsets' gradient [3, K] from the values' gradient `g`.
    fn contract(&self, g: &[f32]) -> Vec<f64> {
        let (s, k) = (self.fields, self.fields - 1);
        let mut d_offset = vec![0f64; 3 * k];
        for (axis, d) in self.derivatives.iter().enumerate() {
            let sums = &mut d_offset[axis * k..(axis + 1) * k];
            match &self.layout {
                &FieldLayout::Major { per_field } => {
                    for (f, (gb, db)) in g
                        .chunks_exact(per_field)
                        .zip(d.chunks_exact(per_field))
                        .enumerate()
                        .take(s)
                        .skip(1)
                    {
                        let dot: f32 = gb.iter().zip(db).map(|(a, b)| a * b).sum();
                        sums[f - 1] += dot as f64;
                    }
                }
                FieldLayout::Minor { background_follows } => {
                    for ((gr, dr), &follows) in g
                        .chunks_exact(s)
                        .zip(d.chunks_exact(s))
                        .zip(background_follows)
                    {
                        for f in 1..s {
                            sums[f - 1] += (gr[f] * dr[f]) as f64;
                        }
                        if follows > 0 {
                            sums[follows as usize - 1] += (gr[0] * dr[0]) as f64;
                        }
                    }
                }
            }
        }
        d_offset
    }
}

/// Encoded lines [S, R, in] (coordinates or shadow lines, one scene) as a function of the
/// foreground frame origins' offsets [3, K] (the second input, zero when read): the forward is
/// the lines themselves; the backward contracts their gradient with the derivative of the
/// encoding in one pass, without writing the derivatives out (`Linearised` with the
/// derivatives of `HostRays::frame_derivatives` is the reference it is tested against, at a
/// fifth of its cost).
///
/// Moving a frame's origin by δ along a world axis moves the line's origin in the frame by
/// −δ·a (a = A⁻¹·e_axis) and not its direction d', so only the moment m = o' × d' / s changes,
/// by −(a × d')/s; the bounded moment m̂ = m/√(1 + |m|²) and its Fourier features follow (see
/// `rays::encode_line_derivative`). With g the gradient of a line's encoding and g_m that of
/// its moment, g·∂x/∂δ = −a·(d' × g_m)/s: per field, one 3-vector Σ d' × g_m over the lines.
#[derive(Clone, Debug)]
struct MovingLines {
    /// Per foreground frame, A⁻¹·e for the three world axes.
    frame_axes: Vec<[DVec3; 3]>,
    rays: usize,
    in_dim: usize,
    freqs: usize,
    /// The foreground slots' [`crate::model::Config::line_scale`].
    slot_scale: f64,
}

impl MovingLines {
    fn new(cfg: &crate::model::Config, frames: &[DMat4], rays: usize) -> Result<MovingLines> {
        let inverses = crate::model::rays::world_to_slot(frames)?;
        Ok(MovingLines {
            frame_axes: inverses
                .iter()
                .map(|inv| [DVec3::X, DVec3::Y, DVec3::Z].map(|e| inv.transform_vector3(e)))
                .collect(),
            rays,
            in_dim: cfg.ray_input_dim(),
            freqs: cfg.ray_fourier_freqs,
            slot_scale: cfg.line_scale(1),
        })
    }

    /// The gradient of foreground slot `slot`'s frame offset along the three world axes, from
    /// its lines' torque ([`MovingLines::moment_torque`]).
    fn offset_gradient(&self, slot: usize, torque: DVec3) -> [f64; 3] {
        self.frame_axes[slot].map(|a| -a.dot(torque) / self.slot_scale)
    }

    /// Σ over the lines of one field of d' × g_m, from their encodings `x` and gradients `g`.
    fn moment_torque(&self, x: &[f32], g: &[f32]) -> DVec3 {
        let mut sum = DVec3::ZERO;
        for (x, g) in x.chunks_exact(self.in_dim).zip(g.chunks_exact(self.in_dim)) {
            // The bounded moment's gradient: its own entry and its Fourier features'
            // (∂sin(ωv) = ω cos(ωv), ∂cos(ωv) = −ω sin(ωv), sin and cos read from x).
            let mut g_hat = [0f64; 3];
            for (j, gj) in g_hat.iter_mut().enumerate() {
                let c = 3 + j;
                let mut v = g[c] as f64;
                let mut omega = std::f64::consts::PI;
                for f in 0..self.freqs {
                    let (sin, cos) = (x[6 + 12 * f + c] as f64, x[12 + 12 * f + c] as f64);
                    v += omega * (g[6 + 12 * f + c] as f64 * cos - g[12 + 12 * f + c] as f64 * sin);
                    omega *= 2.0;
                }
                *gj = v;
            }
            // Through m̂ = m/√(1 + |m|²): ∂m̂ = √(1 − |m̂|²)·(I − m̂m̂ᵀ)·∂m, a symmetric map.
            let g_hat = DVec3::from_array(g_hat);
            let m_hat = DVec3::new(x[3] as f64, x[4] as f64, x[5] as f64);
            let g_m =
                (1.0 - m_hat.length_squared()).max(0.0).sqrt() * (g_hat - m_hat * m_hat.dot(g_hat));
            let d_frame = DVec3::new(x[0] as f64, x[1] as f64, x[2] as f64);
            sum += d_frame.cross(g_m);
        }
        sum
    }
}

impl CustomOp2 for MovingLines {
    fn name(&self) -> &'static str {
        "colf-moving-lines"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        os: &CpuStorage,
        ol: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, offset) = (cpu_f32(xs, xl)?, cpu_f32(os, ol)?);
        let k = self.frame_axes.len();
        if offset.len() != 3 * k || x.len() != (1 + k) * self.rays * self.in_dim {
            candle_core::bail!("moving lines: sizes do not match");
        }
        if offset.iter().any(|v| *v != 0.0) {
            candle_core::bail!("moving lines: the offsets must be zero when read");
        }
        Ok((CpuStorage::F32(x.to_vec()), xl.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        offset: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let x = x.flatten_all()?.to_vec1::<f32>()?;
        let g = grad.flatten_all()?.to_vec1::<f32>()?;
        let k = self.frame_axes.len();
        let per_field = self.rays * self.in_dim;
        // One field per task, each summed in order: the same bytes for any thread count.
        let torques: Vec<DVec3> = (1..=k)
            .into_par_iter()
            .map(|f| {
                let block = f * per_field..(f + 1) * per_field;
                self.moment_torque(&x[block.clone()], &g[block])
            })
            .collect();
        let mut d_offset = vec![0f32; 3 * k];
        for (slot, torque) in torques.iter().enumerate() {
            for (axis, d) in self.offset_gradient(slot, *torque).into_iter().enumerate() {
                d_offset[axis * k + slot] = d as f32;
            }
        }
        Ok((
            None,
            Some(Tensor::from_vec(d_offset, offset.shape(), offset.device())?),
        ))
    }
}

/// How a refinement batch's rays move with the foreground frame origins' offsets [3, K], for
/// the decode kernel ([`RayMotion`]): the coordinates and shadow lines as [`MovingLines`], the
/// ordering shifts as [`Linearised`], contracted inside the kernel's parallel field passes.
/// The same gradient as those two ops on the explicit batch (tested), without handing candle
/// the gradient of every encoded ray.
#[derive(Debug)]
struct FrameMotion {
    lines: MovingLines,
    shift: Linearised,
}

impl RayMotion for FrameMotion {
    fn offsets(&self) -> usize {
        3 * self.lines.frame_axes.len()
    }

    fn field_gradient(
        &self,
        u: usize,
        coords: (&[f32], &[f32]),
        lines: Option<(&[f32], &[f32])>,
    ) -> Vec<f64> {
        let k = self.lines.frame_axes.len();
        let mut d_offset = vec![0f64; 3 * k];
        // One scene: field u is slot u − 1; the background does not move.
        if u == 0 {
            return d_offset;
        }
        let mut torque = self.lines.moment_torque(coords.0, coords.1);
        if let Some((x, g)) = lines {
            torque += self.lines.moment_torque(x, g);
        }
        for (axis, d) in self
            .lines
            .offset_gradient(u - 1, torque)
            .into_iter()
            .enumerate()
        {
            d_offset[axis * k + u - 1] = d;
        }
        d_offset
    }

    fn shift_gradient(&self, d_shift: &[f32]) -> Vec<f64> {
        self.shift.contract(d_shift)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};
    use crate::model::{Config, FrameDerivatives};

    fn camera(size: u32) -> Frame {
        Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(size, size, 49.13),
            camera_to_world: look_at(DVec3::new(0.0, -8.0, 9.0), DVec3::ZERO, DVec3::Z).unwrap(),
        }
    }

    fn latents(k: usize, d: usize, seed: u64) -> Vec<Vec<f32>> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..k)
            .map(|_| (0..d).map(|_| rng.random_range(-1.5f32..1.5)).collect())
            .collect()
    }

    /// A target the model can render exactly: its own image of latents `truth`.
    fn target(model: &Colf, truth: &[Vec<f32>], bg: &[f32], cam: &Frame) -> RgbImage32 {
        let frames = vec![cam.camera_to_world; truth.len()];
        let prepared = model.prepare(truth, bg).unwrap();
        let blank = RgbImage32 {
            w: cam.intrinsics.w,
            h: cam.intrinsics.h,
            data: vec![0.0; 3 * (cam.intrinsics.w * cam.intrinsics.h) as usize],
        };
        let view = InputView::new(cam, &blank);
        let out = model
            .render_rays(&prepared, &frames, &view.origins, &view.dirs)
            .unwrap();
        RgbImage32 {
            w: cam.intrinsics.w,
            h: cam.intrinsics.h,
            data: out.rgb,
        }
    }

    #[test]
    fn refinement_fits_the_input_view_and_is_deterministic() {
        let model = Colf::init(&Config::small(), 3).unwrap();
        let d = model.config().slot_dim;
        let cam = camera(24);
        let bg = vec![0.0; d];
        let image = target(&model, &latents(3, d, 1), &bg, &cam);
        let start = latents(3, d, 2);
        let frames = vec![cam.camera_to_world; 3];
        let opts = RefineOptions {
            steps: 30,
            lr: 0.05,
            rays: 256,
            ..Default::default()
        };
        let run = || {
            let (mut fg, mut bg, mut frames) = (start.clone(), bg.clone(), frames.clone());
            let report =
                refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).unwrap();
            (fg, bg, report)
        };
        let (fg, _, report) = run();
        assert!(
            report.last_psnr > report.first_psnr + 3.0,
            "refinement should fit the view: {report:?}"
        );
        assert_ne!(fg, start);
        assert_eq!(run().0, fg, "the same inputs give the same latents");
    }

    #[test]
    fn refining_on_two_copies_of_a_view_is_refining_on_it() {
        let model = Colf::init(&Config::small(), 3).unwrap();
        let d = model.config().slot_dim;
        let cam = camera(12);
        let bg = vec![0.0; d];
        let image = target(&model, &latents(2, d, 1), &bg, &cam);
        // Every pixel each step and fixed frames: the loss is the same mean either way.
        let opts = RefineOptions {
            steps: 5,
            lr: 0.05,
            rays: 2 * 12 * 12,
            frame_lr: 0.0,
            ..Default::default()
        };
        let view = InputView::new(&cam, &image);
        let run = |views: &[&InputView]| {
            let (mut fg, mut bg, mut frames) =
                (latents(2, d, 2), bg.clone(), vec![cam.camera_to_world; 2]);
            refine_latents_on_views(&model, &mut fg, &mut bg, &mut frames, views, &opts).unwrap();
            fg
        };
        let one = run(&[&view]);
        let two = run(&[&view, &view]);
        assert_ne!(one, latents(2, d, 2));
        for (a, b) in one.iter().flatten().zip(two.iter().flatten()) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
        let empty = RgbImage32 {
            w: 0,
            h: 0,
            data: Vec::new(),
        };
        let (mut fg, mut bg, mut frames) = (latents(2, d, 2), bg.clone(), vec![DMat4::IDENTITY; 2]);
        let empty_view = InputView::new(&cam, &empty);
        for views in [&[][..], &[&empty_view][..]] {
            let err = refine_latents_on_views(&model, &mut fg, &mut bg, &mut frames, views, &opts)
                .unwrap_err();
            assert!(err.to_string().contains("at least one view"), "{err}");
        }
    }

    /// A refinement-only shadow reach changes the refinement of a model whose slots cast
    /// shadows along the light (its far lines are left out), and nothing for a model that sets
    /// a reach of its own or casts no such shadows; a negative reach is refused.
    #[test]
    fn a_refinement_shadow_reach_leaves_out_far_lines_only_where_the_model_has_none() {
        let shadows = [
            "shadow_head=true".to_string(),
            "shadow_light=[30, 55]".to_string(),
        ];
        let lit = Config::small().with_overrides(&shadows).unwrap();
        let bounded = lit.with_overrides(&["shadow_reach=5".to_string()]).unwrap();
        let cam = camera(16);
        let refined = |cfg: &Config, reach: f64| {
            // A strong shadow head (σ ≈ 0.3 everywhere it is evaluated) so every line counts.
            let mut model = Colf::init(cfg, 3).unwrap();
            if cfg.shadow_head {
                let bias = Tensor::new(&[-0.1f32], &candle_core::Device::Cpu).unwrap();
                model = model.with_tensor("heads.shadow.bias", bias).unwrap();
            }
            let d = cfg.slot_dim;
            let image = target(&model, &latents(2, d, 1), &vec![0.0; d], &cam);
            let (mut fg, mut bg) = (latents(2, d, 2), vec![0.0; d]);
            let mut frames = vec![cam.camera_to_world; 2];
            let opts = RefineOptions {
                shadow_reach: reach,
                ..three_steps_on_every_pixel()
            };
            refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).map(|_| fg)
        };
        // The camera frames lie ~12 units from the ground points: a 1-unit reach cuts them all.
        assert_ne!(refined(&lit, 1.0).unwrap(), refined(&lit, 0.0).unwrap());
        assert_eq!(
            refined(&bounded, 1.0).unwrap(),
            refined(&bounded, 0.0).unwrap()
        );
        let dark = Config::small();
        assert_eq!(refined(&dark, 1.0).unwrap(), refined(&dark, 0.0).unwrap());
        let err = refined(&lit, -1.0).unwrap_err();
        assert!(err.to_string().contains("shadow reach"), "{err}");
    }

    /// The mask loss against the proposals: on a view with a red square the static
    /// background's render does not explain, the proposals find the square, and either form
    /// of the loss changes the refined latents, deterministically; the loss is refused for a
    /// model whose background reads the image, and for a negative weight.
    #[test]
    fn a_refinement_mask_loss_reaches_the_latents() {
        let sets = ["static_background=true", "zero_background=true"].map(String::from);
        let cfg = Config::small().with_overrides(&sets).unwrap();
        let model = Colf::init(&cfg, 3).unwrap();
        let (d, side) = (cfg.slot_dim, 16usize);
        let cam = camera(side as u32);
        // The background alone, then a red square on it: an object the proposals find.
        let mut image = target(&model, &[], &vec![0.0; d], &cam);
        let square: Vec<usize> = (5..11)
            .flat_map(|y| (5..11).map(move |x| y * side + x))
            .collect();
        for &p in &square {
            image.data[3 * p..3 * p + 3].copy_from_slice(&[0.9, 0.05, 0.05]);
        }
        let view = InputView::new(&cam, &image);
        let ids = view.proposal_ids(&model).unwrap();
        assert!(square
            .iter()
            .all(|&p| crate::proposals::is_instance(ids[p])));
        let refined = |mask_weight: f64, mask_match: bool| {
            let (mut fg, mut bg) = (latents(2, d, 2), vec![0.0; d]);
            let mut frames = vec![cam.camera_to_world; 2];
            let opts = RefineOptions {
                steps: 5,
                mask_weight,
                mask_match,
                ..three_steps_on_every_pixel()
            };
            refine_latents_on_views(&model, &mut fg, &mut bg, &mut frames, &[&view], &opts)
                .unwrap();
            fg
        };
        // Each form of the loss reaches the latents (the effect on real scenes is measured in
        // docs/refinement.md), and each the same way on the same inputs.
        let colour_only = refined(0.0, false);
        let (unmatched, matched) = (refined(1.0, false), refined(1.0, true));
        assert_ne!(unmatched, colour_only);
        assert_ne!(matched, colour_only);
        assert_ne!(matched, unmatched);
        assert_eq!(refined(1.0, false), unmatched);

        let reader = Colf::init(&Config::small(), 3).unwrap();
        let (mut fg, mut bg, mut frames) =
            (latents(2, d, 2), vec![0.0; d], vec![cam.camera_to_world; 2]);
        for (model, weight, says) in [
            (&reader, 1.0, "static background"),
            (&model, -1.0, "mask weight"),
        ] {
            let opts = RefineOptions {
                mask_weight: weight,
                ..three_steps_on_every_pixel()
            };
            let err =
                refine_latents_on_views(model, &mut fg, &mut bg, &mut frames, &[&view], &opts)
                    .unwrap_err();
            assert!(err.to_string().contains(says), "{err}");
        }
    }

    /// Three steps on every pixel of a 16² view, fixed frames: the reach tests' refinement.
    fn three_steps_on_every_pixel() -> RefineOptions {
        RefineOptions {
            steps: 3,
            lr: 0.05,
            rays: 16 * 16,
            frame_lr: 0.0,
            ..Default::default()
        }
    }

    /// A slot reach during refinement changes the refined latents of a model without one (the
    /// far pixels no longer reach the slots), and nothing for a model with its own; a negative
    /// reach is refused.
    #[test]
    fn a_refinement_slot_reach_leaves_out_far_slots_only_where_the_model_has_none() {
        let cam = camera(16);
        // The slots' frames 12 units in front of the camera: its rays pass them at 0–5 units.
        let ahead =
            cam.camera_to_world * DMat4::from_translation(glam::DVec3::new(0.0, 0.0, -12.0));
        let refined = |cfg: &Config, reach: f64| {
            let model = Colf::init(cfg, 3).unwrap();
            let d = cfg.slot_dim;
            let image = target(&model, &latents(2, d, 1), &vec![0.0; d], &cam);
            let (mut fg, mut bg) = (latents(2, d, 2), vec![0.0; d]);
            let mut frames = vec![ahead; 2];
            let opts = RefineOptions {
                slot_reach: reach,
                ..three_steps_on_every_pixel()
            };
            refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).map(|_| fg)
        };
        let free = Config::small();
        assert_ne!(refined(&free, 1.0).unwrap(), refined(&free, 0.0).unwrap());
        let bounded = free.with_overrides(&["slot_reach=2".to_string()]).unwrap();
        assert_eq!(
            refined(&bounded, 1.0).unwrap(),
            refined(&bounded, 0.0).unwrap()
        );
        let err = refined(&free, -1.0).unwrap_err();
        assert!(err.to_string().contains("slot reach"), "{err}");
    }

    /// An encoding's reaches are added only where the model has none of its own, and only the
    /// ones its config can use (shadow lines need a light; a volumetric model has no slots to
    /// leave out).
    #[test]
    fn reached_config_adds_only_the_missing_reaches() {
        let opts = RefineOptions::default();
        let dark = Config::small();
        let reached = opts.reached_config(&dark).unwrap();
        assert_eq!((reached.slot_reach, reached.shadow_reach), (3.0, 0.0));
        let lit = dark
            .with_overrides(&[
                "shadow_head=true".to_string(),
                "shadow_light=[30, 55]".into(),
                "slot_reach=2".into(),
            ])
            .unwrap();
        let reached = opts.reached_config(&lit).unwrap();
        assert_eq!((reached.slot_reach, reached.shadow_reach), (2.0, 3.0));
        let own = lit.with_overrides(&["shadow_reach=5".into()]).unwrap();
        assert!(opts.reached_config(&own).is_none());
        let none = RefineOptions {
            slot_reach: 0.0,
            shadow_reach: 0.0,
            ..opts
        };
        assert!(none.reached_config(&lit).is_none());
        assert!(opts.reached_config(&Config::volumetric()).is_none());
    }

    #[test]
    fn no_steps_leave_the_latents_alone() {
        let model = Colf::init(&Config::small(), 3).unwrap();
        let d = model.config().slot_dim;
        let cam = camera(16);
        let (mut fg, mut bg) = (latents(2, d, 5), vec![0.5; d]);
        let image = target(&model, &fg, &bg, &cam);
        let before = (fg.clone(), bg.clone());
        let mut frames = vec![cam.camera_to_world; 2];
        let opts = RefineOptions::default();
        let report =
            refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).unwrap();
        assert_eq!(report.steps, 0);
        assert_eq!((fg, bg), before);
    }

    #[test]
    fn a_zero_background_model_keeps_its_background() {
        let mut cfg = Config::small();
        cfg.zero_background = true;
        let model = Colf::init(&cfg, 4).unwrap();
        let d = cfg.slot_dim;
        let cam = camera(16);
        let (mut fg, mut bg) = (latents(2, d, 6), vec![0.0; d]);
        let image = target(&model, &latents(2, d, 7), &bg, &cam);
        let mut frames = vec![cam.camera_to_world; 2];
        let opts = RefineOptions {
            steps: 3,
            ..Default::default()
        };
        refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).unwrap();
        assert!(bg.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn bad_options_are_refused() {
        let model = Colf::init(&Config::small(), 3).unwrap();
        let d = model.config().slot_dim;
        let cam = camera(8);
        let (mut fg, mut bg) = (latents(1, d, 5), vec![0.0; d]);
        let image = target(&model, &fg, &bg, &cam);
        let mut frames = vec![cam.camera_to_world];
        for opts in [
            RefineOptions {
                steps: 1,
                lr: f64::NAN,
                ..Default::default()
            },
            RefineOptions {
                steps: 1,
                lr: -1.0,
                ..Default::default()
            },
            RefineOptions {
                steps: 1,
                rays: 0,
                ..Default::default()
            },
            RefineOptions {
                steps: 1,
                anchor_weight: -1.0,
                ..Default::default()
            },
            RefineOptions {
                steps: 1,
                frame_lr: f64::INFINITY,
                ..Default::default()
            },
        ] {
            assert!(
                refine_latents(&model, &mut fg, &mut bg, &mut frames, &cam, &image, &opts).is_err()
            );
        }
    }

    /// The one-pass contraction of the encoded lines' gradient against the written-out
    /// derivatives (`HostRays::frame_derivatives` through `Linearised`), for rotated frames,
    /// Fourier features, shadow lines, lines near and far, the slots' own line scale and floor
    /// features.
    #[test]
    fn moving_lines_give_the_gradient_of_the_written_out_derivatives() {
        // And with the background's floor columns after the lines' (`floor_fourier_freqs`).
        for (slot_scale, floor) in [
            ("slot_scale=0", "floor_fourier_freqs=0"),
            ("slot_scale=1.5", "floor_fourier_freqs=0"),
            ("slot_scale=0", "floor_fourier_freqs=3"),
        ] {
            let overrides = [
                "ray_fourier_freqs=4",
                "shadow_head=true",
                "shadow_light=[30, 55]",
                slot_scale,
                floor,
            ]
            .map(String::from);
            moving_lines_match(&Config::small().with_overrides(&overrides).unwrap());
        }
    }

    fn moving_lines_match(cfg: &Config) {
        let dev = candle_core::Device::Cpu;
        let frames: Vec<DMat4> = (0..3)
            .map(|i| {
                let a = 0.7 + 1.9 * i as f64;
                DMat4::from_scale_rotation_translation(
                    DVec3::splat(1.0 + 0.3 * i as f64),
                    glam::DQuat::from_axis_angle(DVec3::new(0.2, 0.3, 1.0).normalize(), a),
                    DVec3::new(2.0 * a.cos(), 3.0 * a.sin(), 0.4 * i as f64),
                )
            })
            .collect();
        let mut rng = StdRng::seed_from_u64(3);
        let r = 97;
        let eye = DVec3::new(7.0, -6.0, 8.0);
        let origins: Vec<DVec3> = (0..r)
            .map(|i| eye * (1.0 + 30.0 * (i % 5 == 0) as u8 as f64))
            .collect();
        let dirs: Vec<DVec3> = (0..r)
            .map(|_| {
                let at = DVec3::new(
                    rng.random_range(-4.0..4.0),
                    rng.random_range(-4.0..4.0),
                    rng.random_range(-1.0..1.0),
                );
                at - eye
            })
            .collect();
        let scene = [SceneRays {
            slot_to_world: &frames,
            origins: &origins,
            dirs: &dirs,
        }];
        let host = HostRays::new(cfg, &scene).unwrap();
        let derivatives: Vec<FrameDerivatives> = (0..3)
            .map(|axis| host.frame_derivatives(cfg, &scene, axis).unwrap())
            .collect();
        let s = 1 + frames.len();
        let in_dim = cfg.ray_input_dim();
        let (coords, lines) = (host.coords.clone(), host.shadow_lines.clone().unwrap().0);
        for (values, written) in [
            (
                coords,
                derivatives.iter().map(|d| d.coords.clone()).collect(),
            ),
            (
                lines,
                derivatives
                    .iter()
                    .map(|d| d.shadow_lines.clone().unwrap())
                    .collect(),
            ),
        ] {
            let n = values.len();
            let x = Tensor::from_vec(values, (s, r, in_dim), &dev).unwrap();
            let weights: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let weights = Tensor::from_vec(weights, (s, r, in_dim), &dev).unwrap();
            let gradient_of = |y: Tensor| {
                (y * &weights)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .backward()
                    .unwrap()
            };
            let offset = Var::zeros((3, s - 1), candle_core::DType::F32, &dev).unwrap();
            let fast = gradient_of(
                x.apply_op2(
                    offset.as_tensor(),
                    MovingLines::new(cfg, &frames, r).unwrap(),
                )
                .unwrap(),
            );
            let reference = gradient_of(
                x.apply_op2(
                    offset.as_tensor(),
                    Linearised::new(
                        written,
                        FieldLayout::Major {
                            per_field: r * in_dim,
                        },
                        s,
                    ),
                )
                .unwrap(),
            );
            let fast = fast
                .get(offset.as_tensor())
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            let reference = reference
                .get(offset.as_tensor())
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for (a, b) in fast.iter().flatten().zip(reference.iter().flatten()) {
                let scale = a.abs().max(b.abs()).max(1e-3);
                assert!((a - b).abs() / scale < 1e-4, "{fast:?} vs {reference:?}");
            }
            assert!(fast.iter().flatten().any(|v| v.abs() > 1e-2));
        }
    }

    /// Also with the background's ordering measured from the nearest slot, whose shift then
    /// moves with that slot's frame.
    #[test]
    fn frame_gradients_match_finite_differences_of_the_loss() {
        // And with the slots' own line scale (`Config::slot_scale`).
        for (from_nearest, slot_scale) in [(false, 0.0), (true, 0.0), (false, 1.5)] {
            let mut cfg = Config::small();
            cfg.ray_fourier_freqs = 2;
            cfg.fg_locality = 2.0;
            cfg.attention_frames = true;
            cfg.background_from_nearest_slot = from_nearest;
            cfg.slot_scale = slot_scale;
            check_frame_gradients(&cfg);
        }
    }

    /// The moving rays' gradients (contracted inside the decode kernel) are those of the
    /// explicit batch (candle ops of the offsets, the kernel's packed rays), for the latents and
    /// the frame offsets, with shadow lines, a reach and a slot scale; the values are the same.
    #[test]
    fn moving_rays_give_the_explicit_batchs_gradients() {
        let base = [
            "shadow_head=true",
            "shadow_light=[30, 55]",
            "ray_fourier_freqs=3",
            "attention_frames=true",
            "fg_locality=2",
        ];
        for extra in [&[][..], &["shadow_reach=2", "slot_scale=1.5"][..]] {
            let sets: Vec<String> = base.iter().chain(extra).map(|s| s.to_string()).collect();
            let cfg = Config::small().with_overrides(&sets).unwrap();
            // A shadow head that reads its features (it starts at zero weights), so the shadow
            // lines carry gradient.
            let mut model = Colf::init(&cfg, 4).unwrap();
            let dims = model.parameters()["heads.shadow.weight"].dims().to_vec();
            let dev = candle_core::Device::Cpu;
            let n = dims.iter().product::<usize>();
            let values: Vec<f32> = (0..n).map(|i| 0.5 * (i as f32 * 0.7).sin()).collect();
            let weight = Tensor::from_vec(values, dims, &dev).unwrap();
            let bias = Tensor::new(&[-0.5f32], &dev).unwrap();
            model = model.with_tensor("heads.shadow.weight", weight).unwrap();
            model = model.with_tensor("heads.shadow.bias", bias).unwrap();
            let (d, k) = (cfg.slot_dim, 3);
            let cam = camera(10);
            let image = target(&model, &latents(k, d, 1), &vec![0.1; d], &cam);
            let mut frames = vec![cam.camera_to_world; k];
            for (i, f) in frames.iter_mut().enumerate() {
                f.w_axis = glam::DVec4::new(0.6 * i as f64 - 0.6, 0.2, 0.1 * i as f64, 1.0);
            }
            let pixels = Pixels::gather(&[&InputView::new(&cam, &image)]);
            let pick: Vec<usize> = (0..pixels.origins.len()).rev().step_by(2).collect();
            let net = model.model();
            let run = |explicit: bool| {
                let fg = Var::from_tensor(
                    &Tensor::from_vec(latents(k, d, 2).concat(), (1, k, d), model.device())
                        .unwrap(),
                )
                .unwrap();
                let bg = Tensor::from_vec(vec![0.1f32; d], (1, d), model.device()).unwrap();
                let offset = Var::zeros((3, k), candle_core::DType::F32, model.device()).unwrap();
                let (rays, target) = pixels
                    .linearised_batch_as(&model, &frames, &offset, &pick, explicit)
                    .unwrap();
                assert_eq!(rays.motion.is_some(), !explicit);
                let fields = net.prepare(fg.as_tensor(), &bg).unwrap();
                let out = net.decode(&fields, &rays).unwrap();
                let rgb = out.rgb.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let loss = (&out.rgb - &target)
                    .unwrap()
                    .sqr()
                    .unwrap()
                    .sum_all()
                    .unwrap();
                let grads = loss.backward().unwrap();
                let flat = |t: &Tensor| grads.get(t).unwrap().flatten_all().unwrap();
                let g_offset = flat(offset.as_tensor()).to_vec1::<f32>().unwrap();
                let g_fg = flat(fg.as_tensor()).to_vec1::<f32>().unwrap();
                (rgb, g_offset, g_fg)
            };
            let (moving, explicit) = (run(false), run(true));
            assert_eq!(moving.0, explicit.0, "the values");
            for (what, a, b) in [
                ("offsets", &moving.1, &explicit.1),
                ("latents", &moving.2, &explicit.2),
            ] {
                let scale = b.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
                assert!(scale > 1e-4, "{what}: no gradient to compare");
                for (x, y) in a.iter().zip(b) {
                    assert!(
                        (x - y).abs() <= 1e-4 * scale,
                        "{what}: {x} vs {y} ({extra:?})"
                    );
                }
            }
        }
    }

    fn check_frame_gradients(cfg: &Config) {
        let model = Colf::init(cfg, 8).unwrap();
        let d = cfg.slot_dim;
        let cam = camera(12);
        let fg = latents(2, d, 9);
        let bg = vec![0.1; d];
        let image = target(&model, &latents(2, d, 10), &bg, &cam);
        let mut frames = vec![cam.camera_to_world; 2];
        frames[0].w_axis = glam::DVec4::new(0.5, -0.3, 0.2, 1.0);
        frames[1].w_axis = glam::DVec4::new(-1.0, 0.4, 0.0, 1.0);
        let pixels = Pixels::gather(&[&InputView::new(&cam, &image)]);
        let pick: Vec<usize> = (0..pixels.origins.len()).collect();
        let net = model.model();
        let fg_t = Tensor::from_vec(fg.concat(), (1, 2, d), model.device()).unwrap();
        let bg_t = Tensor::from_vec(bg.clone(), (1, d), model.device()).unwrap();
        let fields = net.prepare(&fg_t, &bg_t).unwrap();
        let loss_of = |rays: &RayBatch, target: &Tensor| {
            let out = net.decode(&fields, rays).unwrap();
            (&out.rgb - target)
                .unwrap()
                .sqr()
                .unwrap()
                .mean_all()
                .unwrap()
        };
        let offset = Var::zeros((3, 2), candle_core::DType::F32, model.device()).unwrap();
        let (rays, target) = pixels
            .linearised_batch(&model, &frames, &offset, &pick)
            .unwrap();
        let grads = loss_of(&rays, &target).backward().unwrap();
        let analytic = grads
            .get(offset.as_tensor())
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        let h = 1e-2;
        for (axis, row) in analytic.iter().enumerate() {
            for (slot, &g) in row.iter().enumerate() {
                let eval = |sign: f64| {
                    let mut moved = frames.clone();
                    moved[slot].w_axis[axis] += sign * h;
                    let (b, t) = pixels.batch(&model, &moved, Some(&pick)).unwrap();
                    loss_of(&b, &t).to_scalar::<f32>().unwrap() as f64
                };
                let numeric = (eval(1.0) - eval(-1.0)) / (2.0 * h);
                let scale = numeric.abs().max(g.abs() as f64).max(1e-4);
                assert!(
                    (numeric - g as f64).abs() / scale < 0.1,
                    "axis {axis} slot {slot}: analytic {g} numeric {numeric}"
                );
            }
        }
    }
}
