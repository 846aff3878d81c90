//! A prepared scene: codes checked against the model, hypernetworks run once, frames rendered
//! exactly or adaptively through the fast renderer.

use crate::camera::Frame;
use crate::codes::Codes;
use crate::model::Colf;
use crate::render::adaptive::{render_adaptive, AdaptiveStats};
use crate::render::fast::FastRenderer;
use crate::render::output::FrameRender;
use anyhow::{bail, Context, Result};
use glam::{DMat4, DVec3};

/// How to render: exact (the default), or adaptive with a threshold ε; samples per ray for a
/// volumetric model.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderOptions {
    /// Samples per ray (volumetric models only; None: the model's default).
    pub samples: Option<usize>,
    /// `Some(ε)`: adaptive rendering (light fields only).
    pub adaptive: Option<f32>,
}

/// A scene ready to render from any number of cameras: the hypernetworks have run once per
/// slot, here, not per view or per chunk, and their weights are laid out for the fast path.
pub struct PreparedScene {
    renderer: FastRenderer,
    slot_to_world: Vec<DMat4>,
}

impl PreparedScene {
    /// Checks that `codes` belong to `model` and runs the hypernetworks.
    pub fn new(model: &Colf, codes: &Codes, codes_name: &str) -> Result<PreparedScene> {
        let identity = model.identity()?;
        if codes.model != identity {
            bail!(
                "{codes_name}: encoded by model `{}`, but the model in use is `{identity}` (render them with the model that encoded them)",
                codes.model
            );
        }
        let dim = model.config().slot_dim;
        if codes.dim() != dim {
            bail!(
                "{codes_name}: latents have {} values, the model's slots have {dim}",
                codes.dim()
            );
        }
        let latents: Vec<Vec<f32>> = codes.slots.iter().map(|s| s.latent.clone()).collect();
        let slot_to_world: Vec<DMat4> = codes.slots.iter().map(|s| s.slot_to_world).collect();
        let prepared = model
            .prepare(&latents, &codes.background)
            .with_context(|| codes_name.to_string())?;
        Ok(PreparedScene {
            renderer: FastRenderer::new(model, &prepared, &slot_to_world)?,
            slot_to_world,
        })
    }

    /// Checks options against the model before any frame is rendered.
    pub fn check_options(&self, opts: &RenderOptions) -> Result<()> {
        if self.renderer.is_volumetric() {
            if opts.adaptive.is_some() {
                bail!("adaptive rendering applies to light-field models only (this model is volumetric)");
            }
        } else if opts.samples.is_some() {
            bail!("samples per ray apply to volumetric models only; this model renders light fields (one evaluation per ray per slot)");
        }
        if let Some(n) = opts.samples {
            if n == 0 || n > 4096 {
                bail!("samples per ray must be in 1..=4096, not {n}");
            }
        }
        if let Some(eps) = opts.adaptive {
            if !(eps.is_finite() && eps >= 0.0) {
                bail!("adaptive rendering: ε must be a finite number ≥ 0, not {eps}");
            }
        }
        Ok(())
    }

    /// Renders without the slots' shadows from now on (see `FastRenderer::drop_shadows`).
    pub fn drop_shadows(&mut self) {
        self.renderer.drop_shadows();
    }

    /// Number of foreground slots.
    pub fn num_slots(&self) -> usize {
        self.slot_to_world.len()
    }

    /// Renders every pixel-centre ray of `frame` exactly (`model` is the one the scene was
    /// prepared with; its weights are already in the scene).
    pub fn render_frame(&self, _model: &Colf, frame: &Frame) -> Result<FrameRender> {
        Ok(self.render_frame_with(frame, &RenderOptions::default())?.0)
    }

    /// Renders rows `rows` of `frame` exactly: the same values as those rows of
    /// [`PreparedScene::render_frame_with`] (every ray is rendered on its own), for a frame
    /// rendered and written in bands.
    pub fn render_rows(
        &self,
        frame: &Frame,
        rows: std::ops::Range<u32>,
        opts: &RenderOptions,
    ) -> Result<FrameRender> {
        self.check_options(opts)?;
        if opts.adaptive.is_some() {
            bail!("internal error: adaptive rendering needs the whole frame");
        }
        let w = frame.intrinsics.w;
        let rays: Vec<crate::camera::Ray> = rows
            .clone()
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| frame.pixel_ray(i, j))
            .collect();
        let origins: Vec<DVec3> = rays.iter().map(|r| r.origin).collect();
        let dirs: Vec<DVec3> = rays.iter().map(|r| r.direction).collect();
        drop(rays);
        let out = self.renderer.render(&origins, &dirs, opts.samples, None)?;
        self.checked(w, rows.end - rows.start, out)
    }

    fn checked(
        &self,
        width: u32,
        height: u32,
        out: crate::model::RayOutput,
    ) -> Result<FrameRender> {
        let frame = FrameRender {
            width,
            height,
            num_slots: self.num_slots(),
            rgb: out.rgb,
            weights: out.weights,
            ordering: out.ordering,
        };
        frame.validate()?;
        if frame
            .rgb
            .iter()
            .chain(&frame.weights)
            .any(|v| !v.is_finite())
        {
            bail!("the model produced non-finite colours or weights");
        }
        Ok(frame)
    }

    /// Renders every pixel-centre ray of `frame` with `opts`; for an adaptive render, also
    /// what it evaluated.
    pub fn render_frame_with(
        &self,
        frame: &Frame,
        opts: &RenderOptions,
    ) -> Result<(FrameRender, Option<AdaptiveStats>)> {
        self.check_options(opts)?;
        let rays = frame.rays();
        let origins: Vec<DVec3> = rays.iter().map(|r| r.origin).collect();
        let dirs: Vec<DVec3> = rays.iter().map(|r| r.direction).collect();
        let (out, stats) = match opts.adaptive {
            Some(eps) => {
                let (out, stats) = render_adaptive(&self.renderer, frame, &origins, &dirs, eps)?;
                (out, Some(stats))
            }
            None => (
                self.renderer.render(&origins, &dirs, opts.samples, None)?,
                None,
            ),
        };
        let frame = self.checked(frame.intrinsics.w, frame.intrinsics.h, out)?;
        Ok((frame, stats))
    }
}

/// A subset of a camera file's frames, as written: `A..B` (half-open), `A..`, `..B`, `..` or a
/// single index `N`. Parsing checks the syntax; [`FrameSelection::resolve`] checks it against a
/// file.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameSelection {
    text: String,
    start: Option<usize>,
    end: Option<usize>,
    single: bool,
}

impl FrameSelection {
    /// Parses the syntax (a clap value parser: a bad selection is a usage error).
    pub fn parse(text: &str) -> std::result::Result<FrameSelection, String> {
        let num = |s: &str| -> std::result::Result<Option<usize>, String> {
            let s = s.trim();
            if s.is_empty() {
                return Ok(None);
            }
            s.parse::<usize>()
                .map(Some)
                .map_err(|_| format!("`{s}` is not a frame index (expected A..B, A.., ..B or N)"))
        };
        let (start, end, single) = match text.split_once("..") {
            Some((a, b)) => (num(a)?, num(b)?, false),
            None => match num(text)? {
                Some(n) => (Some(n), n.checked_add(1), true),
                None => return Err("empty frame selection (expected A..B, A.., ..B or N)".into()),
            },
        };
        if let (Some(a), Some(b)) = (start, end) {
            if a >= b {
                return Err(format!("{text} selects no frames (A..B needs A < B)"));
            }
        }
        Ok(FrameSelection {
            text: text.to_string(),
            start,
            end,
            single,
        })
    }

    /// The index range in a file of `count` frames.
    pub fn resolve(&self, count: usize) -> Result<std::ops::Range<usize>> {
        let start = self.start.unwrap_or(0);
        let end = self.end.unwrap_or(count);
        if self.single && start >= count {
            bail!("frame {start} does not exist (the file has {count} frames: 0..{count})");
        }
        if end > count || start >= end {
            bail!(
                "frames {} reach beyond the {count} frames of the file (valid: 0..{count})",
                self.text
            );
        }
        Ok(start..end)
    }
}

/// Parses a frame selection (see [`FrameSelection`]) against `count` frames; returns the index
/// range.
pub fn parse_frame_range(text: &str, count: usize) -> Result<std::ops::Range<usize>> {
    FrameSelection::parse(text)
        .map_err(|e| anyhow::anyhow!("frames `{text}`: {e}"))?
        .resolve(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_ranges() {
        assert_eq!(parse_frame_range("2..5", 10).unwrap(), 2..5);
        assert_eq!(parse_frame_range("..3", 10).unwrap(), 0..3);
        assert_eq!(parse_frame_range("7..", 10).unwrap(), 7..10);
        assert_eq!(parse_frame_range("4", 10).unwrap(), 4..5);
        assert_eq!(parse_frame_range("..", 10).unwrap(), 0..10);
        for bad in ["5..2", "0..11", "10", "x..3", "3..3", "-1"] {
            assert!(parse_frame_range(bad, 10).is_err(), "{bad}");
        }
        // Syntax errors are found without a file; ranges beyond it say so.
        for bad in ["abc", "", "5..2", "1..x", "-1"] {
            assert!(FrameSelection::parse(bad).is_err(), "{bad}");
        }
        let msg = parse_frame_range("1..100", 2).unwrap_err().to_string();
        assert!(msg.contains("beyond the 2 frames"), "{msg}");
        let msg = parse_frame_range("7", 2).unwrap_err().to_string();
        assert!(msg.contains("frame 7 does not exist"), "{msg}");
    }
}
