//! CLI tests of `colf-edit`: the real binary, real files, pipes and failure paths.

mod common;

use assert_cmd::Command;
use colf::codes::{Codes, Slot};
use common::{fails_with, write};
use glam::{DMat4, DVec3};

fn sample(k: usize, model: &str) -> Codes {
    Codes {
        slots: (0..k)
            .map(|i| Slot {
                latent: vec![i as f32; 8],
                slot_to_world: DMat4::from_translation(DVec3::new(i as f64, 0.0, 0.0)),
                mass: 0.05 * i as f32,
                source: format!("s.png#{i}"),
            })
            .collect(),
        background: vec![0.5; 8],
        model: model.into(),
    }
}

fn edit() -> Command {
    Command::cargo_bin("colf-edit").unwrap()
}

#[test]
fn pipe_edit_into_inspect() {
    let dir = tempfile::tempdir().unwrap();
    let edits = write(
        dir.path(),
        "e.json",
        br#"[{"op":"translate","slots":"all","by":[0,0,1]},{"op":"delete","slots":[0]},
             {"op":"translate","slots":{"near":[2.2,0.1,1],"within":0.5},"by":[0,4,0]}]"#,
    );
    let edited = edit()
        .arg(&edits)
        .write_stdin(sample(3, "m").to_bytes().unwrap())
        .output()
        .unwrap();
    assert!(edited.status.success(), "{edited:?}");
    let inspected = edit()
        .arg("--inspect")
        .write_stdin(edited.stdout)
        .output()
        .unwrap();
    assert!(inspected.status.success());
    let summary: serde_json::Value = serde_json::from_slice(&inspected.stdout).unwrap();
    assert_eq!(summary["num_slots"], 2);
    assert_eq!(summary["model"], "m");
    assert_eq!(
        summary["slots"][0]["origin"],
        serde_json::json!([1.0, 0.0, 1.0])
    );
    assert_eq!(summary["slots"][1]["source"], "s.png#2");
    // The slot named by where it stood moved, the other did not.
    assert_eq!(
        summary["slots"][1]["origin"],
        serde_json::json!([2.0, 4.0, 1.0])
    );
}

#[test]
fn files_in_files_out_and_determinism() {
    let dir = tempfile::tempdir().unwrap();
    let codes = write(dir.path(), "in.codes", &sample(4, "m").to_bytes().unwrap());
    let edits = write(
        dir.path(),
        "e.json",
        br#"{"ops":[{"op":"rotate","slots":[1],"axis":[0,0,1],"degrees":90},{"op":"prune","min_mass":0.07}]}"#,
    );
    let out1 = dir.path().join("o1.codes");
    let out2 = dir.path().join("o2.codes");
    for out in [&out1, &out2] {
        edit()
            .args([&edits, &codes, "-o"])
            .arg(out)
            .assert()
            .success();
    }
    let a = std::fs::read(&out1).unwrap();
    assert_eq!(a, std::fs::read(&out2).unwrap());
    let read = Codes::from_bytes(&a, "o1").unwrap();
    assert_eq!(read.slots.len(), 2); // masses .05 (slot 1) and 0 are pruned below .07
}

#[test]
fn bad_edits_write_nothing_and_keep_existing_output() {
    let dir = tempfile::tempdir().unwrap();
    let codes = write(dir.path(), "in.codes", &sample(2, "m").to_bytes().unwrap());
    let out = dir.path().join("out.codes");
    std::fs::write(&out, b"precious").unwrap();
    let cases: [(&[u8], &str); 6] = [
        (
            br#"[{"op":"translate","slots":[0],"by":[1,"x",0]}]"#,
            "op 0 (translate): field `by`",
        ),
        (
            br#"[{"op":"delete","slots":[0]},{"op":"keep","slots":[5]}]"#,
            "op 1 (keep): field `slots`: slot 5 does not exist",
        ),
        (br#"{"ops": [ {"op": "translate""#, "e.json: invalid JSON"),
        (
            br#"[{"op":"merge","from":"/no/such.codes"}]"#,
            "op 0 (merge): field `from`",
        ),
        (br#"[{"op":"explode"}]"#, "unknown op `explode`"),
        (
            br#"[{"op":"delete","slots":{"near":[0,3,0],"within":1}}]"#,
            "op 0 (delete): field `slots`: no slot within 1 of [0, 3, 0] (the nearest, slot 0, is 3.000 away)",
        ),
    ];
    for (text, needle) in cases {
        let edits = write(dir.path(), "e.json", text);
        fails_with(
            edit().args([&edits, &codes, "-o"]).arg(&out),
            "edit",
            1,
            needle,
        );
        assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    }
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 3, "temporary files left behind");
}

#[test]
fn bad_codes_are_one_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let edits = write(dir.path(), "e.json", b"[]");
    let good = sample(2, "m").to_bytes().unwrap();
    let truncated = write(dir.path(), "t.codes", &good[..good.len() - 5]);
    let garbage = write(dir.path(), "g.codes", b"\x01\x00\x00\x00\x00\x00\x00\x00{");
    let mut nan = sample(2, "m");
    nan.background[3] = 0.0;
    let mut nan_bytes = nan.to_bytes().unwrap();
    let n = nan_bytes.len();
    nan_bytes[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    let nan_path = write(dir.path(), "nan.codes", &nan_bytes);
    for (path, needle) in [
        (&truncated, "t.codes: not a valid safetensors file"),
        (&garbage, "g.codes: not a valid safetensors file"),
        (
            &nan_path,
            "nan.codes: tensor `slots` has a non-finite value",
        ),
    ] {
        let out = dir.path().join("o.codes");
        fails_with(
            edit().args([&edits, path, "-o"]).arg(&out),
            "edit",
            1,
            needle,
        );
        assert!(!out.exists());
    }
    fails_with(
        edit().args([&edits, "/no/such/file.codes", "-o", "x"]),
        "edit",
        1,
        "/no/such/file.codes: cannot read",
    );
}

#[test]
fn usage_errors_exit_2() {
    fails_with(edit().arg("--bogus"), "edit", 2, "--bogus");
    fails_with(
        edit().args(["a", "b", "c"]),
        "edit",
        2,
        "unexpected argument",
    );
}
