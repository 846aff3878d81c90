use clap::Parser;
use colf::cli::sheet::{run, SheetArgs};

fn main() {
    let args = SheetArgs::parse();
    colf::cli::run("sheet", || run(&args))
}
