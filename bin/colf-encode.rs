use clap::Parser;
use colf::cli::encode::{run, EncodeArgs};

fn main() {
    let args = EncodeArgs::parse();
    colf::cli::run("encode", || run(&args))
}
