//! The last step of an encoding: drop the slots the input views do not need.
//!
//! Given more slots than objects (the default encoding uses 12), slot attention sometimes gives
//! one object two slots that draw it alike; the one that loses the compositor's competition
//! changes nothing visible, but deleting or moving its twin in an edit would leave a copy
//! behind. Slots with no visible content are dropped the same way.

use super::latents_and_frames;
use super::view::InputView;
use crate::codes::Slot;
use crate::model::{Colf, Config};
use crate::render::fast::FastRenderer;
use anyhow::Result;

/// Drops the slots `views` do not need: in order of attention mass (smallest first), a slot
/// is removed when the slots left still render the views with a mean squared error (the mean
/// of the views') at most `tolerance` above that of all `slots`. The bound is on the total, so
/// many small removals cannot add up to a visible loss. With `reached` (the model's config with
/// the encoding's reaches, `RefineOptions::reached_config`) the renders leave out the far shadow
/// lines and slots it bounds.
pub fn drop_redundant_slots(
    model: &Colf,
    slots: Vec<Slot>,
    background: &[f32],
    views: &[&InputView],
    tolerance: f64,
    reached: Option<&Config>,
) -> Result<Vec<Slot>> {
    if tolerance <= 0.0 || slots.is_empty() || views.is_empty() {
        return Ok(slots);
    }
    let (latents, frames) = latents_and_frames(&slots);
    // Light fields: the hypernetworks run once and every field is evaluated once per view; a
    // subset is then only composited, the other slots left out of every ray's composition (the
    // same as deleting them). The volumetric baseline has no such composition and renders each
    // subset anew.
    let evaluated = if model.config().is_volumetric() {
        None
    } else {
        let prepared = model.prepare(&latents, background)?;
        let renderer = FastRenderer::new(model, &prepared, &frames)?.within_reaches(reached);
        let values = views
            .iter()
            .map(|v| renderer.evaluate_fields(&v.compared.origins, &v.compared.dirs))
            .collect::<Result<Vec<_>>>()?;
        Some((renderer, values))
    };
    let error_on = |vi: usize, keep: &[bool]| -> Result<f64> {
        let view = views[vi];
        let Some((renderer, values)) = &evaluated else {
            let (latents, frames): (Vec<_>, Vec<_>) = latents
                .iter()
                .zip(&frames)
                .zip(keep)
                .filter(|(_, &k)| k)
                .map(|((l, f), _)| (l.clone(), *f))
                .unzip();
            return view.mse(model, &latents, background, &frames, reached);
        };
        let fields: Vec<bool> = std::iter::once(true).chain(keep.iter().copied()).collect();
        let out = renderer.composite(&values[vi], &fields)?;
        Ok(view.compared.mse(&out.rgb))
    };
    let error_of = |keep: &[bool]| -> Result<f64> {
        let mut total = 0.0;
        for vi in 0..views.len() {
            total += error_on(vi, keep)?;
        }
        Ok(total / views.len() as f64)
    };
    let mut keep = vec![true; slots.len()];
    let budget = error_of(&keep)? + tolerance;
    let mut by_mass: Vec<usize> = (0..slots.len()).collect();
    by_mass.sort_by(|&a, &b| slots[a].mass.total_cmp(&slots[b].mass).then(a.cmp(&b)));
    for k in by_mass {
        keep[k] = false;
        if error_of(&keep)? > budget {
            keep[k] = true;
        }
    }
    Ok(slots
        .into_iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(s, _)| s)
        .collect())
}
