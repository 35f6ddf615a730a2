use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = local_cli::Cli::parse();
    cli::main_with("lbctl local", args.global, local_cli::run(args))
}
