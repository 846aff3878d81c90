//! `colf-eval` agrees with the reference implementations uORF reports (scikit-image's
//! `peak_signal_noise_ratio` and `structural_similarity`, scikit-learn's `adjusted_rand_score`)
//! to 1e-4 on random and structured image and mask pairs (tests/python/metrics_crosscheck.py).
//! Needs `python3` with numpy, scipy, Pillow, scikit-image and scikit-learn (`.ci/run` installs
//! them).

use std::process::Command;

#[test]
fn colf_eval_agrees_with_scikit_image_and_scikit_learn() {
    let probe = Command::new("python3")
        .args(["-c", "import numpy, scipy, PIL, skimage, sklearn"])
        .output();
    match probe {
        Ok(o) if o.status.success() => {}
        _ => panic!(
            "this test needs python3 with numpy, scipy, Pillow, scikit-image and scikit-learn: \
             pip install numpy scikit-image scikit-learn"
        ),
    }
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/metrics_crosscheck.py"
        ))
        .arg(env!("CARGO_BIN_EXE_colf-eval"))
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Every case ran: 8 image pairs × 2 metrics + 8 mask pairs × 2 metrics.
    assert_eq!(
        stdout.lines().filter(|l| l.ends_with(" ok")).count(),
        32,
        "{stdout}"
    );
}
