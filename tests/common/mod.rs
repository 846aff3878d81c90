//! Helpers shared by the CLI test crates (`mod common;` in each). A test crate compiles only the
//! helpers it calls, hence the `dead_code` allowance.
#![allow(dead_code)]

use assert_cmd::Command;
use std::path::{Path, PathBuf};
use std::process::Output;

/// The release binary `name` (e.g. `colf-render`) of this build.
pub fn bin(name: &str) -> Command {
    Command::cargo_bin(name).unwrap()
}

/// Writes `bytes` to `dir/name`; returns the path as a string for command arguments.
pub fn write(dir: &Path, name: &str, bytes: &[u8]) -> String {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p.to_str().unwrap().to_string()
}

/// A one-scene clevr567 dataset (64², 4 views) of `colf-synth` in `dir/data`, from `args` added
/// to `--scenes 1 -q`; returns the scene folder.
pub fn synth_scene(dir: &Path, args: &[&str]) -> PathBuf {
    bin("colf-synth")
        .args(["--scenes", "1", "-q"])
        .args(args)
        .arg("--out")
        .arg(dir.join("data"))
        .assert()
        .success();
    dir.join("data/scene_00000")
}

/// Checks the error contract of `colf-STAGE` on `out`: exit 1, one line starting
/// `colf-STAGE: error: ` that contains `needle`, no panic, nothing on stdout.
pub fn one_line_error(out: &Output, stage: &str, needle: &str) {
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err}");
    assert!(err.starts_with(&format!("colf-{stage}: error: ")), "{err}");
    assert!(err.contains(needle), "`{err}` lacks `{needle}`");
    assert!(!err.contains("panicked"), "{err}");
    assert!(out.stdout.is_empty(), "data written on failure");
}

/// Runs `cmd` (a `colf-STAGE` command) expecting exit `code` and `needle` in stderr; for exit 1
/// also the one-line contract of [`one_line_error`]. Returns stderr.
pub fn fails_with(cmd: &mut Command, stage: &str, code: i32, needle: &str) -> String {
    let out = cmd.output().unwrap();
    if code == 1 {
        one_line_error(&out, stage, needle);
    } else {
        assert_eq!(out.status.code(), Some(code), "{out:?}");
        assert!(out.stdout.is_empty(), "data written on failure");
    }
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains(needle), "stderr `{err}` lacks `{needle}`");
    err
}

/// A folder of test photos, `dir/images`: the first views of two tiny (32²) synthetic scenes,
/// `alpha` with its camera file (`alpha.json`), `beta` without. Returns the folder and the
/// image names.
pub fn photo_folder(dir: &Path) -> (PathBuf, Vec<&'static str>) {
    let data = dir.join("data");
    bin("colf-synth")
        .args([
            "--scenes", "2", "--size", "32", "--seed", "3", "-q", "--out",
        ])
        .arg(&data)
        .assert()
        .success();
    let images = dir.join("images");
    std::fs::create_dir(&images).unwrap();
    let names = vec!["alpha", "beta"];
    for (i, name) in names.iter().enumerate() {
        let scene = data.join(format!("scene_{i:05}"));
        std::fs::copy(
            scene.join("view_000.png"),
            images.join(format!("{name}.png")),
        )
        .unwrap();
        if i == 0 {
            std::fs::copy(scene.join("transforms.json"), images.join("alpha.json")).unwrap();
        }
    }
    (images, names)
}

/// Runs tests/python/uorf_loader_check.py (uORF's loaders redone with numpy and Pillow) on the
/// uORF-layout folder `dir` with `args`; returns (success, stdout + stderr). Panics if python3
/// lacks numpy or Pillow (`make test` puts the project's environment first on PATH).
pub fn uorf_loader_check(dir: &Path, args: &[&str]) -> (bool, String) {
    let probe = std::process::Command::new("python3")
        .args(["-c", "import numpy, PIL"])
        .output();
    assert!(
        probe.is_ok_and(|o| o.status.success()),
        "this test needs python3 with numpy and Pillow (make pyenv; make test)"
    );
    let o = std::process::Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/uorf_loader_check.py"
        ))
        .arg(dir)
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    (o.status.success(), text)
}
