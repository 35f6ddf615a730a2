use clap::Parser;

fn main() -> std::process::ExitCode {
    let args = cli::Cli::parse();
    cli::main_with("lbctl", args.global, cli::run(args))
}
