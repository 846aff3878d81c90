use clap::{CommandFactory, Parser};
use colf::cli::synth::SynthArgs;

fn main() {
    let args = SynthArgs::parse();
    if let Err(msg) = args.validate() {
        SynthArgs::command()
            .error(clap::error::ErrorKind::ValueValidation, msg)
            .exit();
    }
    colf::cli::run("synth", || colf::cli::synth::run(&args))
}
