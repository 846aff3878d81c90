//! `examples/batch/Makefile` under `make -j2`: encodes every image of a folder, renders an orbit
//! for each, and on a second run re-does only what changed.

mod common;

use std::path::Path;
use std::process::Command;

fn make(dir: &Path, images: &Path, out: &Path) -> String {
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_colf-encode"))
        .parent()
        .unwrap();
    let result = Command::new("make")
        .arg("-f")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/examples/batch/Makefile"
        ))
        .arg("-j2")
        .arg(format!("IN={}", images.display()))
        .arg(format!("OUT={}", out.display()))
        .arg(format!("COLF={}", bin_dir.display()))
        // One encoder pass: the batch mechanics are tested, not the encoding.
        .args(["FRAMES=2", "SIZE=16", "ENCODE_FLAGS=--fast"])
        .current_dir(dir)
        .output()
        .expect("make");
    let stdout = String::from_utf8_lossy(&result.stdout).into_owned();
    assert!(
        result.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&result.stderr)
    );
    stdout
}

#[test]
fn batch_makefile_is_incremental() {
    let dir = tempfile::tempdir().unwrap();
    // Two tiny scenes as a folder of images; the first keeps its camera file.
    let (images, _) = common::photo_folder(dir.path());
    let out = dir.path().join("out");
    let first = make(dir.path(), &images, &out);
    assert!(
        first.contains("--camera"),
        "the camera file was not used:\n{first}"
    );
    assert!(
        first.contains("--fast"),
        "ENCODE_FLAGS not passed:\n{first}"
    );
    for name in ["alpha", "beta"] {
        assert!(out.join(format!("{name}.codes")).is_file());
        for f in 0..2 {
            assert!(out.join(format!("{name}/frame_{f:04}.png")).is_file());
            assert!(out.join(format!("{name}/frame_{f:04}.mask.png")).is_file());
        }
    }
    // Nothing changed: nothing runs.
    let second = make(dir.path(), &images, &out);
    assert!(!second.contains("colf-"), "re-ran work:\n{second}");
    // One image changed: only it is encoded and rendered again.
    let later = std::time::SystemTime::now() + std::time::Duration::from_secs(5);
    let f = std::fs::File::options()
        .append(true)
        .open(images.join("beta.png"))
        .unwrap();
    f.set_modified(later).unwrap();
    let third = make(dir.path(), &images, &out);
    assert!(
        third.contains("beta.png") && !third.contains("alpha"),
        "{third}"
    );
}
