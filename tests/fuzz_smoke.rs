//! A short run of the fuzz harness (`examples/fuzz/`, docs/fuzzing.md) per parser, and a replay
//! of every input that ever failed (`testdata/fuzz/<parser>/`).

#[path = "../examples/fuzz/harness.rs"]
mod harness;

use std::path::Path;

/// Inputs per parser: 3,000, a few seconds in all on 2 cores.
const SMOKE_INPUTS: u64 = 3_000;

#[test]
fn fuzz_smoke_and_fixture_replay() {
    harness::limit_memory().unwrap();
    let fuzzer = harness::Fuzzer::new().unwrap();
    let mut problems = Vec::new();
    let mut replayed = 0;
    harness::with_silent_panics(|| {
        for parser in harness::PARSERS {
            let report = harness::fuzz_parser(&fuzzer, parser, 20_261_124, SMOKE_INPUTS);
            assert_eq!(report.inputs, SMOKE_INPUTS);
            // The mutations must reach past the parsers' first checks: some inputs are refused.
            assert!(report.errors > 0, "{parser}: no input was refused");
            for f in report.failures {
                problems.push(format!("{parser} index {}: {}", f.index, f.what));
            }
            let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("testdata/fuzz")
                .join(parser);
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            for entry in entries {
                let path = entry.unwrap().path();
                let bytes = std::fs::read(&path).unwrap();
                let (result, _) = harness::check(parser, &bytes);
                replayed += 1;
                if let Err(what) = result {
                    problems.push(format!("{}: {what}", path.display()));
                }
            }
        }
    });
    assert!(
        problems.is_empty(),
        "fuzz failures:\n{}",
        problems.join("\n")
    );
    eprintln!("replayed {replayed} fixtures");
}
