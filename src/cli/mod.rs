//! Command-line definitions of every colf stage, and the glue that runs a stage body with the
//! project's conventions (one error line, exit codes 0/1/2). The man pages in `man/` are
//! generated from these definitions (`tests/man_pages.rs`), so they cannot drift from `--help`.

pub mod cameras;
pub mod edit;
pub mod encode;
pub mod eval;
pub mod render;
pub mod sheet;
pub mod synth;
pub mod train;

/// Runs the body of stage `colf-<stage>`: exit 0 on success; on error, one line
/// `colf-<stage>: error: <cause chain>` on stderr and exit 1. Usage errors are clap's (exit 2).
pub fn run(stage: &str, body: impl FnOnce() -> anyhow::Result<()>) -> ! {
    crate::alloc::tune_for_tensors();
    match body() {
        Ok(()) => std::process::exit(0),
        Err(err) => {
            // `{:#}` joins the context chain on one line: "file: what: why".
            let line = format!("{err:#}").replace('\n', " ");
            eprintln!("colf-{stage}: error: {line}");
            std::process::exit(1)
        }
    }
}

/// Every stage's clap command, by binary name: the man pages are generated from this list.
pub fn commands() -> Vec<clap::Command> {
    use clap::CommandFactory;
    vec![
        encode::EncodeArgs::command(),
        edit::EditArgs::command(),
        render::RenderArgs::command(),
        cameras::CamerasArgs::command(),
        eval::EvalArgs::command(),
        synth::SynthArgs::command(),
        train::TrainArgs::command(),
        sheet::SheetArgs::command(),
    ]
}
