//! `colf-train`: make and train COLF models.

use clap::{Args, Parser, Subcommand};

/// Make and train COLF models.
#[derive(Parser, Debug)]
#[command(
    name = "colf-train",
    version,
    about = "Make and train colf models",
    long_about = "Make and train colf models (safetensors files holding every weight, the \
model's config and its identity; see docs/model.md).\n\n\
`colf-train init` writes a freshly initialised model: every weight is drawn from a random \
generator seeded by --seed and the weight's name, so the same preset and seed give a \
byte-identical file. Presets: small (trains on a 2-core CPU: 64x64 encoder input, 32x32 \
tokens, slot dimension 64, about 3 M parameters) and paper (the sizes of the COLF supplement: \
128x128 encoder input, slot dimension 128, light fields with 2 hidden layers of 256 units).",
    after_help = "Examples:\n  colf-train init --preset small --seed 0 -o models/default.safetensors\n  \
colf-train init --preset paper -o paper-init.safetensors"
)]
pub struct TrainArgs {
    #[command(subcommand)]
    pub command: TrainCommand,
}

/// The subcommands of colf-train.
#[derive(Subcommand, Debug)]
pub enum TrainCommand {
    /// Write a freshly initialised model.
    Init(InitArgs),
}

/// `colf-train init`.
#[derive(Args, Debug)]
#[command(
    about = "Write a freshly initialised colf model",
    long_about = "Write a freshly initialised colf model to OUT (atomically; `-` for stdout, \
refused on a terminal). The same --preset and --seed give a byte-identical file. The model's \
parameter count and identity are printed on stderr."
)]
pub struct InitArgs {
    /// Size preset.
    #[arg(long, value_name = "PRESET", value_parser = ["small", "paper"], default_value = "small")]
    pub preset: String,

    /// Seed of the weight initialisation.
    #[arg(long, default_value_t = 0, value_name = "S")]
    pub seed: u64,

    /// Where to write the model (`-`: stdout).
    #[arg(short, long, value_name = "MODEL")]
    pub output: String,
}
