//! Adaptive rendering (`colf-render --adaptive [EPS]`): evaluate a slot's light field only where
//! that slot can be seen, and its shadow only where the shadow can fall.
//!
//! 1. Render the compositor weights of all slots at reduced resolution: one ray through the
//!    centre of every `factor`×`factor` block of pixels (`factor` = [`COARSE_FACTOR`]). For a
//!    model whose slots cast shadows read along the light (`shadow_light`: a second light-field
//!    evaluation per ray and slot, on the ray's shadow line), the shadows of this coarse pass are
//!    found in two steps ([`coarse_pass`]): each slot's shadow density σ on every other coarse
//!    sample in each direction (a scout grid of 2·`factor`-pixel blocks), then on the other
//!    coarse samples only where the slot's shadow can fall: next to a scout sample where σ >
//!    ε·[`SCOUT_FRACTION`], or next to where the slot itself is seen (where a shadow meets its
//!    object). Elsewhere the slot casts no shadow at that sample.
//! 2. For every full-resolution pixel, take each slot's largest coarse weight and, separately,
//!    its largest coarse σ over the pixel's support: the 2×2 coarse samples a bilinear
//!    upsampling would blend for it (widened by [`DILATE_BLOCKS`] − 1 samples each way), so a
//!    slot visible at either side of a pixel's cell is still evaluated there.
//! 3. Render the full-resolution frame, evaluating slot k's light field on a pixel's ray only
//!    where its weight maximum exceeds ε (elsewhere the slot is left out of that pixel's
//!    composition: weight 0, ordering +∞), and on the pixel's shadow line only where its σ
//!    maximum exceeds ε (elsewhere it casts no shadow there). The background is always
//!    evaluated, so every pixel has at least one field and its weights still sum to 1. (A model
//!    whose shadows are read from the ray's own features evaluates them with the field, where
//!    either maximum exceeds ε.)
//!
//! Where a slot is evaluated, the result is exact for the fields evaluated there; the error is
//! the weight (< ε, up to the coarse sampling) of the slots left out, and the darkening
//! (1 − e^−σ < ε) of the shadows left out. ε = 0 evaluates every slot and shadow wherever its
//! coarse value is not exactly 0, which is nearly everywhere; the recommended ε and the
//! measured speed/PSNR trade are in `docs/tradeoff.md`.

use crate::camera::Frame;
use crate::model::RayOutput;
use crate::render::fast::{Active, FastRenderer};
use anyhow::{bail, Result};
use glam::DVec3;

/// Side of the pixel block one coarse ray stands for.
pub const COARSE_FACTOR: u32 = 4;
/// Support of a pixel in the coarse grid, per direction: 1 = the 2×2 samples of bilinear
/// upsampling; each step more widens it by one coarse sample on every side.
pub const DILATE_BLOCKS: i64 = 1;
/// The ε `--adaptive` uses without a value (chosen from the measurements in docs/tradeoff.md).
pub const RECOMMENDED_EPS: f32 = 0.03;
/// A coarse sample between scout samples has its shadow evaluated where a neighbouring scout
/// sample's σ exceeds this fraction of ε (a shadow's edge seen at the scout grid).
pub const SCOUT_FRACTION: f32 = 0.25;

/// What an adaptive render did, for logs and the trade-off measurements.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptiveStats {
    /// Coarse rays rendered.
    pub coarse_rays: usize,
    /// Foreground light-field evaluations done at full resolution (a slot on a ray, or on a
    /// ray's shadow line), and those of an exact render.
    pub evaluated: usize,
    pub possible: usize,
}

/// The ray × field masks of the full-resolution pass (see the module documentation).
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptiveMasks {
    /// Where each field is evaluated on the ray (the background everywhere).
    pub fields: Vec<bool>,
    /// Where each slot's shadow line is evaluated, for a model that reads shadows along the
    /// light; `None` otherwise (shadows come with the field).
    pub shadows: Option<Vec<bool>>,
}

impl AdaptiveMasks {
    /// The renderer's view of these masks.
    pub fn active(&self) -> Active<'_> {
        Active {
            fields: &self.fields,
            shadows: self.shadows.as_deref(),
        }
    }
}

/// The coarse pass: weights (and σ) of every field at the coarse rays `origins`, `dirs` (a
/// `cw`×`ch` grid, row-major). With shadows read along the light, σ is evaluated on the scout
/// grid (even columns and rows), then on the other samples where it may exceed ε (see the module
/// documentation); elsewhere it is 0.
pub fn coarse_pass(
    renderer: &FastRenderer,
    origins: &[DVec3],
    dirs: &[DVec3],
    (cw, ch): (usize, usize),
    eps: f32,
) -> Result<RayOutput> {
    let s = renderer.fields();
    if !renderer.shadows_along_light() {
        return renderer.render(origins, dirs, None, None);
    }
    let scout = |i: usize, j: usize| i.is_multiple_of(2) && j.is_multiple_of(2);
    let all = vec![true; origins.len() * s];
    let mut shadows = vec![false; origins.len() * s];
    for j in 0..ch {
        for i in 0..cw {
            if scout(i, j) {
                shadows[(j * cw + i) * s + 1..(j * cw + i + 1) * s].fill(true);
            }
        }
    }
    let mut coarse = renderer.render_active(
        origins,
        dirs,
        Active {
            fields: &all,
            shadows: Some(&shadows),
        },
    )?;
    // The other samples: where a neighbouring scout sample's σ, or the slot's own weight at a
    // neighbouring sample, says the shadow may be there.
    let near = |x: usize, n: usize| x.saturating_sub(2)..=(x + 2).min(n - 1);
    let (mut rays, mut refine) = (Vec::new(), Vec::new());
    for j in 0..ch {
        for i in 0..cw {
            if scout(i, j) {
                continue;
            }
            let mut row = vec![false; s];
            for (k, on) in row.iter_mut().enumerate().skip(1) {
                'search: for bj in near(j, ch) {
                    for bi in near(i, cw) {
                        let at = (bj * cw + bi) * s + k;
                        let seen =
                            bj.abs_diff(j) <= 1 && bi.abs_diff(i) <= 1 && coarse.weights[at] > eps;
                        if seen || (scout(bi, bj) && coarse.shadow[at] > eps * SCOUT_FRACTION) {
                            *on = true;
                            break 'search;
                        }
                    }
                }
            }
            if row.iter().any(|&on| on) {
                rays.push(j * cw + i);
                refine.extend(row);
            }
        }
    }
    if !rays.is_empty() {
        let background_only: Vec<bool> = (0..rays.len() * s).map(|at| at % s == 0).collect();
        let o: Vec<DVec3> = rays.iter().map(|&r| origins[r]).collect();
        let d: Vec<DVec3> = rays.iter().map(|&r| dirs[r]).collect();
        let cast = renderer.render_active(
            &o,
            &d,
            Active {
                fields: &background_only,
                shadows: Some(&refine),
            },
        )?;
        for (n, &r) in rays.iter().enumerate() {
            coarse.shadow[r * s + 1..(r + 1) * s]
                .copy_from_slice(&cast.shadow[n * s + 1..(n + 1) * s]);
        }
    }
    Ok(coarse)
}

/// For each value of a = ⌊u⌋, u the coarse coordinate of a pixel (a = −1 … `n` − 1), the coarse
/// samples of its support (see the module documentation), clamped to the grid.
fn support(a: i64, n: usize) -> std::ops::RangeInclusive<usize> {
    let lo = (a - (DILATE_BLOCKS - 1)).max(0) as usize;
    let hi = (a + DILATE_BLOCKS).min(n as i64 - 1).max(0) as usize;
    lo..=hi
}

/// `values` (a `cw`×`ch` grid of `s` fields) maximised over each support window: the result is a
/// (`cw` + 1)×(`ch` + 1) grid, entry (a + 1, b + 1) for the pixels with ⌊u⌋ = a, ⌊v⌋ = b.
fn window_max(values: &[f32], (cw, ch): (usize, usize), s: usize) -> Vec<f32> {
    let mut rows = vec![0f32; ch * (cw + 1) * s];
    for j in 0..ch {
        for a in 0..=cw {
            let out = &mut rows[(j * (cw + 1) + a) * s..(j * (cw + 1) + a + 1) * s];
            for i in support(a as i64 - 1, cw) {
                for (o, v) in out.iter_mut().zip(&values[(j * cw + i) * s..]) {
                    *o = o.max(*v);
                }
            }
        }
    }
    let mut out = vec![0f32; (ch + 1) * (cw + 1) * s];
    for b in 0..=ch {
        for a in 0..=cw {
            let cell = &mut out[(b * (cw + 1) + a) * s..(b * (cw + 1) + a + 1) * s];
            for j in support(b as i64 - 1, ch) {
                for (o, v) in cell.iter_mut().zip(&rows[(j * (cw + 1) + a) * s..]) {
                    *o = o.max(*v);
                }
            }
        }
    }
    out
}

/// The ray × field masks of the full-resolution pass (see the module documentation).
pub fn active_masks(
    renderer: &FastRenderer,
    frame: &Frame,
    eps: f32,
) -> Result<(AdaptiveMasks, AdaptiveStats)> {
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
    let coarse = coarse_pass(renderer, &origins, &dirs, (cw, ch), eps)?;
    let along_light = renderer.shadows_along_light();
    let weights = window_max(&coarse.weights, (cw, ch), s);
    let shadows = window_max(&coarse.shadow, (cw, ch), s);
    // ⌊u⌋ + 1 of a pixel, u its coarse coordinate (pixel centres, blocks of f).
    let cell = |x: usize| ((x as f64 + 0.5) / f as f64 - 0.5).floor() as i64 + 1;
    let mut fields = vec![false; w * h * s];
    let mut shadow_mask = along_light.then(|| vec![false; w * h * s]);
    let mut evaluated = 0;
    for y in 0..h {
        let b = cell(y) as usize;
        for x in 0..w {
            let a = cell(x) as usize;
            let c = (b * (cw + 1) + a) * s;
            let at = (y * w + x) * s;
            fields[at] = true;
            for k in 1..s {
                let (wk, sk) = (weights[c + k], shadows[c + k]);
                match &mut shadow_mask {
                    Some(m) => {
                        fields[at + k] = wk > eps;
                        m[at + k] = sk > eps;
                        evaluated += fields[at + k] as usize + m[at + k] as usize;
                    }
                    None => {
                        fields[at + k] = wk.max(sk) > eps;
                        evaluated += fields[at + k] as usize;
                    }
                }
            }
        }
    }
    let per_slot = if along_light { 2 } else { 1 };
    Ok((
        AdaptiveMasks {
            fields,
            shadows: shadow_mask,
        },
        AdaptiveStats {
            coarse_rays: cw * ch,
            evaluated,
            possible: w * h * (s - 1) * per_slot,
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
    let (masks, stats) = active_masks(renderer, frame, eps)?;
    Ok((
        renderer.render_active(origins, dirs, masks.active())?,
        stats,
    ))
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
        let (masks, stats) = active_masks(&r, &frame, 0.3).unwrap();
        assert!(masks.shadows.is_none());
        let mask = masks.fields;
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
        let (_, stats) = active_masks(&plain, &frame, 0.3).unwrap();
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

    /// A model that reads shadows along the light, its shadow head given weights that vary
    /// with the line's features and the bias `bias` (σ = softplus(10 (w·f + b))).
    fn along_light(bias: f32) -> (Colf, FastRenderer, Frame) {
        use candle_core::{Device, Tensor};
        let cfg = Config::small()
            .with_overrides(&["shadow_head=true".into(), "shadow_light=[30,55]".into()])
            .unwrap();
        let grown = Colf::init(&Config::small(), 1)
            .unwrap()
            .reconfigured(&cfg, 1, "m")
            .unwrap();
        let dims = grown.parameters()["heads.shadow.weight"].dims().to_vec();
        let n: usize = dims.iter().product();
        let weight: Vec<f32> = (0..n).map(|i| ((i * 5 % 7) as f32 - 3.0) * 0.1).collect();
        let model = grown
            .with_tensor(
                "heads.shadow.weight",
                Tensor::from_vec(weight, dims, &Device::Cpu).unwrap(),
            )
            .unwrap()
            .with_tensor(
                "heads.shadow.bias",
                Tensor::new(&[bias], &Device::Cpu).unwrap(),
            )
            .unwrap();
        setup_with(model)
    }

    /// Issue 38: a slot's shadow line is evaluated apart from its field — where its coarse σ
    /// exceeds ε, whether or not the slot is seen there, and nowhere else; with every
    /// evaluation switched on the render is the exact one, and a shadow switched off casts none.
    #[test]
    fn shadows_along_the_light_are_masked_apart_from_their_slots() {
        let (_m, r, frame) = along_light(-0.1);
        assert!(r.shadows_along_light());
        let (o, d) = rays(&frame);
        let exact = r.render(&o, &d, None, None).unwrap();
        let s = r.fields();
        let all = vec![true; o.len() * s];
        let everything = Active {
            fields: &all,
            shadows: Some(&all),
        };
        assert_eq!(r.render_active(&o, &d, everything).unwrap(), exact);
        // Shadows only where the field is off, and the reverse.
        let fields: Vec<bool> = (0..o.len() * s)
            .map(|at| at % s == 0 || at % 3 == 0)
            .collect();
        let shadows: Vec<bool> = fields.iter().map(|f| !f).collect();
        let split = r
            .render_active(
                &o,
                &d,
                Active {
                    fields: &fields,
                    shadows: Some(&shadows),
                },
            )
            .unwrap();
        for at in 0..o.len() * s {
            if at % s == 0 {
                continue;
            }
            let expected = if shadows[at] { exact.shadow[at] } else { 0.0 };
            assert_eq!(split.shadow[at], expected, "entry {at}");
            if !fields[at] {
                assert_eq!(split.weights[at], 0.0);
            }
        }
        // The masks follow the coarse values; both kinds of evaluation are counted. (ε: a high
        // quantile of σ, so that some shadows are evaluated and some not.)
        let mut sigmas: Vec<f32> = (0..o.len() * s)
            .filter(|at| at % s != 0)
            .map(|at| exact.shadow[at])
            .collect();
        sigmas.sort_by(f32::total_cmp);
        let eps = sigmas[sigmas.len() * 9 / 10];
        let (masks, stats) = active_masks(&r, &frame, eps).unwrap();
        let shadows = masks.shadows.as_ref().unwrap();
        let count = |m: &[bool]| {
            m.chunks_exact(s)
                .map(|row| row[1..].iter().filter(|v| **v).count())
                .sum::<usize>()
        };
        assert_eq!(stats.evaluated, count(&masks.fields) + count(shadows));
        assert_eq!(stats.possible, 2 * 18 * 13 * (s - 1));
        let (cast, all) = (count(shadows), 18 * 13 * (s - 1));
        assert!(
            cast > 0 && cast < all,
            "{cast} of {all} shadows at ε = {eps}"
        );
        assert_ne!(&masks.fields, shadows);
        // ε = 0: every evaluation, the exact render.
        let (out, stats) = render_adaptive(&r, &frame, &o, &d, 0.0).unwrap();
        assert_eq!(stats.evaluated, stats.possible);
        assert_eq!(out, exact);
    }

    /// The coarse pass's scouting finds every shadow a full coarse evaluation finds above ε
    /// (same values), and skips shadow lines where shadows are faint. (With random weights every
    /// slot is seen nearly everywhere below ε ≈ 0.5, so the large ε make the scout decide.)
    #[test]
    fn the_coarse_pass_finds_every_shadow_above_eps() {
        let (mut skipped, mut found) = (0, 0);
        for bias in [0.0f32, -0.3, -0.6, -1.0] {
            let (_m, r, mut frame) = along_light(bias);
            frame.intrinsics = crate::camera::Intrinsics::from_fov(64, 48, 49.13);
            let s = r.fields();
            let (cw, ch) = (16u32, 12u32);
            let coarse_rays: Vec<_> = (0..ch)
                .flat_map(|j| (0..cw).map(move |i| (i, j)))
                .map(|(i, j)| frame.ray_at((i * 4) as f64 + 2.0, (j * 4) as f64 + 2.0))
                .collect();
            let o: Vec<DVec3> = coarse_rays.iter().map(|r| r.origin).collect();
            let d: Vec<DVec3> = coarse_rays.iter().map(|r| r.direction).collect();
            let full = r.render(&o, &d, None, None).unwrap();
            for eps in [0.0, 0.03, 0.3, 0.6, 1.0] {
                let scouted = coarse_pass(&r, &o, &d, (16, 12), eps).unwrap();
                assert_eq!(scouted.weights, full.weights);
                for at in 0..o.len() * s {
                    let (a, b) = (full.shadow[at], scouted.shadow[at]);
                    skipped += (b == 0.0 && a > 0.0) as usize;
                    found += (b == a && a > eps) as usize;
                    assert!(
                        b == a || (b == 0.0 && a <= eps),
                        "bias {bias}, ε {eps}, entry {at}: {b} for {a}"
                    );
                }
            }
        }
        // Both happened: shadows found above ε, and evaluations skipped.
        assert!(skipped > 0 && found > 0, "skipped {skipped}, found {found}");
    }
}
