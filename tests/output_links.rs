//! Regression tests of issue 38, item 1: a link planted in a stage's output folder, where the
//! stage writes a file it names itself (a frame, a mask, an EXR, a scene file, a checkpoint, a
//! log, a kept snapshot, a proposal), is replaced by a regular file and never written through:
//! the file it points to, outside the folder, is untouched. A file the user names (`-o FILE`,
//! `colf-train --out MODEL`) that is a link still has its target written, as a shell redirect
//! would. One test per stage, on the real binaries.
#![cfg(unix)]

mod common;

use common::bin;
use std::path::{Path, PathBuf};

const VICTIM: &[u8] = b"not yours to overwrite";

/// A file outside the output folder that a planted link points to.
fn victim(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, VICTIM).unwrap();
    path
}

/// Plants `link` → `target`.
fn plant(link: &Path, target: &Path) {
    std::os::unix::fs::symlink(target, link).unwrap();
}

fn is_regular_file(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_file())
}

fn is_real_folder(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_dir())
}

fn untouched(victim: &Path) {
    assert_eq!(
        std::fs::read(victim).unwrap(),
        VICTIM,
        "{} was written through a link",
        victim.display()
    );
}

fn empty_folder(path: &Path) {
    assert_eq!(
        std::fs::read_dir(path).unwrap().count(),
        0,
        "{} was written through a link",
        path.display()
    );
}

/// colf-render: frames, masks and EXRs replace links planted in --out (the recipe:
/// `ln -s ../victim.png out/frame_0000.png`), and a link to a missing file creates nothing.
#[test]
fn render_replaces_links_in_its_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let codes = dir.path().join("s.codes");
    bin("colf-encode")
        .args([
            "testdata/synth/clevr567_seed0_scene00000_view_000.png",
            "--fast",
        ])
        .arg("-o")
        .arg(&codes)
        .assert()
        .success();
    let cameras = dir.path().join("c.json");
    bin("colf-cameras")
        .args(["orbit", "--frames", "2", "--size", "16", "-o"])
        .arg(&cameras)
        .assert()
        .success();
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let victims = [
        ("frame_0000.png", victim(dir.path(), "victim.png")),
        ("frame_0000.mask.png", victim(dir.path(), "victim.mask.png")),
        ("frame_0001.exr", victim(dir.path(), "victim.exr")),
        ("frame_0001.png", dir.path().join("absent.png")),
    ];
    for (name, target) in &victims {
        // Relative, as in the issue: `../victim.png` from inside the folder.
        let relative = Path::new("..").join(target.file_name().unwrap());
        plant(&out.join(name), &relative);
    }
    for adaptive in [false, true] {
        let mut cmd = bin("colf-render");
        cmd.arg(&codes)
            .arg("--cameras")
            .arg(&cameras)
            .arg("--out")
            .arg(&out)
            .args(["--masks", "--exr"]);
        if adaptive {
            cmd.arg("--adaptive");
        }
        cmd.assert().success();
        for (name, target) in &victims[..3] {
            untouched(target);
            assert!(is_regular_file(&out.join(name)), "{name} is still a link");
        }
        assert!(
            !victims[3].1.exists(),
            "a file was made through a dangling link"
        );
        for name in ["frame_0001.png", "frame_0001.mask.png", "frame_0000.exr"] {
            assert!(is_regular_file(&out.join(name)), "{name}");
        }
    }
    assert!(image::open(out.join("frame_0000.png")).is_ok());
}

/// colf-synth: a folder holding planted links is refused without --force, and with --force
/// the links (scene folders, dataset.json, uORF's flat files) are replaced, in both layouts.
#[test]
fn synth_replaces_links_in_its_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    let dataset_victim = victim(dir.path(), "victim.json");
    let view_victim = victim(dir.path(), "victim.png");

    let out = dir.path().join("colf");
    std::fs::create_dir(&out).unwrap();
    plant(&out.join("scene_00000"), &elsewhere);
    plant(&out.join("dataset.json"), &dataset_victim);
    let synth = |out: &Path, extra: &[&str]| {
        let mut cmd = bin("colf-synth");
        cmd.args(["--scenes", "1", "--size", "16", "-q", "--out"])
            .arg(out)
            .args(extra);
        cmd
    };
    common::fails_with(&mut synth(&out, &[]), "synth", 1, "not empty");
    synth(&out, &["--force"]).assert().success();
    assert!(is_real_folder(&out.join("scene_00000")));
    assert!(is_regular_file(&out.join("scene_00000/view_000.png")));
    assert!(is_regular_file(&out.join("dataset.json")));
    empty_folder(&elsewhere);
    untouched(&dataset_victim);

    let flat = dir.path().join("uorf");
    std::fs::create_dir(&flat).unwrap();
    plant(&flat.join("00000_sc0000_az00.png"), &view_victim);
    plant(&flat.join("sc0000_scene.json"), &dataset_victim);
    synth(&flat, &["--layout", "uorf", "--force"])
        .assert()
        .success();
    for name in ["00000_sc0000_az00.png", "sc0000_scene.json"] {
        assert!(is_regular_file(&flat.join(name)), "{name} is still a link");
    }
    untouched(&view_victim);
    untouched(&dataset_victim);
}

/// colf-train: the checkpoint (OUT.ckpt), the log (OUT.log.jsonl) and a kept snapshot
/// (OUT.stepN) replace links planted beside OUT; OUT itself, the file the user named, keeps
/// its link and has the link's target written (documented in colf-train's manual).
#[test]
fn train_replaces_links_beside_its_output() {
    let dir = tempfile::tempdir().unwrap();
    let data = common::synth_scene(dir.path(), &["--size", "32"])
        .parent()
        .unwrap()
        .to_path_buf();
    let runs = dir.path().join("runs");
    std::fs::create_dir(&runs).unwrap();
    let model = runs.join("m.safetensors");
    let beside = [
        ("m.safetensors.ckpt", victim(dir.path(), "victim.ckpt")),
        ("m.safetensors.log.jsonl", victim(dir.path(), "victim.log")),
        ("m.step1.safetensors", victim(dir.path(), "victim.step1")),
        ("m.step2.safetensors", dir.path().join("absent.step2")),
    ];
    for (name, target) in &beside {
        plant(&runs.join(name), target);
    }
    let mine = dir.path().join("mine.safetensors");
    std::fs::write(&mine, b"replaced by the model").unwrap();
    plant(&model, &mine);
    let train = |extra: &[&str]| {
        bin("colf-train")
            .arg("--data")
            .arg(&data)
            .arg("--out")
            .arg(&model)
            .args(["--batch", "1", "--rays", "32", "--views", "1"])
            .args(["--checkpoint-every", "1", "--keep-every", "1"])
            .args(extra)
            .assert()
            .success();
    };
    train(&["--steps", "2"]);
    for (name, target) in &beside[..3] {
        untouched(target);
        assert!(is_regular_file(&runs.join(name)), "{name} is still a link");
    }
    assert!(
        !beside[3].1.exists(),
        "a file was made through a dangling link"
    );
    assert!(is_regular_file(&runs.join("m.step2.safetensors")));
    // The log holds this run's two steps, not the victim's text.
    let log = std::fs::read_to_string(runs.join("m.safetensors.log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 2, "{log}");
    // --out named by the user: still a link, its target now the model.
    assert!(std::fs::symlink_metadata(&model)
        .unwrap()
        .file_type()
        .is_symlink());
    assert!(colf::model::Colf::load(&mine).is_ok());
    // Resuming appends to the (now regular) log.
    train(&["--steps", "3", "--resume"]);
    let log = std::fs::read_to_string(runs.join("m.safetensors.log.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 3, "{log}");
}

/// colf-eval --renders DIR and colf-train propose --out DIR: renders, masks and proposal
/// folders replace planted links.
#[test]
fn eval_renders_and_proposals_replace_links() {
    let dir = tempfile::tempdir().unwrap();
    let data = common::synth_scene(dir.path(), &["--size", "32"])
        .parent()
        .unwrap()
        .to_path_buf();
    let renders = dir.path().join("renders");
    std::fs::create_dir(&renders).unwrap();
    let png_victim = victim(dir.path(), "victim.png");
    let mask_victim = victim(dir.path(), "victim.mask.png");
    plant(&renders.join("scene_00000_v1.png"), &png_victim);
    plant(&renders.join("scene_00000_v1.mask.png"), &mask_victim);
    bin("colf-eval")
        .arg("--data")
        .arg(&data)
        .args(["--fast", "--renders"])
        .arg(&renders)
        .assert()
        .success();
    untouched(&png_victim);
    untouched(&mask_victim);
    for name in ["scene_00000_v1.png", "scene_00000_v1.mask.png"] {
        assert!(
            is_regular_file(&renders.join(name)),
            "{name} is still a link"
        );
    }

    let proposals = dir.path().join("proposals");
    std::fs::create_dir(&proposals).unwrap();
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    plant(&proposals.join("scene_00000"), &elsewhere);
    bin("colf-train")
        .args(["propose", "--data"])
        .arg(&data)
        .arg("--out")
        .arg(&proposals)
        .assert()
        .success();
    empty_folder(&elsewhere);
    assert!(is_real_folder(&proposals.join("scene_00000")));
    assert!(is_regular_file(
        &proposals.join("scene_00000/view_000.proposal.png")
    ));
}
