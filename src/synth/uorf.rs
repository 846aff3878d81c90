//! uORF's flat dataset layout (`--layout uorf`), written so that uORF's own loaders read it
//! (KovenYu/uORF: `data/multiscenes_dataset.py` with the options of
//! `scripts/eval_nvs_seg_clevr.sh`, and `data/multiscenes_manip_dataset.py` of
//! `scripts/eval_scene_manip.sh`). The conventions, as those loaders and models apply them:
//!
//! - **Cameras.** `_RT.txt`: camera-to-world, OpenCV camera axes. uORF's `Projection`
//!   hard-codes fx = 350/320·W and fy = 350/240·H ([`FOCAL_X_PER_WIDTH`],
//!   [`FOCAL_Y_PER_HEIGHT`]); the views are rendered with exactly those intrinsics.
//! - **Azimuth.** Without `--fixed_locality` (uORF's CLEVR and room scripts) the loader reads
//!   a 3×3 `_azi_rot.txt` per view, and the models use the input view's as `cam2world_azi`:
//!   foreground slots decode points `inverse(azi_rot)·x` of the normalised world. It is the
//!   azimuth-only part of the camera's pose, a rotation about the world's +Z by the camera's
//!   azimuth φ = atan2(y, x) of its centre ([`azimuth_rotation`]), so that the input camera
//!   sits at azimuth 0 in the foreground frame.
//! - **Masks.** The loader turns a mask grey, takes its sorted distinct grey levels, and calls
//!   the *second-smallest* the background (`bg_color = greyscale_dict[1]`); every other level is
//!   foreground, and the level's rank is the label (`mask_idx`). So in every view exactly one
//!   object's level lies below the background's ([`mask_levels`]).
//! - **Scene manipulation** (with a move): `_moved.png` (object K moved), `_mask_for_moving.png`
//!   (object K white on black, in the original view: its smallest level is not the object),
//!   `_changed.png` (this scene's objects on another scene's background, the same camera),
//!   `_providing_bg.png` (that other scene, the same camera), `_mask_for_bg.png` and
//!   `_mask_for_providing_bg.png` (black = background of this view and of the providing
//!   view, white = objects), `{s:03}_movement.txt` (DX and DY, one a line).

use super::{uorf_stem, writer, SceneRender, SynthOptions};
use crate::camera::Frame;
use anyhow::{bail, Result};
use glam::{DMat3, DMat4, DVec4};
use serde_json::json;
use std::path::Path;

pub use crate::camera::{
    UORF_FOCAL_X_PER_WIDTH as FOCAL_X_PER_WIDTH, UORF_FOCAL_Y_PER_HEIGHT as FOCAL_Y_PER_HEIGHT,
};
/// Grey level of the background in `_mask.png`.
pub const BACKGROUND_LEVEL: u8 = 64;
/// Most objects a scene may have in uORF's masks (levels below the background).
pub const MAX_OBJECTS: usize = BACKGROUND_LEVEL as usize;

/// The rotation uORF's `_azi_rot.txt` holds for a camera: about the world's +Z by the azimuth
/// of the camera's centre, φ = atan2(y, x) (0 for a camera above the origin), i.e.
/// `[[cos φ, −sin φ, 0], [sin φ, cos φ, 0], [0, 0, 1]]`.
pub fn azimuth_rotation(camera_to_world: &DMat4) -> DMat3 {
    let centre = camera_to_world.w_axis.truncate();
    DMat3::from_rotation_z(centre.y.atan2(centre.x))
}

/// A 3×3 matrix as `np.loadtxt` reads it: three rows of three numbers.
pub fn matrix3_text(m: &DMat3) -> String {
    (0..3)
        .map(|r| {
            let row = m.row(r);
            format!("{} {} {}\n", row.x, row.y, row.z)
        })
        .collect()
}

/// A 4×4 matrix as `np.loadtxt` reads it: four rows of four numbers.
pub fn matrix4_text(m: &DMat4) -> String {
    (0..4)
        .map(|r| {
            let row = m.row(r);
            format!("{} {} {} {}\n", row.x, row.y, row.z, row.w)
        })
        .collect()
}

/// Grey levels of object k (1-based) of `n` in uORF masks: (below the background, above it).
fn object_levels(k: usize, n: usize) -> (u8, u8) {
    let low = (k - 1) * (MAX_OBJECTS / n);
    let high = BACKGROUND_LEVEL as usize + k * ((255 - BACKGROUND_LEVEL as usize) / n);
    (low as u8, high as u8)
}

/// The grey level of every id (0 = background, k = object k of `n`) in each of `masks` (colf
/// ids, one per view), such that uORF's loader finds the background in every view: it is
/// [`BACKGROUND_LEVEL`], and one object seen in the view (the anchor) gets a level below it,
/// the others levels above it. The anchor is, when there is one, the same object in every view
/// (of the objects seen in all of them, the one whose smallest view shows the most pixels),
/// so an object keeps its level across the views; otherwise each view's largest object.
/// Levels are distinct within a view. A view that shows no object has a one-level mask, which
/// uORF's loader cannot read (it has no second level).
pub fn mask_levels(masks: &[&[u8]], n: usize) -> Result<Vec<Vec<u8>>> {
    if n > MAX_OBJECTS {
        bail!("uORF's masks hold at most {MAX_OBJECTS} objects, the scene has {n}");
    }
    let mut counts = vec![vec![0u64; n + 1]; masks.len()];
    for (c, mask) in counts.iter_mut().zip(masks) {
        for &id in mask.iter() {
            if id as usize > n {
                bail!("mask id {id} but the scene has {n} objects");
            }
            c[id as usize] += 1;
        }
    }
    // The key prefers more pixels, then the lower id.
    let best = |key: &dyn Fn(usize) -> u64| -> Option<usize> {
        (1..=n)
            .filter(|&k| key(k) > 0)
            .max_by_key(|&k| (key(k), std::cmp::Reverse(k)))
    };
    let scene_anchor = best(&|k| counts.iter().map(|c| c[k]).min().unwrap_or(0));
    Ok(counts
        .iter()
        .map(|c| {
            let anchor = scene_anchor.or_else(|| best(&|k| c[k]));
            (0..=n)
                .map(|k| match k {
                    0 => BACKGROUND_LEVEL,
                    k if Some(k) == anchor => object_levels(k, n).0,
                    k => object_levels(k, n).1,
                })
                .collect()
        })
        .collect())
}

/// A two-level mask: 255 where `pick(id)`, else 0.
pub fn binary_mask(mask: &[u8], pick: impl Fn(u8) -> bool) -> Vec<u8> {
    mask.iter()
        .map(|&id| if pick(id) { 255 } else { 0 })
        .collect()
}

/// The scene whose background scene `index` of `scenes` gets in `_changed.png`: the next one
/// (the last scene takes the first's; a single scene its own).
pub fn providing_scene(index: u64, scenes: u64) -> u64 {
    (index + 1) % scenes.max(1)
}

/// Writes the uORF files of scene `index` (`n` objects) into `out`, and records in `doc` (its
/// `scNNNN_scene.json`) the grey level of every id in each mask, and the providing scene.
pub fn write_scene(
    out: &Path,
    index: u64,
    args: &SynthOptions,
    frames: &[Frame],
    render: &SceneRender,
    n: usize,
    doc: &mut serde_json::Value,
) -> Result<()> {
    let size = args.size;
    let stem = |v: usize| uorf_stem(index, v, args.views);
    let png = |name: String, pixels: &[u8], channels| {
        writer::write_png(&out.join(name), pixels, size, size, channels)
    };
    let grey = |mask: &[u8], levels: &[u8]| -> Vec<u8> {
        mask.iter().map(|&id| levels[id as usize]).collect()
    };
    let shown = |e: anyhow::Error| e.context(format!("scene {index} ({})", stem(0)));
    // Our OpenGL camera axes → OpenCV's (flip the camera's Y and Z).
    let flip = DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0));
    let masks: Vec<&[u8]> = render.views.iter().map(|v| v.mask.as_slice()).collect();
    let levels = mask_levels(&masks, n).map_err(shown)?;
    for (v, view) in render.views.iter().enumerate() {
        let s = stem(v);
        png(format!("{s}.png"), &view.rgb, 3)?;
        png(format!("{s}_mask.png"), &grey(&view.mask, &levels[v]), 1)?;
        let pose = frames[v].camera_to_world;
        let rt = matrix4_text(&(pose * flip));
        crate::io::write_in_folder(&out.join(format!("{s}_RT.txt")), rt.as_bytes())?;
        let azi = matrix3_text(&azimuth_rotation(&pose));
        crate::io::write_in_folder(&out.join(format!("{s}_azi_rot.txt")), azi.as_bytes())?;
    }
    doc["uorf_mask_levels"] = json!(levels);
    if let (Some(m), Some(moved)) = (args.moved, render.moved.as_ref()) {
        let masks: Vec<&[u8]> = moved.iter().map(|v| v.mask.as_slice()).collect();
        let moved_levels = mask_levels(&masks, n).map_err(shown)?;
        for (v, view) in moved.iter().enumerate() {
            let s = stem(v);
            png(format!("{s}_moved.png"), &view.rgb, 3)?;
            png(
                format!("{s}_moved_mask.png"),
                &grey(&view.mask, &moved_levels[v]),
                1,
            )?;
        }
        doc["uorf_moved_mask_levels"] = json!(moved_levels);
        for (v, view) in render.views.iter().enumerate() {
            let s = stem(v);
            let object = m.object as u8;
            png(
                format!("{s}_mask_for_moving.png"),
                &binary_mask(&view.mask, |id| id == object),
                1,
            )?;
            png(
                format!("{s}_mask_for_bg.png"),
                &binary_mask(&view.mask, |id| id != 0),
                1,
            )?;
        }
        let text = format!("{}\n{}\n", m.dx, m.dy);
        crate::io::write_in_folder(
            &out.join(format!("{index:03}_movement.txt")),
            text.as_bytes(),
        )?;
    }
    if let Some(manip) = &render.manip {
        for (v, (changed, bg)) in manip.changed.iter().zip(&manip.providing_bg).enumerate() {
            let s = stem(v);
            png(format!("{s}_changed.png"), &changed.rgb, 3)?;
            png(format!("{s}_providing_bg.png"), &bg.rgb, 3)?;
            png(
                format!("{s}_mask_for_providing_bg.png"),
                &binary_mask(&bg.mask, |id| id != 0),
                1,
            )?;
        }
        doc["uorf_providing_bg_scene"] = json!(manip.providing_scene);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    /// uORF's loader: the sorted distinct levels, the second-smallest is the background.
    fn uorf_background(levels: &[u8]) -> Option<u8> {
        levels
            .iter()
            .copied()
            .collect::<BTreeSet<u8>>()
            .into_iter()
            .nth(1)
    }

    #[test]
    fn the_background_is_the_second_smallest_level_in_every_view() {
        // Object 2 is seen in every view, 1 and 3 are not.
        let views: Vec<Vec<u8>> = vec![
            vec![0, 1, 2, 2, 0],
            vec![0, 0, 2, 3, 3],
            vec![2, 0, 0, 0, 0],
        ];
        let refs: Vec<&[u8]> = views.iter().map(|v| v.as_slice()).collect();
        let levels = mask_levels(&refs, 3).unwrap();
        for (view, lv) in views.iter().zip(&levels) {
            let grey: Vec<u8> = view.iter().map(|&id| lv[id as usize]).collect();
            assert_eq!(uorf_background(&grey), Some(BACKGROUND_LEVEL));
            let distinct: BTreeSet<u8> = lv.iter().copied().collect();
            assert_eq!(distinct.len(), 4);
        }
        // The same anchor (object 2, the only one seen everywhere) in every view.
        assert!(levels.iter().all(|lv| lv[2] < BACKGROUND_LEVEL));
        assert!(levels
            .iter()
            .all(|lv| lv[1] > BACKGROUND_LEVEL && lv[3] > BACKGROUND_LEVEL));
        // No object in every view: each view's largest object is its anchor.
        let views: Vec<Vec<u8>> = vec![vec![1, 1, 0, 0], vec![0, 2, 2, 0]];
        let refs: Vec<&[u8]> = views.iter().map(|v| v.as_slice()).collect();
        let levels = mask_levels(&refs, 2).unwrap();
        assert!(levels[0][1] < BACKGROUND_LEVEL && levels[0][2] > BACKGROUND_LEVEL);
        assert!(levels[1][2] < BACKGROUND_LEVEL && levels[1][1] > BACKGROUND_LEVEL);
        for (view, lv) in views.iter().zip(&levels) {
            let grey: Vec<u8> = view.iter().map(|&id| lv[id as usize]).collect();
            assert_eq!(uorf_background(&grey), Some(BACKGROUND_LEVEL));
        }
        assert!(mask_levels(&[&[0, 3]], 2).is_err());
        assert!(mask_levels(&[&[0]], MAX_OBJECTS + 1).is_err());
    }

    #[test]
    fn object_levels_are_distinct_for_every_count() {
        for n in 1..=MAX_OBJECTS {
            let mut all = BTreeSet::from([BACKGROUND_LEVEL]);
            for k in 1..=n {
                let (low, high) = object_levels(k, n);
                assert!(
                    low < BACKGROUND_LEVEL && high > BACKGROUND_LEVEL,
                    "{k} of {n}"
                );
                assert!(all.insert(low) && all.insert(high), "{k} of {n}");
            }
        }
    }

    #[test]
    fn azimuth_rotation_turns_the_camera_to_azimuth_zero() {
        let eye = glam::DVec3::new(-4.5, -8.3, 8.0);
        let pose = crate::camera::look_at(eye, glam::DVec3::ZERO, glam::DVec3::Z).unwrap();
        let r = azimuth_rotation(&pose);
        let local = r.transpose() * eye;
        assert!(local.y.abs() < 1e-12 && local.x > 0.0 && (local.z - 8.0).abs() < 1e-12);
        assert!((r.determinant() - 1.0).abs() < 1e-12);
        assert_eq!(r.z_axis, glam::DVec3::Z);
        let text = matrix3_text(&r);
        assert_eq!(text.lines().count(), 3);
        assert!(text.ends_with("0 0 1\n"), "{text}");
        assert_eq!(FOCAL_X_PER_WIDTH, 1.09375);
    }
}
