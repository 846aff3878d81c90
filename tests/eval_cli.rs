//! CLI tests of `colf-eval`: the real binary on PNGs written by colf's own encoders, stdin,
//! and the failure paths (one error line, exit 1; usage errors exit 2).

mod common;

use assert_cmd::Command;
use colf::image_io::{encode_png_grey, encode_png_rgb};
use common::{fails_with, write};
use std::path::Path;

fn eval() -> Command {
    Command::cargo_bin("colf-eval").unwrap()
}

/// A 16x12 RGB test card: a horizontal ramp in red, vertical in green, constant blue.
fn card(offset: f32) -> Vec<f32> {
    let (w, h) = (16, 12);
    (0..w * h)
        .flat_map(|p| {
            let (x, y) = ((p % w) as f32, (p / w) as f32);
            [x / 15.0 + offset, y / 11.0, 0.25 + offset]
        })
        .collect()
}

/// Runs and parses the JSON line on stdout.
fn json(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "{out:?}");
    assert!(out.stderr.is_empty(), "{out:?}");
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 1, "not one line: {text}");
    serde_json::from_str(&text).unwrap()
}

#[test]
fn images_gives_psnr_and_ssim() {
    let dir = tempfile::tempdir().unwrap();
    let gt = write(dir.path(), "gt.png", &encode_png_rgb(16, 12, &card(0.0)));
    // +0.2 on R and B where that stays in range: a known error after 8-bit rounding.
    let shifted: Vec<f32> = card(0.0)
        .iter()
        .enumerate()
        .map(|(i, &v)| if i % 3 == 1 { v } else { (v + 0.2).min(1.0) })
        .collect();
    let pred = write(dir.path(), "pred.png", &encode_png_rgb(16, 12, &shifted));
    let scores = json(eval().args(["images", &pred, &gt]));
    let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as f64 / 255.0;
    let mse: f64 = shifted
        .iter()
        .zip(card(0.0))
        .map(|(&a, b)| (to8(a) - to8(b)).powi(2))
        .sum::<f64>()
        / shifted.len() as f64;
    let psnr = scores["psnr"].as_f64().unwrap();
    assert!((psnr - 10.0 * (1.0 / mse).log10()).abs() < 1e-5, "{scores}");
    let ssim = scores["ssim"].as_f64().unwrap();
    assert!(ssim > 0.0 && ssim < 1.0, "{scores}");
    // The metrics of a pair do not depend on the order PSNR-wise, and identical images
    // give PSNR null (infinite) and SSIM 1.
    let swapped = json(eval().args(["images", &gt, &pred]));
    assert_eq!(swapped["psnr"], scores["psnr"]);
    let same = json(eval().args(["images", &gt, &gt]));
    assert_eq!(same, serde_json::json!({"psnr": null, "ssim": 1.0}));
}

#[test]
fn images_and_masks_read_stdin() {
    let dir = tempfile::tempdir().unwrap();
    let png = encode_png_rgb(16, 12, &card(0.0));
    let gt = write(dir.path(), "gt.png", &png);
    let from_stdin = json(eval().args(["images", "-", &gt]).write_stdin(png));
    assert_eq!(from_stdin["psnr"], serde_json::Value::Null);
    let mask = encode_png_grey(4, 1, &[0, 1, 1, 2]);
    let gt_mask = write(dir.path(), "gt.mask.png", &mask);
    let scores = json(eval().args(["masks", &gt_mask, "-"]).write_stdin(mask));
    assert_eq!(scores, serde_json::json!({"ari": 1.0, "fg_ari": 1.0}));
}

#[test]
fn masks_give_ari_and_fg_ari() {
    let dir = tempfile::tempdir().unwrap();
    // 4x2 masks: the prediction splits the background in two but gets both objects right.
    let gt = write(
        dir.path(),
        "gt.mask.png",
        &encode_png_grey(4, 2, &[0, 0, 1, 1, 0, 0, 2, 2]),
    );
    let pred = write(
        dir.path(),
        "pred.mask.png",
        &encode_png_grey(4, 2, &[5, 6, 1, 1, 5, 6, 3, 3]),
    );
    let scores = json(eval().args(["masks", &pred, &gt]));
    assert_eq!(scores["fg_ari"], 1.0);
    // Contingency {2, 2, 2, 2}: Σ C(nij,2) = 4, GT rows {4, 2, 2} → 8, pred columns
    // {2, 2, 2, 2} → 4, C(8,2) = 28: (4 - 32/28) / (6 - 32/28) = 80/136.
    let ari = scores["ari"].as_f64().unwrap();
    assert!((ari - 80.0 / 136.0).abs() < 1e-12, "{scores}");
    // A ground truth with no foreground has no FG-ARI.
    let empty = write(dir.path(), "bg.mask.png", &encode_png_grey(4, 2, &[0; 8]));
    let scores = json(eval().args(["masks", &pred, &empty]));
    assert_eq!(scores["fg_ari"], serde_json::Value::Null);
    assert_eq!(scores["ari"], 0.0);
}

#[test]
fn bad_inputs_are_one_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let good = encode_png_rgb(16, 12, &card(0.0));
    let gt = write(dir.path(), "gt.png", &good);
    let truncated = write(dir.path(), "trunc.png", &good[..good.len() / 2]);
    let garbage = write(dir.path(), "garbage.png", b"GIF89a not a png");
    let small = write(dir.path(), "small.png", &encode_png_rgb(12, 16, &card(0.0)));
    let tiny = write(dir.path(), "tiny.png", &encode_png_rgb(8, 8, &[0.5; 192]));
    for sub in ["images", "masks"] {
        fails_with(
            eval().args([sub, "/no/such/pred.png", &gt]),
            "eval",
            1,
            "/no/such/pred.png: cannot read",
        );
        fails_with(
            eval().args([sub, &truncated, &gt]),
            "eval",
            1,
            "trunc.png: not a valid PNG image",
        );
        fails_with(
            eval().args([sub, &gt, &garbage]),
            "eval",
            1,
            "garbage.png: not a valid PNG image",
        );
        let err = fails_with(eval().args([sub, &small, &gt]), "eval", 1, "is 12x16 but");
        assert!(
            err.contains("small.png") && err.contains("gt.png is 16x12"),
            "{err}"
        );
        // A usage error (issue 24).
        fails_with(
            eval().args([sub, "-", "-"]),
            "eval",
            2,
            "cannot both be stdin",
        );
    }
    fails_with(
        eval().args(["images", &tiny, &tiny]),
        "eval",
        1,
        "8x8 is smaller than the 11x11 SSIM window",
    );
}

#[test]
fn usage_errors_exit_2() {
    fails_with(eval().args(["images", "only-one.png"]), "eval", 2, "GT.png");
    fails_with(
        eval().args(["pixels", "a.png", "b.png"]),
        "eval",
        2,
        "pixels",
    );
    fails_with(&mut eval(), "eval", 2, "Usage");
    fails_with(
        eval().args(["masks", "a", "b", "c"]),
        "eval",
        2,
        "unexpected argument",
    );
}

#[test]
fn help_documents_the_json_of_both_modes() {
    let out = eval().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for needle in [
        "images",
        "masks",
        "printed as null",
        "11x11",
        "models/uorf_eval_model.py",
        "background included",
        "nv_fg_ari",
        "object_psnr",
        "NAME_std",
        "NAME_seed_std",
        "--seeds",
        "--journal",
    ] {
        assert!(text.contains(needle), "--help lacks `{needle}`");
    }
}

/// A one-scene dataset of colf-synth (64², 4 views) in `dir/data`.
fn dataset(dir: &Path) -> std::path::PathBuf {
    common::synth_scene(dir, &["--seed", "3", "--split", "test"]);
    dir.join("data")
}

#[test]
fn dataset_scores_follow_the_published_definitions() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(dir.path());
    let renders = dir.path().join("renders");
    let doc = json(
        eval()
            .arg("--data")
            .arg(&data)
            .args(["--fast", "-q", "--renders"])
            .arg(&renders),
    );
    // NV-ARI is uORF's: the ARI of the full label maps (background included) of the novel
    // views; nv_fg_ari the FG-ARI of the same views.
    let labels =
        |p: std::path::PathBuf| colf::image_io::read_labels(p.to_str().unwrap()).unwrap().2;
    let (mut full, mut fg) = (Vec::new(), Vec::new());
    for v in 1..4 {
        let pred = labels(renders.join(format!("scene_00000_v{v}.mask.png")));
        let gt = labels(data.join(format!("scene_00000/view_{v:03}.mask.png")));
        full.push(colf::metrics::ari(&pred, &gt).unwrap());
        fg.extend(colf::metrics::fg_ari(&pred, &gt).unwrap());
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(
        (doc["nv_ari"].as_f64().unwrap() - mean(&full)).abs() < 1e-12,
        "{doc}"
    );
    assert!(
        (doc["nv_fg_ari"].as_f64().unwrap() - mean(&fg)).abs() < 1e-12,
        "{doc}"
    );
    assert_ne!(doc["nv_ari"], doc["nv_fg_ari"]);
    // One scene: every standard deviation over scenes is 0.
    for name in [
        "psnr",
        "ssim",
        "object_psnr",
        "background_psnr",
        "input_psnr",
        "ari",
        "fg_ari",
        "nv_ari",
        "nv_fg_ari",
    ] {
        assert_eq!(
            doc[format!("{name}_std")].as_f64(),
            Some(0.0),
            "{name}: {doc}"
        );
    }
}

#[test]
fn seeds_repeat_the_evaluation_and_report_the_spread() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(dir.path());
    let run = |extra: &[&str]| {
        json(
            eval()
                .arg("--data")
                .arg(&data)
                .args(["--fast", "-q"])
                .args(extra),
        )
    };
    // --seeds 1 is the plain evaluation.
    let plain = run(&[]);
    assert_eq!(run(&["--seeds", "1"]), plain);
    let two = run(&["--seeds", "2", "--seed", "5"]);
    assert_eq!(two["seeds"], 2);
    let per_seed = two["per_seed"].as_array().unwrap();
    assert_eq!(per_seed.len(), 2);
    assert_eq!(
        (per_seed[0]["seed"].as_u64(), per_seed[1]["seed"].as_u64()),
        (Some(5), Some(1005))
    );
    // The first run is the plain evaluation with its seed; the summary is the runs' mean.
    let seed5 = run(&["--seed", "5"]);
    assert_eq!(per_seed[0]["psnr"], seed5["psnr"]);
    let (a, b) = (
        per_seed[0]["psnr"].as_f64().unwrap(),
        per_seed[1]["psnr"].as_f64().unwrap(),
    );
    assert!(
        (two["psnr"].as_f64().unwrap() - (a + b) / 2.0).abs() < 1e-9,
        "{two}"
    );
    assert!((two["psnr_seed_std"].as_f64().unwrap() - (a - b).abs() / 2.0).abs() < 1e-9);
    assert_eq!(two["scenes"], 1);
    // Out of range: a usage error.
    fails_with(
        eval().arg("--data").arg(&data).args(["--seeds", "0"]),
        "eval",
        2,
        "--seeds",
    );
}

#[test]
fn a_journal_resumes_an_evaluation_stopped_part_way() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    Command::cargo_bin("colf-synth")
        .unwrap()
        .args([
            "--scenes", "3", "--seed", "3", "--split", "test", "-q", "--out",
        ])
        .arg(&data)
        .assert()
        .success();
    let journal = dir.path().join("test.journal");
    let run = |extra: &[&str]| {
        let mut cmd = eval();
        cmd.arg("--data")
            .arg(&data)
            .args(["--fast", "-q", "--per-scene"])
            .args(extra);
        json(&mut cmd)
    };
    let whole = run(&[]);
    let with_journal = run(&["--journal", journal.to_str().unwrap()]);
    assert_eq!(with_journal, whole);
    let text = std::fs::read_to_string(&journal).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4, "a header and a row a scene: {text}");
    // Stopped while writing scene 1's row: the header, scene 0's row and a torn line remain.
    let torn = format!("{}\n{}\n{}", lines[0], lines[1], &lines[2][..20]);
    std::fs::write(&journal, torn).unwrap();
    let resumed = eval()
        .arg("--data")
        .arg(&data)
        .args(["--fast", "--per-scene", "--journal"])
        .arg(&journal)
        .output()
        .unwrap();
    assert!(resumed.status.success(), "{resumed:?}");
    let progress = String::from_utf8(resumed.stderr).unwrap();
    assert!(progress.contains("1 scene scored before"), "{progress}");
    assert!(
        !progress.contains("1/3"),
        "scene 0 scored again: {progress}"
    );
    assert!(
        progress.contains("2/3") && progress.contains("3/3"),
        "{progress}"
    );
    let resumed: serde_json::Value = serde_json::from_slice(&resumed.stdout).unwrap();
    assert_eq!(
        resumed, whole,
        "a resumed evaluation prints what an unbroken one does"
    );
    assert_eq!(std::fs::read_to_string(&journal).unwrap(), text);
    // Another evaluation (one encoding try more) refuses the journal and leaves it as it is.
    fails_with(
        eval()
            .arg("--data")
            .arg(&data)
            .args(["--tries", "2", "--refine", "0", "--journal"])
            .arg(&journal),
        "eval",
        1,
        "belongs to another evaluation (encoding differs)",
    );
    assert_eq!(std::fs::read_to_string(&journal).unwrap(), text);
    // A file that is no journal is refused, untouched.
    let notes = dir.path().join("notes.txt");
    std::fs::write(&notes, "not a journal\n").unwrap();
    fails_with(
        eval()
            .arg("--data")
            .arg(&data)
            .args(["--fast", "--journal"])
            .arg(&notes),
        "eval",
        1,
        "line 1 is not a colf-eval journal's header",
    );
    assert_eq!(std::fs::read_to_string(&notes).unwrap(), "not a journal\n");
}
