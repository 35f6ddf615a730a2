//! `fake-evaluator`: a stand-in for `leaderboard_evaluator.py` (see the crate README).

use std::process::ExitCode;

use fake_workloads::args::{evaluator_usage, parse_evaluator, Env, Parsed};
use fake_workloads::faults::{run_child, CHILD_FLAG};

#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    fake_workloads::init_tracing();
    let args: Vec<String> = std::env::args_os()
        .skip(1)
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    if args.first().map(String::as_str) == Some(CHILD_FLAG) {
        return ExitCode::from(run_child(&args[1..]).await as u8);
    }
    let env = Env::from_process();
    match parse_evaluator(&args, &env) {
        Ok(Parsed::Help(text)) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Ok(Parsed::Run(cfg)) => ExitCode::from(fake_workloads::evaluator::run(cfg).await.code()),
        Err(error) => {
            // argparse's layout: usage, then `prog: error: ...`, exit 2.
            let leaderboard = if args.iter().any(|a| a.starts_with("--scenarios")) {
                lb_domain::results::Leaderboard::V1
            } else {
                lb_domain::results::Leaderboard::V2
            };
            eprintln!("{}", evaluator_usage(leaderboard));
            eprintln!("leaderboard_evaluator.py: error: {error}");
            ExitCode::from(2)
        }
    }
}
