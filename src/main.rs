fn main() -> std::process::ExitCode {
    bgkmap::cli::main()
}
