//! `colf-synth`: multi-view synthetic scenes with ground truth, rendered by an analytic ray
//! tracer (no external renderer) or, for the CLEVR presets, by Blender's Cycles.
//!
//! - [`scene`]: what a scene is, as written to `scene.json`.
//! - [`presets`]: the scene distributions (clevr567, packed11, clevr567-textured, city,
//!   room-chair, room-diverse).
//! - [`room`]: the room presets' procedural chairs, floor textures and walls.
//! - [`geometry`]: ray–solid intersection.
//! - [`shading`]: sRGB, the Lambertian model, ground materials, sky.
//! - [`look`]: the randomised look (floor, light, exposure, noise).
//! - [`render`]: the tracer (anti-aliased colour, exact masks).
//! - [`blender`]: the Blender engine (runs `scripts/blender_clevr.py`).
//! - [`hash`]: the seed-mixing hash.
//! - [`uorf`]: uORF's flat layout, as uORF's own loaders read it.
//! - [`writer`]: PNG/JSON files, atomically.
//!
//! [`run`] takes a [`SynthOptions`] and reports progress through a callback; the command
//! line is in `crate::cli::synth`. Layout of an output folder (colf layout):
//! `DIR/scene_NNNNN/{view_NNN.png, view_NNN.mask.png, transforms.json, scene.json}`
//! (+ `view_NNN.moved{,.mask}.png` with a move), and `DIR/dataset.json`, written last; the
//! uORF layout is flat (see [`uorf_stem`]). Seeds: scene i of split s with base seed S is
//! drawn from `StdRng::seed_from_u64(scene_seed(S, s, i))`; nothing depends on the thread
//! schedule.

pub mod blender;
pub mod geometry;
pub mod hash;
pub mod look;
pub mod presets;
pub mod render;
pub mod resume;
pub mod room;
pub mod scene;
pub mod shading;
pub mod uorf;
pub mod writer;

pub use presets::Preset;

use crate::camera::{look_at, Cameras, Frame, Intrinsics};
use anyhow::{bail, Context, Result};
use glam::DVec3;
use hash::mix64;
use rand::rngs::StdRng;
use rand::SeedableRng;
use rayon::prelude::*;
use render::{RenderedView, Tracer};
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
    pub engine: Engine,
    pub layout: OutputLayout,
    /// Randomise each scene's floor albedo, light, exposure and sensor noise (analytic
    /// engine; see [`look`]).
    pub randomize_look: bool,
    /// Vary each CLEVR view's camera distance and elevation (any engine; see
    /// [`presets::sample_cameras`]); objects and light stay as without it.
    pub randomize_camera: bool,
    /// Replace the files of an earlier run in `out` (see [`clear_output`]) instead of refusing
    /// a folder that is not empty.
    pub replace: bool,
    /// Continue an interrupted run of the same options in `out` (see [`resume`]).
    pub resume: bool,
}

impl SynthOptions {
    /// Scene `index` of these options: objects, light and cameras (not yet rendered).
    pub fn sample(&self, index: u64) -> Result<SampledScene> {
        sample(
            self.preset,
            self.seed,
            self.split,
            index,
            self.size,
            self.views,
            self.randomize_camera,
        )
    }
}

/// The renderer.
#[derive(Clone, Debug, PartialEq)]
pub enum Engine {
    /// The analytic ray tracer of this module.
    Analytic,
    /// Blender's Cycles, run as separate processes (CLEVR presets only).
    Blender(blender::BlenderOptions),
}

/// How the files of a dataset are laid out.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OutputLayout {
    /// `scene_NNNNN/{view_NNN.png, view_NNN.mask.png, transforms.json, scene.json}`.
    Colf,
    /// uORF's flat layout: `{i:05}_sc{s:04}_az{v:02}.png`, `…_mask.png`, `…_RT.txt`.
    Uorf,
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
/// Tag of the varied cameras' stream (`SynthOptions::randomize_camera`).
const CAMERA_STREAM_TAG: u64 = 0x4341_4d45_5241_0005;

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
/// otherwise). Each object's `visible_pixels` is filled in. With `randomize_camera`, each CLEVR
/// view's camera distance and elevation come from a stream of their own (derived from the scene
/// seed, so the objects and the light are those of the same scene without it, and the azimuths
/// too unless the cameras had to be redrawn).
pub fn sample(
    preset: Preset,
    seed: u64,
    split: Split,
    index: u64,
    size: u32,
    views: usize,
    randomize_camera: bool,
) -> Result<SampledScene> {
    let scene_seed = scene_seed(seed, split, index);
    let mut rng = StdRng::seed_from_u64(scene_seed);
    let mut camera_rng =
        randomize_camera.then(|| StdRng::seed_from_u64(mix64(scene_seed ^ CAMERA_STREAM_TAG)));
    let mut scene = presets::sample_scene(preset, &mut rng);
    let tracer = Tracer::new(&scene, None)?;
    let mut best: Option<(usize, Vec<scene::CameraPlacement>, Vec<Vec<u64>>)> = None;
    for _ in 0..CAMERA_DRAWS {
        let cameras = presets::sample_cameras(preset, &scene, &mut rng, views, camera_rng.as_mut());
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

/// The rendered views of one scene: every view, and with a move every view again with the
/// object moved (and, in uORF's layout, the views of its scene manipulation).
pub struct SceneRender {
    pub views: Vec<RenderedView>,
    pub moved: Option<Vec<RenderedView>>,
    pub manip: Option<ManipRender>,
}

/// uORF's background change, seen from every camera of a scene: `changed` shows the scene's
/// objects on the background (ground, sky, light) of scene `providing_scene`; `providing_bg`
/// shows that scene itself (its masks have its own object ids).
pub struct ManipRender {
    pub providing_scene: u64,
    pub changed: Vec<RenderedView>,
    pub providing_bg: Vec<RenderedView>,
}

/// Whether [`run`] renders the views of uORF's scene manipulation ([`ManipRender`]).
pub fn renders_manip(args: &SynthOptions) -> bool {
    args.moved.is_some() && args.layout == OutputLayout::Uorf
}

/// Gives the scene its randomised look: a new light and (for a uniform floor) floor albedo;
/// returns the look to render with.
pub fn randomize_look(sampled: &mut SampledScene) -> look::Look {
    let (look, light, floor) = look::sample_look(sampled.scene_seed);
    sampled.scene.light = light;
    if let shading::Ground::Uniform { albedo } = &mut sampled.scene.ground {
        *albedo = floor;
    }
    look
}

/// Renders a sampled scene with the analytic tracer, in `frames` (the sampled cameras as
/// written), with `look`.
fn render_analytic(
    sampled: &SampledScene,
    frames: &[Frame],
    moved: Option<MoveSpec>,
    look: look::Look,
    providing: Option<(u64, &SampledScene, look::Look)>,
) -> Result<SceneRender> {
    let render_all = |tracer: Tracer| -> Vec<RenderedView> { render_views(tracer, look, frames) };
    let views = render_all(Tracer::new(&sampled.scene, None)?);
    let moved = match moved {
        Some(m) => {
            let delta = DVec3::new(m.dx, m.dy, 0.0);
            Some(render_all(Tracer::new(
                &sampled.scene,
                Some((m.object, delta)),
            )?))
        }
        None => None,
    };
    let manip = match providing {
        Some((providing_scene, other, other_look)) => {
            // The other scene's background with this scene's objects.
            let mut changed = other.scene.clone();
            changed.objects = sampled.scene.objects.clone();
            Some(ManipRender {
                providing_scene,
                changed: render_views(Tracer::new(&changed, None)?, other_look, frames),
                providing_bg: render_views(Tracer::new(&other.scene, None)?, other_look, frames),
            })
        }
        None => None,
    };
    Ok(SceneRender {
        views,
        moved,
        manip,
    })
}

fn render_views(tracer: Tracer, look: look::Look, frames: &[Frame]) -> Vec<RenderedView> {
    let tracer = tracer.with_look(look);
    frames
        .iter()
        .enumerate()
        .map(|(v, f)| tracer.render_view(f, v as u64))
        .collect()
}

/// The cameras of a scene as written in `layout`: colf's as sampled; uORF's with uORF's
/// vertical focal length (fl_y = UORF_FOCAL_Y_PER_HEIGHT·h: its images are 4:3 renders
/// stretched to a square).
pub fn layout_frames(frames: &[Frame], layout: OutputLayout) -> Vec<Frame> {
    frames
        .iter()
        .map(|f| {
            let mut f = f.clone();
            if layout == OutputLayout::Uorf {
                f.intrinsics.fl_x = uorf::FOCAL_X_PER_WIDTH * f.intrinsics.w as f64;
                f.intrinsics.fl_y = uorf::FOCAL_Y_PER_HEIGHT * f.intrinsics.h as f64;
            }
            f
        })
        .collect()
}

/// uORF's vertical focal length in units of the image height (350/240).
pub const UORF_FOCAL_Y_PER_HEIGHT: f64 = uorf::FOCAL_Y_PER_HEIGHT;

/// The `scene.json` document of scene `index`: `scene` as sampled, with each object's
/// `visible_pixels` counted from the masks as written, and `extra` (the look, Blender's
/// settings) merged in.
pub(crate) fn scene_doc(
    args: &SynthOptions,
    index: u64,
    scene: &Scene,
    scene_seed: u64,
    extra: serde_json::Value,
) -> Result<serde_json::Value> {
    let mut moved_json = serde_json::Value::Null;
    if let Some(m) = args.moved {
        let object = scene.objects.get(m.object - 1).with_context(|| {
            format!(
                "scene {index}: cannot move object {}: the scene has only {} objects",
                m.object,
                scene.objects.len()
            )
        })?;
        moved_json = json!({
            "object": m.object,
            "by": [m.dx, m.dy, 0.0],
            "position": (object.center() + DVec3::new(m.dx, m.dy, 0.0)).to_array(),
        });
    }
    let mut doc = json!({
        "format": SCENE_FORMAT,
        "preset": args.preset.name(),
        "split": args.split.name(),
        "seed": args.seed,
        "index": index,
        "scene_seed": scene_seed,
        "size": args.size,
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
    if let Some(room) = &scene.room {
        doc["room"] = serde_json::to_value(room)?;
    }
    if !moved_json.is_null() {
        doc["moved"] = moved_json;
    }
    if let serde_json::Value::Object(fields) = extra {
        for (k, v) in fields {
            doc[k] = v;
        }
    }
    Ok(doc)
}

/// The look of an analytic scene and what `scene.json` records of it: with
/// `randomize_look`, drawn (changing `sampled`'s floor and light) and recorded; else the
/// default look, unrecorded.
fn analytic_look(
    args: &SynthOptions,
    sampled: &mut SampledScene,
) -> (look::Look, serde_json::Value) {
    if args.randomize_look {
        let look = randomize_look(sampled);
        (look, json!({ "look": look }))
    } else {
        (look::Look::default(), json!({}))
    }
}

/// Writes the files of scene `index` in `args.layout`, `scene.json` last (so a scene whose
/// `scene.json` exists is complete: see [`resume`]). `frames` are the cameras the views
/// were rendered with; `visible_pixels` of each object is counted from the rendered masks.
fn write_outputs(
    args: &SynthOptions,
    index: u64,
    sampled: &SampledScene,
    frames: &[Frame],
    render: &SceneRender,
    extra: serde_json::Value,
) -> Result<()> {
    let out = args.out.as_path();
    let size = args.size;
    let mut scene = sampled.scene.clone();
    for (k, object) in scene.objects.iter_mut().enumerate() {
        let id = (k + 1) as u8;
        object.visible_pixels = render
            .views
            .iter()
            .map(|v| v.mask.iter().filter(|&&m| m == id).count() as u64)
            .collect();
    }
    let mut doc = scene_doc(args, index, &scene, sampled.scene_seed, extra)?;
    let png = |path: &Path, pixels: &[u8], channels| {
        writer::write_png(path, pixels, size, size, channels)
    };
    match args.layout {
        OutputLayout::Colf => {
            let dir = out.join(scene_dir_name(index));
            crate::io::create_folder_in_folder(&dir)?;
            for (v, view) in render.views.iter().enumerate() {
                let stem = view_stem(v);
                png(&dir.join(format!("{stem}.png")), &view.rgb, 3)?;
                png(&dir.join(format!("{stem}.mask.png")), &view.mask, 1)?;
            }
            for (v, view) in render.moved.iter().flatten().enumerate() {
                let stem = view_stem(v);
                png(&dir.join(format!("{stem}.moved.png")), &view.rgb, 3)?;
                png(&dir.join(format!("{stem}.moved.mask.png")), &view.mask, 1)?;
            }
            let cameras = Cameras {
                frames: frames.to_vec(),
            };
            crate::io::write_in_folder(&dir.join("transforms.json"), cameras.to_json().as_bytes())?;
            writer::write_json(&dir.join("scene.json"), &doc)
        }
        OutputLayout::Uorf => {
            let n = scene.objects.len();
            uorf::write_scene(out, index, args, frames, render, n, &mut doc)?;
            writer::write_json(&out.join(format!("sc{index:04}_scene.json")), &doc)
        }
    }
}

/// uORF's flat file stem of view `v` of scene `index`: `{i:05}_sc{index:04}_az{v:02}` with
/// i = index·views + v.
pub fn uorf_stem(index: u64, v: usize, views: usize) -> String {
    let i = index * views as u64 + v as u64;
    format!("{i:05}_sc{index:04}_az{v:02}")
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

/// Whether `name` is a file or folder colf-synth writes: `dataset.json`, colf's `scene_NNNNN`
/// folders, or uORF's flat files (`…_scNNNN_azNN…`, `NNN_movement.txt`, `scNNNN_scene.json`).
fn written_by_synth(name: &str) -> bool {
    name == "dataset.json"
        || resume::colf_scene_of(name).is_some()
        || resume::uorf_scene_of(name).is_some()
}

/// Makes sure scenes of an earlier run cannot mix with this run's: a folder that holds
/// anything is refused, unless `replace`, when the files colf-synth writes are removed first
/// (other files are left alone).
pub fn clear_output(out: &Path, replace: bool) -> Result<()> {
    let shown = out.display();
    if !out.is_dir() {
        // Absent (created later) or not a folder (refused by `run`).
        return Ok(());
    }
    let entries = match std::fs::read_dir(out) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => bail!("{shown}: cannot read the folder: {e}"),
    };
    let names: Vec<std::ffi::OsString> = entries
        .map(|e| e.map(|e| e.file_name()))
        .collect::<std::io::Result<_>>()
        .with_context(|| format!("{shown}: cannot read the folder"))?;
    if names.is_empty() {
        return Ok(());
    }
    if !replace {
        bail!(
            "{shown}: the folder is not empty ({} entries); scenes of an earlier run would mix with these",
            names.len()
        );
    }
    for name in names {
        if !name.to_str().is_some_and(written_by_synth) {
            continue;
        }
        let path = out.join(&name);
        let removed = if path.is_dir() && !path.is_symlink() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        removed.with_context(|| format!("{}: cannot remove it", path.display()))?;
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
    let todo: Vec<u64> = if args.resume {
        resume::pending_scenes(args)?
    } else {
        clear_output(out, args.replace)?;
        (0..n).collect()
    };
    std::fs::create_dir_all(out).with_context(|| format!("{shown}: cannot create the folder"))?;
    let done = AtomicUsize::new((n - todo.len() as u64) as usize);
    let report = || {
        let k = done.fetch_add(1, Ordering::Relaxed) as u64 + 1;
        progress(Progress { done: k, total: n });
    };
    match &args.engine {
        Engine::Analytic => {
            todo.par_iter().try_for_each(|&index| -> Result<()> {
                let mut sampled = args.sample(index)?;
                let (look, extra) = analytic_look(args, &mut sampled);
                let frames = layout_frames(&sampled.frames, args.layout);
                let providing = if renders_manip(args) {
                    let j = uorf::providing_scene(index, n);
                    let mut other = args.sample(j)?;
                    let other_look = if args.randomize_look {
                        randomize_look(&mut other)
                    } else {
                        look::Look::default()
                    };
                    Some((j, other, other_look))
                } else {
                    None
                };
                let providing = providing.as_ref().map(|(j, s, l)| (*j, s, *l));
                let render = render_analytic(&sampled, &frames, args.moved, look, providing)?;
                write_outputs(args, index, &sampled, &frames, &render, extra)?;
                report();
                Ok(())
            })?;
        }
        Engine::Blender(b) => {
            blender::run(args, b, &todo, &|index, sampled, frames, render, extra| {
                write_outputs(args, index, sampled, frames, render, extra)?;
                report();
                Ok(())
            })?
        }
    }
    let dataset = json!({
        "format": DATASET_FORMAT,
        "preset": args.preset.name(),
        "split": args.split.name(),
        "seed": args.seed,
        "scenes": n,
        "size": args.size,
        "views": args.views,
        "layout": match args.layout {
            OutputLayout::Colf => "scene_NNNNN/{view_NNN.png, view_NNN.mask.png, transforms.json, scene.json}",
            OutputLayout::Uorf => "{i:05}_sc{scene:04}_az{view:02}{.png, _mask.png, _RT.txt, _azi_rot.txt}, sc{scene:04}_scene.json",
        },
    });
    let mut dataset = dataset;
    if let Engine::Blender(b) = &args.engine {
        dataset["engine"] = json!("blender");
        dataset["samples"] = json!(b.samples);
    }
    if args.randomize_look {
        dataset["randomize_look"] = json!(true);
    }
    if args.randomize_camera {
        dataset["randomize_camera"] = json!(true);
    }
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
            let s = sample(Preset::Clevr567, 1, Split::Train, index, 32, 4, false).unwrap();
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
