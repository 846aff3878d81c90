//! Object proposals against a known background (`colf-train --proposals-against MODEL`): for
//! scenes that share one background — the city's street — a model trained on that background
//! alone (the city recipe's c0: a static background field, no slots) renders what each view
//! shows without its objects, and what the image adds to that render is the objects
//! ([`crate::proposals::propose_against`]). No mask is read.

use crate::camera::Frame;
use crate::codes::Codes;
use crate::dataset::View;
use crate::image_io::RgbImage32;
use crate::model::Colf;
use crate::proposals::{propose_against, ProposalParams};
use crate::render::PreparedScene;
use anyhow::{bail, Context, Result};
use std::path::Path;

/// Chromaticity difference from the background render above which a pixel that differs from it
/// is an object candidate (chosen on 6 city-block validation scenes against c0 at 64²: 94 % of
/// the car pixels, 97 % of the candidates on cars, with a channel threshold of 0.1; without the
/// hue test the blurred building edges made a third of the candidates).
pub const RENDER_HUE: f32 = 0.03;

/// The channel threshold of proposals against a render (the render's blur needs a little more
/// than a fitted floor's 0.08).
pub const RENDER_THRESHOLD: f32 = 0.1;

/// A model's background, rendered alone.
pub struct KnownBackground {
    model: Colf,
    scene: PreparedScene,
}

impl KnownBackground {
    /// Loads `path`, which must draw the same background whatever the image (its
    /// `zero_background`; a static background field has it).
    pub fn load(path: &Path) -> Result<KnownBackground> {
        let shown = path.display();
        let model = Colf::load(path).with_context(|| format!("{shown}: the known background"))?;
        let cfg = model.config();
        if !cfg.zero_background {
            bail!(
                "{shown}: its background depends on the image (zero_background is off), so it is no known background to propose objects against"
            );
        }
        let codes = Codes {
            slots: Vec::new(),
            background: vec![0.0; cfg.slot_dim],
            model: model.identity()?,
        };
        let scene = PreparedScene::new(&model, &codes, &shown.to_string())?;
        Ok(KnownBackground { model, scene })
    }

    /// The background as `frame`'s camera sees it: RGB, row-major.
    pub fn render(&self, frame: &Frame) -> Result<Vec<f32>> {
        Ok(self.scene.render_frame(&self.model, frame)?.rgb)
    }

    /// The object proposals of `image`, seen by `frame`'s camera.
    pub fn propose(&self, image: &RgbImage32, frame: &Frame) -> Result<Vec<u8>> {
        if (frame.intrinsics.w, frame.intrinsics.h) != (image.w, image.h) {
            bail!(
                "the camera is {}x{} pixels, the image {}x{}",
                frame.intrinsics.w,
                frame.intrinsics.h,
                image.w,
                image.h
            );
        }
        proposals_against_render(image, &self.render(frame)?)
    }
}

/// The object proposals of `image` against `render`, a render of its background alone (RGB,
/// row-major, the image's size), with the settings `--proposals-against` uses.
pub fn proposals_against_render(image: &RgbImage32, render: &[f32]) -> Result<Vec<u8>> {
    let params = ProposalParams {
        threshold: RENDER_THRESHOLD,
        ..ProposalParams::default()
    };
    propose_against(image, render, RENDER_HUE, &params)
}

/// A view's object proposals: against `known`'s background where there is one, else against
/// the fitted floor ([`crate::proposals::propose`] with `params`). Errors name the view's file.
pub fn view_proposals(
    known: Option<&KnownBackground>,
    view: &View,
    params: &ProposalParams,
) -> Result<Vec<u8>> {
    match known {
        Some(known) => known
            .propose(&view.image, &view.frame)
            .with_context(|| view.path.display().to_string()),
        None => Ok(crate::proposals::propose(&view.image, params)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{look_at, Intrinsics};
    use crate::model::Config;
    use crate::proposals::is_instance;
    use glam::DVec3;

    /// An object the background render lacks is proposed; where the image is the render,
    /// nothing is.
    #[test]
    fn what_the_image_adds_to_the_render_is_proposed() {
        let mut cfg = Config::small();
        cfg.zero_background = true;
        cfg.static_background = true;
        let model = Colf::init(&cfg, 3).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("street.safetensors");
        model.save(&path).unwrap();
        let known = KnownBackground::load(&path).unwrap();
        let frame = Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(16, 16, 49.13),
            camera_to_world: look_at(DVec3::new(0.0, -8.0, 6.0), DVec3::ZERO, DVec3::Z).unwrap(),
        };
        let mut data = known.render(&frame).unwrap();
        // A saturated red 4×4 object.
        for y in 4..8 {
            for x in 4..8 {
                data[3 * (y * 16 + x)..3 * (y * 16 + x) + 3].copy_from_slice(&[0.9, 0.1, 0.1]);
            }
        }
        let image = RgbImage32 { w: 16, h: 16, data };
        let ids = known.propose(&image, &frame).unwrap();
        for y in 0..16 {
            for x in 0..16 {
                let id = ids[y * 16 + x];
                if (4..8).contains(&y) && (4..8).contains(&x) {
                    assert_eq!(id, 1, "({x}, {y})");
                } else {
                    assert!(!is_instance(id), "({x}, {y})");
                }
            }
        }
        // A camera of another size than the image is refused.
        let small = Frame {
            intrinsics: Intrinsics::from_fov(8, 8, 49.13),
            ..frame
        };
        assert!(known.propose(&image, &small).is_err());
    }

    #[test]
    fn an_image_dependent_background_is_refused() {
        let model = Colf::init(&Config::small(), 3).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("clevr.safetensors");
        model.save(&path).unwrap();
        let err = KnownBackground::load(&path).err().unwrap();
        assert!(
            format!("{err:#}").contains("depends on the image"),
            "{err:#}"
        );
    }
}
