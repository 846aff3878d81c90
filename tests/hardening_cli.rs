//! Regression tests of issue 24 ("Hardening"): absurd sizes, special output files, output name
//! clashes, signals, writers that must not write what readers refuse, numeric extremes,
//! decompression bombs, exit codes and error messages. Each test names the defect it guards.

mod common;

use colf::codes::{Codes, Slot};
use common::{bin, fails_with, write};
use glam::{DMat4, DVec3};
use rand::{Rng, SeedableRng};
use std::path::{Path, PathBuf};
use std::process::{Command as StdCommand, ExitStatus, Stdio};
use std::time::{Duration, Instant};

const GOOD_PNG: &str = "testdata/synth/clevr567_seed0_scene00000_view_000.png";

fn sample(k: usize, dim: usize) -> Codes {
    Codes {
        slots: (0..k)
            .map(|i| Slot {
                latent: vec![0.25; dim],
                slot_to_world: DMat4::from_translation(DVec3::new(i as f64, 0.0, 0.0)),
                mass: 0.5,
                source: format!("s.png#{i}"),
            })
            .collect(),
        background: vec![0.5; dim],
        model: "m".into(),
    }
}

fn codes_file(dir: &Path, name: &str, codes: &Codes) -> String {
    write(dir, name, &codes.to_bytes().unwrap())
}

fn temporaries(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".colf-tmp-"))
        .collect()
}

// ---- 1. colf-sheet sizes -------------------------------------------------------------------

#[test]
fn sheet_with_absurd_gap_or_columns_is_an_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.png");
    for (cols, gap, tiles) in [
        ("1", "2147483648", 1),
        ("4294967297", "4", 6),
        ("4294967297", "4", 2),
    ] {
        fails_with(
            bin("colf-sheet")
                .args(vec![GOOD_PNG; tiles])
                .args(["--cols", cols, "--gap", gap, "-o"])
                .arg(&out),
            "sheet",
            1,
            "pixels, more than the",
        );
        assert!(!out.exists(), "a sheet was written for --cols {cols}");
    }
}

// ---- 2. -o on special files ------------------------------------------------------------------

#[cfg(unix)]
#[test]
fn output_to_devices_and_fifos_is_written_through() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let edits = write(dir.path(), "e.json", b"[]");
    let codes = codes_file(dir.path(), "a.codes", &sample(2, 8));
    // A FIFO in a temporary folder first: its reader gets the codes, and it stays a FIFO.
    let fifo = dir.path().join("pipe");
    let c_path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o644) }, 0);
    let reader = {
        let fifo = fifo.clone();
        std::thread::spawn(move || std::fs::read(fifo).unwrap())
    };
    bin("colf-edit")
        .args([&edits, &codes, "-o"])
        .arg(&fifo)
        .timeout(Duration::from_secs(60))
        .assert()
        .success();
    let read = reader.join().unwrap();
    assert!(Codes::from_bytes(&read, "fifo").is_ok());
    assert!(std::fs::symlink_metadata(&fifo)
        .unwrap()
        .file_type()
        .is_fifo());
    // /dev/full: "no space", exit 1.
    fails_with(
        bin("colf-edit").args([&edits, &codes, "-o", "/dev/full"]),
        "edit",
        1,
        "No space left on device",
    );
    // /dev/null: accepted, and still a character device.
    bin("colf-edit")
        .args([&edits, &codes, "-o", "/dev/null"])
        .assert()
        .success();
    for dev in ["/dev/null", "/dev/full"] {
        let kind = std::fs::symlink_metadata(dev).unwrap().file_type();
        assert!(kind.is_char_device(), "{dev} is no longer a device");
    }
    assert!(temporaries(dir.path()).is_empty());
}

// ---- 3. render output names ------------------------------------------------------------------

/// A codes file of the bundled model (one encoder pass of the test image) in `dir`.
fn model_codes(dir: &Path) -> PathBuf {
    let out = dir.join("scene.codes");
    bin("colf-encode")
        .args([GOOD_PNG, "--fast", "-o"])
        .arg(&out)
        .assert()
        .success();
    out
}

fn cameras(dir: &Path, frames: usize, size: u32) -> PathBuf {
    let out = dir.join("cameras.json");
    bin("colf-cameras")
        .args(["orbit", "--frames", &frames.to_string()])
        .args(["--size", &size.to_string(), "-o"])
        .arg(&out)
        .assert()
        .success();
    out
}

#[test]
fn render_outputs_that_would_overwrite_each_other_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let codes = model_codes(dir.path());
    let text = std::fs::read_to_string(cameras(dir.path(), 2, 8)).unwrap();
    let text =
        text.replacen("frame_0000.png", "x.png", 1)
            .replacen("frame_0001.png", "x.mask.png", 1);
    let clash = write(dir.path(), "clash.json", text.as_bytes());
    let out = dir.path().join("out");
    fails_with(
        bin("colf-render")
            .arg(&codes)
            .args(["--cameras", &clash, "--masks", "--out"])
            .arg(&out),
        "render",
        1,
        "frames 0 and 1 would both write `x.mask.png`",
    );
    assert!(!out.exists() || std::fs::read_dir(&out).unwrap().count() == 0);
    fails_with(
        bin("colf-render")
            .arg(&codes)
            .args(["--cameras", &clash, "--out", ""]),
        "render",
        2,
        "--out",
    );
}

// ---- 4. signals --------------------------------------------------------------------------------

/// Runs `cmd`, sends `signal` after `delay` (or lets it finish), and returns its status.
fn interrupt(cmd: &mut StdCommand, delay: Duration, signal: &str) -> ExitStatus {
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while started.elapsed() < delay {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let pid = child.id().to_string();
    let _ = StdCommand::new("kill")
        .args([&format!("-{signal}"), &pid])
        .stderr(Stdio::null())
        .status();
    child.wait().unwrap()
}

/// An interrupted stage exits 130 (SIGINT) or 143 (SIGTERM), or was done before the signal
/// came; killed before its handler was installed, the signal's default action ends it.
fn assert_interrupted_status(status: ExitStatus, signal: &str) {
    use std::os::unix::process::ExitStatusExt;
    let (code, number) = match signal {
        "INT" => (130, libc::SIGINT),
        _ => (143, libc::SIGTERM),
    };
    assert!(
        status.code() == Some(code) || status.success() || status.signal() == Some(number),
        "SIG{signal}: {status:?}"
    );
}

/// Kill points drawn from a fixed seed, alternating SIGINT and SIGTERM.
fn kill_points(seed: u64, count: usize, max: Duration) -> Vec<(Duration, &'static str)> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    (0..count)
        .map(|i| {
            let ms = rng.random_range(0..max.as_millis() as u64);
            (
                Duration::from_millis(ms),
                if i % 2 == 0 { "INT" } else { "TERM" },
            )
        })
        .collect()
}

/// Every file in `dir` is byte-identical to the file of the same name in `reference` (outputs
/// are deterministic, so a finished output equals the reference and a partial one would not).
fn assert_outputs_complete(dir: &Path, reference: &Path) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap();
        let expected = std::fs::read(reference.join(name))
            .unwrap_or_else(|_| panic!("unexpected file {}", path.display()));
        assert!(
            std::fs::read(&path).unwrap() == expected,
            "{} is partial",
            path.display()
        );
    }
}

#[test]
fn interrupted_render_leaves_no_partial_or_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let codes = model_codes(dir.path());
    let cams = cameras(dir.path(), 6, 192);
    let render = |out: &Path| {
        let mut cmd = StdCommand::new(env!("CARGO_BIN_EXE_colf-render"));
        cmd.arg(&codes)
            .arg("--cameras")
            .arg(&cams)
            .args(["--masks", "--exr", "-q", "--out"])
            .arg(out);
        cmd
    };
    let reference = dir.path().join("reference");
    assert!(render(&reference).status().unwrap().success());
    for (n, (delay, signal)) in kill_points(4, 6, Duration::from_millis(1500))
        .into_iter()
        .enumerate()
    {
        let out = dir.path().join(format!("out{n}"));
        // An earlier, finished output that the interrupted run must leave intact or rewrite whole.
        std::fs::create_dir_all(&out).unwrap();
        std::fs::copy(reference.join("frame_0003.exr"), out.join("frame_0003.exr")).unwrap();
        let status = interrupt(&mut render(&out), delay, signal);
        assert_interrupted_status(status, signal);
        assert!(temporaries(&out).is_empty(), "{:?}", temporaries(&out));
        assert_outputs_complete(&out, &reference);
        assert!(out.join("frame_0003.exr").exists());
    }
}

#[test]
fn interrupted_encode_and_edit_keep_the_old_output() {
    let dir = tempfile::tempdir().unwrap();
    let old = sample(1, 8).to_bytes().unwrap();
    // encode: a refined encoding takes seconds.
    let reference = dir.path().join("reference.codes");
    let encode = |out: &Path| {
        let mut cmd = StdCommand::new(env!("CARGO_BIN_EXE_colf-encode"));
        cmd.args([GOOD_PNG, "--tries", "2", "--refine", "20", "-o"])
            .arg(out);
        cmd
    };
    assert!(encode(&reference).status().unwrap().success());
    let fresh = std::fs::read(&reference).unwrap();
    let out = dir.path().join("out").join("scene.codes");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    for (delay, signal) in kill_points(7, 4, Duration::from_millis(3000)) {
        std::fs::write(&out, &old).unwrap();
        let status = interrupt(&mut encode(&out), delay, signal);
        assert_interrupted_status(status, signal);
        let now = std::fs::read(&out).unwrap();
        assert!(
            now == old || now == fresh,
            "partial codes after SIG{signal}"
        );
        assert!(temporaries(out.parent().unwrap()).is_empty());
    }
    // edit: 60,000 slots of 64 values (15 MB) duplicated to 120,000... would be refused, so
    // translate them all: the write is the long part.
    let big = codes_file(dir.path(), "big.codes", &sample(60_000, 64));
    let edits = write(
        dir.path(),
        "e.json",
        br#"[{"op":"translate","slots":"all","by":[0,0,1]}]"#,
    );
    let edit = |out: &Path| {
        let mut cmd = StdCommand::new(env!("CARGO_BIN_EXE_colf-edit"));
        cmd.args([&edits, &big, "-o"]).arg(out);
        cmd
    };
    let reference = dir.path().join("edited.codes");
    assert!(edit(&reference).status().unwrap().success());
    let fresh = std::fs::read(&reference).unwrap();
    for (delay, signal) in kill_points(8, 6, Duration::from_millis(400)) {
        std::fs::write(&out, &old).unwrap();
        let status = interrupt(&mut edit(&out), delay, signal);
        assert_interrupted_status(status, signal);
        let now = std::fs::read(&out).unwrap();
        assert!(
            now == old || now == fresh,
            "partial codes after SIG{signal}"
        );
        assert!(temporaries(out.parent().unwrap()).is_empty());
    }
    // A stage waiting on stdin exits 130 on SIGINT.
    let child = StdCommand::new(env!("CARGO_BIN_EXE_colf-edit"))
        .args([&edits, "-o"])
        .arg(&out)
        .stdin(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    StdCommand::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    let waited = child.wait_with_output().unwrap();
    assert_eq!(waited.status.code(), Some(130), "{waited:?}");
    assert_eq!(
        String::from_utf8_lossy(&waited.stderr).trim(),
        "colf-edit: interrupted by SIGINT"
    );
}

#[test]
fn interrupted_training_checkpoints_and_exits_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    bin("colf-synth")
        .args([
            "--scenes", "2", "--size", "32", "--seed", "4", "-q", "--out",
        ])
        .arg(&data)
        .assert()
        .success();
    for (n, (delay, signal)) in kill_points(11, 2, Duration::from_millis(3000))
        .into_iter()
        .enumerate()
    {
        let out = dir.path().join(format!("m{n}.safetensors"));
        let mut cmd = StdCommand::new(env!("CARGO_BIN_EXE_colf-train"));
        cmd.arg("--data")
            .arg(&data)
            .arg("--out")
            .arg(&out)
            .args(["--steps", "100000", "--batch", "1", "--rays", "64"])
            .args(["--checkpoint-every", "7"]);
        // At least one step first, then the seeded kill point.
        let log = format!("{}.log.jsonl", out.display());
        let mut child = cmd.stderr(Stdio::null()).spawn().unwrap();
        let started = Instant::now();
        while std::fs::read_to_string(&log).map_or(0, |t| t.lines().count()) < 1 {
            assert!(started.elapsed().as_secs() < 120, "training did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        std::thread::sleep(delay);
        StdCommand::new("kill")
            .args([&format!("-{signal}"), &child.id().to_string()])
            .status()
            .unwrap();
        let status = child.wait().unwrap();
        let expected = if signal == "INT" { 130 } else { 143 };
        assert_eq!(status.code(), Some(expected), "SIG{signal}");
        assert!(temporaries(dir.path()).is_empty());
        let ckpt = std::fs::read(format!("{}.ckpt", out.display())).unwrap();
        let file = colf::tensorfile::TensorFile::parse(&ckpt, "ckpt").unwrap();
        let step: u64 = file.require_metadata("step").unwrap().parse().unwrap();
        assert!(step >= 1, "checkpoint at step {step}");
        colf::model::Colf::load(&out).unwrap();
    }
}

// ---- 5, 6. writers refuse what readers refuse; rotations about huge axes --------------------

fn edit_with(dir: &Path, script: &str, codes: &str) -> std::process::Output {
    let edits = write(dir, "e.json", script.as_bytes());
    bin("colf-edit")
        .args([&edits, codes, "-o"])
        .arg(dir.join("out.codes"))
        .output()
        .unwrap()
}

#[test]
fn edits_that_readers_would_refuse_are_errors_naming_the_op() {
    let dir = tempfile::tempdir().unwrap();
    let codes = codes_file(dir.path(), "a.codes", &sample(7, 8));
    let dup = vec![r#"{"op":"duplicate","slots":"all"}"#; 14].join(",");
    for (script, needle) in [
        (
            r#"[{"op":"translate","slots":[0],"by":[1e39,0,0]}]"#.to_string(),
            "e.json: op 0 (translate): slot 0: slot_to_world: the origin",
        ),
        (
            r#"[{"op":"translate","slots":[0],"by":[1e308,0,0]},
                {"op":"translate","slots":[0],"by":[1e308,0,0]}]"#
                .to_string(),
            "e.json: op 0 (translate): slot 0",
        ),
        (
            format!("[{dup}]"),
            "e.json: op 13 (duplicate): 114688 slots is more than the 100000",
        ),
    ] {
        let out = edit_with(dir.path(), &script, &codes);
        common::one_line_error(&out, "edit", needle);
        assert!(!dir.path().join("out.codes").exists());
    }
}

#[test]
fn rotation_about_a_huge_axis_turns_the_slot() {
    let dir = tempfile::tempdir().unwrap();
    let codes = codes_file(dir.path(), "a.codes", &sample(2, 8));
    let out = edit_with(
        dir.path(),
        r#"[{"op":"rotate","slots":[1],"axis":[0,0,1e200],"degrees":90}]"#,
        &codes,
    );
    assert!(out.status.success(), "{out:?}");
    let edited = Codes::read(dir.path().join("out.codes").to_str().unwrap()).unwrap();
    let origin = edited.slots[1].slot_to_world.w_axis.truncate();
    assert!((origin - DVec3::Y).length() < 1e-6, "{origin:?}");
}

#[test]
fn inspect_reports_finite_norms_of_huge_latents() {
    let dir = tempfile::tempdir().unwrap();
    let mut codes = sample(1, 4);
    codes.slots[0].latent = vec![3e30; 4];
    let path = codes_file(dir.path(), "a.codes", &codes);
    let out = bin("colf-edit")
        .args(["--inspect", &path])
        .output()
        .unwrap();
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let norm = summary["slots"][0]["latent_norm"].as_f64().unwrap();
    assert!((norm / 6e30 - 1.0).abs() < 1e-6, "{norm}");
}

// ---- 7. decompression bombs -------------------------------------------------------------------

/// A valid PNG of a `side`² black RGB image: a few hundred kB that decode to side² pixels.
fn bomb(dir: &Path, side: u32) -> String {
    let mut png = Vec::new();
    use image::ImageEncoder;
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(
            &vec![0u8; side as usize * side as usize],
            side,
            side,
            image::ExtendedColorType::L8,
        )
        .unwrap();
    write(dir, "bomb.png", &png)
}

#[test]
fn decompression_bombs_are_refused_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let png = bomb(dir.path(), 9000);
    let needle = "the image is 9000x9000 pixels, more than the 67108864";
    fails_with(
        bin("colf-encode").args([&png, "--fast", "-o", "/dev/null"]),
        "encode",
        1,
        needle,
    );
    fails_with(
        bin("colf-sheet").args([&png, "-o", "/dev/null"]),
        "sheet",
        1,
        needle,
    );
}

// ---- 9. plot of extreme values -----------------------------------------------------------------

#[test]
fn plot_of_a_log_with_huge_psnr_ends() {
    let dir = tempfile::tempdir().unwrap();
    let log = write(
        dir.path(),
        "m.log.jsonl",
        b"{\"step\":0,\"loss\":1,\"psnr\":1e308}\n{\"step\":1,\"loss\":1,\"psnr\":-1e308}\n",
    );
    bin("colf-train")
        .args(["plot", &log, "-o"])
        .arg(dir.path().join("p.png"))
        .timeout(Duration::from_secs(60))
        .assert()
        .success();
}

// ---- 10. usage errors exit 2 -------------------------------------------------------------------

#[test]
fn usage_errors_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let codes = codes_file(dir.path(), "a.codes", &sample(1, 8));
    let cases: Vec<(&str, Vec<&str>)> = vec![
        ("edit", vec![]),
        ("edit", vec!["--inspect", &codes, &codes]),
        ("edit", vec!["-", "-"]),
        ("render", vec!["-", "--cameras", "-", "--out", "o"]),
        ("encode", vec!["-", "--camera", "-"]),
        (
            "render",
            vec![&codes, "--cameras", "c", "--out", "o", "--frames", "abc"],
        ),
        (
            "render",
            vec![&codes, "--cameras", "c", "--out", "o", "--adaptive", "nan"],
        ),
        ("render", vec![&codes, "--cameras", "c", "--out", ""]),
        ("cameras", vec!["orbit", "--frames", "0"]),
        ("cameras", vec!["orbit", "--size", "0"]),
        ("cameras", vec!["orbit", "--fov", "180"]),
        ("encode", vec![GOOD_PNG, "--prune", "2"]),
        ("encode", vec![GOOD_PNG, "--slots", "1025"]),
        ("encode", vec![GOOD_PNG, "--tries", "0"]),
        ("encode", vec![GOOD_PNG, "--refine-lr", "1e38"]),
        ("encode", vec![GOOD_PNG, "--refine-shadow-reach", "-1"]),
        ("encode", vec![GOOD_PNG, "--refine-shadow-reach", "nan"]),
        ("encode", vec![GOOD_PNG, "--refine-slot-reach", "-1"]),
        ("encode", vec![GOOD_PNG, "--refine-slot-reach", "inf"]),
        ("encode", vec![GOOD_PNG, "--refine-mask", "-1"]),
        ("encode", vec![GOOD_PNG, "--refine-mask", "nan"]),
        ("encode", vec![GOOD_PNG, "--refine-mask-claim", "-1"]),
        ("sheet", vec![GOOD_PNG, "--scale", "0", "-o", "s.png"]),
    ];
    for (stage, args) in cases {
        let out = bin(&format!("colf-{stage}"))
            .args(&args)
            .write_stdin("")
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "colf-{stage} {args:?}: {out:?}");
        assert!(out.stdout.is_empty());
        assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"));
    }
}

/// Refinement's mask loss needs a model with a static background: the bundled model reads its
/// background from the image, so the encoding is refused at once, with nothing written.
#[test]
fn a_refinement_mask_loss_needs_a_static_background() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scene.codes");
    fails_with(
        bin("colf-encode")
            .args([GOOD_PNG, "--refine-mask", "1", "-o"])
            .arg(&out),
        "encode",
        1,
        "needs a model with a static background",
    );
    assert!(!out.exists());
}

// ---- 11. messages name the file ----------------------------------------------------------------

#[test]
fn errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let cams = cameras(dir.path(), 2, 8);
    // Latents of another size than the model's.
    let mut codes = sample(1, 32);
    let model = colf::cli::model_path::load_model(None).unwrap();
    codes.model = model.identity().unwrap();
    let expected = format!(
        "short.codes: latents have 32 values, the model's slots have {}",
        model.config().slot_dim
    );
    let short = codes_file(dir.path(), "short.codes", &codes);
    let out = dir.path().join("out");
    fails_with(
        bin("colf-render")
            .args([&short, "--cameras", cams.to_str().unwrap(), "--out"])
            .arg(&out),
        "render",
        1,
        &expected,
    );
    // A focal length of 1e-300.
    let text = std::fs::read_to_string(&cams).unwrap();
    let value: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut value = value;
    value["fl_x"] = serde_json::json!(1e-300);
    if let Some(frames) = value["frames"].as_array_mut() {
        for f in frames {
            if f.get("fl_x").is_some() {
                f["fl_x"] = serde_json::json!(1e-300);
            }
        }
    }
    let tiny = write(dir.path(), "tiny.json", value.to_string().as_bytes());
    let codes = model_codes(dir.path());
    fails_with(
        bin("colf-render")
            .arg(&codes)
            .args(["--cameras", &tiny, "--out"])
            .arg(&out),
        "render",
        1,
        "tiny.json: frame 0: fl_x = 1e-300",
    );
    // A frame range beyond the file.
    let err = fails_with(
        bin("colf-render")
            .arg(&codes)
            .args([
                "--cameras",
                cams.to_str().unwrap(),
                "--frames",
                "1..100",
                "--out",
            ])
            .arg(&out),
        "render",
        1,
        "frames 1..100 reach beyond the 2 frames of the file",
    );
    assert!(err.contains("cameras.json"), "{err}");
    // A camera far away is written (and rendered), not blamed on the up vector.
    bin("colf-cameras")
        .args(["orbit", "--radius", "1e308", "--frames", "2", "-o"])
        .arg(dir.path().join("far.json"))
        .assert()
        .success();
}

// ---- 12. colf-train checks its output path first ------------------------------------------------

#[test]
fn training_into_a_missing_folder_fails_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    fails_with(
        bin("colf-train")
            .args(["--data", "testdata/synth", "--steps", "100000", "--out"])
            .arg(dir.path().join("no/such/m.safetensors")),
        "train",
        1,
        "no/such/m.safetensors: cannot write",
    );
    assert!(started.elapsed() < Duration::from_secs(30));
}
