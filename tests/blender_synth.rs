//! The Blender engine of `colf-synth` (`--engine blender`): masks against the analytic
//! engine's masks at projected object centres, the same layout and cameras as the analytic
//! engine, uORF's layout, and the missing-Blender error. The rendering tests print one line
//! and pass when `blender` is not on PATH (CI installs it).

use assert_cmd::Command;
use colf::camera::Cameras;
use colf::dataset::{Dataset, Layout};
use colf::synth::scene::Object;
use glam::DVec3;
use std::path::Path;

mod common;

fn synth() -> Command {
    Command::cargo_bin("colf-synth").unwrap()
}

/// Whether Blender can be run; prints why not.
fn have_blender() -> bool {
    let ok = std::process::Command::new("blender")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        println!("blender is not on PATH: skipping the Blender rendering test");
    }
    ok
}

fn generate(out: &Path, args: &[&str]) {
    let o = synth()
        .arg("--out")
        .arg(out)
        .arg("--quiet")
        .args(args)
        .env_remove("COLF_BLENDER")
        .output()
        .unwrap();
    assert!(o.status.success(), "{o:?}");
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

fn mask(path: &Path) -> Vec<u8> {
    let img = image::open(path).unwrap();
    assert_eq!(img.color(), image::ColorType::L8, "{}", path.display());
    img.to_luma8().into_raw()
}

/// The share of pixels showing an object in either mask on which the two masks agree.
fn foreground_agreement(a: &[u8], b: &[u8]) -> f64 {
    let either = a.iter().zip(b).filter(|(x, y)| **x > 0 || **y > 0);
    let (same, all) = either.fold((0, 0), |(s, n), (x, y)| (s + (x == y) as usize, n + 1));
    same as f64 / all as f64
}

/// Both engines, same seed: the same objects and cameras; Blender's masks hold only valid ids
/// and, at every projected object centre where the analytic mask shows that object over the
/// whole 5×5 neighbourhood (visible, away from edges), Blender's mask shows it too.
#[test]
fn blender_masks_match_projected_object_centres() {
    if !have_blender() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (b, a) = (tmp.path().join("blender"), tmp.path().join("analytic"));
    let common = [
        "--scenes", "1", "--views", "2", "--size", "64", "--seed", "3",
    ];
    generate(
        &b,
        &[&common[..], &["--engine", "blender", "-j", "1"]].concat(),
    );
    generate(&a, &common);
    let (sb, sa) = (b.join("scene_00000"), a.join("scene_00000"));
    let (jb, ja) = (json(&sb.join("scene.json")), json(&sa.join("scene.json")));
    assert_eq!(jb["engine"], "blender");
    let objects: Vec<Object> = serde_json::from_value(jb["objects"].clone()).unwrap();
    let analytic: Vec<Object> = serde_json::from_value(ja["objects"].clone()).unwrap();
    assert_eq!(objects.len(), analytic.len());
    for (o, p) in objects.iter().zip(&analytic) {
        assert_eq!((&o.shape, o.rgb, o.position), (&p.shape, p.rgb, p.position));
    }
    assert_eq!(
        std::fs::read(sb.join("transforms.json")).unwrap(),
        std::fs::read(sa.join("transforms.json")).unwrap(),
        "same cameras"
    );
    let cameras = Cameras::from_json(
        &std::fs::read(sb.join("transforms.json")).unwrap(),
        "transforms.json",
    )
    .unwrap();
    let n = objects.len() as u8;
    let mut checked = 0;
    for (v, frame) in cameras.frames.iter().enumerate() {
        let mb = mask(&sb.join(format!("view_{v:03}.mask.png")));
        let ma = mask(&sa.join(format!("view_{v:03}.mask.png")));
        assert!(mb.iter().all(|&id| id <= n), "ids are 0..={n}");
        // Tessellated meshes versus exact solids: the masks differ only along edges.
        let share = foreground_agreement(&mb, &ma);
        eprintln!("view {v}: the masks agree on {share:.4} of the object pixels");
        assert!(
            share > 0.85,
            "view {v}: masks agree on {share:.4} of the object pixels"
        );
        for (k, o) in objects.iter().enumerate() {
            let id = (k + 1) as u8;
            let Some((u, w)) = frame.project(DVec3::from_array(o.position)) else {
                continue;
            };
            let (i, j) = (u.floor() as i64, w.floor() as i64);
            let inside = |i: i64, j: i64| (0..64).contains(&i) && (0..64).contains(&j);
            let clear = (-2..=2).all(|dj| {
                (-2..=2)
                    .all(|di| inside(i + di, j + dj) && ma[((j + dj) * 64 + i + di) as usize] == id)
            });
            if clear {
                let got = mb[(j * 64 + i) as usize];
                assert_eq!(got, id, "view {v}, object {id} at pixel ({i}, {j})");
                checked += 1;
            }
        }
    }
    assert!(checked >= 3, "only {checked} object centres were checkable");
}

/// Pearson correlation of two equally long series.
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
    let va: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
    let vb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
    cov / (va * vb).sqrt()
}

/// The room presets with Blender: the same chairs and cameras as the analytic engine, masks
/// with valid ids only that agree with the analytic masks on most chair pixels (meshes of 64
/// segments against exact solids), every chair seen, and the same floor texture: on the pixels
/// of the image's lower half (the floor between the camera and the room's centre) that both
/// engines call background, their grey levels correlate (the lights differ, the pattern does
/// not).
#[test]
fn blender_room_presets_match_the_analytic_engine() {
    if !have_blender() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    for preset in ["room-chair", "room-diverse"] {
        let (b, a) = (
            tmp.path().join(format!("{preset}-b")),
            tmp.path().join(preset),
        );
        let common = [
            "--scenes", "1", "--views", "2", "--size", "64", "--seed", "2", "--preset", preset,
        ];
        generate(
            &b,
            &[
                &common[..],
                &["--engine", "blender", "-j", "1", "--samples", "16"],
            ]
            .concat(),
        );
        generate(&a, &common);
        let (sb, sa) = (b.join("scene_00000"), a.join("scene_00000"));
        let (jb, ja) = (json(&sb.join("scene.json")), json(&sa.join("scene.json")));
        assert_eq!(jb["engine"], "blender");
        assert_eq!(jb["objects"], ja["objects"], "{preset}: the same chairs");
        assert_eq!(
            std::fs::read(sb.join("transforms.json")).unwrap(),
            std::fs::read(sa.join("transforms.json")).unwrap(),
            "same cameras"
        );
        let n = jb["objects"].as_array().unwrap().len() as u8;
        let mut seen = std::collections::BTreeSet::new();
        for v in 0..2 {
            let mb = mask(&sb.join(format!("view_{v:03}.mask.png")));
            let ma = mask(&sa.join(format!("view_{v:03}.mask.png")));
            assert!(mb.iter().all(|&id| id <= n), "ids are 0..={n}");
            seen.extend(mb.iter().copied().filter(|&id| id > 0));
            let share = foreground_agreement(&mb, &ma);
            eprintln!("{preset} view {v}: the masks agree on {share:.4} of the chair pixels");
            assert!(share > 0.8, "{preset} view {v}: masks agree on {share:.4}");
            let grey = |path: &Path| -> Vec<f64> {
                let img = image::open(path).unwrap().to_luma8().into_raw();
                img.iter().map(|&g| g as f64).collect()
            };
            let (gb, ga) = (
                grey(&sb.join(format!("view_{v:03}.png"))),
                grey(&sa.join(format!("view_{v:03}.png"))),
            );
            let background: Vec<usize> = (mb.len() / 2..mb.len())
                .filter(|&i| mb[i] == 0 && ma[i] == 0)
                .collect();
            let pick = |g: &[f64]| background.iter().map(|&i| g[i]).collect::<Vec<_>>();
            let r = correlation(&pick(&gb), &pick(&ga));
            eprintln!("{preset} view {v}: background grey levels correlate at {r:.3}");
            assert!(r > 0.5, "{preset} view {v}: the floors differ (r = {r:.3})");
        }
        assert_eq!(seen.len(), n as usize, "{preset}: every chair is seen");
    }
}

/// `--layout uorf` with Blender: uORF's flat files, read by uORF's loaders as they should be
/// (tests/python/uorf_loader_check.py) and read back by colf's uORF reader with the same camera
/// poses as the colf layout and uORF's intrinsics; `--move` adds the moved views, uORF's
/// scene-manipulation files and the movement file.
#[test]
fn blender_uorf_layout_reads_back() {
    if !have_blender() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (u, c) = (tmp.path().join("uorf"), tmp.path().join("colf"));
    let common = [
        "--scenes", "1", "--views", "2", "--size", "32", "--engine", "blender",
    ];
    generate(
        &u,
        &[
            &common[..],
            &["--layout", "uorf", "--move", "1", "0.5", "0"],
        ]
        .concat(),
    );
    generate(&c, &common);
    // The analytic engine in uORF's layout renders the same (non-square-pixel) cameras.
    let a = tmp.path().join("analytic");
    generate(
        &a,
        &[
            "--scenes", "1", "--views", "2", "--size", "32", "--layout", "uorf",
        ],
    );
    // colf's ids of a uORF mask, through scene.json's grey level of every id.
    let ids = |dir: &Path, v: usize| -> Vec<u8> {
        let doc: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("sc0000_scene.json")).unwrap()).unwrap();
        let levels: Vec<u8> = serde_json::from_value(doc["uorf_mask_levels"][v].clone()).unwrap();
        mask(&dir.join(format!("{v:05}_sc0000_az{v:02}_mask.png")))
            .iter()
            .map(|g| levels.iter().position(|l| l == g).unwrap() as u8)
            .collect()
    };
    for v in 0..2 {
        let name = format!("{v:05}_sc0000_az{v:02}_mask.png");
        let (mb, ma) = (ids(&u, v), ids(&a, v));
        let share = foreground_agreement(&mb, &ma);
        eprintln!("{name}: the masks agree on {share:.4} of the object pixels");
        assert!(
            share > 0.8,
            "{name}: masks agree on {share:.4} of the object pixels"
        );
    }
    for f in [
        "00000_sc0000_az00.png",
        "00001_sc0000_az01_mask.png",
        "00001_sc0000_az01_RT.txt",
        "00000_sc0000_az00_moved.png",
        "00000_sc0000_az00_moved_mask.png",
        "000_movement.txt",
        "sc0000_scene.json",
        "dataset.json",
    ] {
        assert!(u.join(f).is_file(), "{f} missing");
    }
    // uORF's own loaders (redone in tests/python/uorf_loader_check.py) read it right.
    let (passed, text) = common::uorf_loader_check(&u, &["1", "2", "--move", "1", "0.5", "0"]);
    assert!(passed, "{text}");
    let ds = Dataset::open(&u).unwrap();
    assert_eq!((ds.layout, ds.len()), (Layout::Uorf, 1));
    let scene = ds.load(0).unwrap();
    let colf = Dataset::open(&c).unwrap().load(0).unwrap();
    for (a, b) in colf.views.iter().zip(&scene.views) {
        let diff = (a.frame.camera_to_world - b.frame.camera_to_world)
            .to_cols_array()
            .iter()
            .fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(diff < 1e-9, "{diff}");
        assert_eq!(b.frame.intrinsics.fl_y, 350.0 / 240.0 * 32.0);
        assert_eq!(b.frame.intrinsics.fl_x, a.frame.intrinsics.fl_x);
    }
}

/// `--resume` with the Blender engine renders only the scenes missing, keeps the others as
/// they were, and refuses a folder the analytic engine wrote.
#[test]
fn blender_resume_renders_only_what_is_missing() {
    if !have_blender() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let (whole, cut) = (tmp.path().join("whole"), tmp.path().join("cut"));
    let args = [
        "--scenes", "2", "--views", "1", "--size", "16", "--engine", "blender",
    ];
    generate(&whole, &args);
    std::fs::create_dir(&cut).unwrap();
    std::fs::create_dir(cut.join("scene_00000")).unwrap();
    for e in std::fs::read_dir(whole.join("scene_00000")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, cut.join("scene_00000").join(p.file_name().unwrap())).unwrap();
    }
    let kept = std::fs::metadata(cut.join("scene_00000/view_000.png"))
        .unwrap()
        .modified()
        .unwrap();
    generate(&cut, &[&args[..], &["--resume"]].concat());
    assert_eq!(
        std::fs::metadata(cut.join("scene_00000/view_000.png"))
            .unwrap()
            .modified()
            .unwrap(),
        kept,
        "a complete scene was rendered again"
    );
    for f in [
        "dataset.json",
        "scene_00001/scene.json",
        "scene_00001/transforms.json",
    ] {
        assert_eq!(json(&cut.join(f)), json(&whole.join(f)), "{f}");
    }
    assert!(cut.join("scene_00001/view_000.png").is_file());
    // A folder of the analytic engine's scenes is not the Blender engine's to continue.
    let analytic = tmp.path().join("analytic");
    generate(
        &analytic,
        &["--scenes", "1", "--views", "1", "--size", "16"],
    );
    let o = synth()
        .arg("--out")
        .arg(&analytic)
        .args(["-q", "--resume"])
        .args(args)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("`engine` differs"), "{err}");
}

/// A Blender that cannot be found is one error line naming the package, exit 1.
#[test]
fn missing_blender_is_one_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    let o = synth()
        .arg("--out")
        .arg(&out)
        .args(["--scenes", "1", "--engine", "blender"])
        .env("COLF_BLENDER", "/nonexistent/blender")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{o:?}");
    let err = String::from_utf8(o.stderr).unwrap();
    assert!(err.starts_with("colf-synth: error: "), "{err}");
    assert!(
        err.contains("/nonexistent/blender") && err.contains("apt-get install blender"),
        "{err}"
    );
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    // A preset the engine cannot render is a usage error.
    let o = synth()
        .arg("--out")
        .arg(&out)
        .args(["--scenes", "1", "--engine", "blender", "--preset", "city"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{o:?}");
}

/// A Blender that fails, or stops before reporting every scene, is one error line, exit 1.
#[test]
fn failing_blender_is_one_clear_error() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    for (body, expected) in [
        (
            "echo 'ValueError: broken job' >&2; exit 3",
            "Blender failed (exit status: 3): ValueError: broken job",
        ),
        ("exit 0", "Blender exited after 0 of its 2 scenes"),
    ] {
        let fake = tmp.path().join("fake-blender");
        std::fs::write(&fake, format!("#!/bin/sh\n{body}\n")).unwrap();
        std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
        let o = synth()
            .arg("--out")
            .arg(tmp.path().join("o"))
            .args(["--scenes", "2", "--engine", "blender", "-j", "1"])
            .env("COLF_BLENDER", &fake)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{o:?}");
        let err = String::from_utf8(o.stderr).unwrap();
        assert!(err.starts_with("colf-synth: error: "), "{err}");
        assert!(err.contains(expected), "{err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    }
}
