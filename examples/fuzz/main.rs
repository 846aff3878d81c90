//! `make fuzz`: seeded, structure-aware fuzzing of every colf input parser, in-process.
//!
//! ```text
//! cargo build --release --example fuzz
//! target/release/examples/fuzz --iterations 100000 --seed 1 --parser all --corpus-out DIR
//! ```
//!
//! Each failing input (a panic, or more than 1 s) is written to `DIR/<parser>/` and the run
//! exits 1. The address space is capped at 4 GiB (`RLIMIT_AS`). See docs/fuzzing.md.

mod harness;

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Parser;

#[derive(Parser)]
#[command(about = "Fuzz colf's input parsers with seeded, structure-aware mutations")]
struct Args {
    /// Inputs per parser.
    #[arg(long, default_value_t = 10_000)]
    iterations: u64,
    /// Seed of the mutations (a run is reproducible from it).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// One of codes, model, transforms, uorf_rt, edits, png, plot, or all.
    #[arg(long, default_value = "all")]
    parser: String,
    /// Folder for the failing inputs (`<parser>/seed<S>-<index>.bin`).
    #[arg(long)]
    corpus_out: Option<PathBuf>,
}

fn peak_rss_mb() -> f64 {
    // SAFETY: getrusage fills a local struct.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) };
    usage.ru_maxrss as f64 / 1024.0
}

fn main() -> Result<()> {
    let args = Args::parse();
    harness::limit_memory().context("setting RLIMIT_AS")?;
    let parsers: Vec<&'static str> = if args.parser == "all" {
        harness::PARSERS.to_vec()
    } else {
        match harness::PARSERS.iter().find(|p| **p == args.parser) {
            Some(p) => vec![*p],
            None => bail!(
                "unknown parser `{}` (one of {} or all)",
                args.parser,
                harness::PARSERS.join(", ")
            ),
        }
    };
    let fuzzer = harness::Fuzzer::new()?;
    let start = Instant::now();
    println!(
        "{:<11} {:>9} {:>9} {:>8} {:>11} {:>9} {:>8}",
        "parser", "inputs", "errors", "failures", "slowest ms", "at index", "wall s"
    );
    let mut failed = 0;
    for parser in parsers {
        let t = Instant::now();
        let report = harness::with_silent_panics(|| {
            harness::fuzz_parser(&fuzzer, parser, args.seed, args.iterations)
        });
        println!(
            "{:<11} {:>9} {:>9} {:>8} {:>11.2} {:>9} {:>8.1}",
            parser,
            report.inputs,
            report.errors,
            report.failures.len(),
            report.slowest.as_secs_f64() * 1e3,
            report.slowest_index,
            t.elapsed().as_secs_f64()
        );
        for f in &report.failures {
            failed += 1;
            eprintln!("FAIL {} index {}: {}", f.parser, f.index, f.what);
            if let Some(dir) = &args.corpus_out {
                let dir = dir.join(f.parser);
                std::fs::create_dir_all(&dir)?;
                let path = dir.join(format!("seed{}-{}.bin", args.seed, f.index));
                std::fs::write(&path, &f.input)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
        }
    }
    println!(
        "total wall {:.1} s, peak RSS {:.0} MB, address-space limit {} GiB",
        start.elapsed().as_secs_f64(),
        peak_rss_mb(),
        harness::MEMORY_LIMIT_BYTES >> 30
    );
    if failed > 0 {
        bail!("{failed} failing inputs");
    }
    Ok(())
}
