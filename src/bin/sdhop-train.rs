//! `sdhop-train`: the companion command-line tool (see [`sdhop::cli`]).

fn main() -> std::process::ExitCode {
    sdhop::cli::main()
}
