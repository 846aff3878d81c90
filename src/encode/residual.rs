//! Slots for the objects no view's encoding found, where several views agree on them.
//!
//! The encoder reads a 64² copy of each image, where the smallest objects are 2–4 pixels wide,
//! and slot attention can leave them to the background in every view (`docs/eval.md`, "Several
//! input views"). What the refined encoding still lacks shows in its renders: pixels that
//! differ from them in hue, grouped into blobs as object proposals against those renders
//! ([`crate::proposals::propose_against`]). One view's blob may be shading or a part of an
//! object the slots draw a little off (a slot per blob of one view fitted that view and not the
//! others: `docs/eval.md`); a blob two views agree on — their centre rays pass within
//! [`MAX_RAY_GAP`] of each other, above the floor, in front of both cameras — is something in
//! 3-D. Each agreed point gets a new slot: its frame at the point (oriented as the first view's
//! slots), its latent a copy of the smallest slot's (in CLEVR-like scenes a small object's is
//! the nearest start). The caller refines again on all views; an added slot then stays only if
//! two views or more see it ([`keep_agreed`]), and the redundant-slot drop removes what no view
//! needs, so a point that is no object costs only time.

use super::view::InputView;
use crate::codes::Slot;
use crate::model::Colf;
use crate::proposals::{propose_against, ProposalParams};
use crate::render::fast::FastRenderer;
use anyhow::Result;
use glam::DVec3;

/// A pixel differs from the render when some channel differs by more than this…
pub const RESIDUAL_THRESHOLD: f32 = 0.18;
/// …and its chromaticity by more than this (chosen on 20 Blender test scenes: the blobs cover
/// 13 of the 16 appearances of objects no slot drew, with 15 blobs elsewhere in 60 views).
pub const RESIDUAL_HUE: f32 = 0.12;
/// The default of [`super::EncodeOptions::agreed_slots`] (colf-encode's and colf-eval's with
/// several views and refinement): on 100 held-out 128² scenes of each look, three views in,
/// they drew view 3 better and left fewer objects without a slot (docs/eval.md, twenty-second
/// session).
pub const DEFAULT_AGREED_SLOTS: usize = 3;
/// Blobs smaller than this many pixels are left alone.
pub const RESIDUAL_MIN_PIXELS: usize = 6;
/// Two views agree on a blob when its centre rays pass within this share of the model's scene
/// scale of each other (0.24 world units for CLEVR's 8: a third of its smallest objects).
pub const MAX_RAY_GAP: f64 = 0.03;
/// An agreed point lies no lower than this share of the scene scale below the floor (z = 0).
const BELOW_FLOOR: f64 = 0.02;

/// A residual blob of one view: its pixel count and the world ray through its centre.
#[derive(Clone, Debug)]
pub struct Blob {
    pub pixels: usize,
    pub origin: DVec3,
    pub dir: DVec3,
}

/// The blobs of `view` that `slots` and `background` do not draw, largest first.
pub fn residual_blobs(
    model: &Colf,
    slots: &[Slot],
    background: &[f32],
    view: &InputView,
) -> Result<Vec<Blob>> {
    let (latents, frames) = super::latents_and_frames(slots);
    let prepared = model.prepare(&latents, background)?;
    let rendered = FastRenderer::new(model, &prepared, &frames)?.render(
        &view.origins,
        &view.dirs,
        None,
        None,
    )?;
    let image = view.image;
    let (w, h) = (image.w as usize, image.h as usize);
    let params = ProposalParams {
        threshold: RESIDUAL_THRESHOLD,
        min_area: RESIDUAL_MIN_PIXELS as f32 / (w * h).max(1) as f32,
        ring: 0,
        ..ProposalParams::default()
    };
    let ids = propose_against(image, &rendered.rgb, RESIDUAL_HUE, &params)?;
    // Instance ids are numbered from the largest blob; UNSURE (255) and smaller ones are not.
    let mut sums = vec![(0.0f64, 0.0f64, 0usize); 255];
    for (p, &id) in ids.iter().enumerate() {
        if (1..255).contains(&id) {
            let s = &mut sums[id as usize];
            s.0 += (p % w) as f64 + 0.5;
            s.1 += (p / w) as f64 + 0.5;
            s.2 += 1;
        }
    }
    let (sx, sy) = (
        view.camera.intrinsics.w as f64 / w as f64,
        view.camera.intrinsics.h as f64 / h as f64,
    );
    Ok(sums[1..]
        .iter()
        .take_while(|(_, _, n)| *n >= RESIDUAL_MIN_PIXELS)
        .map(|&(x, y, n)| {
            let ray = view.camera.ray_at(x / n as f64 * sx, y / n as f64 * sy);
            Blob {
                pixels: n,
                origin: ray.origin,
                dir: ray.direction.normalize(),
            }
        })
        .collect())
}

/// Points two views agree on: for blobs of different views, the midpoint of their centre rays'
/// closest approach where the rays pass within `max_gap` (in front of both cameras, not below
/// the floor by more than `below_floor`); closest pairs first, each blob in one pair at most;
/// at most `max` points. Each point comes with the view of its first blob.
pub fn agreed_points(
    blobs: &[Vec<Blob>],
    max_gap: f64,
    below_floor: f64,
    max: usize,
) -> Vec<(DVec3, usize)> {
    let mut pairs = Vec::new();
    for (va, a_blobs) in blobs.iter().enumerate() {
        for (vb, b_blobs) in blobs.iter().enumerate().skip(va + 1) {
            for (ia, a) in a_blobs.iter().enumerate() {
                for (ib, b) in b_blobs.iter().enumerate() {
                    if let Some((point, gap)) = closest_approach(a, b) {
                        if gap <= max_gap && point.z >= -below_floor {
                            pairs.push((gap, (va, ia), (vb, ib), point));
                        }
                    }
                }
            }
        }
    }
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let mut used = std::collections::HashSet::new();
    let mut points = Vec::new();
    for (_, a, b, point) in pairs {
        if points.len() == max {
            break;
        }
        if used.contains(&a) || used.contains(&b) {
            continue;
        }
        used.insert(a);
        used.insert(b);
        points.push((point, a.0));
    }
    points
}

/// The midpoint of the shortest segment between two rays and its length; None for (nearly)
/// parallel rays or a closest approach behind either origin.
fn closest_approach(a: &Blob, b: &Blob) -> Option<(DVec3, f64)> {
    let w = a.origin - b.origin;
    let (da, db) = (a.dir, b.dir);
    let cross = da.dot(db);
    let denominator = 1.0 - cross * cross;
    if denominator < 1e-9 {
        return None;
    }
    let ta = (cross * db.dot(w) - da.dot(w)) / denominator;
    let tb = (db.dot(w) - cross * da.dot(w)) / denominator;
    if ta <= 0.0 || tb <= 0.0 {
        return None;
    }
    let (pa, pb) = (a.origin + da * ta, b.origin + db * tb);
    Some(((pa + pb) * 0.5, (pa - pb).length()))
}

/// Appends up to `max` slots at the points `views`' residual blobs agree on (see the module
/// documentation); returns how many. Needs at least one slot to copy a latent from.
pub fn add_agreed_slots(
    model: &Colf,
    slots: &mut Vec<Slot>,
    background: &[f32],
    views: &[&InputView],
    max: usize,
) -> Result<usize> {
    let Some(smallest) = slots
        .iter()
        .min_by(|a, b| a.mass.total_cmp(&b.mass))
        .map(|s| s.latent.clone())
    else {
        return Ok(0);
    };
    if max == 0 || views.len() < 2 {
        return Ok(0);
    }
    let blobs = views
        .iter()
        .map(|view| residual_blobs(model, slots, background, view))
        .collect::<Result<Vec<_>>>()?;
    let scale = model.config().scene_scale;
    let points = agreed_points(&blobs, MAX_RAY_GAP * scale, BELOW_FLOOR * scale, max);
    for (i, &(point, view)) in points.iter().enumerate() {
        let mut slot_to_world = views[view].camera.camera_to_world;
        slot_to_world.w_axis = point.extend(1.0);
        slots.push(Slot {
            latent: smallest.clone(),
            slot_to_world,
            mass: 0.0,
            source: format!("agreed#{i}"),
        });
    }
    Ok(points.len())
}

/// An added slot stays only if, after refinement, it wins at least this many of the judged
/// pixels ([`InputView::compared`]) in each of two views or more: what one view alone asks for
/// (shading, a part of an object drawn a little off) is not an object the views agree on.
pub const AGREED_KEEP_PIXELS: usize = 2;

/// `slots` without those of index `first_added` or later that fewer than two `views` see
/// ([`AGREED_KEEP_PIXELS`]).
pub fn keep_agreed(
    model: &Colf,
    slots: Vec<Slot>,
    background: &[f32],
    views: &[&InputView],
    first_added: usize,
) -> Result<Vec<Slot>> {
    if first_added >= slots.len() {
        return Ok(slots);
    }
    let label_maps = views
        .iter()
        .map(|view| super::multiview::labels(model, &slots, background, view))
        .collect::<Result<Vec<_>>>()?;
    let seen_by = views_seeing(&label_maps, slots.len(), AGREED_KEEP_PIXELS);
    Ok(slots
        .into_iter()
        .zip(seen_by)
        .enumerate()
        .filter(|(k, (_, views))| *k < first_added || *views >= 2)
        .map(|(_, (slot, _))| slot)
        .collect())
}

/// Per slot (label k + 1 in the maps, 0 the background), in how many of the label maps it
/// wins at least `min_pixels` pixels.
fn views_seeing(label_maps: &[Vec<u32>], slots: usize, min_pixels: usize) -> Vec<usize> {
    let mut seen_by = vec![0usize; slots];
    for labels in label_maps {
        let mut won = vec![0usize; slots];
        for &l in labels.iter().filter(|&&l| l > 0 && (l as usize) <= slots) {
            won[l as usize - 1] += 1;
        }
        for (seen, n) in seen_by.iter_mut().zip(won) {
            *seen += (n >= min_pixels) as usize;
        }
    }
    seen_by
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob(origin: DVec3, towards: DVec3) -> Blob {
        Blob {
            pixels: 10,
            origin,
            dir: (towards - origin).normalize(),
        }
    }

    /// A blob of another hue that the slots do not draw is found, its ray through the blob's
    /// centre; the rest of the image (the slots' own render) gives none.
    #[test]
    fn a_blob_the_render_lacks_is_found_on_its_ray() {
        use crate::camera::{look_at, Frame, Intrinsics};
        use crate::image_io::RgbImage32;
        use crate::model::Config;
        let mut cfg = Config::small();
        cfg.attention_frames = true;
        let model = Colf::init(&cfg, 5).unwrap();
        let camera = Frame {
            file_path: None,
            intrinsics: Intrinsics::from_fov(16, 16, 49.13),
            camera_to_world: look_at(DVec3::new(0.0, -8.0, 6.0), DVec3::ZERO, DVec3::Z).unwrap(),
        };
        let d = cfg.slot_dim;
        let slots: Vec<Slot> = [0.1f32, -0.2]
            .iter()
            .map(|&v| Slot {
                latent: vec![v; d],
                slot_to_world: camera.camera_to_world,
                mass: 0.1,
                source: "s".into(),
            })
            .collect();
        let background = vec![0.0; d];
        let blank = RgbImage32 {
            w: 16,
            h: 16,
            data: vec![0.5; 16 * 16 * 3],
        };
        let plain = InputView::new(&camera, &blank);
        let (latents, frames) = super::super::latents_and_frames(&slots);
        let prepared = model.prepare(&latents, &background).unwrap();
        let mut data = FastRenderer::new(&model, &prepared, &frames)
            .unwrap()
            .render(&plain.origins, &plain.dirs, None, None)
            .unwrap()
            .rgb;
        let image = RgbImage32 {
            w: 16,
            h: 16,
            data: data.clone(),
        };
        let view = InputView::new(&camera, &image);
        assert!(residual_blobs(&model, &slots, &background, &view)
            .unwrap()
            .is_empty());
        // A saturated 3×3 blob at x 10–12, y 4–6, of a hue far from the render's.
        for y in 4..7 {
            for x in 10..13 {
                let p = 3 * (y * 16 + x);
                let red_share = data[p] / (data[p] + data[p + 1] + data[p + 2]).max(1e-3);
                let colour = if red_share > 0.4 {
                    [0.1, 0.2, 0.9]
                } else {
                    [0.9, 0.1, 0.1]
                };
                data[p..p + 3].copy_from_slice(&colour);
            }
        }
        let image = RgbImage32 { w: 16, h: 16, data };
        let view = InputView::new(&camera, &image);
        let blobs = residual_blobs(&model, &slots, &background, &view).unwrap();
        assert_eq!(blobs.len(), 1, "{blobs:?}");
        assert_eq!(blobs[0].pixels, 9);
        let ray = camera.ray_at(11.5, 5.5);
        assert!((blobs[0].dir - ray.direction.normalize()).length() < 1e-9);
    }

    #[test]
    fn a_slot_counts_in_the_views_where_it_wins_enough_pixels() {
        let maps = vec![
            vec![0, 1, 1, 2, 3, 3, 3],
            vec![1, 1, 0, 0, 3, 2, 2],
            vec![3, 3, 0, 0, 0, 0, 2],
        ];
        assert_eq!(views_seeing(&maps, 3, 2), vec![2, 1, 2]);
        assert_eq!(views_seeing(&maps, 3, 1), vec![2, 3, 3]);
        assert_eq!(views_seeing(&[], 2, 1), vec![0, 0]);
    }

    #[test]
    fn rays_through_one_point_agree_on_it_and_others_do_not() {
        let target = DVec3::new(0.5, -0.3, 0.35);
        let (a, b, c) = (
            DVec3::new(0.0, -9.0, 8.0),
            DVec3::new(9.0, 0.0, 8.0),
            DVec3::new(-6.0, 6.0, 8.0),
        );
        let blobs = vec![
            vec![blob(a, target), blob(a, DVec3::new(2.0, 2.0, 0.2))],
            vec![blob(b, DVec3::new(-2.0, 1.0, 0.4)), blob(b, target)],
            vec![blob(c, DVec3::new(3.0, -3.0, 0.3))],
        ];
        let points = agreed_points(&blobs, 0.1, 0.1, 3);
        assert_eq!(points.len(), 1, "{points:?}");
        assert!((points[0].0 - target).length() < 1e-9);
        assert_eq!(points[0].1, 0);
        // A third view through the same point adds no second slot for it (each blob pairs once,
        // and view 0's blob is taken); at most `max` points.
        let mut three = blobs.clone();
        three[2].push(blob(c, target));
        let points = agreed_points(&three, 0.1, 0.1, 3);
        assert_eq!(points.len(), 1, "{points:?}");
        assert!(agreed_points(&blobs, 0.1, 0.1, 0).is_empty());
        // Below the floor, or behind a camera: no point.
        let under = DVec3::new(0.0, 0.0, -1.0);
        let below = vec![vec![blob(a, under)], vec![blob(b, under)]];
        assert!(agreed_points(&below, 0.1, 0.1, 3).is_empty());
        let behind = vec![
            vec![Blob {
                pixels: 10,
                origin: a,
                dir: (a - target).normalize(),
            }],
            vec![blob(b, target)],
        ];
        assert!(agreed_points(&behind, 0.1, 0.1, 3).is_empty());
    }
}
