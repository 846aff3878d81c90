use clap::Parser;
use colf::cli::edit::{run, EditArgs};

fn main() {
    let args = EditArgs::parse();
    colf::cli::run("edit", || run(&args))
}
