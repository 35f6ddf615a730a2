use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = local_cli::Cli::parse();
    cli::telemetry(args.log_format, args.verbose);
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("lbctl local: cannot start the async runtime: {e}");
            return std::process::ExitCode::from(1);
        }
    };
    match runtime.block_on(local_cli::run(args)) {
        Ok(code) => std::process::ExitCode::from(code),
        Err(e) => {
            eprintln!("lbctl local: {}", cli::describe(&e));
            std::process::ExitCode::from(cli::exit_code(&e))
        }
    }
}
