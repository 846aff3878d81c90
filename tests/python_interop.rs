//! A codes file written by Python's `safetensors` package is edited by every op of colf-edit and
//! read back by Python with the contract's names, shapes and metadata (tests/python/).
//! Needs `python3` with `numpy` and `safetensors` (`make test` installs them into target/py).

use std::process::Command;

#[test]
fn python_written_codes_survive_every_op() {
    let probe = Command::new("python3")
        .args(["-c", "import numpy, safetensors"])
        .output();
    match probe {
        Ok(o) if o.status.success() => {}
        _ => panic!(
            "this test needs python3 with numpy and safetensors: run it through `make test`, which puts them in target/py"
        ),
    }
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/codes_interop.py"
        ))
        .arg(env!("CARGO_BIN_EXE_colf-edit"))
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
