use clap::Parser;
use colf::cli::render::{run, RenderArgs};

fn main() {
    let args = RenderArgs::parse();
    colf::cli::run("render", || run(&args))
}
