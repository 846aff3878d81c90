//! `colf-eval` agrees with the reference implementations uORF reports (scikit-image's
//! `peak_signal_noise_ratio` and `structural_similarity`, scikit-learn's `adjusted_rand_score`)
//! to 1e-4 on random and structured image and mask pairs, and that `colf-eval --data`'s ari,
//! fg_ari, nv_ari and nv_fg_ari (means and standard deviations over scenes) are those of uORF's
//! evaluation code recomputed with `adjusted_rand_score` from the renders it saved: NV-ARI of
//! the full label maps, background included, and on city streets with one car in view the FG-ARI
//! split by objects in view, and the novel views' PSNR over the ground-truth object pixels and
//! over the rest, recomputed with `peak_signal_noise_ratio` (tests/python/metrics_crosscheck.py).
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
    // Two scenes of colf-synth (64², 4 views) for the dataset scores.
    let data = dir.path().join("data");
    let synth = Command::new(env!("CARGO_BIN_EXE_colf-synth"))
        .args([
            "--scenes", "2", "-q", "--seed", "3", "--split", "test", "--out",
        ])
        .arg(&data)
        .output()
        .unwrap();
    assert!(synth.status.success(), "{synth:?}");
    // Two city-block streets whose first shows one car in every view (the second in none): the
    // FG-ARI split by objects in view, written for the first scene and the summary only.
    let streets = dir.path().join("streets");
    let synth = Command::new(env!("CARGO_BIN_EXE_colf-synth"))
        .args([
            "--preset",
            "city-block",
            "--scenes",
            "2",
            "-q",
            "--seed",
            "2",
            "--split",
            "test",
            "--out",
        ])
        .arg(&streets)
        .output()
        .unwrap();
    assert!(synth.status.success(), "{synth:?}");
    let out = Command::new("python3")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/python/metrics_crosscheck.py"
        ))
        .arg(env!("CARGO_BIN_EXE_colf-eval"))
        .arg(dir.path())
        .arg(&data)
        .arg(&streets)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Every case ran: 8 image pairs × 2 metrics + 8 mask pairs × 2 metrics; for each data set
    // 2 scenes × 4 segmentation scores and the summary's 4 means and 4 standard deviations, and
    // (2 scenes + the summary) × 2 region PSNRs; for the streets' split, the first scene's 2 × 3
    // fields and the summary's 2 × 3.
    assert_eq!(
        stdout.lines().filter(|l| l.ends_with(" ok")).count(),
        32 + 2 * (8 + 8 + 6) + 6 + 6,
        "{stdout}"
    );
    assert_eq!(
        stdout
            .lines()
            .filter(|l| l.starts_with("lone-") && l.ends_with(" ok"))
            .count(),
        12,
        "{stdout}"
    );
}
