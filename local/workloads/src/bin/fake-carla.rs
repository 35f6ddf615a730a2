//! `fake-carla`: a stand-in for `./CarlaUE4.sh` (see the crate README).

use std::process::ExitCode;

use fake_workloads::args::{parse_carla, Env, Parsed};

#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    fake_workloads::init_tracing();
    let args: Vec<String> = std::env::args_os()
        .skip(1)
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    match parse_carla(&args, &Env::from_process()) {
        Ok(Parsed::Help(text)) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Ok(Parsed::Run(cfg)) => ExitCode::from(fake_workloads::carla::run(cfg).await),
        Err(error) => {
            eprintln!("fake-carla: error: {error}");
            ExitCode::from(2)
        }
    }
}
