use clap::Parser;
use colf::cli::train::{
    run_average, run_configure, run_info, run_plot, run_propose, run_training, TrainArgs,
    TrainCommand,
};

fn main() {
    let args = TrainArgs::parse();
    colf::cli::run("train", || match &args.command {
        Some(TrainCommand::Init(init)) => {
            let summary = colf::train::init::init_model_file(
                &init.preset,
                &init.config_overrides,
                init.seed,
                &init.output,
            )?;
            eprintln!("colf-train: {summary}");
            Ok(())
        }
        Some(TrainCommand::Plot(plot)) => run_plot(plot),
        Some(TrainCommand::Average(average)) => run_average(average),
        Some(TrainCommand::Configure(configure)) => run_configure(configure),
        Some(TrainCommand::Info(info)) => run_info(info),
        Some(TrainCommand::Propose(propose)) => run_propose(propose),
        None => run_training(&args.run),
    })
}
