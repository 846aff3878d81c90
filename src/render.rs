//! Rendering: prepared slots + a camera → one frame (colour, compositor weights, ordering).

use crate::camera::Frame;
use crate::codes::Codes;
use crate::model::{Colf, PreparedSlots};
use crate::render_output::FrameRender;
use anyhow::{bail, Result};
use glam::{DMat4, DVec3};

/// A scene ready to render from any number of cameras: the hypernetworks have run once per
/// slot, here, not per view or per chunk.
pub struct PreparedScene {
    prepared: PreparedSlots,
    slot_to_world: Vec<DMat4>,
}

impl PreparedScene {
    /// Checks that `codes` belong to `model` and runs the hypernetworks.
    pub fn new(model: &Colf, codes: &Codes, codes_name: &str) -> Result<PreparedScene> {
        let identity = model.identity()?;
        if codes.model != identity {
            bail!(
                "{codes_name}: encoded by model `{}`, but the model in use is `{identity}` (pass the encoding model with --model or COLF_MODEL)",
                codes.model
            );
        }
        let latents: Vec<Vec<f32>> = codes.slots.iter().map(|s| s.latent.clone()).collect();
        Ok(PreparedScene {
            prepared: model.prepare(&latents, &codes.background)?,
            slot_to_world: codes.slots.iter().map(|s| s.slot_to_world).collect(),
        })
    }

    /// Number of foreground slots.
    pub fn num_slots(&self) -> usize {
        self.slot_to_world.len()
    }

    /// Renders every pixel-centre ray of `frame`.
    pub fn render_frame(&self, model: &Colf, frame: &Frame) -> Result<FrameRender> {
        let rays = frame.rays();
        let origins: Vec<DVec3> = rays.iter().map(|r| r.origin).collect();
        let dirs: Vec<DVec3> = rays.iter().map(|r| r.direction).collect();
        let out = model.render_rays(&self.prepared, &self.slot_to_world, &origins, &dirs)?;
        let frame = FrameRender {
            width: frame.intrinsics.w,
            height: frame.intrinsics.h,
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
}

/// Parses `--frames`: `A..B` (half-open), `A..`, `..B`, `..` or a single index `N`, against
/// `count` frames; returns the index range.
pub fn parse_frame_range(text: &str, count: usize) -> Result<std::ops::Range<usize>> {
    let num = |s: &str, default: usize| -> Result<usize> {
        if s.is_empty() {
            return Ok(default);
        }
        s.trim()
            .parse::<usize>()
            .map_err(|_| anyhow::anyhow!("--frames `{text}`: `{s}` is not a frame index"))
    };
    let range = match text.split_once("..") {
        Some((a, b)) => num(a, 0)?..num(b, count)?,
        None => {
            let n = num(text, usize::MAX)?;
            n..n.saturating_add(1)
        }
    };
    if range.start >= range.end || range.end > count {
        bail!(
            "--frames `{text}` selects no frames of the {count} in the camera file (valid: 0..{count})"
        );
    }
    Ok(range)
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
    }
}
