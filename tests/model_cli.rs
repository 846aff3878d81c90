//! `colf-train init` and the bundled default model.

mod common;

use assert_cmd::Command;
use colf::model::{Colf, Config};
use common::{bin, one_line_error};

fn train() -> Command {
    bin("colf-train")
}

#[test]
fn init_is_byte_reproducible_and_loads() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a.safetensors");
    let b = dir.path().join("b.safetensors");
    let c = dir.path().join("c.safetensors");
    for (path, seed) in [(&a, "3"), (&b, "3"), (&c, "4")] {
        train()
            .args(["init", "--preset", "small", "--seed", seed, "-o"])
            .arg(path)
            .assert()
            .success()
            .stderr(predicates::str::contains("3136517 parameters"));
    }
    let bytes = std::fs::read(&a).unwrap();
    assert_eq!(bytes, std::fs::read(&b).unwrap());
    assert_ne!(bytes, std::fs::read(&c).unwrap());
    assert_eq!(
        bytes,
        Colf::init(&Config::small(), 3)
            .unwrap()
            .to_bytes()
            .unwrap()
            .0
    );
    let model = Colf::load(&a).unwrap();
    assert_eq!(model.config(), &Config::small());
    // Only the model file is left in the folder (no temporary files).
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
}

#[test]
fn usage_and_io_errors_exit_cleanly() {
    train()
        .args(["init", "--preset", "huge", "-o", "x.safetensors"])
        .assert()
        .code(2);
    train().assert().code(2);
    let out = train()
        .args(["init", "-o", "/no/such/folder/m.safetensors"])
        .output()
        .unwrap();
    one_line_error(&out, "train", "error: /no/such/folder/m.safetensors");
}

#[test]
fn the_bundled_default_model_is_found_and_loads() {
    let candidates = colf::cli::model_path::default_model_candidates();
    let bundled = candidates.last().unwrap();
    assert!(bundled.ends_with("models/default.safetensors"));
    assert!(bundled.is_file(), "{} is missing", bundled.display());
    let model = Colf::load(bundled).unwrap();
    assert!(model.config().validate().is_ok());
    let raw = std::fs::read(bundled).unwrap();
    // Issue 37's limit on the shipped file: 60 MB.
    assert!(
        raw.len() <= 60_000_000,
        "default model is {} bytes",
        raw.len()
    );
    // With an explicit path, the default lookup is bypassed.
    let explicit = colf::cli::model_path::resolve_model_path(Some("/x/m.safetensors")).unwrap();
    assert_eq!(explicit, std::path::PathBuf::from("/x/m.safetensors"));
}

/// Indices of the background pixels (label 0) of a mask PNG.
fn floor_pixels(mask: &std::path::Path) -> Vec<usize> {
    let (_, _, labels) = colf::image_io::read_labels(mask.to_str().unwrap()).unwrap();
    (0..labels.len()).filter(|&i| labels[i] == 0).collect()
}

/// Mean value of interleaved RGB values `rgb` over the pixels `floor`.
fn mean_over(rgb: &[f32], floor: &[usize]) -> f64 {
    let sum: f64 = floor
        .iter()
        .flat_map(|&i| &rgb[3 * i..3 * i + 3])
        .map(|&v| v as f64)
        .sum();
    sum / (3 * floor.len()) as f64
}

#[test]
fn the_bundled_default_model_draws_the_floor_of_the_image_it_is_given() {
    // The default model reads its background from the image, so a darker photo of the same
    // scene (Blender's renders of CLEVR are darker than colf-synth's) gets a darker floor. A
    // model with one fixed background (zero_background) draws the same floor for both, and
    // fails here.
    let dir = tempfile::tempdir().unwrap();
    let scene = common::synth_scene(dir.path(), &["--split", "test"]);
    let view = scene.join("view_000.png");
    let floor = floor_pixels(&scene.join("view_000.mask.png"));
    let bright = colf::image_io::read_rgb(view.to_str().unwrap()).unwrap();
    let dark: Vec<f32> = bright.data.iter().map(|v| v * 0.6).collect();
    let dark_view = dir.path().join("dark.png");
    std::fs::write(
        &dark_view,
        colf::image_io::encode_png_rgb(bright.w, bright.h, &dark),
    )
    .unwrap();
    assert!(
        floor.len() > bright.pixels() / 2,
        "the view is mostly floor"
    );
    let cameras = scene.join("transforms.json");
    let mut drawn = Vec::new();
    for (name, input) in [("bright", &view), ("dark", &dark_view)] {
        let codes = dir.path().join(format!("{name}.codes"));
        bin("colf-encode")
            .arg(input)
            .args(["--fast", "--camera"])
            .arg(&cameras)
            .arg("-o")
            .arg(&codes)
            .assert()
            .success();
        let out = dir.path().join(name);
        bin("colf-render")
            .arg(&codes)
            .arg("--cameras")
            .arg(&cameras)
            .arg("--out")
            .arg(&out)
            .arg("-q")
            .assert()
            .success();
        // A transforms.json camera keeps its frame's file name.
        let render = colf::image_io::read_rgb(out.join("view_000.png").to_str().unwrap()).unwrap();
        drawn.push(mean_over(&render.data, &floor));
    }
    let (given_bright, given_dark) = (mean_over(&bright.data, &floor), mean_over(&dark, &floor));
    let step = given_bright - given_dark;
    assert!(step > 0.15, "{given_bright} {given_dark}");
    // Each render's floor lies within 15 % of the step of its own input's floor (measured:
    // 2 % and 5 %; the fixed-background `blender` model and the analytic-only model this one
    // grew from miss the dark floor by 56 % and 89 %).
    assert!(
        (drawn[0] - given_bright).abs() < 0.15 * step,
        "{drawn:?} vs {given_bright}"
    );
    assert!(
        (drawn[1] - given_dark).abs() < 0.15 * step,
        "{drawn:?} vs {given_dark}"
    );
}
