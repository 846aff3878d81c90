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

/// How an encoding is fitted to its input image, shared by `colf-encode` and `colf-eval --data`.
#[derive(clap::Args, Debug, Clone)]
pub struct FitArgs {
    /// Encode N times (slot noise seeds S, S+1, ...) and keep the encoding that reconstructs the
    /// input image best.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub tries: usize,

    /// Refine the slot latents with N Adam steps on the input image (0: the encoder's latents).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub refine: usize,

    /// Learning rate of the refinement.
    #[arg(long, default_value_t = crate::refine::RefineOptions::default().lr, value_name = "LR", allow_negative_numbers = true)]
    pub refine_lr: f64,

    /// Pixels of the input image rendered per refinement step (all when the image has fewer).
    #[arg(long, default_value_t = crate::refine::RefineOptions::default().rays, value_name = "R")]
    pub refine_rays: usize,

    /// Pull toward the encoder's latents during refinement: W * mean((z - z0)^2).
    #[arg(long, default_value_t = crate::refine::RefineOptions::default().anchor_weight, value_name = "W", allow_negative_numbers = true)]
    pub refine_anchor: f64,

    /// Also move the slots' frame origins during refinement, with this learning rate (world
    /// units; 0: frames fixed).
    #[arg(long, default_value_t = crate::refine::RefineOptions::default().frame_lr, value_name = "LR", allow_negative_numbers = true)]
    pub refine_frame_lr: f64,
}

impl FitArgs {
    /// The refinement options; the pixel subsets are drawn from `seed`.
    pub fn options(&self, seed: u64) -> crate::refine::RefineOptions {
        crate::refine::RefineOptions {
            steps: self.refine,
            lr: self.refine_lr,
            rays: self.refine_rays,
            anchor_weight: self.refine_anchor,
            frame_lr: self.refine_frame_lr,
            seed,
        }
    }
}
