//! The Blender engine: scenes sampled here (the same layouts and cameras as the analytic
//! engine; for the room presets the same chair parts, walls and floor texture, baked into an
//! image) rendered by Blender's Cycles on the CPU, one Blender process per chunk of scenes,
//! each on one thread. The Python side is `scripts/blender_clevr.py`, embedded in the binary
//! and written to a temporary folder at run time; it reads a JSON job and writes PNGs into
//! that folder, which are decoded here (the id image into the mask) and written in the
//! requested layout.

use super::hash::mix64;
use super::presets::Preset;
use super::render::RenderedView;
use super::room::{FloorTexture, PartShape};
use super::scene::{spherical, Object};
use super::shading::{albedo_of_srgb8, Ground};
use super::{
    layout_frames, renders_manip, uorf, ManipRender, MoveSpec, SampledScene, SceneRender,
    SynthOptions,
};
use crate::camera::Frame;
use anyhow::{anyhow, bail, Context, Result};
use glam::DVec3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// The Python script Blender runs.
pub const SCRIPT: &str = include_str!("../../scripts/blender_clevr.py");

/// Default path-tracing samples per pixel.
pub const DEFAULT_SAMPLES: u32 = 64;

/// Linear albedo of the floor (as the analytic clevr567 floor).
const FLOOR_ALBEDO: f64 = 0.5;
/// Side of the square floor: it fills every clevr567 view.
const FLOOR_SIZE: f64 = 200.0;
/// Radiance of the world around the scene (a little ambient light).
const AMBIENT: f64 = 0.05;

/// How to run Blender.
#[derive(Clone, Debug, PartialEq)]
pub struct BlenderOptions {
    /// The `blender` executable (a name looked up on PATH, or a path).
    pub executable: PathBuf,
    /// Path-tracing samples per pixel.
    pub samples: u32,
    /// Blender processes run at once (each renders on one thread).
    pub jobs: usize,
}

/// Writes one finished scene: (index, sampled scene, cameras as written, views, extra
/// scene.json fields).
pub type SceneSink<'a> =
    dyn Fn(u64, &SampledScene, &[Frame], &SceneRender, Value) -> Result<()> + Sync + 'a;

/// Whether the engine can render `preset`.
pub fn supports(preset: Preset) -> bool {
    matches!(
        preset,
        Preset::Clevr567 | Preset::Packed11 | Preset::RoomChair | Preset::RoomDiverse
    )
}

/// Side in texels of the floor image of a room (the floor texture baked for Blender).
pub const FLOOR_TEXELS: u32 = 1024;

/// Distance of the lights from the centre: inside the room's walls for the room presets.
fn light_distance(sampled: &SampledScene) -> f64 {
    if sampled.scene.room.is_some() {
        6.0
    } else {
        10.0
    }
}

/// The three area lights (key, fill, back) of a scene: the key light comes from the scene's
/// light direction, the fill light from 100° to its side, the back light from behind; every
/// position is jittered by up to ±1 unit per axis from a stream derived from the scene seed
/// (so the layout's own stream is untouched). They stand 10 units from the centre (6 inside a
/// room's walls, with their energy scaled by (6/10)² so the centre gets the same light).
pub fn lights(sampled: &SampledScene) -> Value {
    let distance = light_distance(sampled);
    let gain = (distance / 10.0).powi(2);
    let mut rng = StdRng::seed_from_u64(mix64(sampled.scene_seed ^ 0x424c_454e_4445_5200));
    let az = sampled.scene.light.azimuth_degrees;
    let el = sampled.scene.light.elevation_degrees;
    let mut light = |azimuth: f64, elevation: f64, distance: f64, energy: f64, size: f64| {
        let jitter = DVec3::new(
            rng.random_range(-1.0..=1.0),
            rng.random_range(-1.0..=1.0),
            rng.random_range(-1.0..=1.0),
        );
        let p = distance * spherical(azimuth, elevation) + jitter;
        json!({
            "position": p.to_array(),
            "target": [0.0, 0.0, 0.0],
            "energy": energy,
            "size": size,
        })
    };
    json!({
        "key": light(az, el, distance, 1000.0 * gain, 3.0),
        "fill": light(az - 100.0, 30.0, distance, 300.0 * gain, 3.0),
        "back": light(az + 180.0, 50.0, distance, 500.0 * gain, 3.0),
    })
}

/// Mask grey level of object k (1-based) of `n` in Blender's id image: spread over 1..=255.
fn id_level(k: usize, n: usize) -> u8 {
    ((k as f64 * 255.0 / n as f64).round() as u8).max(1)
}

/// The id image of a view decoded into mask ids: every pixel must be within 2 grey levels of
/// 0 (background) or of an object's level.
fn decode_ids(bytes: &[u8], n: usize, name: &str) -> Result<Vec<u8>> {
    let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| anyhow!("{name}: not a valid PNG image: {e}"))?
        .to_luma8();
    let levels: Vec<u8> = (0..=n)
        .map(|k| if k == 0 { 0 } else { id_level(k, n) })
        .collect();
    img.into_raw()
        .into_iter()
        .map(|g| {
            let (id, level) = levels
                .iter()
                .enumerate()
                .min_by_key(|(_, &l)| (l as i32 - g as i32).abs())
                .expect("levels is not empty");
            if (*level as i32 - g as i32).abs() > 2 {
                bail!("{name}: grey level {g} is no object's id level");
            }
            Ok(id as u8)
        })
        .collect()
}

/// The parts of a chair for Blender: each a box (`half`) or a cylinder (`radius`,
/// `half_height`, axis along its third axis) with its `center` relative to the object's
/// position and its `rotation` (row-major 3×3, columns the part's axes), in world axes.
fn chair_parts_json(o: &Object) -> Option<Value> {
    let design = o.chair?;
    let position = o.center();
    let parts: Vec<Value> = design
        .parts(position, o.rotation_z_degrees)
        .iter()
        .map(|p| {
            let rotation = p.rotation.transpose().to_cols_array();
            let center = (p.center - position).to_array();
            match p.shape {
                PartShape::Box { half } => json!({
                    "kind": "box", "center": center, "rotation": rotation,
                    "half": half.to_array(),
                }),
                PartShape::Cylinder {
                    radius,
                    half_height,
                } => json!({
                    "kind": "cylinder", "center": center, "rotation": rotation,
                    "radius": radius, "half_height": half_height,
                }),
            }
        })
        .collect();
    Some(Value::Array(parts))
}

/// The job entries of a scene's objects.
fn objects_job(sampled: &SampledScene) -> Vec<Value> {
    let n = sampled.scene.objects.len();
    sampled
        .scene
        .objects
        .iter()
        .enumerate()
        .map(|(k, o)| {
            let mut object = json!({
                "shape": o.shape,
                "size": o.size,
                "position": o.position,
                "rotation_z_degrees": o.rotation_z_degrees,
                "albedo": albedo_of_srgb8(o.rgb).to_array(),
                "mask_level": id_level(k + 1, n),
            });
            if let Some(parts) = chair_parts_json(o) {
                object["parts"] = parts;
            }
            object
        })
        .collect()
}

/// The job entry of one scene; its PNGs go to `tmp` (and a room's floor image is there, see
/// [`bake_floors`]). `providing` is the scene whose background (its lights: the floor is the
/// same) uORF's scene manipulation puts behind this scene's objects.
fn scene_job(
    args: &SynthOptions,
    index: u64,
    sampled: &SampledScene,
    frames: &[Frame],
    tmp: &Path,
    providing: Option<&SampledScene>,
) -> Result<Value> {
    let objects = objects_job(sampled);
    let views = |tag: &str| -> Vec<Value> {
        frames
            .iter()
            .enumerate()
            .map(|(v, f)| {
                let m = f.camera_to_world.transpose().to_cols_array();
                json!({
                    "camera_to_world": m,
                    "fl_x": f.intrinsics.fl_x,
                    "rgb": tmp.join(format!("{index}_{tag}{v}.png")),
                    "mask": tmp.join(format!("{index}_{tag}{v}_id.png")),
                })
            })
            .collect()
    };
    let f0 = frames[0].intrinsics;
    let mut s = json!({
        "index": index,
        "width": f0.w,
        "height": f0.h,
        // Non-square pixels give fl_y ≠ fl_x (uORF's layout).
        "pixel_aspect_x": f0.fl_y / f0.fl_x,
        "cycles_seed": (sampled.scene_seed & 0x7fff_ffff),
        "floor_albedo": [FLOOR_ALBEDO, FLOOR_ALBEDO, FLOOR_ALBEDO],
        "floor_size": FLOOR_SIZE,
        "ambient": AMBIENT,
        "objects": objects,
        "lights": lights(sampled),
        "views": views("v"),
    });
    if let Some(MoveSpec { object, dx, dy }) = args.moved {
        s["moved"] = json!({ "object": object, "by": [dx, dy, 0.0], "views": views("m") });
    }
    if let Some(other) = providing {
        // Rendered as scenes of their own, with this scene's cameras.
        s["extra_scenes"] = json!([
            { "objects": s["objects"].clone(), "lights": lights(other), "views": views("c") },
            { "objects": objects_job(other), "lights": lights(other), "views": views("p") },
        ]);
    }
    if let Some(room) = &sampled.scene.room {
        let Ground::Floor(texture) = &sampled.scene.ground else {
            bail!("scene {index}: a room without a floor texture");
        };
        s["floor_texture"] = json!(tmp.join(floor_image_name(texture)));
        s["floor_size"] = json!(2.0 * room.half_extent);
        s["walls"] = serde_json::to_value(room.walls())?;
    }
    Ok(s)
}

/// The file name of a floor texture's baked image: one per texture of a family, shared by
/// the scenes on that floor.
fn floor_image_name(texture: &FloorTexture) -> String {
    format!("floor-{}-{}.png", texture.family, texture.index)
}

/// Bakes the floor image of every distinct floor texture of `sampled` into `tmp`.
fn bake_floors(sampled: &[(SampledScene, Vec<Frame>)], tmp: &Path) -> Result<()> {
    let mut floors: BTreeMap<String, (&FloorTexture, f64)> = BTreeMap::new();
    for (s, _) in sampled {
        if let (Some(room), Ground::Floor(texture)) = (&s.scene.room, &s.scene.ground) {
            floors
                .entry(floor_image_name(texture))
                .or_insert((texture, room.half_extent));
        }
    }
    floors
        .into_par_iter()
        .try_for_each(|(name, (texture, half_extent))| {
            let pixels = texture.bake(half_extent, FLOOR_TEXELS);
            super::writer::write_png(&tmp.join(name), &pixels, FLOOR_TEXELS, FLOOR_TEXELS, 3)
        })
}

/// Reads back the views Blender wrote for one scene.
fn read_views(job: &Value, key: &str, n: usize) -> Result<Vec<RenderedView>> {
    let Some(views) = job[key].as_array() else {
        return Ok(Vec::new());
    };
    views
        .iter()
        .map(|v| {
            let path = |k: &str| PathBuf::from(v[k].as_str().unwrap_or_default());
            let (rgb_path, mask_path) = (path("rgb"), path("mask"));
            let read = |p: &Path| {
                std::fs::read(p).with_context(|| format!("{}: Blender wrote no image", p.display()))
            };
            let rgb =
                image::load_from_memory_with_format(&read(&rgb_path)?, image::ImageFormat::Png)
                    .map_err(|e| anyhow!("{}: not a valid PNG image: {e}", rgb_path.display()))?
                    .to_rgb8()
                    .into_raw();
            let mask = decode_ids(&read(&mask_path)?, n, &mask_path.display().to_string())?;
            Ok(RenderedView { rgb, mask })
        })
        .collect()
}

/// Renders the scenes `todo` of `args` with Blender: `args.jobs` processes, the k-th scene of
/// `todo` in process k mod jobs; `sink` gets each scene as soon as its process reports it done.
pub fn run(
    args: &SynthOptions,
    blender: &BlenderOptions,
    todo: &[u64],
    sink: &SceneSink,
) -> Result<()> {
    if args.randomize_look {
        bail!("the randomised look is an analytic-engine feature");
    }
    if !supports(args.preset) {
        bail!(
            "the Blender engine renders the presets clevr567, packed11, room-chair and \
             room-diverse, not {}",
            args.preset.name()
        );
    }
    let exe = &blender.executable;
    let tmp = tempfile::Builder::new()
        .prefix("colf-synth-blender")
        .tempdir()
        .context("cannot create a temporary folder")?;
    let script = tmp.path().join("blender_clevr.py");
    std::fs::write(&script, SCRIPT)
        .with_context(|| format!("{}: cannot write", script.display()))?;
    let n = args.scenes;
    let sampled: Vec<(SampledScene, Vec<Frame>)> = (0..n)
        .into_par_iter()
        .map(|index| {
            let s = args.sample(index)?;
            let frames = layout_frames(&s.frames, args.layout);
            Ok((s, frames))
        })
        .collect::<Result<_>>()?;
    if todo.is_empty() {
        return Ok(());
    }
    let jobs = blender.jobs.clamp(1, todo.len());
    bake_floors(&sampled, tmp.path())?;
    let scene_jobs: Vec<Value> = sampled
        .par_iter()
        .enumerate()
        .map(|(index, (s, frames))| {
            let providing = renders_manip(args)
                .then(|| &sampled[uorf::providing_scene(index as u64, n) as usize].0);
            scene_job(args, index as u64, s, frames, tmp.path(), providing)
        })
        .collect::<Result<_>>()?;
    std::thread::scope(|scope| -> Result<()> {
        let mut handles = Vec::new();
        for p in 0..jobs {
            let chunk: Vec<Value> = todo
                .iter()
                .skip(p)
                .step_by(jobs)
                .map(|&index| scene_jobs[index as usize].clone())
                .collect();
            let expected = chunk.len();
            let job = json!({ "samples": blender.samples, "threads": 1, "scenes": chunk });
            let job_path = tmp.path().join(format!("job{p}.json"));
            std::fs::write(&job_path, serde_json::to_vec(&job)?)
                .with_context(|| format!("{}: cannot write", job_path.display()))?;
            let mut child = Command::new(exe)
                .args(["-b", "--factory-startup", "--threads", "1"])
                .args(["--python-exit-code", "1", "--python"])
                .arg(&script)
                .arg("--")
                .arg(&job_path)
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .map_err(|e| {
                    if e.kind() == std::io::ErrorKind::NotFound {
                        anyhow!(
                            "{}: Blender not found; the Blender engine needs Blender 3.x \
                             (Debian: apt-get install blender)",
                            exe.display()
                        )
                    } else {
                        anyhow!("{}: cannot run Blender: {e}", exe.display())
                    }
                })?;
            let stdout = child.stdout.take().expect("piped");
            let mut stderr = child.stderr.take().expect("piped");
            let (sampled, scene_jobs) = (&sampled, &scene_jobs);
            handles.push(scope.spawn(move || -> Result<()> {
                let err_reader = std::thread::spawn(move || {
                    let mut text = String::new();
                    let _ = stderr.read_to_string(&mut text);
                    text
                });
                let mut last_lines: Vec<String> = Vec::new();
                let mut result = Ok(());
                let mut reported = 0usize;
                for line in BufReader::new(stdout).lines() {
                    let line = line.unwrap_or_default();
                    if let Some(i) = line.strip_prefix("colf-scene-done ") {
                        if result.is_err() {
                            continue;
                        }
                        let index: usize = i.trim().parse().context("bad report from Blender")?;
                        reported += 1;
                        let (s, frames) = &sampled[index];
                        let job = &scene_jobs[index];
                        let k = s.scene.objects.len();
                        let views = read_views(job, "views", k)?;
                        let moved = match args.moved {
                            Some(_) => Some(read_views(&job["moved"], "views", k)?),
                            None => None,
                        };
                        let manip = if renders_manip(args) {
                            let j = uorf::providing_scene(index as u64, n);
                            let other = sampled[j as usize].0.scene.objects.len();
                            let extra = &job["extra_scenes"];
                            Some(ManipRender {
                                providing_scene: j,
                                changed: read_views(&extra[0], "views", k)?,
                                providing_bg: read_views(&extra[1], "views", other)?,
                            })
                        } else {
                            None
                        };
                        let extra = json!({
                            "engine": "blender",
                            "samples": blender.samples,
                            "blender_lights": job["lights"],
                        });
                        result = sink(
                            index as u64,
                            s,
                            frames,
                            &SceneRender {
                                views,
                                moved,
                                manip,
                            },
                            extra,
                        );
                    } else if !line.trim().is_empty() {
                        last_lines.push(line);
                        if last_lines.len() > 20 {
                            last_lines.remove(0);
                        }
                    }
                }
                let status = child.wait().context("waiting for Blender")?;
                let err_text = err_reader.join().unwrap_or_default();
                result?;
                if !status.success() {
                    let why = err_text
                        .lines()
                        .chain(last_lines.iter().map(String::as_str))
                        .rfind(|l| {
                            (l.contains("Error") || l.contains("error") || l.starts_with("usage"))
                                && !l.contains("script failed")
                        })
                        .unwrap_or("no error message")
                        .trim()
                        .to_string();
                    bail!("{}: Blender failed ({status}): {why}", exe.display());
                }
                if reported != expected {
                    bail!(
                        "{}: Blender exited after {reported} of its {expected} scenes",
                        exe.display()
                    );
                }
                Ok(())
            }));
        }
        for h in handles {
            h.join()
                .map_err(|_| anyhow!("a Blender reader thread panicked"))??;
        }
        Ok(())
    })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn id_levels_are_distinct_and_decode_exactly() {
        for n in 1..=11 {
            let levels: Vec<u8> = (1..=n).map(|k| id_level(k, n)).collect();
            let mut sorted = levels.clone();
            sorted.dedup();
            assert_eq!(sorted.len(), n);
            assert!(levels.windows(2).all(|w| w[1] > w[0] + 4));
            let mut pixels = vec![0u8];
            pixels.extend(&levels);
            pixels.push(levels[0] - 1);
            let png = super::super::writer::png_bytes(&pixels, pixels.len() as u32, 1, 1).unwrap();
            let ids = decode_ids(&png, n, "t").unwrap();
            let mut want: Vec<u8> = (0..=n as u8).collect();
            want.push(1);
            assert_eq!(ids, want);
        }
        let png = super::super::writer::png_bytes(&[0, 120], 2, 1, 1).unwrap();
        assert!(decode_ids(&png, 1, "x.png")
            .unwrap_err()
            .to_string()
            .contains("x.png"));
    }

    #[test]
    fn lights_are_seeded_by_the_scene() {
        let scene = |index| {
            super::super::sample(
                Preset::Clevr567,
                0,
                super::super::Split::Train,
                index,
                16,
                1,
                false,
            )
            .unwrap()
        };
        let (a, b) = (scene(0), scene(1));
        assert_eq!(lights(&a), lights(&a));
        assert_ne!(lights(&a), lights(&b));
        let key = &lights(&a)["key"]["position"];
        assert!(
            key[2].as_f64().unwrap() > 5.0,
            "the key light is above the scene"
        );
    }
}
