//! Test-time refinement of slot latents: the encoder's slots are an amortised guess, made in one
//! pass for any scene; a few Adam steps on the latents (and, gently, on the slot frames'
//! origins; the model's weights fixed) then lower the input view's colour error for this scene. Only the input
//! image is used, so novel views are still predictions; the decoder, trained on many views of
//! many scenes, is the prior that keeps a refined latent a 3-D object (how far that holds is
//! measured, README "Refinement").
//!
//! Each step renders a seeded random subset of the input view's pixels (all of them when the
//! image has no more than `rays` pixels), so a step costs one training step's decoder pass on
//! one view, and the result is the same for the same inputs.

use crate::camera::Frame;
use crate::image_io::RgbImage32;
use crate::model::{Colf, RayBatch, SceneRays};
use crate::train::adam::{Adam, AdamConfig};
use anyhow::{bail, Context, Result};
use candle_core::{Tensor, Var};
use glam::{DMat4, DVec3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

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
            seed: 0,
        }
    }
}

/// What a refinement did: the input view's PSNR (on the rendered subsets) at the first and the
/// last step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineReport {
    pub steps: usize,
    pub first_psnr: f64,
    pub last_psnr: f64,
}

/// The world rays of `image`'s pixel centres seen by `camera` (scaled when the camera's
/// intrinsics are for another resolution) and their colours.
fn pixel_rays(camera: &Frame, image: &RgbImage32) -> (Vec<DVec3>, Vec<DVec3>) {
    let (w, h) = (image.w as usize, image.h as usize);
    let sx = camera.intrinsics.w as f64 / w as f64;
    let sy = camera.intrinsics.h as f64 / h as f64;
    let mut origins = Vec::with_capacity(w * h);
    let mut dirs = Vec::with_capacity(w * h);
    for j in 0..h {
        for i in 0..w {
            let ray = camera.ray_at((i as f64 + 0.5) * sx, (j as f64 + 0.5) * sy);
            origins.push(ray.origin);
            dirs.push(ray.direction);
        }
    }
    (origins, dirs)
}

fn psnr_of_mse(mse: f64) -> f64 {
    -10.0 * mse.max(1e-12).log10()
}

/// Pixels of the input view compared when choosing between encodings (a seeded subset when the
/// image has more).
const COMPARE_PIXELS: usize = 4096;

/// The mean squared colour error of slots (`fg_latents` in frames `slot_to_world`, and
/// `bg_latent`) against `image` seen by `camera`, over all pixels or a fixed seeded subset of
/// `COMPARE_PIXELS` of them (the same subset for every call on the same image).
pub fn input_view_mse(
    model: &Colf,
    fg_latents: &[Vec<f32>],
    bg_latent: &[f32],
    slot_to_world: &[DMat4],
    camera: &Frame,
    image: &RgbImage32,
) -> Result<f64> {
    let pixels = ComparedPixels::new(camera, image);
    let prepared = model.prepare(fg_latents, bg_latent)?;
    let out = model.render_rays(&prepared, slot_to_world, &pixels.origins, &pixels.dirs)?;
    Ok(pixels.mse(&out.rgb))
}

/// The pixels of an input view that encodings are judged on (all of them, or a fixed seeded
/// subset of `COMPARE_PIXELS`: the same subset for every call on the same image).
pub struct ComparedPixels {
    /// World rays through the pixels.
    pub origins: Vec<DVec3>,
    pub dirs: Vec<DVec3>,
    /// Their colours in the image, RGB.
    target: Vec<f32>,
}

impl ComparedPixels {
    pub fn new(camera: &Frame, image: &RgbImage32) -> ComparedPixels {
        let (origins, dirs) = pixel_rays(camera, image);
        let n = origins.len();
        let pick: Vec<usize> = if n <= COMPARE_PIXELS {
            (0..n).collect()
        } else {
            let mut rng = StdRng::seed_from_u64(0);
            (0..COMPARE_PIXELS)
                .map(|_| rng.random_range(0..n))
                .collect()
        };
        ComparedPixels {
            origins: pick.iter().map(|&p| origins[p]).collect(),
            dirs: pick.iter().map(|&p| dirs[p]).collect(),
            target: pick
                .iter()
                .flat_map(|&p| image.data[3 * p..3 * p + 3].iter().copied())
                .collect(),
        }
    }

    /// Mean squared colour error of `rgb` (RGB per compared pixel, in order).
    pub fn mse(&self, rgb: &[f32]) -> f64 {
        let sum: f64 = rgb
            .iter()
            .zip(&self.target)
            .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
            .sum();
        sum / self.target.len().max(1) as f64
    }
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
    refine_latents_on_views(
        model,
        fg_latents,
        bg_latent,
        slot_to_world,
        &[(camera, image)],
        opts,
    )
}

/// [`refine_latents`] against several views of the scene at once: each step draws its pixels
/// from all of them.
pub fn refine_latents_on_views(
    model: &Colf,
    fg_latents: &mut [Vec<f32>],
    bg_latent: &mut Vec<f32>,
    slot_to_world: &mut [DMat4],
    views: &[(&Frame, &RgbImage32)],
    opts: &RefineOptions,
) -> Result<RefineReport> {
    if !(opts.lr.is_finite() && opts.lr > 0.0) {
        bail!("--refine-lr must be a positive number, not {}", opts.lr);
    }
    if !(opts.anchor_weight.is_finite() && opts.anchor_weight >= 0.0) {
        bail!(
            "--refine-anchor must be a number ≥ 0, not {}",
            opts.anchor_weight
        );
    }
    if opts.rays == 0 {
        bail!("--refine-rays must be at least 1");
    }
    if !(opts.frame_lr.is_finite() && opts.frame_lr >= 0.0) {
        bail!(
            "--refine-frame-lr must be a number ≥ 0, not {}",
            opts.frame_lr
        );
    }
    if views.iter().all(|(_, image)| image.data.is_empty()) {
        bail!("refinement needs at least one view with pixels");
    }
    let net = model.model();
    let cfg = model.config();
    if net.light_field().is_none() {
        bail!("refinement applies to light-field models, not the volumetric baseline");
    }
    let k = fg_latents.len();
    let d = cfg.slot_dim;
    if opts.steps == 0 || k == 0 {
        return Ok(RefineReport {
            steps: 0,
            first_psnr: f64::NAN,
            last_psnr: f64::NAN,
        });
    }
    let dev = model.device();
    let fg0 = Tensor::from_vec(
        fg_latents.iter().flatten().copied().collect::<Vec<f32>>(),
        (1, k, d),
        dev,
    )?;
    let bg0 = Tensor::from_vec(bg_latent.clone(), (1, d), dev)?;
    let fg = Var::from_tensor(&fg0)?;
    let bg = Var::from_tensor(&bg0)?;
    let mut params = vec![("fg".to_string(), fg.clone())];
    if !cfg.zero_background {
        params.push(("bg".to_string(), bg.clone()));
    }
    let mut adam = Adam::new(
        params,
        AdamConfig {
            clip_norm: None,
            ..AdamConfig::default()
        },
    )?;
    let (mut origins, mut dirs, mut colours) = (Vec::new(), Vec::new(), Vec::new());
    for (camera, image) in views {
        let (o, d) = pixel_rays(camera, image);
        origins.extend(o);
        dirs.extend(d);
        colours.extend_from_slice(&image.data);
    }
    let n = origins.len();
    let per_step = opts.rays.min(n);
    let mut rng = StdRng::seed_from_u64(opts.seed);
    let move_frames = opts.frame_lr > 0.0;
    // Every pixel once and fixed frames: one batch for all steps.
    let fixed = (per_step == n && !move_frames)
        .then(|| batch(model, slot_to_world, &origins, &dirs, &colours, None))
        .transpose()?;
    let mut frames = slot_to_world.to_vec();
    // The frame origins' offsets from `frames` (foreground slots; axis-major [3, K]), always
    // zero when read: each step's update is moved into `frames`.
    let offset = Var::zeros((3, k), candle_core::DType::F32, dev)?;
    let mut frame_adam = Adam::new(
        vec![("offset".to_string(), offset.clone())],
        AdamConfig {
            clip_norm: None,
            ..AdamConfig::default()
        },
    )?;
    let (mut first, mut last) = (f64::NAN, f64::NAN);
    for step in 0..opts.steps {
        let drawn;
        let (rays, target) = match &fixed {
            Some(b) => (&b.0, &b.1),
            None => {
                let pick: Vec<usize> = if per_step == n {
                    (0..n).collect()
                } else {
                    (0..per_step).map(|_| rng.random_range(0..n)).collect()
                };
                drawn = if move_frames {
                    linearised_batch(model, &frames, &offset, &origins, &dirs, &colours, &pick)?
                } else {
                    batch(model, &frames, &origins, &dirs, &colours, Some(&pick))?
                };
                (&drawn.0, &drawn.1)
            }
        };
        let fields = net.prepare(fg.as_tensor(), bg.as_tensor())?;
        let decoded = net.decode(&fields, rays)?;
        let mse = (&decoded.rgb - target)?.sqr()?.mean_all()?;
        let mse_value = mse.to_scalar::<f32>()? as f64;
        if step == 0 {
            first = psnr_of_mse(mse_value);
        }
        last = psnr_of_mse(mse_value);
        let mut loss = mse;
        if opts.anchor_weight > 0.0 {
            let pull = (fg.as_tensor() - &fg0)?.sqr()?.mean_all()?;
            loss = (loss + (pull * opts.anchor_weight)?)?;
        }
        let grads = loss.backward()?;
        // A non-finite gradient: keep what the last good step gave.
        if adam.step(&grads, opts.lr).is_err() {
            break;
        }
        if move_frames {
            if frame_adam.step(&grads, opts.frame_lr).is_err() {
                break;
            }
            let moved = offset.as_tensor().to_vec2::<f32>()?;
            for (slot, frame) in frames.iter_mut().enumerate() {
                let delta = DVec3::new(
                    moved[0][slot] as f64,
                    moved[1][slot] as f64,
                    moved[2][slot] as f64,
                );
                frame.w_axis += delta.extend(0.0);
            }
            offset.set(&offset.as_tensor().zeros_like()?)?;
        }
    }
    let refined_fg = fg.as_tensor().squeeze(0)?.to_vec2::<f32>()?;
    let refined_bg = bg.as_tensor().squeeze(0)?.to_vec1::<f32>()?;
    let finite = refined_fg
        .iter()
        .flatten()
        .chain(&refined_bg)
        .all(|v| v.is_finite())
        && frames.iter().all(|f| f.is_finite());
    if finite {
        slot_to_world.copy_from_slice(&frames);
        for (dst, src) in fg_latents.iter_mut().zip(refined_fg) {
            *dst = src;
        }
        *bg_latent = refined_bg;
    }
    Ok(RefineReport {
        steps: opts.steps,
        first_psnr: first,
        last_psnr: last,
    })
}

/// Forward-difference step for the frame origins' linearisation (world units).
const FRAME_STEP: f64 = 1e-3;

/// The rays of the pixels `pick` encoded as a function of the foreground frame origins'
/// offsets `offset` [3, K] (zero at the call): coordinates and ordering shifts at `frames`, plus
/// their forward-difference derivatives along each world axis times the offsets, so gradients
/// reach `offset`. Returns the batch and the target colours [1, R, 3].
fn linearised_batch(
    model: &Colf,
    frames: &[DMat4],
    offset: &Var,
    origins: &[DVec3],
    dirs: &[DVec3],
    rgb: &[f32],
    pick: &[usize],
) -> Result<(RayBatch, Tensor)> {
    let (at, target) = batch(model, frames, origins, dirs, rgb, Some(pick))?;
    let (s, r) = (at.fields, at.rays);
    let dev = model.device();
    // Shifts before the per-ray base is subtracted, so batches at different origins compare.
    let absolute = |b: &RayBatch| -> Result<Tensor> {
        let base = Tensor::from_vec(
            b.base.iter().map(|&v| v as f32).collect::<Vec<f32>>(),
            (1, r, 1),
            dev,
        )?;
        Ok(b.shift.broadcast_add(&base)?)
    };
    let shift_at = absolute(&at)?;
    let mut coords = at.coords.clone();
    let mut shadow_lines = at.shadow_lines.clone();
    let mut shift = at.shift.clone();
    // The background (field 0) never moves: its offset is a constant 0.
    let zero = Tensor::zeros(1, candle_core::DType::F32, dev)?;
    for axis in 0..3 {
        let mut moved = frames.to_vec();
        for f in moved.iter_mut() {
            f.w_axis[axis] += FRAME_STEP;
        }
        let (ahead, _) = batch(model, &moved, origins, dirs, rgb, Some(pick))?;
        let per_field = Tensor::cat(&[&zero, &offset.as_tensor().get(axis)?], 0)?; // [S]
        let per_line = per_field.reshape((s, 1, 1))?;
        let d_coords = ((&ahead.coords - &at.coords)? / FRAME_STEP)?;
        coords = (coords + d_coords.broadcast_mul(&per_line)?)?;
        // Shadow lines move with the frames too (their ground mask does not).
        if let (Some((lines, _)), Some((ahead_lines, _)), Some((at_lines, _))) =
            (shadow_lines.as_mut(), &ahead.shadow_lines, &at.shadow_lines)
        {
            let d_lines = ((ahead_lines - at_lines)? / FRAME_STEP)?;
            *lines = (&*lines + d_lines.broadcast_mul(&per_line)?)?;
        }
        let d_shift = ((absolute(&ahead)? - &shift_at)? / FRAME_STEP)?;
        shift = (shift + d_shift.broadcast_mul(&per_field.reshape((1, 1, s))?)?)?;
    }
    Ok((
        RayBatch {
            coords,
            shadow_lines,
            shift,
            base: at.base,
            scenes: 1,
            fields: s,
            rays: r,
        },
        target,
    ))
}

/// The encoded rays and target colours [1, R, 3] of the pixels `pick` (all when `None`).
fn batch(
    model: &Colf,
    slot_to_world: &[DMat4],
    origins: &[DVec3],
    dirs: &[DVec3],
    rgb: &[f32],
    pick: Option<&[usize]>,
) -> Result<(RayBatch, Tensor)> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};
    use crate::model::Config;

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
        let (o, d) = pixel_rays(
            cam,
            &RgbImage32 {
                w: cam.intrinsics.w,
                h: cam.intrinsics.h,
                data: Vec::new(),
            },
        );
        let out = model.render_rays(&prepared, &frames, &o, &d).unwrap();
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
        let run = |views: &[(&Frame, &RgbImage32)]| {
            let (mut fg, mut bg, mut frames) =
                (latents(2, d, 2), bg.clone(), vec![cam.camera_to_world; 2]);
            refine_latents_on_views(&model, &mut fg, &mut bg, &mut frames, views, &opts).unwrap();
            fg
        };
        let one = run(&[(&cam, &image)]);
        let two = run(&[(&cam, &image), (&cam, &image)]);
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
        for views in [&[][..], &[(&cam, &empty)][..]] {
            let err = refine_latents_on_views(&model, &mut fg, &mut bg, &mut frames, views, &opts)
                .unwrap_err();
            assert!(err.to_string().contains("at least one view"), "{err}");
        }
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

    #[test]
    fn frame_gradients_match_finite_differences_of_the_loss() {
        let mut cfg = Config::small();
        cfg.ray_fourier_freqs = 2;
        cfg.fg_locality = 2.0;
        cfg.attention_frames = true;
        let model = Colf::init(&cfg, 8).unwrap();
        let d = cfg.slot_dim;
        let cam = camera(12);
        let fg = latents(2, d, 9);
        let bg = vec![0.1; d];
        let image = target(&model, &latents(2, d, 10), &bg, &cam);
        let mut frames = vec![cam.camera_to_world; 2];
        frames[0].w_axis = glam::DVec4::new(0.5, -0.3, 0.2, 1.0);
        frames[1].w_axis = glam::DVec4::new(-1.0, 0.4, 0.0, 1.0);
        let (origins, dirs) = pixel_rays(&cam, &image);
        let pick: Vec<usize> = (0..origins.len()).collect();
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
        let (rays, target) = linearised_batch(
            &model,
            &frames,
            &offset,
            &origins,
            &dirs,
            &image.data,
            &pick,
        )
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
                    let (b, t) =
                        batch(&model, &moved, &origins, &dirs, &image.data, Some(&pick)).unwrap();
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
