use std::process::ExitCode;

use clap::Parser;
use sidecar::cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    sidecar::telemetry::init();
    let result = match cli.command {
        Command::Merge(args) => sidecar::merge::run(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("lb-sidecar: {}: {err}", err.name());
            ExitCode::FAILURE
        }
    }
}
