use std::fmt::Display;
use std::process::ExitCode;

use clap::Parser;
use sidecar::cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    sidecar::telemetry::init();
    match cli.command {
        Command::Merge(args) => finish(sidecar::merge::run(&args), |e| {
            (e.name(), ExitCode::FAILURE)
        }),
        Command::Init => finish(sidecar::init::run().map(|_| ()), |e| {
            (e.name(), e.exit_code())
        }),
        Command::Simulator(args) => exit(sidecar::simulator::run(&args.command)),
        Command::Agent(args) => exit(sidecar::agent::run(&args.command)),
        Command::Logcopy => finish(sidecar::logcopy::run().map(|_| ()), |e| {
            (e.name(), e.exit_code())
        }),
    }
}

fn exit(result: Result<sidecar::pair::PairOutcome, sidecar::pair::PairError>) -> ExitCode {
    match result {
        Ok(outcome) => outcome.exit_code(),
        Err(err) => report(&err, |e| (e.name(), e.exit_code())),
    }
}

fn finish<E: Display>(result: Result<(), E>, how: fn(&E) -> (&'static str, ExitCode)) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => report(&err, how),
    }
}

fn report<E: Display>(err: &E, how: fn(&E) -> (&'static str, ExitCode)) -> ExitCode {
    let (name, code) = how(err);
    eprintln!("lb-sidecar: {name}: {err}");
    code
}
