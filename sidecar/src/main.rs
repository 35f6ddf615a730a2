use std::fmt::Display;
use std::process::ExitCode;

use clap::Parser;
use sidecar::cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    sidecar::telemetry::init();
    match cli.command {
        Command::Merge(args) => finish(sidecar::merge::run(&args), |e| e.name()),
        Command::Init => finish(sidecar::init::run().map(|_| ()), |e| e.name()),
        Command::Simulator(args) => exit(sidecar::simulator::run(&args.command), |e| e.name()),
        Command::Agent(args) => exit(sidecar::agent::run(&args.command), |e| e.name()),
        Command::Logcopy => finish(sidecar::logcopy::run().map(|_| ()), |e| e.name()),
    }
}

fn exit<E: Display>(
    result: Result<sidecar::pair::PairOutcome, E>,
    name: fn(&E) -> &'static str,
) -> ExitCode {
    match result {
        Ok(outcome) => outcome.exit_code(),
        Err(err) => report(&err, name),
    }
}

fn finish<E: Display>(result: Result<(), E>, name: fn(&E) -> &'static str) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => report(&err, name),
    }
}

fn report<E: Display>(err: &E, name: fn(&E) -> &'static str) -> ExitCode {
    eprintln!("lb-sidecar: {}: {err}", name(err));
    ExitCode::FAILURE
}
