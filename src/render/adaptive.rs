//! Adaptive rendering (`colf-render --adaptive [EPS]`): evaluate a slot's light field only where
//! that slot can be seen.
//!
//! 1. Render the compositor weights of all slots at reduced resolution: one ray through the
//!    centre of every `factor`×`factor` block of pixels (`factor` = [`COARSE_FACTOR`]).
//! 2. For every full-resolution pixel, take each slot's largest coarse weight (or shadow
//!    density σ, for a model whose slots cast shadows: they darken pixels they do not win) over the pixel's
//!    support: the 2×2 coarse samples a bilinear upsampling would blend for it (widened by
//!    [`DILATE_BLOCKS`] − 1 samples each way), so a slot visible at either side of a pixel's
//!    cell is still evaluated there.
//! 3. Render the full-resolution frame, evaluating slot k at a pixel only where that maximum
//!    exceeds ε; elsewhere the slot is left out of that pixel's composition
//!    (weight 0, ordering +∞). The background is always evaluated, so every pixel has at least
//!    one field and its weights still sum to 1.
//!
//! Where a slot is evaluated, the result is exact for the fields evaluated there; the error is
//! the weight (< ε, up to the coarse sampling) of the slots left out. ε = 0 evaluates every slot
//! wherever its coarse weight is not exactly 0, which is nearly everywhere; the recommended ε
//! and the measured speed/PSNR trade are in `docs/tradeoff.md`.

use crate::camera::Frame;
use crate::model::RayOutput;
use crate::render::fast::FastRenderer;
use anyhow::{bail, Result};
use glam::DVec3;

/// Side of the pixel block one coarse ray stands for.
pub const COARSE_FACTOR: u32 = 4;
/// Support of a pixel in the coarse grid, per direction: 1 = the 2×2 samples of bilinear
/// upsampling; each step more widens it by one coarse sample on every side.
pub const DILATE_BLOCKS: i64 = 1;
/// The ε `--adaptive` uses without a value (chosen from the measurements in docs/tradeoff.md).
pub const RECOMMENDED_EPS: f32 = 0.03;

/// What an adaptive render did, for logs and the trade-off measurements.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptiveStats {
    /// Coarse rays rendered.
    pub coarse_rays: usize,
    /// Foreground (slot, pixel) evaluations done at full resolution, and possible.
    pub evaluated: usize,
    pub possible: usize,
}

/// The ray × field mask of the full-resolution pass (see the module documentation).
pub fn active_mask(
    renderer: &FastRenderer,
    frame: &Frame,
    eps: f32,
) -> Result<(Vec<bool>, AdaptiveStats)> {
    if !(eps.is_finite() && eps >= 0.0) {
        bail!("adaptive rendering: ε must be a finite number ≥ 0, not {eps}");
    }
    let s = renderer.fields();
    let (w, h) = (frame.intrinsics.w as usize, frame.intrinsics.h as usize);
    let f = COARSE_FACTOR as usize;
    let (cw, ch) = (w.div_ceil(f), h.div_ceil(f));
    let mut origins = Vec::with_capacity(cw * ch);
    let mut dirs = Vec::with_capacity(cw * ch);
    for j in 0..ch {
        for i in 0..cw {
            // The centre of the block, clamped into the image for partial blocks.
            let u = ((i * f) as f64 + 0.5 * f as f64).min(w as f64 - 0.5);
            let v = ((j * f) as f64 + 0.5 * f as f64).min(h as f64 - 0.5);
            let ray = frame.ray_at(u, v);
            origins.push(ray.origin);
            dirs.push(ray.direction);
        }
    }
    let coarse: RayOutput = renderer.render(&origins, &dirs, None, None)?;
    // A pixel's support: the coarse samples a bilinear upsampling would blend for it (the 2×2
    // around it, fewer at the border), widened by `DILATE_BLOCKS` − 1 in every direction.
    let support = |x: usize, n: usize, cn: usize| -> (usize, usize) {
        let u = (x as f64 + 0.5) / f as f64 - 0.5;
        let lo = u.floor() as i64 - (DILATE_BLOCKS - 1);
        let hi = u.floor() as i64 + DILATE_BLOCKS;
        let _ = n;
        (lo.max(0) as usize, hi.min(cn as i64 - 1) as usize)
    };
    let mut mask = vec![false; w * h * s];
    let mut evaluated = 0;
    for y in 0..h {
        let (y0, y1) = support(y, h, ch);
        for x in 0..w {
            let (x0, x1) = support(x, w, cw);
            let at = (y * w + x) * s;
            mask[at] = true;
            for k in 1..s {
                let mut best = 0f32;
                for by in y0..=y1 {
                    for bx in x0..=x1 {
                        let at = (by * cw + bx) * s + k;
                        best = best.max(coarse.weights[at]).max(coarse.shadow[at]);
                    }
                }
                let on = best > eps;
                mask[at + k] = on;
                evaluated += on as usize;
            }
        }
    }
    Ok((
        mask,
        AdaptiveStats {
            coarse_rays: cw * ch,
            evaluated,
            possible: w * h * (s - 1),
        },
    ))
}

/// Renders every pixel of `frame` adaptively with threshold `eps`.
pub fn render_adaptive(
    renderer: &FastRenderer,
    frame: &Frame,
    origins: &[DVec3],
    dirs: &[DVec3],
    eps: f32,
) -> Result<(RayOutput, AdaptiveStats)> {
    if renderer.is_volumetric() {
        bail!("adaptive rendering applies to light-field models only (this model is volumetric)");
    }
    let (mask, stats) = active_mask(renderer, frame, eps)?;
    Ok((renderer.render(origins, dirs, None, Some(&mask))?, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Colf, Config};
    use glam::DMat4;

    fn setup() -> (Colf, FastRenderer, Frame) {
        setup_with(Colf::init(&Config::small(), 1).unwrap())
    }

    fn setup_with(model: Colf) -> (Colf, FastRenderer, Frame) {
        let latents: Vec<Vec<f32>> = (0..3)
            .map(|k| {
                (0..64)
                    .map(|i| ((i * 7 + k * 13) % 11) as f32 / 5.0 - 1.0)
                    .collect()
            })
            .collect();
        let bg: Vec<f32> = (0..64).map(|i| (i % 5) as f32 / 4.0 - 0.5).collect();
        let prepared = model.prepare(&latents, &bg).unwrap();
        let frames: Vec<DMat4> = (0..3)
            .map(|k| DMat4::from_translation(DVec3::new(k as f64, -1.0, 0.0)))
            .collect();
        let renderer = FastRenderer::new(&model, &prepared, &frames).unwrap();
        let frame = Frame {
            file_path: None,
            intrinsics: crate::camera::Intrinsics::from_fov(18, 13, 49.13),
            camera_to_world: crate::camera::look_at(
                DVec3::new(9.0, -8.0, 8.0),
                DVec3::ZERO,
                DVec3::Z,
            )
            .unwrap(),
        };
        (model, renderer, frame)
    }

    fn rays(frame: &Frame) -> (Vec<DVec3>, Vec<DVec3>) {
        frame.rays().iter().map(|r| (r.origin, r.direction)).unzip()
    }

    #[test]
    fn eps_above_every_weight_keeps_only_the_background_and_zero_eps_is_exact_where_weights_are_positive(
    ) {
        let (_m, r, frame) = setup();
        let (o, d) = rays(&frame);
        let exact = r.render(&o, &d, None, None).unwrap();
        // Partial blocks (18×13 is not a multiple of 4) are covered.
        let (out, stats) = render_adaptive(&r, &frame, &o, &d, 0.0).unwrap();
        assert_eq!(stats.coarse_rays, 5 * 4);
        assert_eq!(stats.evaluated, stats.possible);
        assert_eq!(out, exact);
        let (out, stats) = render_adaptive(&r, &frame, &o, &d, 1.0).unwrap();
        assert_eq!(stats.evaluated, 0);
        for px in out.weights.chunks_exact(4) {
            assert_eq!(px, &[1.0, 0.0, 0.0, 0.0]);
        }
        assert!(render_adaptive(&r, &frame, &o, &d, f32::NAN).is_err());
    }

    #[test]
    fn a_slot_is_evaluated_exactly_where_its_dilated_coarse_weight_exceeds_eps() {
        let (_m, r, frame) = setup();
        let (mask, stats) = active_mask(&r, &frame, 0.3).unwrap();
        assert_eq!(
            mask.iter().filter(|v| **v).count(),
            stats.evaluated + 18 * 13
        );
        // Recompute one pixel's decision by hand.
        let coarse_frame_rays: Vec<_> = (0..4)
            .flat_map(|j| (0..5).map(move |i| (i, j)))
            .map(|(i, j): (u32, u32)| {
                frame.ray_at(
                    ((i * 4) as f64 + 2.0).min(17.5),
                    ((j * 4) as f64 + 2.0).min(12.5),
                )
            })
            .collect();
        let o: Vec<DVec3> = coarse_frame_rays.iter().map(|r| r.origin).collect();
        let d: Vec<DVec3> = coarse_frame_rays.iter().map(|r| r.direction).collect();
        let coarse = r.render(&o, &d, None, None).unwrap();
        // Pixel (9, 6) sits between coarse samples 1 and 2 in both directions.
        let (x, y) = (9usize, 6usize);
        for k in 1..4 {
            let mut best = 0f32;
            for bj in 1..3 {
                for bi in 1..3 {
                    best = best.max(coarse.weights[(bj * 5 + bi) * 4 + k]);
                }
            }
            assert_eq!(mask[(y * 18 + x) * 4 + k], best > 0.3, "slot {k}");
        }
    }

    #[test]
    fn a_slot_is_evaluated_where_its_shadow_reaches_even_where_it_has_no_weight() {
        let (_m, plain, frame) = setup();
        let (_, stats) = active_mask(&plain, &frame, 0.3).unwrap();
        assert!(stats.evaluated < stats.possible);
        // The same weights with a shadow head casting σ = softplus(−1) ≈ 0.31 on every ray.
        let cfg = Config::small()
            .with_overrides(&["shadow_head=true".into()])
            .unwrap();
        let shadowed = Colf::init(&Config::small(), 1)
            .unwrap()
            .reconfigured(&cfg, 1, "m")
            .unwrap()
            .with_tensor(
                "heads.shadow.bias",
                candle_core::Tensor::new(&[-0.1f32], &candle_core::Device::Cpu).unwrap(),
            )
            .unwrap();
        let (_m, r, frame) = setup_with(shadowed);
        let (o, d) = rays(&frame);
        let (out, stats) = render_adaptive(&r, &frame, &o, &d, 0.3).unwrap();
        assert_eq!(stats.evaluated, stats.possible);
        assert_eq!(out, r.render(&o, &d, None, None).unwrap());
    }
}
