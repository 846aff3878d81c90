//! CLI tests of colf-encode, colf-render and colf-cameras on the bundled default model: pipes,
//! files, determinism, contracts of the outputs, and failure paths.

mod common;

use colf::codes::Codes;
use common::{bin, one_line_error, synth_scene};
use std::path::{Path, PathBuf};

/// A one-scene synthetic dataset (64², 4 views) in `dir`; returns the scene folder.
fn scene(dir: &Path) -> PathBuf {
    synth_scene(dir, &["--seed", "5"])
}

fn encode(scene: &Path, out: &Path) {
    encode_with(scene, out, &[]);
}

/// `colf-encode` of the scene's first view with `flags` added to the default encoding.
fn encode_with(scene: &Path, out: &Path, flags: &[&str]) {
    let run = encode_output(scene, out, flags);
    assert!(run.status.success(), "{run:?}");
}

/// Runs `colf-encode` of the scene's first view with `flags`, writing `out`.
fn encode_output(scene: &Path, out: &Path, flags: &[&str]) -> std::process::Output {
    bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .arg("--camera")
        .arg(scene.join("transforms.json"))
        .args(flags)
        .arg("-o")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn encode_edit_render_as_files_is_deterministic_and_meets_the_contract() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let (a, b) = (dir.path().join("a.codes"), dir.path().join("b.codes"));
    encode(&scene, &a);
    encode(&scene, &b);
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let codes = Codes::read(a.to_str().unwrap()).unwrap();
    // The bundled model's default encoding: its `inference` slot count, refined, best of tries.
    let default = colf::cli::model_path::load_model(None).unwrap();
    let inference = default.config().default_inference();
    assert!(inference.refine > 0 && inference.tries > 1, "{inference:?}");
    // Slots the input view does not need are dropped (--redundant); --redundant 0 keeps all.
    assert!(
        (1..=inference.slots).contains(&codes.slots.len()),
        "{}",
        codes.slots.len()
    );
    let all = dir.path().join("all.codes");
    encode_with(&scene, &all, &["--redundant", "0"]);
    let all = Codes::read(all.to_str().unwrap()).unwrap();
    assert_eq!(all.slots.len(), inference.slots);
    assert!(codes.slots.iter().all(|s| all.slots.contains(s)));
    // Every slot's frame has the input camera's rotation (the default model's attention frames
    // move only the origin, to where the slot attends).
    let cams =
        colf::camera::Cameras::read(scene.join("transforms.json").to_str().unwrap()).unwrap();
    let camera = cams.frames[0].camera_to_world;
    for s in &codes.slots {
        for (axis, camera_axis) in [
            (s.slot_to_world.x_axis, camera.x_axis),
            (s.slot_to_world.y_axis, camera.y_axis),
            (s.slot_to_world.z_axis, camera.z_axis),
        ] {
            assert!(
                axis.abs_diff_eq(camera_axis, 1e-6),
                "{axis} vs {camera_axis}"
            );
        }
        assert!((0.0..=1.0).contains(&s.mass));
        assert!(s.source.starts_with("view_000.png#"));
    }
    for out in ["r1", "r2"] {
        bin("colf-render")
            .arg(&a)
            .arg("--cameras")
            .arg(scene.join("transforms.json"))
            .arg("--out")
            .arg(dir.path().join(out))
            .args(["--masks", "--exr", "-q"])
            .assert()
            .success();
    }
    for v in 0..4 {
        for ext in ["png", "mask.png", "exr"] {
            let name = format!("view_{v:03}.{ext}");
            let one = std::fs::read(dir.path().join("r1").join(&name)).unwrap();
            assert_eq!(
                one,
                std::fs::read(dir.path().join("r2").join(&name)).unwrap(),
                "{name}"
            );
        }
        let (w, h, labels) = colf::image_io::read_labels(
            dir.path()
                .join(format!("r1/view_{v:03}.mask.png"))
                .to_str()
                .unwrap(),
        )
        .unwrap();
        assert_eq!((w, h), (64, 64));
        assert!(
            labels.iter().all(|&l| l as usize <= codes.slots.len()),
            "mask labels beyond K"
        );
    }
    let exr = dir.path().join("r1/view_000.exr");
    let channels = colf::render::output::read_exr_channels(&exr).unwrap();
    assert!(channels["R"].iter().all(|v| v.is_finite()));
    let last = codes.slots.len() - 1;
    assert!(
        channels.contains_key(&format!("slot{last}.order"))
            && !channels.contains_key(&format!("slot{}.order", last + 1))
    );
    let python = std::process::Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/exr_check.py"
        ))
        .arg(&exr)
        .args([&codes.slots.len().to_string(), "64", "64"])
        .output()
        .expect("python3");
    assert!(
        python.status.success(),
        "OpenEXR check failed (run through `make test`, which installs OpenEXR and numpy in target/py): {}",
        String::from_utf8_lossy(&python.stderr)
    );
}

#[test]
fn encode_edit_render_in_a_pipe_and_orbit_from_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let edits = dir.path().join("e.json");
    std::fs::write(
        &edits,
        r#"[{"op":"translate","slots":[0],"by":[0,1,0]},{"op":"delete","slots":[1]}]"#,
    )
    .unwrap();
    let encoded = bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .args(["--slots", "3", "-o", "-"])
        .output()
        .unwrap();
    assert!(encoded.status.success());
    let edited = bin("colf-edit")
        .arg(&edits)
        .write_stdin(encoded.stdout)
        .output()
        .unwrap();
    assert!(edited.status.success(), "{edited:?}");
    let codes = dir.path().join("edited.codes");
    std::fs::write(&codes, &edited.stdout).unwrap();
    let out = dir.path().join("piped");
    bin("colf-render")
        .args(["-", "--cameras"])
        .arg(scene.join("transforms.json"))
        .arg("--out")
        .arg(&out)
        .args(["--frames", "1..3", "--masks", "-q"])
        .write_stdin(edited.stdout)
        .assert()
        .success();
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "view_001.mask.png",
            "view_001.png",
            "view_002.mask.png",
            "view_002.png"
        ]
    );
    // colf-cameras orbit | colf-render --cameras -
    let orbit = bin("colf-cameras")
        .args(["orbit", "--frames", "3", "--size", "32"])
        .output()
        .unwrap();
    assert!(orbit.status.success());
    let orbit_out = dir.path().join("orbit");
    bin("colf-render")
        .arg(&codes)
        .args(["--cameras", "-", "--out"])
        .arg(&orbit_out)
        .arg("-q")
        .write_stdin(orbit.stdout)
        .assert()
        .success();
    for f in 0..3 {
        let img = colf::image_io::read_rgb(
            orbit_out
                .join(format!("frame_{f:04}.png"))
                .to_str()
                .unwrap(),
        )
        .unwrap();
        assert_eq!((img.w, img.h), (32, 32));
    }
}

#[test]
fn codes_of_another_model_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let codes = dir.path().join("a.codes");
    encode(&scene, &codes);
    let other = dir.path().join("other.safetensors");
    bin("colf-train")
        .args(["init", "--preset", "small", "--seed", "99", "-o"])
        .arg(&other)
        .assert()
        .success();
    let out = bin("colf-render")
        .arg(&codes)
        .arg("--cameras")
        .arg(scene.join("transforms.json"))
        .arg("--out")
        .arg(dir.path().join("r"))
        .arg("--model")
        .arg(&other)
        .output()
        .unwrap();
    one_line_error(&out, "render", "encoded by model");
    assert!(!dir.path().join("r/view_000.png").exists());
}

#[test]
fn bad_inputs_leave_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let bad_png = dir.path().join("bad.png");
    std::fs::write(&bad_png, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    let codes_out = dir.path().join("x.codes");
    let out = bin("colf-encode")
        .arg(&bad_png)
        .arg("-o")
        .arg(&codes_out)
        .output()
        .unwrap();
    one_line_error(&out, "encode", "bad.png");
    assert!(!codes_out.exists());

    let out = bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .arg("--camera")
        .arg(scene.join("transforms.json"))
        .args(["--frame", "9", "-o"])
        .arg(&codes_out)
        .output()
        .unwrap();
    one_line_error(&out, "encode", "--frame 9 does not exist");

    let out = bin("colf-encode")
        .arg(scene.join("view_000.png"))
        .args(["--model", "/no/such/model.safetensors", "-o"])
        .arg(&codes_out)
        .output()
        .unwrap();
    one_line_error(&out, "encode", "/no/such/model.safetensors");
    assert!(!codes_out.exists());

    let codes = dir.path().join("a.codes");
    encode(&scene, &codes);
    let cams = dir.path().join("cams.json");
    std::fs::write(&cams, r#"{"w":64,"h":64,"fl_x":0,"frames":[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#).unwrap();
    let out = bin("colf-render")
        .arg(&codes)
        .arg("--cameras")
        .arg(&cams)
        .arg("--out")
        .arg(dir.path().join("r"))
        .output()
        .unwrap();
    one_line_error(&out, "render", "focal length");
    assert!(!dir.path().join("r").exists());

    let out = bin("colf-render")
        .arg(&codes)
        .arg("--cameras")
        .arg(scene.join("transforms.json"))
        .args(["--frames", "7..9", "--out"])
        .arg(dir.path().join("r"))
        .output()
        .unwrap();
    one_line_error(
        &out,
        "render",
        "frames 7..9 reach beyond the 4 frames of the file",
    );
    let out = bin("colf-render").args(["--out", "x"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn refined_encoding_fits_the_input_view_and_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let encode_refined = |out: &Path, extra: &[&str]| encode_output(&scene, out, extra);
    // The model's default slots and tries, without refinement. Every slot is kept
    // (`--redundant 0`), so the three encodings can be compared slot by slot. The frames'
    // rate is given, not the model's, so the bound on how far they move below holds for
    // any bundled model.
    let plain = dir.path().join("plain.codes");
    let run = encode_refined(&plain, &["--refine", "0", "--redundant", "0"]);
    assert!(run.status.success(), "{run:?}");
    let (a, b) = (dir.path().join("a.codes"), dir.path().join("b.codes"));
    for out in [&a, &b] {
        let run = encode_refined(
            out,
            &[
                "--refine",
                "10",
                "--refine-frame-lr",
                "0.003",
                "--redundant",
                "0",
            ],
        );
        assert!(run.status.success(), "{run:?}");
    }
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let fixed_frames = dir.path().join("fixed.codes");
    let run = encode_refined(
        &fixed_frames,
        &[
            "--refine",
            "10",
            "--refine-frame-lr",
            "0",
            "--redundant",
            "0",
        ],
    );
    assert!(run.status.success(), "{run:?}");
    let read = |p: &Path| Codes::read(p.to_str().unwrap()).unwrap();
    let (plain_codes, refined, fixed) = (read(&plain), read(&a), read(&fixed_frames));
    assert_eq!(plain_codes.slots.len(), refined.slots.len());
    assert_eq!(plain_codes.slots.len(), fixed.slots.len());
    // Refinement changes every latent; it moves the frames' origins a little (Adam steps of
    // about --refine-frame-lr each: 10 × 0.003 × √3 ≈ 0.05 at most) and never turns them;
    // --refine-frame-lr 0 keeps them.
    for ((p, r), f) in plain_codes
        .slots
        .iter()
        .zip(&refined.slots)
        .zip(&fixed.slots)
    {
        assert!(p.latent != r.latent && p.latent != f.latent);
        assert_eq!(p.slot_to_world, f.slot_to_world);
        assert_eq!(p.slot_to_world.x_axis, r.slot_to_world.x_axis);
        assert_eq!(p.slot_to_world.y_axis, r.slot_to_world.y_axis);
        assert_eq!(p.slot_to_world.z_axis, r.slot_to_world.z_axis);
        let moved = (r.slot_to_world.w_axis - p.slot_to_world.w_axis).length();
        assert!(moved < 0.1, "a frame moved {moved} in 10 steps");
    }
    assert!(plain_codes
        .slots
        .iter()
        .zip(&refined.slots)
        .any(|(p, r)| p.slot_to_world != r.slot_to_world));
    // The input view is reconstructed better.
    let psnr_of = |codes: &Path, name: &str| {
        let out = dir.path().join(name);
        bin("colf-render")
            .arg(codes)
            .arg("--cameras")
            .arg(scene.join("transforms.json"))
            .args(["--frames", "0", "-q", "--out"])
            .arg(&out)
            .assert()
            .success();
        let eval = bin("colf-eval")
            .arg("images")
            .arg(out.join("view_000.png"))
            .arg(scene.join("view_000.png"))
            .output()
            .unwrap();
        let doc: serde_json::Value = serde_json::from_slice(&eval.stdout).unwrap();
        doc["psnr"].as_f64().unwrap()
    };
    let (before, after) = (psnr_of(&plain, "r0"), psnr_of(&a, "r1"));
    assert!(after > before + 0.5, "refined {after} dB vs {before} dB");

    let bad = dir.path().join("bad.codes");
    // Out of range: a usage error naming the flag (issue 24).
    let out = encode_refined(&bad, &["--refine", "3", "--refine-lr", "-1"]);
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("--refine-lr"));
    assert!(!bad.exists());
    let out = encode_refined(&bad, &["--refine", "many"]);
    assert_eq!(out.status.code(), Some(2));
}
