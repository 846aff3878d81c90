//! Several views in, one scene out: `colf-encode IMAGE... --camera` and `colf-eval
//! --input-views` on the real binaries (issue 39).

mod common;

use common::{bin, fails_with};
use std::path::Path;

/// A one-scene clevr567 dataset (64², 4 views) in `dir/data`; returns the scene folder.
fn scene(dir: &Path) -> std::path::PathBuf {
    common::synth_scene(dir, &["--seed", "3", "--split", "test"])
}

fn inspect(codes: &Path) -> serde_json::Value {
    let out = bin("colf-edit")
        .arg("--inspect")
        .arg(codes)
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn one_image_encodes_as_it_always_did_and_several_give_one_scene() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let cameras = scene.join("transforms.json");
    let view = |v: usize| scene.join(format!("view_{v:03}.png"));
    let encode = |images: &[std::path::PathBuf], extra: &[&str], out: &str| {
        let out = dir.path().join(out);
        bin("colf-encode")
            .args(images)
            .arg("--camera")
            .arg(&cameras)
            .args(["--fast", "-o"])
            .arg(&out)
            .args(extra)
            .assert()
            .success();
        out
    };
    // One image: the same bytes with and without an explicit --frame 0.
    let one = encode(&[view(0)], &[], "one.codes");
    let framed = encode(&[view(0)], &["--frame", "0"], "framed.codes");
    assert_eq!(
        std::fs::read(&one).unwrap(),
        std::fs::read(&framed).unwrap()
    );
    // Three views: one scene whose slots name the images they came from. Each of view 0's
    // slots is kept or taken over by a later view's slot of the same object that draws it
    // better, so none is lost; later views add only what they alone show.
    let three = encode(&[view(0), view(1), view(2)], &[], "three.codes");
    let doc = inspect(&three);
    let sources: Vec<String> = doc["slots"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["source"].as_str().unwrap().to_string())
        .collect();
    let first = inspect(&one)["slots"].as_array().unwrap().len();
    let from_view_0 = sources
        .iter()
        .filter(|s| s.starts_with("view_000.png#"))
        .count();
    assert!(from_view_0 > 0 && from_view_0 <= first, "{sources:?}");
    assert!(
        sources.len() >= first,
        "a slot of view 0 was lost: {sources:?}"
    );
    assert!(
        sources.len() < 3 * first,
        "no slot was matched: {sources:?}"
    );
    // Same inputs, same bytes; --frame picks the cameras (here in a different spelling).
    let again = encode(
        &[view(0), view(1), view(2)],
        &["--frame", "0,1,2"],
        "again.codes",
    );
    assert_eq!(
        std::fs::read(&three).unwrap(),
        std::fs::read(&again).unwrap()
    );
}

/// Slots where the views agree (`--agreed-slots`): a refined multi-view encoding with and
/// without them is valid and byte-deterministic, `--fast` adds none unless told, and the added
/// slots, if kept, name where they came from.
#[test]
fn slots_where_the_views_agree_are_deterministic_and_off_with_fast() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let cameras = scene.join("transforms.json");
    let views: Vec<_> = (0..3)
        .map(|v| scene.join(format!("view_{v:03}.png")))
        .collect();
    let encode = |extra: &[&str], out: &str| {
        let out = dir.path().join(out);
        bin("colf-encode")
            .args(&views)
            .arg("--camera")
            .arg(&cameras)
            .args(["--slots", "4", "--tries", "1", "--refine", "4", "-o"])
            .arg(&out)
            .args(extra)
            .assert()
            .success();
        std::fs::read(out).unwrap()
    };
    let agreed = encode(&["--agreed-slots", "3"], "a.codes");
    assert_eq!(agreed, encode(&["--agreed-slots", "3"], "b.codes"));
    let doc = inspect(&dir.path().join("a.codes"));
    for slot in doc["slots"].as_array().unwrap() {
        let source = slot["source"].as_str().unwrap();
        assert!(
            source.starts_with("view_00") || source.starts_with("agreed#"),
            "{source}"
        );
    }
    encode(&["--agreed-slots", "0"], "none.codes");
    // The default adds up to three.
    assert_eq!(agreed, encode(&[], "default.codes"));
    // --fast: one pass, nothing added, whatever the default.
    let fast = |extra: &[&str], out: &str| {
        let out = dir.path().join(out);
        bin("colf-encode")
            .args(&views)
            .arg("--camera")
            .arg(&cameras)
            .args(["--fast", "-o"])
            .arg(&out)
            .args(extra)
            .assert()
            .success();
        std::fs::read(out).unwrap()
    };
    assert_eq!(
        fast(&[], "fast.codes"),
        fast(&["--agreed-slots", "0"], "fast0.codes")
    );
}

#[test]
fn several_images_need_their_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let (a, b) = (scene.join("view_000.png"), scene.join("view_001.png"));
    let cameras = scene.join("transforms.json");
    fails_with(
        bin("colf-encode").arg(&a).arg(&b).arg("--fast"),
        "encode",
        2,
        "need --camera",
    );
    // Views 0 and 1 with their cameras, and `extra`.
    let two_views = |extra: &[&str]| {
        let mut cmd = bin("colf-encode");
        cmd.arg(&a)
            .arg(&b)
            .arg("--camera")
            .arg(&cameras)
            .args(extra);
        cmd
    };
    fails_with(
        &mut two_views(&["--frame", "0", "--fast"]),
        "encode",
        2,
        "one frame per image",
    );
    fails_with(
        bin("colf-encode")
            .args(["-", "-", "--camera"])
            .arg(&cameras)
            .arg("--fast"),
        "encode",
        2,
        "stdin",
    );
    let out = dir.path().join("never.codes");
    fails_with(
        two_views(&["--frame", "0", "9", "--fast", "-o"]).arg(&out),
        "encode",
        1,
        "--frame 9 does not exist",
    );
    assert!(!out.exists(), "nothing written on failure");
}

#[test]
fn eval_encodes_the_input_views_together_and_scores_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path());
    let data = dir.path().join("data");
    let run = |extra: &[&str]| {
        let out = bin("colf-eval")
            .arg("--data")
            .arg(&data)
            .args(["--fast", "-q"])
            .args(extra)
            .output()
            .unwrap();
        assert!(out.status.success(), "{out:?}");
        serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
    };
    // The protocol's defaults, spelt out, change nothing.
    let plain = run(&[]);
    assert_eq!(run(&["--input-views", "0"]), plain);
    assert!(plain.get("one_slot_share").is_none(), "{plain}");
    // Only view 3 as the novel view.
    let view3 = run(&["--novel-views", "3"]);
    assert_eq!(view3["novel_views"], serde_json::json!([3]));
    assert_eq!(view3["input_psnr"], plain["input_psnr"]);
    let three = run(&["--input-views", "0,1,2", "--novel-views", "3"]);
    assert_eq!(three["input_views"], serde_json::json!([0, 1, 2]));
    let seen = three["objects_seen_twice"].as_u64().unwrap();
    assert!(seen >= 1, "{three}");
    let share = three["one_slot_share"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&share), "{three}");
    for name in ["psnr", "ssim", "input_psnr", "fg_ari", "nv_fg_ari"] {
        assert!(three[name].as_f64().is_some(), "{name}: {three}");
    }
    fails_with(
        bin("colf-eval")
            .arg("--data")
            .arg(&data)
            .args(["--fast", "-q", "--input-views", "0,7"]),
        "eval",
        1,
        "no input view 7",
    );
    fails_with(
        bin("colf-eval")
            .arg("--data")
            .arg(&data)
            .args(["--fast", "-q", "--input-views", "1,1"]),
        "eval",
        2,
        "named twice",
    );
}
