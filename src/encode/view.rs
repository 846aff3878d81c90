//! The input view: an image, its camera, and the world rays through its pixels, built once per
//! encoding and read by every step (choosing between tries, refinement, the redundant-slot drop).

use crate::camera::Frame;
use crate::image_io::RgbImage32;
use crate::model::{Colf, Config};
use crate::render::fast::FastRenderer;
use anyhow::Result;
use glam::{DMat4, DVec3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::sync::OnceLock;

/// Pixels of the input view compared when judging encodings (a seeded subset when the image
/// has more): enough to rank encodings, few enough that judging costs little next to encoding.
const COMPARE_PIXELS: usize = 4096;

/// An image seen by a camera, with the world ray of every pixel centre.
pub struct InputView<'a> {
    pub camera: &'a Frame,
    pub image: &'a RgbImage32,
    /// World rays through the pixel centres, row-major (scaled when the camera's intrinsics are
    /// for another resolution than the image's).
    pub origins: Vec<DVec3>,
    pub dirs: Vec<DVec3>,
    /// The pixels encodings are judged on.
    pub compared: ComparedPixels,
    /// For a model with a static background: the view's object proposals against that
    /// background's render (computed once, by [`InputView::proposal_ids`]).
    proposals: OnceLock<Vec<u8>>,
    /// With `Config::frames_from_residual`: 1 on the pixels the model's background alone does
    /// not draw, 0 elsewhere (computed once, by [`InputView::object_pixels`]).
    objects: OnceLock<Vec<f32>>,
}

impl<'a> InputView<'a> {
    pub fn new(camera: &'a Frame, image: &'a RgbImage32) -> InputView<'a> {
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
        let compared = ComparedPixels::new(&origins, &dirs, &image.data);
        InputView {
            camera,
            image,
            origins,
            dirs,
            compared,
            proposals: OnceLock::new(),
            objects: OnceLock::new(),
        }
    }

    /// The object proposals (row-major ids, `crate::proposals`' meaning: 0 background, 1…254
    /// instances, `UNSURE`) of this view against `model`'s background rendered alone at its
    /// camera, as `--proposals-against` makes them in training. Meant for a model whose
    /// background is static (the same street in every scene): the render is then what the view
    /// shows without its objects.
    pub fn proposal_ids(&self, model: &Colf) -> Result<&[u8]> {
        if let Some(ids) = self.proposals.get() {
            return Ok(ids);
        }
        let background = vec![0f32; model.config().slot_dim];
        let prepared = model.prepare(&[], &background)?;
        let render = FastRenderer::new(model, &prepared, &[])?.render(
            &self.origins,
            &self.dirs,
            None,
            None,
        )?;
        let ids =
            crate::train::known_background::proposals_against_render(self.image, &render.rgb)?;
        Ok(self.proposals.get_or_init(|| ids))
    }

    /// The pixels (row-major, 1 or 0) that `model`'s background, rendered alone at this view's
    /// camera, does not explain: the instances of [`InputView::proposal_ids`]
    /// (`Config::frames_from_residual` places slots from them).
    pub fn object_pixels(&self, model: &Colf) -> Result<&[f32]> {
        if let Some(objects) = self.objects.get() {
            return Ok(objects);
        }
        let objects = crate::proposals::object_pixels(self.proposal_ids(model)?);
        Ok(self.objects.get_or_init(|| objects))
    }

    /// The mean squared colour error, on the compared pixels, of slots (`fg_latents` in frames
    /// `slot_to_world`, and `bg_latent`) rendered by the fast renderer (the reference path's
    /// function to float rounding, at a third of its time: the tries of an encoding are judged
    /// this way). With `reached` (the model's config with an encoding's reaches,
    /// `RefineOptions::reached_config`), the far shadow lines and slots it bounds are left out.
    pub fn mse(
        &self,
        model: &Colf,
        fg_latents: &[Vec<f32>],
        bg_latent: &[f32],
        slot_to_world: &[DMat4],
        reached: Option<&Config>,
    ) -> Result<f64> {
        let prepared = model.prepare(fg_latents, bg_latent)?;
        let renderer = FastRenderer::new(model, &prepared, slot_to_world)?.within_reaches(reached);
        self.mse_by(&renderer)
    }

    /// [`InputView::mse`] with slots already prepared: one renderer serves every view.
    pub fn mse_by(&self, renderer: &FastRenderer) -> Result<f64> {
        let out = renderer.render(&self.compared.origins, &self.compared.dirs, None, None)?;
        Ok(self.compared.mse(&out.rgb))
    }
}

/// The pixels of an input view that encodings are judged on: all of them, or a fixed seeded
/// subset of `COMPARE_PIXELS` (the same subset for every call on the same image).
pub struct ComparedPixels {
    /// World rays through the pixels.
    pub origins: Vec<DVec3>,
    pub dirs: Vec<DVec3>,
    /// Their colours in the image, RGB.
    target: Vec<f32>,
}

impl ComparedPixels {
    fn new(origins: &[DVec3], dirs: &[DVec3], rgb: &[f32]) -> ComparedPixels {
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
                .flat_map(|&p| rgb[3 * p..3 * p + 3].iter().copied())
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;

    fn image(size: u32) -> RgbImage32 {
        RgbImage32 {
            w: size,
            h: size,
            data: (0..3 * size * size).map(|i| (i % 7) as f32 / 7.0).collect(),
        }
    }

    fn camera(size: u32) -> Frame {
        Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(size, size, 49.13),
            camera_to_world: DMat4::IDENTITY,
        }
    }

    #[test]
    fn rays_cover_every_pixel_and_small_images_are_compared_whole() {
        let camera = camera(8);
        let img = image(8);
        let view = InputView::new(&camera, &img);
        assert_eq!(view.origins.len(), 64);
        assert!(view.dirs.iter().all(|d| (d.length() - 1.0).abs() < 1e-9));
        assert_eq!(view.compared.origins.len(), 64);
        // Its own colours have no error.
        assert_eq!(view.compared.mse(&img.data), 0.0);
    }

    #[test]
    fn large_images_are_compared_on_a_fixed_subset() {
        let camera = camera(128);
        let img = image(128);
        let a = InputView::new(&camera, &img);
        let b = InputView::new(&camera, &img);
        assert_eq!(a.compared.origins.len(), COMPARE_PIXELS);
        assert_eq!(a.compared.origins, b.compared.origins);
    }

    /// The pixels a static background's render lacks are the object pixels, with a camera
    /// given for twice the image's size (its rays are scaled to the image).
    #[test]
    fn object_pixels_are_what_the_background_does_not_draw() {
        let mut cfg = crate::model::Config::small();
        cfg.zero_background = true;
        cfg.static_background = true;
        let model = Colf::init(&cfg, 3).unwrap();
        let camera = Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(32, 32, 49.13),
            camera_to_world: crate::camera::look_at(
                DVec3::new(0.0, -8.0, 6.0),
                DVec3::ZERO,
                DVec3::Z,
            )
            .unwrap(),
        };
        let blank = RgbImage32 {
            w: 16,
            h: 16,
            data: vec![0.0; 16 * 16 * 3],
        };
        let background = InputView::new(&camera, &blank);
        let prepared = model.prepare(&[], &vec![0.0; cfg.slot_dim]).unwrap();
        let mut data = FastRenderer::new(&model, &prepared, &[])
            .unwrap()
            .render(&background.origins, &background.dirs, None, None)
            .unwrap()
            .rgb;
        for y in 4..8 {
            for x in 9..13 {
                data[3 * (y * 16 + x)..3 * (y * 16 + x) + 3].copy_from_slice(&[0.9, 0.1, 0.1]);
            }
        }
        let img = RgbImage32 { w: 16, h: 16, data };
        let view = InputView::new(&camera, &img);
        let objects = view.object_pixels(&model).unwrap();
        for y in 0..16 {
            for x in 0..16 {
                let inside = (4..8).contains(&y) && (9..13).contains(&x);
                assert_eq!(
                    objects[y * 16 + x],
                    f32::from(u8::from(inside)),
                    "({x}, {y})"
                );
            }
        }
    }
}
