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
    assert!(raw.len() < 20 << 20, "default model is {} bytes", raw.len());
    // With an explicit path, the default lookup is bypassed.
    let explicit = colf::cli::model_path::resolve_model_path(Some("/x/m.safetensors")).unwrap();
    assert_eq!(explicit, std::path::PathBuf::from("/x/m.safetensors"));
}
