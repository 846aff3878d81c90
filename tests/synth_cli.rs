//! CLI tests of `colf-synth`: the real binary in temp dirs — determinism, masks against
//! scene.json, projection of object centres through the written cameras, `--move`, the dataset
//! readers (our layout and uORF's), uORF's layout as uORF's own loaders read it
//! (tests/python/uorf_loader_check.py), and the error contract.

mod common;

use assert_cmd::Command;
use colf::camera::{Cameras, Frame};
use colf::dataset::{Dataset, Layout};
use colf::synth::geometry::Solid;
use colf::synth::room::Room;
use colf::synth::scene::{Building, Object};
use glam::{DMat4, DVec3, DVec4};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn synth() -> Command {
    Command::cargo_bin("colf-synth").unwrap()
}

/// Runs colf-synth with `args` into `out`, quietly, and asserts success.
fn generate(out: &Path, args: &[&str]) {
    let o = synth()
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
}

/// Every file under `dir`, relative path → bytes.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// Runs colf-synth into `out` with `args`, quietly, and asserts it fails as bad input must:
/// exit 1, one line on stderr (returned), the folder unchanged.
fn refused(out: &Path, args: &[&str]) -> String {
    let before = files(out);
    let run = synth()
        .arg("--out")
        .arg(out)
        .arg("-q")
        .args(args)
        .output()
        .unwrap();
    assert_eq!(run.status.code(), Some(1), "{run:?}");
    let err = String::from_utf8_lossy(&run.stderr).into_owned();
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert_eq!(files(out), before, "{err}");
    err
}

fn scene_json(dir: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(dir.join("scene.json")).unwrap()).unwrap()
}

fn objects(scene: &serde_json::Value) -> Vec<Object> {
    serde_json::from_value(scene["objects"].clone()).unwrap()
}

fn mask(path: &Path) -> (u32, u32, Vec<u8>) {
    let img = image::open(path).unwrap();
    assert_eq!(img.color(), image::ColorType::L8, "{}", path.display());
    let img = img.to_luma8();
    (img.width(), img.height(), img.into_raw())
}

#[test]
fn same_seed_same_bytes_other_seed_or_split_other_scenes() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b, c, d) = (
        tmp.path().join("a"),
        tmp.path().join("b"),
        tmp.path().join("c"),
        tmp.path().join("d"),
    );
    generate(&a, &["--scenes", "3", "--seed", "7"]);
    generate(&b, &["--scenes", "3", "--seed", "7"]);
    let (fa, fb) = (files(&a), files(&b));
    // 3 scenes × (4 views × 2 PNGs + transforms.json + scene.json) + dataset.json.
    assert_eq!(fa.len(), 3 * 10 + 1);
    assert!(fa == fb, "same seed gave different files");
    // A smaller run is a prefix of a larger one: scene i does not depend on --scenes.
    generate(&c, &["--scenes", "1", "--seed", "7"]);
    let fc = files(&c);
    let view = Path::new("scene_00000/view_000.png");
    assert_eq!(fc[view], fa[view]);
    generate(&d, &["--scenes", "1", "--seed", "8"]);
    assert_ne!(files(&d)[view], fa[view]);
    generate(
        &d,
        &["--scenes", "1", "--seed", "7", "--split", "test", "--force"],
    );
    let fd = files(&d);
    assert_ne!(fd[view], fa[view]);
    let json = scene_json(&d.join("scene_00000"));
    assert_eq!(json["split"], "test");
}

/// Mask ids never exceed the object count, every object of a CLEVR preset shows up in some
/// view, and scene.json's per-view pixel counts are the masks' counts.
#[test]
fn masks_agree_with_scene_json() {
    let tmp = tempfile::tempdir().unwrap();
    for (preset, scenes, all_seen) in [
        ("clevr567", "6", true),
        ("packed11", "2", true),
        ("clevr567-textured", "2", true),
        ("city", "2", false),
    ] {
        let out = tmp.path().join(preset);
        generate(
            &out,
            &["--scenes", scenes, "--preset", preset, "--size", "48"],
        );
        let dataset: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("dataset.json")).unwrap()).unwrap();
        assert_eq!(dataset["preset"], preset);
        for s in 0..scenes.parse::<usize>().unwrap() {
            let dir = out.join(format!("scene_{s:05}"));
            let scene = scene_json(&dir);
            let objs = objects(&scene);
            match preset {
                "clevr567" | "clevr567-textured" => assert!((5..=7).contains(&objs.len())),
                "packed11" => assert_eq!(objs.len(), 11),
                _ => assert!(objs.len() >= 2),
            }
            let mut seen = vec![false; objs.len()];
            for v in 0..4 {
                let (w, h, m) = mask(&dir.join(format!("view_{v:03}.mask.png")));
                assert_eq!((w, h), (48, 48));
                let mut counts = vec![0u64; objs.len() + 1];
                for &id in &m {
                    assert!((id as usize) <= objs.len(), "{preset}: id {id} in {dir:?}");
                    counts[id as usize] += 1;
                }
                for (k, o) in objs.iter().enumerate() {
                    assert_eq!(o.visible_pixels[v], counts[k + 1], "{preset} {dir:?}");
                    seen[k] |= counts[k + 1] > 0;
                }
                assert!(counts[0] > 0, "background visible");
            }
            if all_seen {
                assert!(seen.iter().all(|&s| s), "{preset}: an object is never seen");
            }
        }
    }
}

/// Scene geometry from scene.json: every solid with its mask id (0 = background building).
fn solids(scene: &serde_json::Value, objs: &[Object]) -> Vec<(Solid, u8)> {
    let mut out = Vec::new();
    for (k, o) in objs.iter().enumerate() {
        for (solid, _) in o.parts().unwrap() {
            out.push((solid, (k + 1) as u8));
        }
    }
    if let Some(b) = scene.get("buildings") {
        let buildings: Vec<Building> = serde_json::from_value(b.clone()).unwrap();
        out.extend(buildings.iter().map(|b| (b.solid(), 0)));
    }
    if let Some(r) = scene.get("room") {
        let room: Room = serde_json::from_value(r.clone()).unwrap();
        out.extend(room.walls().iter().map(|w| (w.solid(), 0)));
    }
    out
}

/// Mask id of the first solid along the ray (0 if none: ground or sky).
fn first_id(solids: &[(Solid, u8)], origin: DVec3, dir: DVec3) -> u8 {
    let mut best = (f64::INFINITY, 0u8);
    for (solid, id) in solids {
        if let Some(hit) = solid.intersect(origin, dir, best.0) {
            best = (hit.t, *id);
        }
    }
    best.1
}

/// Projects each object's centre with the written transforms.json and looks at the mask pixel
/// holding the projection. Its id must be what the line of sight through that pixel's centre
/// (the ray the mask is sampled on) meets first in the scene.json geometry: the object itself
/// when unoccluded, else the nearer occluder. Returns (pairs checked, pairs where the mask
/// showed the object itself).
fn check_projection(
    dir: &Path,
    scene: &serde_json::Value,
    objs: &[Object],
    suffix: &str,
) -> (usize, usize) {
    let cams = Cameras::read(dir.join("transforms.json").to_str().unwrap()).unwrap();
    assert_eq!(cams.frames.len(), 4);
    let solids = solids(scene, objs);
    let (mut checked, mut direct) = (0, 0);
    for (v, frame) in cams.frames.iter().enumerate() {
        assert_eq!(
            frame.file_path.as_deref(),
            Some(format!("view_{v:03}.png").as_str())
        );
        let k = frame.intrinsics;
        assert_eq!(
            (k.fl_x, k.fl_y),
            (1.09375 * k.w as f64, 1.09375 * k.w as f64)
        );
        assert_eq!((k.cx, k.cy), (0.5 * k.w as f64, 0.5 * k.h as f64));
        let (w, _, m) = mask(&dir.join(format!("view_{v:03}{suffix}.mask.png")));
        for (i, o) in objs.iter().enumerate() {
            let Some((u, vv)) = frame.project(o.center()) else {
                continue;
            };
            if u < 0.0 || vv < 0.0 || u >= k.w as f64 || vv >= k.h as f64 {
                continue;
            }
            checked += 1;
            let (pi, pj) = (u as u32, vv as u32);
            let id = m[pj as usize * w as usize + pi as usize];
            let ray = frame.pixel_ray(pi, pj);
            let expected = first_id(&solids, ray.origin, ray.direction);
            assert_eq!(
                id,
                expected,
                "{dir:?} view {v}: object {} projects to ({u:.2}, {vv:.2}), mask id {id}, \
                 line of sight meets {expected}",
                i + 1
            );
            if id as usize == i + 1 {
                direct += 1;
            }
        }
    }
    (checked, direct)
}

#[test]
fn object_centres_project_onto_their_own_mask_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut checked, mut direct) = (0, 0);
    for preset in ["clevr567", "packed11", "city"] {
        let out = tmp.path().join(preset);
        generate(&out, &["--scenes", "4", "--preset", preset, "--seed", "3"]);
        for s in 0..4 {
            let dir = out.join(format!("scene_{s:05}"));
            let scene = scene_json(&dir);
            let (c, d) = check_projection(&dir, &scene, &objects(&scene), "");
            checked += c;
            direct += d;
        }
    }
    // Not vacuous: most centres are seen directly.
    assert!(checked >= 80, "{checked}");
    assert!(direct * 10 >= checked * 7, "{direct} of {checked}");
}

/// The room presets: 3-4 chairs on a room floor, exact masks (ids and visible pixels agree
/// with scene.json, every chair is seen, and the mask pixel under each seat centre is what
/// that pixel's line of sight meets in the chairs and walls rebuilt from scene.json), the
/// same bytes with one thread or two, and uORF's layout read back.
#[test]
fn room_presets_hold_three_or_four_chairs_with_exact_masks() {
    let tmp = tempfile::tempdir().unwrap();
    let (mut checked, mut direct) = (0, 0);
    for preset in ["room-chair", "room-diverse"] {
        let args = [
            "--scenes", "3", "--preset", preset, "--size", "32", "--seed", "5",
        ];
        let run = |out: &Path, threads: &str| {
            let o = synth()
                .arg("--out")
                .arg(out)
                .arg("--quiet")
                .args(args)
                .env("RAYON_NUM_THREADS", threads)
                .output()
                .unwrap();
            assert!(o.status.success(), "{o:?}");
        };
        let (out, one) = (
            tmp.path().join(preset),
            tmp.path().join(format!("{preset}-1")),
        );
        run(&out, "2");
        run(&one, "1");
        assert!(
            files(&out) == files(&one),
            "{preset}: the thread count changed bytes"
        );
        let mut designs = std::collections::BTreeSet::new();
        for s in 0..3 {
            let dir = out.join(format!("scene_{s:05}"));
            let scene = scene_json(&dir);
            assert_eq!(scene["preset"], preset);
            assert_eq!(scene["ground"]["kind"], "floor");
            assert!(scene["room"]["half_extent"].as_f64().unwrap() > 0.0);
            let objs = objects(&scene);
            assert!(
                (3..=4).contains(&objs.len()),
                "{preset}: {} chairs",
                objs.len()
            );
            let mut seen = std::collections::BTreeSet::new();
            for v in 0..4 {
                let (_, _, m) = mask(&dir.join(format!("view_{v:03}.mask.png")));
                for (k, o) in objs.iter().enumerate() {
                    let n = m.iter().filter(|&&id| id as usize == k + 1).count() as u64;
                    assert_eq!(o.visible_pixels[v], n);
                }
                assert!(m.iter().all(|&id| id as usize <= objs.len()));
                seen.extend(m.iter().copied().filter(|&id| id > 0));
            }
            assert_eq!(seen.len(), objs.len(), "{preset}: every chair is seen");
            for o in &objs {
                assert_eq!(o.shape, "chair");
                designs.insert(o.chair.unwrap().design_index);
            }
            let (c, d) = check_projection(&dir, &scene, &objs, "");
            checked += c;
            direct += d;
        }
        if preset == "room-chair" {
            assert_eq!(designs, [None].into());
        } else {
            assert!(designs.len() >= 6, "{designs:?}");
        }
        let uorf = tmp.path().join(format!("{preset}-uorf"));
        generate(
            &uorf,
            &[
                "--scenes", "1", "--preset", preset, "--size", "32", "--layout", "uorf",
            ],
        );
        let ds = Dataset::open(&uorf).unwrap();
        assert_eq!((ds.layout, ds.len()), (Layout::Uorf, 1));
        assert_eq!(ds.load(0).unwrap().views.len(), 4);
    }
    assert!(checked >= 30, "{checked}");
    assert!(direct * 10 >= checked * 6, "{direct} of {checked}");
}

#[test]
fn move_renders_the_object_elsewhere_with_the_same_cameras() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("m");
    generate(&out, &["--scenes", "2", "--move", "2", "1.25", "-0.75"]);
    for s in 0..2 {
        let dir = out.join(format!("scene_{s:05}"));
        let scene = scene_json(&dir);
        let mut objs = objects(&scene);
        let before = objs[1].center();
        let moved: Vec<f64> = serde_json::from_value(scene["moved"]["position"].clone()).unwrap();
        assert_eq!(scene["moved"]["object"], 2);
        let after = DVec3::new(moved[0], moved[1], moved[2]);
        assert!((after - before - DVec3::new(1.25, -0.75, 0.0)).length() < 1e-12);
        objs[1].position = after.to_array();
        let (checked, direct) = check_projection(&dir, &scene, &objs, ".moved");
        assert!(checked > 0 && direct > 0);
        let mut changed = false;
        for v in 0..4 {
            assert!(dir.join(format!("view_{v:03}.moved.png")).is_file());
            let (_, _, a) = mask(&dir.join(format!("view_{v:03}.mask.png")));
            let (_, _, b) = mask(&dir.join(format!("view_{v:03}.moved.mask.png")));
            changed |= a.iter().zip(&b).any(|(x, y)| (*x == 2) != (*y == 2));
        }
        assert!(changed, "object 2's mask did not move");
    }
    // An object some scene lacks is an error before anything is written.
    let none = tmp.path().join("none");
    let o = synth()
        .args(["--scenes", "3", "--quiet", "--move", "9", "0", "0", "--out"])
        .arg(&none)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8(o.stderr).unwrap();
    assert!(
        err.starts_with("colf-synth: error: --move 9: scene 0"),
        "{err}"
    );
    assert_eq!(err.trim_end().lines().count(), 1);
    assert!(!none.exists());
}

#[test]
fn colf_reader_returns_what_synth_wrote() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    generate(&out, &["--scenes", "2", "--size", "32"]);
    let ds = Dataset::open(&out).unwrap();
    assert_eq!((ds.layout, ds.len()), (Layout::Colf, 2));
    let scene = ds.load(1).unwrap();
    assert_eq!(scene.name, "scene_00001");
    assert_eq!(scene.views.len(), 4);
    let cams = Cameras::read(out.join("scene_00001/transforms.json").to_str().unwrap()).unwrap();
    for (v, view) in scene.views.iter().enumerate() {
        assert_eq!(view.frame, cams.frames[v]);
        let png = image::open(out.join(format!("scene_00001/view_{v:03}.png")))
            .unwrap()
            .to_rgb8();
        let expected: Vec<f32> = png.as_raw().iter().map(|&b| b as f32 / 255.0).collect();
        assert_eq!(view.image.data, expected, "sRGB values as stored");
        let (_, _, m) = mask(&out.join(format!("scene_00001/view_{v:03}.mask.png")));
        assert_eq!(view.mask.as_ref(), Some(&m));
    }
    // A single scene folder is a dataset of one scene.
    let one = Dataset::open(out.join("scene_00000")).unwrap();
    assert_eq!(one.len(), 1);
}

/// Writes a 4×4 row-major matrix as uORF's `_RT.txt` does.
fn rt_text(m: &DMat4) -> String {
    (0..4)
        .map(|r| {
            let row = m.row(r);
            format!("{:.17} {:.17} {:.17} {:.17}\n", row.x, row.y, row.z, row.w)
        })
        .collect()
}

fn write_png(path: &Path, pixels: &[u8], w: u32, h: u32, colour: image::ExtendedColorType) {
    image::save_buffer(path, pixels, w, h, colour).unwrap();
}

/// A synthetic scene re-written in the uORF flat layout reads back with the same images and
/// the same OpenGL cameras (its RT files hold OpenCV axes).
#[test]
fn uorf_reader_converts_cameras_from_opencv_axes() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("colf");
    generate(&out, &["--scenes", "1", "--size", "32"]);
    let colf = Dataset::open(&out).unwrap().load(0).unwrap();
    let uorf = tmp.path().join("uorf");
    std::fs::create_dir(&uorf).unwrap();
    let flip = DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0));
    for (v, view) in colf.views.iter().enumerate() {
        // Index numbers need not follow the view order: views are ordered by az.
        let stem = format!("{:05}_sc0005_az{v:02}", 10 - v);
        std::fs::copy(&view.path, uorf.join(format!("{stem}.png"))).unwrap();
        let opencv = view.frame.camera_to_world * flip;
        std::fs::write(uorf.join(format!("{stem}_RT.txt")), rt_text(&opencv)).unwrap();
    }
    let ds = Dataset::open(&uorf).unwrap();
    assert_eq!((ds.layout, ds.len()), (Layout::Uorf, 1));
    assert_eq!(ds.scene_name(0), "sc0005");
    let scene = ds.load(0).unwrap();
    assert_eq!(scene.views.len(), 4);
    for (a, b) in colf.views.iter().zip(&scene.views) {
        assert_eq!(a.image, b.image);
        assert!(b.mask.is_none());
        let diff = (a.frame.camera_to_world - b.frame.camera_to_world)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(diff < 1e-12, "{diff}");
        let k = b.frame.intrinsics;
        assert_eq!(
            (k.fl_x, k.fl_y, k.cx, k.cy),
            (35.0, 350.0 / 240.0 * 32.0, 16.0, 16.0)
        );
        // The world origin (every clevr camera's target) projects to the image centre.
        let (u, v) = b.frame.project(DVec3::ZERO).unwrap();
        assert!((u - 16.0).abs() < 1e-9 && (v - 16.0).abs() < 1e-9);
    }
}

/// uORF masks: per view the second-smallest grey level is the background; the other levels
/// get ids in increasing grey order, consistently across the scene's views; RGB masks are
/// turned grey as PIL does.
#[test]
fn uorf_reader_maps_mask_levels_to_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let pose = |x: f64| {
        colf::camera::look_at(DVec3::new(x, -8.0, 6.0), DVec3::ZERO, DVec3::Z).unwrap()
            * DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0))
    };
    // Grey levels: 10 = an object in every view, 60 = background, 100 and 200 = objects.
    let views: [[u8; 4]; 2] = [[10, 60, 100, 200], [10, 60, 60, 200]];
    for scene in [3u32, 1] {
        for (v, levels) in views.iter().enumerate() {
            let stem = format!("{:05}_sc{scene:04}_az{v:02}", scene * 2 + v as u32);
            let image: Vec<u8> = (0..2 * 2 * 3).map(|i| (i * 20 + v) as u8).collect();
            write_png(
                &dir.join(format!("{stem}.png")),
                &image,
                2,
                2,
                image::ExtendedColorType::Rgb8,
            );
            let rgb: Vec<u8> = levels.iter().flat_map(|&l| [l, l, l]).collect();
            write_png(
                &dir.join(format!("{stem}_mask.png")),
                &rgb,
                2,
                2,
                image::ExtendedColorType::Rgb8,
            );
            std::fs::write(dir.join(format!("{stem}_RT.txt")), rt_text(&pose(v as f64))).unwrap();
        }
    }
    let ds = Dataset::open(dir).unwrap();
    assert_eq!(ds.len(), 2);
    assert_eq!(ds.scene_name(0), "sc0001");
    let scene = ds.load(0).unwrap();
    assert_eq!(scene.views[0].mask.as_deref(), Some(&[1u8, 0, 2, 3][..]));
    assert_eq!(scene.views[1].mask.as_deref(), Some(&[1u8, 0, 0, 3][..]));
    let expected: Vec<f32> = (0..12).map(|i| (i * 20 + 1) as f32 / 255.0).collect();
    assert_eq!(scene.views[1].image.data, expected);
    let frame: &Frame = &scene.views[1].frame;
    assert!((frame.origin() - DVec3::new(1.0, -8.0, 6.0)).length() < 1e-12);
    // OpenGL axes after conversion: the camera looks along −Z at the origin.
    let forward = frame.camera_to_world.transform_vector3(-DVec3::Z);
    assert!((forward - (-frame.origin()).normalize()).length() < 1e-12);
    // A broken RT file is a clear error naming it.
    std::fs::write(dir.join("00002_sc0001_az00_RT.txt"), "1 0 0").unwrap();
    let msg = format!("{:#}", ds.load(0).unwrap_err());
    assert!(msg.contains("00002_sc0001_az00_RT.txt"), "{msg}");
}

/// `--layout uorf` as uORF's own loaders read it (tests/python/uorf_loader_check.py redoes
/// `multiscenes_dataset.py` and `multiscenes_manip_dataset.py`): in every view uORF's
/// background (the second-smallest grey level) and its `fg_idx` and `mask_idx` are colf's ids
/// rendered for the written cameras, `_azi_rot.txt` is the camera's azimuth rotation, and the
/// scene-manipulation files of `--move` mean what uORF takes them to mean. colf's uORF reader
/// splits every mask as colf's ids do (so the segmentation scores are the same) and uses
/// uORF's exact intrinsics. A mask with colf's own values (0 = background) fails the check.
#[test]
fn uorf_layout_reads_as_uorf_reads_it() {
    use colf::synth::{layout_frames, render::Tracer, OutputLayout, Preset, Split};
    let tmp = tempfile::tempdir().unwrap();
    let (u, gt) = (tmp.path().join("uorf"), tmp.path().join("gt"));
    let (scenes, views, size, seed) = (2u64, 3usize, 32u32, 5u64);
    generate(
        &u,
        &[
            "--scenes",
            "2",
            "--views",
            "3",
            "--size",
            "32",
            "--seed",
            "5",
            "--layout",
            "uorf",
            "--move",
            "1",
            "0.5",
            "-0.25",
            "--randomize-look",
        ],
    );
    // colf's ids for the written cameras, from colf's tracer.
    std::fs::create_dir(&gt).unwrap();
    let sampled: Vec<_> = (0..scenes)
        .map(|i| {
            colf::synth::sample(Preset::Clevr567, seed, Split::Train, i, size, views, false)
                .unwrap()
        })
        .collect();
    let mut truth = Vec::new();
    for (i, s) in sampled.iter().enumerate() {
        let frames = layout_frames(&s.frames, OutputLayout::Uorf);
        let providing = &sampled[(i + 1) % scenes as usize];
        let (own, other) = (
            Tracer::new(&s.scene, None).unwrap(),
            Tracer::new(&providing.scene, None).unwrap(),
        );
        let mut scene_truth = Vec::new();
        for (v, f) in frames.iter().enumerate() {
            let stem = colf::synth::uorf_stem(i as u64, v, views);
            let ids = own.render_mask(f);
            let png = |name: String, m: &[u8]| {
                image::save_buffer(gt.join(name), m, size, size, image::ExtendedColorType::L8)
                    .unwrap()
            };
            png(format!("{stem}_ids.png"), &ids);
            png(format!("{stem}_providing_ids.png"), &other.render_mask(f));
            scene_truth.push(ids);
        }
        truth.push(scene_truth);
    }
    let gt_arg = gt.to_str().unwrap();
    let args = ["2", "3", "--gt", gt_arg, "--move", "1", "0.5", "-0.25"];
    let (passed, text) = common::uorf_loader_check(&u, &args);
    assert!(passed, "{text}");
    assert_eq!(
        text.lines().filter(|l| l.ends_with(" ok")).count(),
        3,
        "{text}"
    );
    // colf's reader: the same partition of every view, uORF's intrinsics.
    let ds = Dataset::open(&u).unwrap();
    assert_eq!((ds.layout, ds.len()), (Layout::Uorf, 2));
    for (i, scene_truth) in truth.iter().enumerate() {
        let scene = ds.load(i).unwrap();
        let mut ids = BTreeMap::new();
        for (view, want) in scene.views.iter().zip(scene_truth) {
            let got = view.mask.as_ref().unwrap();
            for (&g, &w) in got.iter().zip(want) {
                // One id per object in the whole scene, 0 for the background.
                assert_eq!(*ids.entry(w).or_insert(g), g, "scene {i}");
                assert_eq!(g == 0, w == 0);
            }
            let k = view.frame.intrinsics;
            assert_eq!((k.fl_x, k.fl_y), (35.0, 350.0 / 240.0 * 32.0));
        }
        let distinct: std::collections::BTreeSet<u8> = ids.values().copied().collect();
        assert_eq!(
            distinct.len(),
            ids.len(),
            "scene {i}: two objects share an id"
        );
    }
    // The check fails on a mask in colf's own values, where uORF misreads the background.
    let name = "00000_sc0000_az00_mask.png";
    let ids = &truth[0][0];
    image::save_buffer(u.join(name), ids, size, size, image::ExtendedColorType::L8).unwrap();
    let (passed, text) = common::uorf_loader_check(&u, &args);
    assert!(!passed && text.contains(name), "{text}");
}

#[test]
fn bad_arguments_fail_with_the_right_exit_code() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    for args in [
        vec!["--scenes", "0"],
        vec!["--scenes", "2", "--preset", "mars"],
        vec!["--scenes", "2", "--size", "3"],
        vec!["--scenes", "2", "--move", "1.5", "0", "0"],
        vec!["--scenes", "2", "--move", "1", "0"],
        vec!["--scenes", "2", "--split", "val"],
        vec!["--scenes", "2", "--layout", "flat"],
        vec!["--scenes", "2", "--engine", "povray"],
        vec!["--scenes", "2", "--engine", "blender", "--randomize-look"],
        vec!["--scenes", "2", "--engine", "blender", "--preset", "city"],
        vec!["--scenes", "2", "--engine", "blender", "--samples", "0"],
        vec![
            "--scenes",
            "2",
            "--preset",
            "room-chair",
            "--randomize-camera",
        ],
        vec!["--scenes", "2", "--preset", "city", "--randomize-camera"],
    ] {
        let o = synth().arg("--out").arg(&out).args(&args).output().unwrap();
        assert_eq!(o.status.code(), Some(2), "{args:?}: {o:?}");
        let err = String::from_utf8(o.stderr).unwrap();
        assert!(err.starts_with("error:"), "{err}");
    }
    // Without --scenes a preset with a paper dataset size generates that many; city has none.
    let o = synth()
        .args(["--out", "x", "--preset", "city"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "missing --scenes");
    assert!(String::from_utf8(o.stderr).unwrap().contains("--scenes N"));
    // Not a usage error: --out names a file.
    let file = tmp.path().join("file");
    std::fs::write(&file, b"x").unwrap();
    let o = synth()
        .arg("--out")
        .arg(&file)
        .args(["--scenes", "1"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8(o.stderr).unwrap();
    assert!(
        err.starts_with("colf-synth: error: ") && err.contains("not a folder"),
        "{err}"
    );
    assert_eq!(err.trim_end().lines().count(), 1);
    assert!(!out.exists());
}

/// The committed examples in testdata/synth/ are what seed 0 renders (pixels compared, so a
/// PNG encoder update does not matter; a change of the scene distribution or the renderer
/// does, and the examples must then be regenerated on purpose).
#[test]
fn committed_examples_are_reproduced() {
    let tmp = tempfile::tempdir().unwrap();
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("testdata/synth");
    for (preset, file, suffix) in [
        ("clevr567", "clevr567_seed0_scene00000_view_000.png", ".png"),
        (
            "clevr567",
            "clevr567_seed0_scene00000_view_000.mask.png",
            ".mask.png",
        ),
        (
            "clevr567-textured",
            "clevr567-textured_seed0_scene00000_view_000.png",
            ".png",
        ),
        ("city", "city_seed0_scene00000_view_000.png", ".png"),
    ] {
        let out = tmp.path().join(preset);
        if !out.exists() {
            generate(&out, &["--scenes", "1", "--preset", preset]);
        }
        let fresh = image::open(out.join(format!("scene_00000/view_000{suffix}"))).unwrap();
        let committed = image::open(data.join(file)).unwrap();
        assert_eq!(fresh.color(), committed.color(), "{file}");
        assert!(fresh.as_bytes() == committed.as_bytes(), "{file} differs");
    }
}

/// Three scenes generated into DIR/plain, and with `flag` into DIR/a and again DIR/b, which
/// must hold the same bytes (the option is seeded); returns (plain, a).
fn plain_and_with(dir: &Path, flag: &str) -> (PathBuf, PathBuf) {
    let (plain, a, b) = (dir.join("plain"), dir.join("a"), dir.join("b"));
    let args = ["--scenes", "3", "--size", "32", "--seed", "4"];
    generate(&plain, &args);
    generate(&a, &[&args[..], &[flag]].concat());
    generate(&b, &[&args[..], &[flag]].concat());
    assert!(
        files(&a) == files(&b),
        "{flag}: same options gave different files"
    );
    (plain, a)
}

/// `--randomize-look`: seeded (same bytes twice), the same objects, cameras and masks as
/// without it, other colours, and scene.json records the look and the light it drew.
#[test]
fn randomized_look_keeps_layouts_cameras_and_masks() {
    let tmp = tempfile::tempdir().unwrap();
    let (plain, a) = plain_and_with(tmp.path(), "--randomize-look");
    let mut floors = Vec::new();
    for s in 0..3 {
        let (dp, da) = (
            plain.join(format!("scene_{s:05}")),
            a.join(format!("scene_{s:05}")),
        );
        for name in ["transforms.json", "view_000.mask.png", "view_003.mask.png"] {
            assert_eq!(
                std::fs::read(dp.join(name)).unwrap(),
                std::fs::read(da.join(name)).unwrap(),
                "{name}"
            );
        }
        assert_ne!(
            std::fs::read(dp.join("view_000.png")).unwrap(),
            std::fs::read(da.join("view_000.png")).unwrap()
        );
        let (jp, ja) = (scene_json(&dp), scene_json(&da));
        assert_eq!(jp["objects"], ja["objects"]);
        assert!(jp.get("look").is_none());
        let look = &ja["look"];
        assert!(look["exposure"].as_f64().unwrap() > 0.0, "{look}");
        assert_ne!(jp["light"], ja["light"]);
        floors.push(ja["ground"]["albedo"].as_f64().unwrap());
    }
    assert!(
        floors.iter().all(|f| (0.25..=0.75).contains(f)),
        "{floors:?}"
    );
    assert!(floors[0] != floors[1], "{floors:?}");
}

/// `--randomize-camera`: seeded, the same objects and light as without it, each view's camera
/// at its own distance and elevation within the documented ranges (still looking at the
/// centre), recorded in scene.json, transforms.json and dataset.json.
#[test]
fn randomized_cameras_keep_objects_and_vary_distance_and_elevation() {
    let tmp = tempfile::tempdir().unwrap();
    let (plain, a) = plain_and_with(tmp.path(), "--randomize-camera");
    let dataset: serde_json::Value =
        serde_json::from_slice(&std::fs::read(a.join("dataset.json")).unwrap()).unwrap();
    assert_eq!(dataset["randomize_camera"], true);
    let (mut distances, mut elevations) = (Vec::new(), Vec::new());
    for s in 0..3 {
        let (dp, da) = (
            plain.join(format!("scene_{s:05}")),
            a.join(format!("scene_{s:05}")),
        );
        let (jp, ja) = (scene_json(&dp), scene_json(&da));
        assert_eq!(
            jp["objects"].as_array().unwrap().len(),
            ja["objects"].as_array().unwrap().len()
        );
        for (op, oa) in objects(&jp).iter().zip(objects(&ja)) {
            assert_eq!(op.position, oa.position);
            assert_eq!(op.color, oa.color);
        }
        assert_eq!(jp["light"], ja["light"]);
        assert_ne!(
            std::fs::read(dp.join("transforms.json")).unwrap(),
            std::fs::read(da.join("transforms.json")).unwrap()
        );
        let frames = Cameras::read(da.join("transforms.json").to_str().unwrap()).unwrap();
        for (v, camera) in ja["cameras"].as_array().unwrap().iter().enumerate() {
            let (d, e) = (
                camera["distance"].as_f64().unwrap(),
                camera["elevation_degrees"].as_f64().unwrap(),
            );
            assert!((0.8 * 12.4..=1.25 * 12.4).contains(&d), "{camera}");
            assert!((25.0..=55.0).contains(&e), "{camera}");
            // The written camera stands there, looking at the centre.
            let c2w = frames.frames[v].camera_to_world;
            let eye = c2w.w_axis.truncate();
            assert!((eye.length() - d).abs() < 1e-6, "{eye} {d}");
            assert!((eye.z / d - e.to_radians().sin()).abs() < 1e-6);
            let forward = -c2w.z_axis.truncate();
            assert!(forward.dot(-eye.normalize()) > 1.0 - 1e-9);
            distances.push(d);
            elevations.push(e);
        }
    }
    let spread = |v: &[f64]| {
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    };
    assert!(spread(&distances) > 1.0, "{distances:?}");
    assert!(spread(&elevations) > 5.0, "{elevations:?}");
}

#[test]
fn a_used_folder_is_refused_unless_forced_and_then_holds_only_the_new_run() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("data");
    generate(&out, &["--scenes", "3", "--size", "16"]);
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    // Without --force: one line naming the folder, exit 1, nothing changed.
    let err = refused(&out, &["--scenes", "1", "--size", "16"]);
    assert!(
        err.contains("not empty") && err.contains("--force"),
        "{err}"
    );
    // With --force: the earlier scenes are gone, the user's file stays.
    generate(&out, &["--scenes", "1", "--size", "16", "--force"]);
    assert!(out.join("scene_00000").is_dir());
    assert!(!out.join("scene_00001").exists() && !out.join("scene_00002").exists());
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
}

#[test]
fn resume_continues_an_interrupted_run_and_refuses_other_options() {
    let dir = tempfile::tempdir().unwrap();
    let (whole, cut) = (dir.path().join("whole"), dir.path().join("cut"));
    let args = ["--scenes", "3", "--size", "16", "--preset", "room-chair"];
    generate(&whole, &args);
    generate(&cut, &args);
    // Stopped while writing scene 1: no dataset.json, scene 1 without its scene.json.
    std::fs::remove_file(cut.join("dataset.json")).unwrap();
    std::fs::remove_file(cut.join("scene_00001/scene.json")).unwrap();
    std::fs::remove_dir_all(cut.join("scene_00002")).unwrap();
    std::fs::write(cut.join("notes.txt"), "mine").unwrap();
    // Other options: one line naming the file and the field, exit 1, nothing changed.
    let err = refused(&cut, &[&args[..], &["--seed", "5", "--resume"]].concat());
    assert!(
        err.contains("scene_00000/scene.json") && err.contains("`seed` differs"),
        "{err}"
    );
    // --force and --resume together are a usage error.
    let both = synth()
        .arg("--out")
        .arg(&cut)
        .args(["--scenes", "3", "--resume", "--force", "-q"])
        .output()
        .unwrap();
    assert_eq!(both.status.code(), Some(2), "{both:?}");
    // The same command resumed: the bytes of the uninterrupted run, the user's file kept.
    generate(&cut, &[&args[..], &["--resume"]].concat());
    let mut resumed = files(&cut);
    assert_eq!(resumed.remove(Path::new("notes.txt")).unwrap(), b"mine");
    assert_eq!(resumed, files(&whole));
}
