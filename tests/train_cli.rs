//! colf-train on a tiny fixed dataset: the loss falls, a stopped run resumes exactly (same
//! weights as an uninterrupted run), SIGTERM checkpoints, and the log plots (one run or several
//! in one picture).

use assert_cmd::Command;
use std::path::Path;

mod common;

fn data(dir: &Path) -> std::path::PathBuf {
    let out = dir.join("data");
    Command::cargo_bin("colf-synth")
        .unwrap()
        .args([
            "--scenes", "2", "--size", "32", "--seed", "4", "-q", "--out",
        ])
        .arg(&out)
        .assert()
        .success();
    out
}

fn train(data: &Path, out: &Path, steps: u64, extra: &[&str]) {
    Command::cargo_bin("colf-train")
        .unwrap()
        .arg("--data")
        .arg(data)
        .arg("--out")
        .arg(out)
        .args(["--steps", &steps.to_string()])
        .args([
            "--batch", "2", "--rays", "128", "--lr", "3e-4", "--warmup", "5",
        ])
        .args(["--checkpoint-every", "5", "--print-every", "5"])
        .args(extra)
        .assert()
        .success();
}

fn log_losses(out: &Path) -> Vec<(u64, f64)> {
    let text = std::fs::read_to_string(format!("{}.log.jsonl", out.display())).unwrap();
    text.lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v.get("eval").is_none())
        .map(|v| (v["step"].as_u64().unwrap(), v["loss"].as_f64().unwrap()))
        .collect()
}

/// With slots absent beyond a tight reach, the mask loss leaves out the rays whose matched slot
/// is absent there (its log weight −∞): every step's loss is finite, and the model keeps the
/// reach in its config.
#[test]
fn a_slot_reach_trains_with_the_mask_loss() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let out = dir.path().join("m.safetensors");
    train(
        &data,
        &out,
        10,
        &[
            "--mask-weight",
            "0.5",
            "--set",
            "attention_frames=true",
            "--set",
            "slot_reach=0.4",
        ],
    );
    let losses = log_losses(&out);
    assert_eq!(losses.len(), 10);
    assert!(losses.iter().all(|(_, l)| l.is_finite()), "{losses:?}");
    let model = colf::model::Colf::load(&out).unwrap();
    assert_eq!(model.config().slot_reach, 0.4);
}

#[test]
fn loss_falls_on_a_tiny_fixed_set() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let out = dir.path().join("m.safetensors");
    train(&data, &out, 40, &[]);
    let losses = log_losses(&out);
    assert_eq!(losses.len(), 40);
    let mean = |s: &[(u64, f64)]| s.iter().map(|x| x.1).sum::<f64>() / s.len() as f64;
    let (first, last) = (mean(&losses[..5]), mean(&losses[35..]));
    assert!(last < 0.5 * first, "loss did not fall: {first} -> {last}");
    // Each step logs the part of its time spent in the decode kernel: some, never more than
    // the whole step.
    let text = std::fs::read_to_string(format!("{}.log.jsonl", out.display())).unwrap();
    for line in text.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        if v.get("eval").is_none() {
            let (kernel, step) = (
                v["decoder_s"].as_f64().unwrap(),
                v["seconds"].as_f64().unwrap(),
            );
            assert!(kernel > 0.0 && kernel <= step, "{line}");
        }
    }
    // The model file is a real model: it loads and encodes.
    colf::model::Colf::load(&out).unwrap();
}

#[test]
fn a_resumed_run_matches_an_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let straight = dir.path().join("a.safetensors");
    train(&data, &straight, 12, &["--keep-every", "6"]);
    // --keep-every kept the models of steps 6 and 12; the last is the final model.
    let kept = |step: u64| dir.path().join(format!("a.step{step}.safetensors"));
    assert!(colf::model::Colf::load(&kept(6)).is_ok());
    assert_eq!(
        std::fs::read(kept(12)).unwrap(),
        std::fs::read(&straight).unwrap()
    );
    assert!(!kept(5).exists());
    // Resuming the finished run trains nothing and leaves the model as it was; it does not
    // read the data (gone here) to find that out.
    let model_before = std::fs::read(&straight).unwrap();
    let moved = dir.path().join("data-moved");
    std::fs::rename(&data, &moved).unwrap();
    let done = Command::cargo_bin("colf-train")
        .unwrap()
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&straight)
        .args(["--steps", "12", "--resume"])
        .assert()
        .success();
    let stderr = String::from_utf8_lossy(&done.get_output().stderr).to_string();
    assert!(
        stderr.contains("is done (its checkpoint is at step 12 of 12)"),
        "{stderr}"
    );
    assert_eq!(std::fs::read(&straight).unwrap(), model_before);
    std::fs::rename(&moved, &data).unwrap();
    // `colf-train average` of the two kept models is a model; a model and a file that is not
    // one give one error line naming the file, exit 1, and no output.
    let mean = dir.path().join("mean.safetensors");
    Command::cargo_bin("colf-train")
        .unwrap()
        .arg("average")
        .args([kept(6), kept(12)])
        .arg("-o")
        .arg(&mean)
        .assert()
        .success();
    assert!(colf::model::Colf::load(&mean).is_ok());
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a model").unwrap();
    common::fails_with(
        Command::cargo_bin("colf-train")
            .unwrap()
            .arg("info")
            .arg(&junk),
        "train",
        1,
        "junk.safetensors",
    );
}

#[test]
fn sigterm_checkpoints_and_the_log_plots() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let out = dir.path().join("m.safetensors");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_colf-train"))
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&out)
        .args([
            "--steps",
            "100000",
            "--batch",
            "1",
            "--rays",
            "64",
            "--checkpoint-every",
            "100000",
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let log = format!("{}.log.jsonl", out.display());
    let started = std::time::Instant::now();
    while std::fs::read_to_string(&log).map_or(0, |t| t.lines().count()) < 3 {
        assert!(started.elapsed().as_secs() < 120, "training did not start");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let pid = child.id().to_string();
    assert!(std::process::Command::new("kill")
        .args(["-TERM", &pid])
        .status()
        .unwrap()
        .success());
    let status = child.wait().unwrap();
    // Checkpointed, and the exit status says the run was stopped (issue 24).
    assert_eq!(status.code(), Some(143), "{status:?}");
    let ckpt = std::fs::read(format!("{}.ckpt", out.display())).unwrap();
    let file = colf::tensorfile::TensorFile::parse(&ckpt, "ckpt").unwrap();
    let step: u64 = file.require_metadata("step").unwrap().parse().unwrap();
    assert!(step >= 3, "checkpoint at step {step}");
    let png = dir.path().join("curves.png");
    Command::cargo_bin("colf-train")
        .unwrap()
        .args(["plot", &log, "-o"])
        .arg(&png)
        .assert()
        .success();
    let img = colf::image_io::read_rgb(png.to_str().unwrap()).unwrap();
    assert_eq!((img.w, img.h), (1000, 700));
}

/// A small training log of `steps` steps whose loss starts at `loss0`, with one evaluation.
fn small_log(steps: u32, loss0: f64) -> String {
    let mut log = String::new();
    for i in 0..steps {
        let record = serde_json::json!({"step": i, "loss": loss0 / (1.0 + f64::from(i)),
            "psnr": 10.0 + f64::from(i), "obj_psnr": 8.0 + f64::from(i), "fg_share": 0.5,
            "fg_ari": null});
        log += &format!("{record}\n");
    }
    log + &format!(
        "{}\n",
        serde_json::json!({"step": steps, "eval": {"psnr": 20.0}})
    )
}

#[test]
fn several_logs_plot_in_one_picture() {
    let dir = tempfile::tempdir().unwrap();
    let fused = common::write(dir.path(), "fused.log.jsonl", small_log(30, 1.0).as_bytes());
    let reference = common::write(dir.path(), "ref.log.jsonl", small_log(20, 2.0).as_bytes());
    let png = dir.path().join("compare.png");
    common::bin("colf-train")
        .args([
            "plot",
            &fused,
            &reference,
            "--label",
            "fused",
            "--label",
            "reference",
        ])
        .args(["--width", "600", "--height", "400", "-o"])
        .arg(&png)
        .assert()
        .success();
    let img = colf::image_io::read_rgb(png.to_str().unwrap()).unwrap();
    assert_eq!((img.w, img.h), (600, 400));
    assert!(img.data.iter().any(|&v| v < 0.5), "blank plot");
    // Default labels, and a log from stdin beside a file.
    common::bin("colf-train")
        .args(["plot", &fused, "-", "-o"])
        .arg(&png)
        .write_stdin(small_log(5, 1.0))
        .assert()
        .success();
    // A bad log is named on one line; no output is written.
    let bad = common::write(dir.path(), "bad.log.jsonl", b"{\"step\":0}\nnot json\n");
    let missing = dir.path().join("none.png");
    common::fails_with(
        common::bin("colf-train")
            .args(["plot", &fused, &bad, "-o"])
            .arg(&missing),
        "train",
        1,
        "bad.log.jsonl: line 2: invalid JSON",
    );
    assert!(!missing.exists());
    // Usage errors (exit 2): labels that do not match the logs, too many logs, two stdins.
    let err = common::fails_with(
        common::bin("colf-train")
            .args(["plot", &fused, &reference, "--label", "fused", "-o"])
            .arg(&missing),
        "train",
        2,
        "--label given once for 2 LOGs",
    );
    assert!(err.starts_with("colf-train: error: "), "{err}");
    let nine = vec![fused.as_str(); 9];
    common::fails_with(
        common::bin("colf-train")
            .arg("plot")
            .args(&nine)
            .arg("-o")
            .arg(&missing),
        "train",
        2,
        "at most 8 logs",
    );
    common::fails_with(
        common::bin("colf-train")
            .args(["plot", "-", "-", "-o"])
            .arg(&missing),
        "train",
        2,
        "only one LOG can be stdin",
    );
    assert!(!missing.exists());
}

#[test]
fn set_with_init_keeps_or_grows_weights_and_refuses_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let start = dir.path().join("start.safetensors");
    train(&data, &start, 1, &[]);
    // A setting that keeps every tensor's shape carries into the new model.
    let out = dir.path().join("more-slots.safetensors");
    train(
        &data,
        &out,
        1,
        &[
            "--init",
            start.to_str().unwrap(),
            "--set",
            "default_slots=9",
        ],
    );
    assert_eq!(
        colf::model::Colf::load(&out)
            .unwrap()
            .config()
            .default_slots,
        9
    );
    // One that changes a shape is one clear error line, exit 1, and no output file.
    let wider = dir.path().join("wider.safetensors");
    let assert = Command::cargo_bin("colf-train")
        .unwrap()
        .arg("--data")
        .arg(&data)
        .arg("--init")
        .arg(&start)
        .args(["--set", "lfn_features=16", "--steps", "1", "--out"])
        .arg(&wider)
        .assert()
        .code(1);
    let stderr = String::from_utf8_lossy(&assert.get_output().stderr).to_string();
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("config change of an initial model"),
        "{stderr}"
    );
    assert!(stderr.contains("start.safetensors"), "{stderr}");
    assert!(!wider.exists());
    // A zero-background model grows: its background becomes fixed weights and the foreground
    // hypernetwork gets more hidden units (same function at the start; see model_core.rs).
    let zero_bg = dir.path().join("zero-bg.safetensors");
    train(&data, &zero_bg, 1, &["--zero-background"]);
    let grown = dir.path().join("grown.safetensors");
    train(
        &data,
        &grown,
        1,
        &[
            "--init",
            zero_bg.to_str().unwrap(),
            "--set",
            "static_background=true",
            "--set",
            "hypernet_hidden=96",
        ],
    );
    let grown = colf::model::Colf::load(&grown).unwrap();
    assert!(grown.config().static_background);
    assert_eq!(grown.config().hypernet_hidden, 96);
    assert!(grown
        .parameters()
        .keys()
        .all(|k| !k.starts_with("hypernet_bg.")));
    // Wider slots: by copies only to a whole multiple; fresh values to any width, recorded.
    let old_dim = colf::model::Colf::load(&start).unwrap().config().slot_dim;
    let wider_slots = format!("slot_dim={}", old_dim + 16);
    let start_arg = start.to_str().unwrap();
    refused(
        &data,
        dir.path(),
        &["--init", start_arg, "--set", &wider_slots],
        "whole multiple",
    );
    let fresh = dir.path().join("fresh.safetensors");
    train(
        &data,
        &fresh,
        1,
        &[
            "--init",
            start.to_str().unwrap(),
            "--set",
            &wider_slots,
            "--slot-values",
            "fresh",
        ],
    );
    let runs = info(&fresh)["training"].as_array().unwrap().clone();
    assert_eq!(runs.last().unwrap()["slot_values"], "fresh", "{runs:?}");
    assert!(runs[0].get("slot_values").is_none(), "{runs:?}");
    assert_eq!(
        colf::model::Colf::load(&fresh).unwrap().config().slot_dim,
        old_dim + 16
    );
}

/// `colf-train init --seed 3 -o path`: a fresh `small` model.
fn init_small_model(path: &Path) {
    Command::cargo_bin("colf-train")
        .unwrap()
        .args(["init", "--seed", "3", "-o"])
        .arg(path)
        .assert()
        .success();
}

#[test]
fn configure_keeps_the_weights_and_sets_the_default_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let start = dir.path().join("start.safetensors");
    init_small_model(&start);
    let configured = dir.path().join("configured.safetensors");
    Command::cargo_bin("colf-train")
        .unwrap()
        .arg("configure")
        .arg(&start)
        .args([
            "--set",
            r#"inference={"slots":3,"tries":2,"refine":1,"refine_lr":0.02,"refine_frame_lr":0,"refine_rays":64}"#,
            "-o",
        ])
        .arg(&configured)
        .assert()
        .success();
    let (before, after) = (
        colf::model::Colf::load(&start).unwrap(),
        colf::model::Colf::load(&configured).unwrap(),
    );
    assert_eq!(before.parameters().len(), after.parameters().len());
    for (name, tensor) in before.parameters() {
        let same = after.parameters()[name]
            .eq(tensor)
            .unwrap()
            .flatten_all()
            .unwrap()
            .min(0)
            .unwrap()
            .to_scalar::<u8>()
            .unwrap();
        assert_eq!(same, 1, "{name} changed");
    }
    assert_ne!(before.identity().unwrap(), after.identity().unwrap());
    // colf-eval encodes as the model says unless told otherwise; --fast is one pass.
    let eval = |extra: &[&str]| -> serde_json::Value {
        let out = Command::cargo_bin("colf-eval")
            .unwrap()
            .arg("--data")
            .arg(&data)
            .arg("--model")
            .arg(&configured)
            .args(["--scenes", "1", "-q"])
            .args(extra)
            .output()
            .unwrap();
        assert!(out.status.success(), "{out:?}");
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let settings = |doc: &serde_json::Value| {
        (
            doc["slots"].as_u64().unwrap(),
            doc["tries"].as_u64().unwrap(),
            doc["refine_steps"].as_u64().unwrap(),
        )
    };
    let rates = |doc: &serde_json::Value| {
        (
            doc["refine"]["lr"].as_f64().unwrap(),
            doc["refine"]["frame_lr"].as_f64().unwrap(),
            doc["refine"]["rays"].as_u64().unwrap(),
        )
    };
    let configured_eval = eval(&[]);
    assert_eq!(settings(&configured_eval), (3, 2, 1));
    assert_eq!(rates(&configured_eval), (0.02, 0.0, 64));
    assert_eq!(
        rates(&eval(&["--refine-lr", "0.05", "--refine-rays", "32"])),
        (0.05, 0.0, 32)
    );
    assert_eq!(settings(&eval(&["--fast"])), (7, 1, 0));
    assert_eq!(
        settings(&eval(&["--refine", "0", "--slots", "4"])),
        (4, 2, 0)
    );
    // One member of the model's encoding changes alone, the rest kept.
    let retried = dir.path().join("retried.safetensors");
    Command::cargo_bin("colf-train")
        .unwrap()
        .arg("configure")
        .arg(&configured)
        .args(["--set", "inference.tries=3", "-o"])
        .arg(&retried)
        .assert()
        .success();
    let retried = colf::model::Colf::load(&retried).unwrap();
    let inference = retried.config().default_inference();
    assert_eq!(
        (inference.slots, inference.tries, inference.refine),
        (3, 3, 1)
    );
    assert_eq!(inference.refine_rays, Some(64));
    // A refused setting is one error line (returned) and no output.
    let refused = |model: &std::path::Path, setting: &str| -> String {
        let out = dir.path().join("refused.safetensors");
        let assert = Command::cargo_bin("colf-train")
            .unwrap()
            .arg("configure")
            .arg(model)
            .args(["--set", setting, "-o"])
            .arg(&out)
            .assert()
            .code(1);
        let stderr = String::from_utf8_lossy(&assert.get_output().stderr).to_string();
        assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
        assert!(!out.exists());
        stderr
    };
    // A setting that changes a tensor, naming the file.
    let stderr = refused(&start, "lfn_features=16");
    assert!(stderr.contains("start.safetensors"), "{stderr}");
    assert!(stderr.contains("tensors"), "{stderr}");
    // A member the model's settings refuse: the mask loss needs a static background.
    let stderr = refused(&configured, "inference.refine_mask=0.3");
    assert!(stderr.contains("static background"), "{stderr}");
}

#[test]
fn configure_half_stores_the_weight_matrices_in_half_precision_and_keeps_them_so() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let start = dir.path().join("start.safetensors");
    init_small_model(&start);
    let configure = |from: &Path, to: &Path, extra: &[&str]| {
        Command::cargo_bin("colf-train")
            .unwrap()
            .arg("configure")
            .arg(from)
            .args(extra)
            .arg("-o")
            .arg(to)
            .assert()
            .success();
    };
    let half = dir.path().join("half.safetensors");
    configure(&start, &half, &["--half"]);
    let size = |p: &Path| std::fs::metadata(p).unwrap().len() as f64;
    let ratio = size(&half) / size(&start);
    assert!(
        (0.5..0.6).contains(&ratio),
        "half file {ratio} of the full one"
    );
    let (full_model, half_model) = (
        colf::model::Colf::load(&start).unwrap(),
        colf::model::Colf::load(&half).unwrap(),
    );
    assert!(!half_model.half_tensors().is_empty());
    for (name, tensor) in full_model.parameters() {
        let (a, b) = (values(&full_model, name), values(&half_model, name));
        let large = tensor.elem_count() >= colf::cli::train::HALF_MIN_VALUES;
        assert_eq!(half_model.half_tensors().contains(name), large, "{name}");
        if large {
            let rounded: Vec<f32> = a.iter().map(|&v| half::f16::from_f32(v).to_f32()).collect();
            assert_eq!(b, rounded, "{name}");
        } else {
            assert_eq!(a, b, "{name}");
        }
    }
    assert_ne!(
        full_model.identity().unwrap(),
        half_model.identity().unwrap()
    );
    // Configured again, the file stays half (the same bytes but for the config).
    let again = dir.path().join("again.safetensors");
    configure(
        &half,
        &again,
        &["--set", r#"inference={"slots":3,"tries":1,"refine":0}"#],
    );
    assert!((size(&again) - size(&half)).abs() < 1024.0);
    let again_model = colf::model::Colf::load(&again).unwrap();
    assert_eq!(again_model.half_tensors(), half_model.half_tensors());
    // The half model works in every stage, e.g. an evaluation.
    let out = Command::cargo_bin("colf-eval")
        .unwrap()
        .arg("--data")
        .arg(&data)
        .arg("--model")
        .arg(&again)
        .args(["--scenes", "1", "-q"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    // Neither --set nor --half: a usage error.
    Command::cargo_bin("colf-train")
        .unwrap()
        .arg("configure")
        .arg(&start)
        .arg("-o")
        .arg(dir.path().join("nothing.safetensors"))
        .assert()
        .code(2);
}

/// A training run on `data` with `extra` flags, refused in one line mentioning `needle`; no
/// model is written.
fn refused(data: &Path, dir: &Path, extra: &[&str], needle: &str) {
    let out = dir.join("refused.safetensors");
    common::fails_with(
        Command::cargo_bin("colf-train")
            .unwrap()
            .arg("--data")
            .arg(data)
            .arg("--out")
            .arg(&out)
            .args(["--steps", "2"])
            .args(extra),
        "train",
        1,
        needle,
    );
    assert!(!out.exists());
}

/// The values of parameter `name` of `model`, flattened.
fn values(model: &colf::model::Colf, name: &str) -> Vec<f32> {
    model.parameters()[name]
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

/// The JSON a `colf-train` command prints on stdout, after checking it succeeded.
fn json_of(cmd: &mut Command) -> serde_json::Value {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// `colf-train info` of a model file, parsed.
fn info(model: &Path) -> serde_json::Value {
    json_of(common::bin("colf-train").arg("info").arg(model))
}

/// A copy of the training set `data` with every mask file deleted: training never needs one.
fn unlabelled_copy(data: &Path, dir: &Path) -> std::path::PathBuf {
    let unlabelled = dir.join("unlabelled");
    for scene in std::fs::read_dir(data).unwrap() {
        let scene = scene.unwrap().path();
        if !scene.is_dir() {
            continue;
        }
        let copy = unlabelled.join(scene.file_name().unwrap());
        std::fs::create_dir_all(&copy).unwrap();
        for file in std::fs::read_dir(&scene).unwrap() {
            let file = file.unwrap().path();
            let name = file.file_name().unwrap().to_string_lossy().into_owned();
            if !name.ends_with(".mask.png") {
                std::fs::copy(&file, copy.join(&name)).unwrap();
            }
        }
    }
    std::fs::copy(data.join("dataset.json"), unlabelled.join("dataset.json")).unwrap();
    unlabelled
}

#[test]
fn proposals_stand_in_for_masks_and_no_mask_file_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let unlabelled = unlabelled_copy(&data, dir.path());
    let flags = [
        "--proposals",
        "--mask-weight",
        "0.1",
        "--attention-mask-weight",
        "0.1",
        "--object-fraction",
        "0.2",
        "--zero-background",
        "--set",
        "attention_frames=true",
    ];
    let on_unlabelled = dir.path().join("u.safetensors");
    train(&unlabelled, &on_unlabelled, 6, &flags);
    // The mask losses ran, on proposals.
    let log = std::fs::read_to_string(format!("{}.log.jsonl", on_unlabelled.display())).unwrap();
    let steps: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(steps.len(), 6);
    assert!(steps
        .iter()
        .all(|s| s["mask_loss"].as_f64().is_some_and(|v| v > 0.0)
            && s["attention_mask_loss"].as_f64().is_some_and(|v| v > 0.0)));
    let described = info(&on_unlabelled);
    let run = &described["training"][0];
    assert_eq!(run["masks_in_data"], false);
    assert_eq!(run["masks_used"], false);
    assert_eq!(run["proposals"], true);
    assert_eq!(run["losses"]["attention_mask"], 0.1);
    assert_eq!(described["masks_used"], false);

    // On the labelled original the masks are never opened: the same run gives the same weights.
    let on_labelled = dir.path().join("l.safetensors");
    train(&data, &on_labelled, 6, &flags);
    let (a, b) = (
        colf::model::Colf::load(&on_unlabelled).unwrap(),
        colf::model::Colf::load(&on_labelled).unwrap(),
    );
    for name in a.parameters().keys() {
        assert_eq!(values(&a, name), values(&b, name), "{name}");
    }
    assert_eq!(info(&on_labelled)["training"][0]["masks_in_data"], false);

    // `colf-train propose` writes the proposals as PNGs and scores them where there are masks.
    let written = dir.path().join("proposals");
    let summary = json_of(
        common::bin("colf-train")
            .args(["propose", "--data"])
            .arg(&data)
            .arg("--out")
            .arg(&written),
    );
    assert_eq!(summary["scenes"], 2);
    assert_eq!(summary["views"], summary["views_with_masks"]);
    let fg_ari = summary["fg_ari"].as_f64().unwrap();
    assert!((-1.0..=1.0).contains(&fg_ari), "{summary}");
    let png = written.join("scene_00000/view_000.proposal.png");
    let (w, h, _) = colf::image_io::read_labels(png.to_str().unwrap()).unwrap();
    assert_eq!((w, h), (32, 32));
    // Without masks there is nothing to score.
    let summary = json_of(
        common::bin("colf-train")
            .args(["propose", "--data"])
            .arg(&unlabelled),
    );
    assert_eq!(summary["views_with_masks"], 0);
    assert!(summary["fg_ari"].is_null());
    // A folder that is not a dataset is one error line.
    common::fails_with(
        common::bin("colf-train")
            .args(["propose", "--data"])
            .arg(dir.path().join("nowhere")),
        "train",
        1,
        "nowhere",
    );

    // Against a known background (a model whose background does not depend on the image, here
    // the zero-background model just trained): scored the same way, and trained on.
    let summary = json_of(
        common::bin("colf-train")
            .args(["propose", "--data"])
            .arg(&data)
            .arg("--against")
            .arg(&on_unlabelled),
    );
    assert_eq!(summary["views"], summary["views_with_masks"]);
    assert!(summary["fg_ari"].as_f64().is_some(), "{summary}");
    let against = dir.path().join("a.safetensors");
    let street = on_unlabelled.to_str().unwrap();
    train(
        &unlabelled,
        &against,
        5,
        &[
            "--proposals-against",
            street,
            "--mask-weight",
            "0.1",
            "--zero-background",
        ],
    );
    let run = &info(&against)["training"][0];
    assert_eq!(run["proposals"], true);
    assert_eq!(run["masks_in_data"], false);
    assert!(run.get("mask_claim").is_none(), "not written when off");

    // Claiming the unsure edges: fewer unsure pixels, the claim recorded, and refused without
    // proposals.
    let claimed = |px: &str| {
        json_of(
            common::bin("colf-train")
                .args(["propose", "--data"])
                .arg(&data)
                .args(["--claim", px]),
        )
    };
    let (plain, wide) = (claimed("0"), claimed("2"));
    let share = |s: &serde_json::Value, key: &str| s[key].as_f64().unwrap();
    assert!(share(&plain, "unsure") > 0.0, "{plain}");
    assert!(share(&wide, "unsure") < share(&plain, "unsure"), "{wide}");
    assert!(share(&wide, "objects_unsure") <= share(&plain, "objects_unsure"));
    let with_claim = dir.path().join("c.safetensors");
    train(
        &unlabelled,
        &with_claim,
        2,
        &["--proposals", "--mask-weight", "0.1", "--mask-claim", "1"],
    );
    assert_eq!(info(&with_claim)["training"][0]["mask_claim"], 1);
    refused(&data, dir.path(), &["--mask-claim", "1"], "--mask-claim");
    // A background that reads the image is no known background: one error line.
    common::fails_with(
        common::bin("colf-train")
            .args(["propose", "--data"])
            .arg(&data)
            .args(["--against", "models/default.safetensors"]),
        "train",
        1,
        "depends on the image",
    );
}

#[test]
fn training_without_masks_runs_and_the_model_records_how_it_was_trained() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let unlabelled = unlabelled_copy(&data, dir.path());
    let first = dir.path().join("first.safetensors");
    train(&unlabelled, &first, 6, &[]);
    let described = info(&first);
    let run = &described["training"][0];
    assert_eq!(described["training"].as_array().unwrap().len(), 1);
    assert_eq!(run["masks_in_data"], false);
    assert_eq!(run["masks_used"], false);
    assert_eq!(described["masks_used"], false);
    assert_eq!(run["engine"], "analytic");
    assert_eq!(run["scenes"], 2);
    assert_eq!(run["steps"], 6);
    assert_eq!(run["preset"], "small");
    assert!(run["init"].is_null());
    assert_eq!(run["losses"]["l2"], 1.0);
    assert_eq!(
        described["identity"],
        colf::model::Colf::load(&first).unwrap().identity().unwrap()
    );

    // A mask loss needs masks: on the unlabelled copy it is refused in one line.
    refused(&unlabelled, dir.path(), &["--mask-weight", "0.1"], "mask");

    // Fine-tuned from it with a mask loss on the labelled data: its records are the first
    // model's, then its own, which starts from the first model and used masks.
    let second = dir.path().join("second.safetensors");
    train(
        &data,
        &second,
        3,
        &["--init", first.to_str().unwrap(), "--mask-weight", "0.1"],
    );
    let described = info(&second);
    let runs = described["training"].as_array().unwrap();
    assert_eq!(runs.len(), 2);
    assert_eq!(runs[0], info(&first)["training"][0]);
    assert_eq!(runs[1]["init"], info(&first)["identity"]);
    assert_eq!(runs[1]["masks_used"], true);
    assert_eq!(runs[1]["losses"]["mask"], 0.1);
    assert_eq!(described["masks_used"], true);

    // --freeze keeps the named parameters as they were and is recorded; a prefix that names
    // no parameter is refused.
    let frozen = dir.path().join("frozen.safetensors");
    train(
        &unlabelled,
        &frozen,
        3,
        &["--init", first.to_str().unwrap(), "--freeze", "encoder."],
    );
    let (before, after) = (
        colf::model::Colf::load(&first).unwrap(),
        colf::model::Colf::load(&frozen).unwrap(),
    );
    let (mut kept, mut moved) = (0, 0);
    for name in before.parameters().keys() {
        let same = values(&before, name) == values(&after, name);
        if name.starts_with("encoder.") {
            assert!(same, "{name} changed although frozen");
            kept += 1;
        } else if !same {
            moved += 1;
        }
    }
    assert!(kept > 0 && moved > 0, "kept {kept}, moved {moved}");
    assert_eq!(info(&frozen)["training"][1]["frozen"][0], "encoder.");
    refused(
        &unlabelled,
        dir.path(),
        &["--freeze", "enc0der."],
        "`enc0der.`",
    );

    // --lr-scale is recorded; a prefix that names no trained parameter (here a frozen one)
    // is refused, and a factor that is not a positive number is a usage error.
    let scaled = dir.path().join("scaled.safetensors");
    train(
        &unlabelled,
        &scaled,
        2,
        &[
            "--init",
            first.to_str().unwrap(),
            "--lr-scale",
            "slot_attention.=4",
        ],
    );
    assert_eq!(
        info(&scaled)["training"][1]["lr_scale"],
        serde_json::json!([["slot_attention.", 4.0]])
    );
    assert!(info(&frozen)["training"][1].get("lr_scale").is_none());
    refused(
        &unlabelled,
        dir.path(),
        &["--freeze", "encoder.", "--lr-scale", "encoder.=2"],
        "`encoder.` (to scale its learning rate)",
    );
    for bad in [
        "encoder.=0",
        "encoder.=-1",
        "encoder.=nan",
        "encoder.",
        "=2",
    ] {
        common::fails_with(
            Command::cargo_bin("colf-train")
                .unwrap()
                .arg("--data")
                .arg(&unlabelled)
                .arg("--out")
                .arg(dir.path().join("bad.safetensors"))
                .args(["--lr-scale", bad]),
            "train",
            2,
            "lr-scale",
        );
    }

    // The bundled default model was trained without labels, and says so run by run; the
    // `supervised` model predates the records. A file that is not a model is one error.
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let default = info(&models.join("default.safetensors"));
    assert_eq!(default["masks_used"], false);
    let runs = default["training"].as_array().unwrap();
    assert!(runs.len() >= 2, "{default}");
    for run in runs {
        assert_eq!(run["masks_in_data"], false, "{run}");
        assert_eq!(run["proposals"], true, "{run}");
    }
    assert!(default["unrecorded_init"].is_null());
    // Issue 38: `supervised` predates the records; its recipe's six runs are written down,
    // marked as such, and say it used masks. `blender` was fine-tuned from it without labels:
    // its own run is its file's, the six before it the supervised model's, so it used masks.
    let supervised = info(&models.join("supervised.safetensors"));
    let runs = supervised["training"].as_array().unwrap();
    assert_eq!(runs.len(), 6, "{supervised}");
    assert!(runs.iter().all(|r| r["reconstructed"].is_string()));
    assert_eq!(supervised["masks_used"], true);
    assert!(supervised["unrecorded_init"].is_null());
    let blender = info(&models.join("blender.safetensors"));
    let runs = blender["training"].as_array().unwrap();
    assert_eq!(runs.len(), 7, "{blender}");
    assert_eq!(runs[..6], supervised["training"].as_array().unwrap()[..]);
    assert_eq!(runs[6]["init"], supervised["identity"]);
    assert_eq!(runs[6]["masks_used"], false);
    assert!(runs[6].get("reconstructed").is_none());
    assert_eq!(blender["masks_used"], true);
    assert!(blender["unrecorded_init"].is_null());
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a model").unwrap();
    let out = Command::cargo_bin("colf-train")
        .unwrap()
        .arg("info")
        .arg(&junk)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.lines().count() == 1 && err.contains("junk.safetensors"),
        "{err}"
    );
    assert!(out.stdout.is_empty());
}

/// Issue 38: a run that starts from a model with no records (here a `colf-train init` file)
/// cannot know what trained that model: `masks_used` is null, not false, and
/// `unrecorded_init` names the model; a model fine-tuned from it inherits both.
#[test]
fn a_run_from_a_model_with_no_records_says_its_start_is_unrecorded() {
    let dir = tempfile::tempdir().unwrap();
    let unlabelled = unlabelled_copy(&data(dir.path()), dir.path());
    let start = dir.path().join("start.safetensors");
    Command::cargo_bin("colf-train")
        .unwrap()
        .args(["init", "--seed", "5", "-o"])
        .arg(&start)
        .assert()
        .success();
    let start_id = info(&start)["identity"].clone();
    assert!(info(&start)["training"].is_null() && info(&start)["masks_used"].is_null());
    let first = dir.path().join("first.safetensors");
    train(&unlabelled, &first, 2, &["--init", start.to_str().unwrap()]);
    let described = info(&first);
    assert_eq!(described["training"].as_array().unwrap().len(), 1);
    assert_eq!(described["training"][0]["masks_used"], false);
    assert!(described["masks_used"].is_null(), "{described}");
    assert_eq!(described["unrecorded_init"], start_id);
    let second = dir.path().join("second.safetensors");
    train(
        &unlabelled,
        &second,
        2,
        &["--init", first.to_str().unwrap()],
    );
    let described = info(&second);
    assert_eq!(described["training"].as_array().unwrap().len(), 2);
    assert!(described["masks_used"].is_null());
    assert_eq!(described["unrecorded_init"], start_id);
}

/// `--context-views`: every scene encodes those views together (the City-Block recipe); the run
/// records them, evaluates from them, and bad lists are refused before anything is written.
#[test]
fn context_views_are_encoded_together_and_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let out = dir.path().join("context.safetensors");
    let eval_data = data.to_str().unwrap();
    train(
        &data,
        &out,
        4,
        &[
            "--context-views",
            "1,0",
            "--views",
            "3",
            "--mask-weight",
            "0.1",
            "--attention-mask-weight",
            "0.1",
            "--eval-data",
            eval_data,
            "--eval-every",
            "4",
            "--eval-scenes",
            "1",
        ],
    );
    let run = &info(&out)["training"][0];
    assert_eq!(run["context_views"], serde_json::json!([1, 0]), "{run}");
    assert_eq!(run["views"], 3);
    let log = std::fs::read_to_string(format!("{}.log.jsonl", out.display())).unwrap();
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.iter().filter(|l| l.get("eval").is_none()).count(), 4);
    assert!(lines
        .iter()
        .all(|l| l.get("eval").is_some() || l["loss"].as_f64().unwrap().is_finite()));
    // Evaluated from views 1 and 0 together: the other two views are the novel ones.
    let eval = lines
        .iter()
        .find_map(|l| l.get("eval"))
        .expect("an evaluation line");
    assert!(eval["objects_seen_twice"].as_u64().is_some(), "{eval}");
    // A run without context views records none (the field is not written).
    let plain = dir.path().join("plain.safetensors");
    train(&data, &plain, 1, &[]);
    assert!(info(&plain)["training"][0].get("context_views").is_none());

    refused(
        &data,
        dir.path(),
        &["--context-views", "0,0", "--views", "2"],
        "named twice",
    );
    refused(
        &data,
        dir.path(),
        &["--context-views", "0,1", "--views", "1"],
        "context views",
    );
    refused(
        &data,
        dir.path(),
        &["--context-views", "0,9", "--views", "2"],
        "no context view 9",
    );
}

/// The same steps give the same bytes on one thread and on three: the bundled model (whose
/// hypernetwork heads are large enough for their products to be split among threads), three
/// training steps, then its encoding of a view with a short refinement.
#[test]
fn training_and_encoding_give_the_same_bytes_on_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let data = data(dir.path());
    let run = |threads: &str| {
        let model = dir.path().join(format!("t{threads}.safetensors"));
        Command::cargo_bin("colf-train")
            .unwrap()
            .env("RAYON_NUM_THREADS", threads)
            .arg("--data")
            .arg(&data)
            .arg("--out")
            .arg(&model)
            .args(["--init", "models/default.safetensors", "--steps", "3"])
            .args([
                "--batch", "2", "--views", "2", "--rays", "64", "--lr", "1e-4",
            ])
            .assert()
            .success();
        let codes = dir.path().join(format!("t{threads}.codes"));
        let scene = data.join("scene_00000");
        Command::cargo_bin("colf-encode")
            .unwrap()
            .env("RAYON_NUM_THREADS", threads)
            .arg(scene.join("view_000.png"))
            .arg("--camera")
            .arg(scene.join("transforms.json"))
            .args(["--frame", "0", "--tries", "2", "--refine", "3", "--model"])
            .arg(&model)
            .arg("-o")
            .arg(&codes)
            .assert()
            .success();
        (std::fs::read(model).unwrap(), std::fs::read(codes).unwrap())
    };
    let (one, three) = (run("1"), run("3"));
    assert!(
        one.0 == three.0,
        "the trained model depends on the thread count"
    );
    assert!(one.1 == three.1, "the codes depend on the thread count");
}
