//! `colf-synth`: multi-view synthetic scenes with ground truth, rendered by an analytic ray
//! tracer (no external renderer).
//!
//! - [`scene`]: what a scene is, as written to `scene.json`.
//! - [`presets`]: the scene distributions (clevr567, packed11, clevr567-textured, city).
//! - [`geometry`]: ray–solid intersection.
//! - [`shading`]: sRGB, the Lambertian model, ground materials, sky.
//! - [`render`]: the tracer (anti-aliased colour, exact masks).
//! - [`writer`]: PNG/JSON files, atomically.
//!
//! Layout of an output folder: `DIR/scene_NNNNN/{view_NNN.png, view_NNN.mask.png,
//! transforms.json, scene.json}` (+ `view_NNN.moved{,.mask}.png` with `--move`), and
//! `DIR/dataset.json`, written last. Seeds: scene i of split s with base seed S is drawn from
//! `StdRng::seed_from_u64(scene_seed(S, s, i))`; nothing depends on the thread schedule.

pub mod geometry;
pub mod hash;
pub mod presets;
pub mod render;
pub mod scene;
pub mod shading;
pub mod writer;

pub use presets::Preset;

use crate::camera::{look_at, Cameras, Frame, Intrinsics};
use anyhow::{bail, Context, Result};
use glam::DVec3;
use hash::mix64;
use rand::rngs::StdRng;
use rand::SeedableRng;
use rayon::prelude::*;
use render::Tracer;
use scene::Scene;
use serde::Serialize;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Which seed stream scenes come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// Object `object` (1-based, as in the masks) displaced by (dx, dy, 0) world units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveSpec {
    pub object: usize,
    pub dx: f64,
    pub dy: f64,
}

/// What to generate: everything [`run`] needs.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    /// Output folder (created).
    pub out: PathBuf,
    pub scenes: u64,
    /// Base seed of the split's seed streams.
    pub seed: u64,
    /// Image width and height in pixels.
    pub size: u32,
    pub views: usize,
    pub preset: Preset,
    pub split: Split,
    /// Also render every view with one object moved.
    pub moved: Option<MoveSpec>,
}

/// What [`run`] reports while it works: `done` of `total` scenes are written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    pub done: u64,
    pub total: u64,
}

/// Format tag of `scene.json`.
pub const SCENE_FORMAT: &str = "colf-synth-scene/1";
/// Format tag of `dataset.json`.
pub const DATASET_FORMAT: &str = "colf-synth/1";
/// Camera redraws allowed to make every object visible in some view.
const CAMERA_DRAWS: usize = 20;

/// The seed of scene `index` of `split`: a mix of the three, so that train and test streams
/// (and neighbouring indices, and neighbouring base seeds) are unrelated.
pub fn scene_seed(seed: u64, split: Split, index: u64) -> u64 {
    let split_tag: u64 = match split {
        Split::Train => 0x7452_4149_4e00_0001,
        Split::Test => 0x5445_5354_0000_0002,
    };
    mix64(mix64(mix64(seed) ^ split_tag) ^ index)
}

/// Name of scene `index`'s folder.
pub fn scene_dir_name(index: u64) -> String {
    format!("scene_{index:05}")
}

/// Name of view `v`'s image (`view_003.png`); masks and moved views add `.mask` / `.moved`.
pub fn view_stem(v: usize) -> String {
    format!("view_{v:03}")
}

/// The camera of a placement: look-at with up +Z and the contract's intrinsics
/// (fl = 1.09375·size, principal point at the image centre).
pub fn frame_of(placement: &scene::CameraPlacement, size: u32) -> Result<Frame> {
    let fl = presets::FOCAL_PER_WIDTH * size as f64;
    Ok(Frame {
        file_path: Some(placement.file_path.clone()),
        intrinsics: Intrinsics {
            w: size,
            h: size,
            fl_x: fl,
            fl_y: fl,
            cx: 0.5 * size as f64,
            cy: 0.5 * size as f64,
        },
        camera_to_world: look_at(
            DVec3::from_array(placement.position),
            DVec3::from_array(placement.look_at),
            DVec3::Z,
        )?,
    })
}

/// A sampled scene with its cameras, ready to render.
pub struct SampledScene {
    pub scene: Scene,
    pub frames: Vec<Frame>,
    pub scene_seed: u64,
}

/// Samples scene `index`: objects, light, then cameras, redrawn up to CAMERA_DRAWS times until
/// every object covers a mask pixel in some view (the draw with the most visible objects wins
/// otherwise). Each object's `visible_pixels` is filled in.
pub fn sample(
    preset: Preset,
    seed: u64,
    split: Split,
    index: u64,
    size: u32,
    views: usize,
) -> Result<SampledScene> {
    let scene_seed = scene_seed(seed, split, index);
    let mut rng = StdRng::seed_from_u64(scene_seed);
    let mut scene = presets::sample_scene(preset, &mut rng);
    let tracer = Tracer::new(&scene, None)?;
    let mut best: Option<(usize, Vec<scene::CameraPlacement>, Vec<Vec<u64>>)> = None;
    for _ in 0..CAMERA_DRAWS {
        let cameras = presets::sample_cameras(preset, &scene, &mut rng, views);
        let mut pixels = vec![vec![0u64; views]; scene.objects.len()];
        for (v, placement) in cameras.iter().enumerate() {
            for id in tracer.render_mask(&frame_of(placement, size)?) {
                if id > 0 {
                    pixels[id as usize - 1][v] += 1;
                }
            }
        }
        let seen = pixels.iter().filter(|p| p.iter().any(|&n| n > 0)).count();
        if best.as_ref().is_none_or(|b| seen > b.0) {
            best = Some((seen, cameras, pixels));
        }
        if seen == scene.objects.len() {
            break;
        }
    }
    let (_, cameras, pixels) = best.expect("CAMERA_DRAWS > 0");
    for (object, p) in scene.objects.iter_mut().zip(pixels) {
        object.visible_pixels = p;
    }
    let frames = cameras
        .iter()
        .map(|c| frame_of(c, size))
        .collect::<Result<Vec<_>>>()?;
    scene.cameras = cameras;
    Ok(SampledScene {
        scene,
        frames,
        scene_seed,
    })
}

/// Renders scene `index` and writes its folder under `out`.
fn write_scene(args: &SynthOptions, index: u64, out: &Path) -> Result<()> {
    let moved = args.moved;
    let dir = out.join(scene_dir_name(index));
    let shown = dir.display().to_string();
    std::fs::create_dir_all(&dir).with_context(|| format!("{shown}: cannot create the folder"))?;
    let sampled = sample(
        args.preset,
        args.seed,
        args.split,
        index,
        args.size,
        args.views,
    )?;
    let scene = &sampled.scene;
    let size = args.size;
    let tracer = Tracer::new(scene, None)?;
    for (v, frame) in sampled.frames.iter().enumerate() {
        let view = tracer.render(frame);
        let stem = view_stem(v);
        writer::write_png(&dir.join(format!("{stem}.png")), &view.rgb, size, size, 3)?;
        writer::write_png(
            &dir.join(format!("{stem}.mask.png")),
            &view.mask,
            size,
            size,
            1,
        )?;
    }
    let mut moved_json = serde_json::Value::Null;
    if let Some(m) = moved {
        let object = scene.objects.get(m.object - 1).with_context(|| {
            format!(
                "{shown}: cannot move object {}: the scene has only {} objects",
                m.object,
                scene.objects.len()
            )
        })?;
        let delta = DVec3::new(m.dx, m.dy, 0.0);
        let tracer = Tracer::new(scene, Some((m.object, delta)))?;
        for (v, frame) in sampled.frames.iter().enumerate() {
            let view = tracer.render(frame);
            let stem = view_stem(v);
            writer::write_png(
                &dir.join(format!("{stem}.moved.png")),
                &view.rgb,
                size,
                size,
                3,
            )?;
            writer::write_png(
                &dir.join(format!("{stem}.moved.mask.png")),
                &view.mask,
                size,
                size,
                1,
            )?;
        }
        moved_json = json!({
            "object": m.object,
            "by": [m.dx, m.dy, 0.0],
            "position": (object.center() + delta).to_array(),
        });
    }
    let cameras = Cameras {
        frames: sampled.frames.clone(),
    };
    crate::io::write_atomic(&dir.join("transforms.json"), cameras.to_json().as_bytes())?;
    let mut doc = json!({
        "format": SCENE_FORMAT,
        "preset": args.preset.name(),
        "split": args.split.name(),
        "seed": args.seed,
        "index": index,
        "scene_seed": sampled.scene_seed,
        "size": size,
        "objects": scene.objects,
        "light": scene.light,
        "ground": scene.ground,
        "sky": scene.sky,
        "cameras": scene.cameras,
    });
    if !scene.buildings.is_empty() {
        doc["buildings"] = serde_json::to_value(&scene.buildings)?;
        doc["rows"] = serde_json::to_value(&scene.rows)?;
    }
    if !moved_json.is_null() {
        doc["moved"] = moved_json;
    }
    writer::write_json(&dir.join("scene.json"), &doc)
}

/// Fails if some scene lacks the object to move (sampling the objects alone is cheap).
pub fn check_moved_object(args: &SynthOptions) -> Result<()> {
    let Some(m) = args.moved else {
        return Ok(());
    };
    for index in 0..args.scenes {
        let mut rng = StdRng::seed_from_u64(scene_seed(args.seed, args.split, index));
        let count = presets::sample_scene(args.preset, &mut rng).objects.len();
        if m.object > count {
            bail!(
                "scene {} ({}) has only {count} objects, no object {} to move",
                index,
                scene_dir_name(index),
                m.object
            );
        }
    }
    Ok(())
}

/// Generates the scenes of `args` into `args.out` (in parallel), then `dataset.json`;
/// `progress` is called after each scene (from any thread). Returns the number of scenes.
pub fn run(args: &SynthOptions, progress: &(dyn Fn(Progress) + Sync)) -> Result<u64> {
    let out = args.out.as_path();
    let shown = out.display();
    if out.exists() && !out.is_dir() {
        bail!("{shown}: exists and is not a folder");
    }
    let n = args.scenes;
    // An object to move that some scene lacks fails before anything is rendered.
    check_moved_object(args)?;
    std::fs::create_dir_all(out).with_context(|| format!("{shown}: cannot create the folder"))?;
    let done = AtomicUsize::new(0);
    (0..n).into_par_iter().try_for_each(|index| -> Result<()> {
        write_scene(args, index, out)?;
        let k = done.fetch_add(1, Ordering::Relaxed) as u64 + 1;
        progress(Progress { done: k, total: n });
        Ok(())
    })?;
    let dataset = json!({
        "format": DATASET_FORMAT,
        "preset": args.preset.name(),
        "split": args.split.name(),
        "seed": args.seed,
        "scenes": n,
        "size": args.size,
        "views": args.views,
        "layout": "scene_NNNNN/{view_NNN.png, view_NNN.mask.png, transforms.json, scene.json}",
    });
    writer::write_json(&out.join("dataset.json"), &dataset)?;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seed_streams_are_distinct() {
        let mut seen = std::collections::HashSet::new();
        for seed in 0..20 {
            for split in [Split::Train, Split::Test] {
                for index in 0..200 {
                    assert!(seen.insert(scene_seed(seed, split, index)));
                }
            }
        }
    }

    #[test]
    fn every_object_is_seen_and_counts_match_the_masks() {
        for index in 0..6 {
            let s = sample(Preset::Clevr567, 1, Split::Train, index, 32, 4).unwrap();
            assert_eq!(s.frames.len(), 4);
            let tracer = Tracer::new(&s.scene, None).unwrap();
            for (v, frame) in s.frames.iter().enumerate() {
                let mask = tracer.render_mask(frame);
                for (k, o) in s.scene.objects.iter().enumerate() {
                    let n = mask.iter().filter(|&&m| m as usize == k + 1).count() as u64;
                    assert_eq!(o.visible_pixels[v], n);
                }
            }
            assert!(s
                .scene
                .objects
                .iter()
                .all(|o| o.visible_pixels.iter().any(|&n| n > 0)));
        }
    }
}
