//! CLI tests of `colf-eval`: the real binary on PNGs written by colf's own encoders, stdin,
//! and the failure paths (one error line, exit 1; usage errors exit 2).

use assert_cmd::Command;
use colf::image_io::{encode_png_grey, encode_png_rgb};
use std::path::Path;

fn eval() -> Command {
    Command::cargo_bin("colf-eval").unwrap()
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> String {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p.to_str().unwrap().to_string()
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

/// Runs and checks the one-line error contract; returns the line.
fn fails_with(cmd: &mut Command, code: i32, needle: &str) -> String {
    let out = cmd.output().unwrap();
    assert_eq!(out.status.code(), Some(code), "{out:?}");
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains(needle), "stderr `{err}` lacks `{needle}`");
    if code == 1 {
        assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err}");
        assert!(err.starts_with("colf-eval: error: "), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    assert!(out.stdout.is_empty(), "data written on failure");
    err
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
            1,
            "/no/such/pred.png: cannot read",
        );
        fails_with(
            eval().args([sub, &truncated, &gt]),
            1,
            "trunc.png: not a valid PNG image",
        );
        fails_with(
            eval().args([sub, &gt, &garbage]),
            1,
            "garbage.png: not a valid PNG image",
        );
        let err = fails_with(eval().args([sub, &small, &gt]), 1, "is 12x16 but");
        assert!(
            err.contains("small.png") && err.contains("gt.png is 16x12"),
            "{err}"
        );
        // A usage error (issue 24).
        fails_with(eval().args([sub, "-", "-"]), 2, "cannot both be stdin");
    }
    fails_with(
        eval().args(["images", &tiny, &tiny]),
        1,
        "8x8 is smaller than the 11x11 SSIM window",
    );
}

#[test]
fn usage_errors_exit_2() {
    fails_with(eval().args(["images", "only-one.png"]), 2, "GT.png");
    fails_with(eval().args(["pixels", "a.png", "b.png"]), 2, "pixels");
    fails_with(&mut eval(), 2, "Usage");
    fails_with(
        eval().args(["masks", "a", "b", "c"]),
        2,
        "unexpected argument",
    );
}

#[test]
fn help_documents_the_json_of_both_modes() {
    let out = eval().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for needle in ["images", "masks", "printed as null", "11x11"] {
        assert!(text.contains(needle), "--help lacks `{needle}`");
    }
}
