use clap::Parser;
use colf::cli::eval::{run, EvalArgs};

fn main() {
    let args = EvalArgs::parse();
    colf::cli::run("eval", || run(&args))
}
