//! The `bgkmap` command line (being written).
pub mod plot;
pub fn main() -> std::process::ExitCode {
    std::process::ExitCode::SUCCESS
}
