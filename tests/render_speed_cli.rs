//! CLI tests of colf-render's speed options: `--adaptive [EPS]`, `--no-shadows`, and the volumetric baseline
//! (`colf-train init --preset volumetric`, `--samples N`) through encode | render.

mod common;

use common::{bin, one_line_error, synth_scene};
use std::path::{Path, PathBuf};

fn scene(dir: &Path) -> PathBuf {
    synth_scene(dir, &["--seed", "11", "--split", "test"])
}

fn render(codes: &Path, cams: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    bin("colf-render")
        .arg(codes)
        .arg("--cameras")
        .arg(cams)
        .arg("--out")
        .arg(out)
        .args(["-q", "--masks"])
        .args(extra)
        .output()
        .unwrap()
}

/// Encodes the scene's view 0 with the default model into `codes`; returns `codes`.
fn encode(scene: &Path, codes: &Path) -> PathBuf {
    bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .arg("--camera")
        .arg(scene.join("transforms.json"))
        .arg("-o")
        .arg(codes)
        .assert()
        .success();
    codes.to_path_buf()
}

fn read(p: PathBuf) -> Vec<u8> {
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn adaptive_renders_deterministically_and_a_large_eps_leaves_only_the_background() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let codes = encode(&scene, &dir.path().join("a.codes"));
    let cams = scene.join("transforms.json");
    for out in ["a1", "a2"] {
        let o = render(&codes, &cams, &dir.path().join(out), &["--adaptive"]);
        assert!(o.status.success(), "{o:?}");
    }
    for v in 0..4 {
        for ext in ["png", "mask.png"] {
            let name = format!("view_{v:03}.{ext}");
            assert_eq!(
                read(dir.path().join("a1").join(&name)),
                read(dir.path().join("a2").join(&name)),
                "{name}"
            );
        }
    }
    // ε above any weight: no foreground slot is evaluated, every pixel is background.
    let o = render(
        &codes,
        &cams,
        &dir.path().join("bg"),
        &["--adaptive", "1.5"],
    );
    assert!(o.status.success(), "{o:?}");
    let (_, _, labels) =
        colf::image_io::read_labels(dir.path().join("bg/view_001.mask.png").to_str().unwrap())
            .unwrap();
    assert!(labels.iter().all(|&l| l == 0));
    // Bad values: usage errors naming the flag (exit 2, issue 24), no output folder.
    for bad in ["nan", "inf"] {
        let out = dir.path().join(format!("bad_{bad}"));
        let run = render(&codes, &cams, &out, &["--adaptive", bad]);
        assert_eq!(run.status.code(), Some(2), "{run:?}");
        assert!(String::from_utf8_lossy(&run.stderr).contains("--adaptive"));
        assert!(!out.exists());
    }
    let out = dir.path().join("bad_samples");
    one_line_error(
        &render(&codes, &cams, &out, &["--samples", "16"]),
        "render",
        "volumetric models only",
    );
    assert!(!out.exists());
}

#[test]
fn a_volumetric_model_encodes_and_renders_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let model = dir.path().join("vol.safetensors");
    bin("colf-train")
        .args(["init", "--preset", "volumetric", "--seed", "2", "-o"])
        .arg(&model)
        .assert()
        .success();
    let codes = dir.path().join("v.codes");
    bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .arg("--camera")
        .arg(scene.join("transforms.json"))
        .args(["--slots", "3", "--model"])
        .arg(&model)
        .arg("-o")
        .arg(&codes)
        .assert()
        .success();
    let cams = scene.join("transforms.json");
    let m = model.to_str().unwrap();
    for out in ["v1", "v2"] {
        let o = render(
            &codes,
            &cams,
            &dir.path().join(out),
            &["--model", m, "--samples", "12", "--exr", "--frames", "1..3"],
        );
        assert!(o.status.success(), "{o:?}");
    }
    for v in 1..3 {
        for ext in ["png", "mask.png", "exr"] {
            let name = format!("view_{v:03}.{ext}");
            assert_eq!(
                read(dir.path().join("v1").join(&name)),
                read(dir.path().join("v2").join(&name)),
                "{name}"
            );
        }
    }
    // More samples change the picture (the samples are really taken).
    let o = render(
        &codes,
        &cams,
        &dir.path().join("v3"),
        &["--model", m, "--samples", "40", "--frames", "1"],
    );
    assert!(o.status.success());
    assert_ne!(
        read(dir.path().join("v1/view_001.png")),
        read(dir.path().join("v3/view_001.png"))
    );
    let out = dir.path().join("bad");
    one_line_error(
        &render(&codes, &cams, &out, &["--model", m, "--adaptive"]),
        "render",
        "light-field models only",
    );
    let run = render(&codes, &cams, &out, &["--model", m, "--samples", "0"]);
    assert_eq!(run.status.code(), Some(2), "{run:?}");
    assert!(String::from_utf8_lossy(&run.stderr).contains("--samples"));
    assert!(!out.exists());
}

#[test]
fn no_shadows_leaves_the_segmentation_and_only_brightens_the_floor() {
    // The bundled default model's slots cast shadows (`shadow_head`, read along the light).
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let codes = encode(&scene, &dir.path().join("a.codes"));
    let cams = scene.join("transforms.json");
    let o = render(&codes, &cams, &dir.path().join("with"), &[]);
    assert!(o.status.success(), "{o:?}");
    let o = render(
        &codes,
        &cams,
        &dir.path().join("without"),
        &["--no-shadows"],
    );
    assert!(o.status.success(), "{o:?}");
    let mut brighter = 0;
    for v in 0..4 {
        let name = format!("view_{v:03}");
        assert_eq!(
            read(dir.path().join("with").join(format!("{name}.mask.png"))),
            read(dir.path().join("without").join(format!("{name}.mask.png"))),
            "{name}"
        );
        let pixels = |d: &str| {
            let p = dir.path().join(d).join(format!("{name}.png"));
            colf::image_io::read_rgb(p.to_str().unwrap()).unwrap().data
        };
        let (with, without) = (pixels("with"), pixels("without"));
        // 8-bit rounding aside, leaving the shadows out never darkens a pixel.
        assert!(with
            .iter()
            .zip(&without)
            .all(|(a, b)| *b >= *a - 1.5 / 255.0));
        brighter += with
            .iter()
            .zip(&without)
            .filter(|(a, b)| **b > **a + 4.0 / 255.0)
            .count();
    }
    assert!(brighter > 0, "no shadow was left out");
}
