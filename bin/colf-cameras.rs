use clap::Parser;
use colf::cli::cameras::{run, CamerasArgs};

fn main() {
    let args = CamerasArgs::parse();
    colf::cli::run("cameras", || run(&args))
}
