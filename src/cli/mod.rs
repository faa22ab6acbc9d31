//! The `bgkmap` command line: offline tools over map files (build, merge, check, retract,
//! repose, export, eval, bench, simulate) and the demo. Each subcommand is a thin layer over the library; errors are
//! reported once, here, with exit code 1 (2 for usage errors, from clap).

mod args;
mod bench;
mod build;
#[cfg(feature = "server")]
mod demo;
mod durable;
mod eval_cmd;
mod export;
mod heap;
#[cfg(feature = "server")]
mod ingest;
pub mod plot;
#[cfg(feature = "server")]
pub mod serve;
mod simulate;
mod slice;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Debug, Parser)]
#[command(
    name = "bgkmap",
    version,
    about = "Exact BGK occupancy maps: build, merge, export, evaluate, benchmark"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Integrate PCD scans, in the order given, into a new map file.
    Build(build::BuildArgs),
    /// Sum the evidence of several map files (exact; parameters must match; scans that several
    /// maps hold are counted once).
    Merge(build::MergeArgs),
    /// Verify a map file: block and journal checksums, SQLite structure.
    Check(durable::CheckArgs),
    /// Remove scans from a map file exactly (as if never integrated).
    Retract(durable::RetractArgs),
    /// Re-integrate scans of a map file under corrected poses, exactly.
    Repose(durable::ReposeArgs),
    /// Write a map's cells as CSV, OctoMap .bt or PLY, or one layer as a PNG picture.
    Export(export::ExportArgs),
    /// ROC / AUC of a map against a ground-truth OctoMap .bt.
    Eval(eval_cmd::EvalArgs),
    /// Benchmarks (integration time only; no file I/O in the timed part).
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Write simulated LiDAR scans (PCD with VIEWPOINT) and the analytic ground truth (.bt).
    Simulate(simulate::SimulateArgs),
    /// Start the server, stream a simulated robot's scans into map `demo`, print examples.
    #[cfg(feature = "server")]
    Demo(demo::DemoArgs),
    /// Stream PCD files to a running server (gRPC), with a progress bar.
    #[cfg(feature = "server")]
    Ingest(ingest::IngestArgs),
    /// Run the map server (gRPC and HTTP).
    #[cfg(feature = "server")]
    Serve(serve::ServeArgs),
}

pub fn main() -> ExitCode {
    heap::keep_freed_memory();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Build(a) => build::run_build(a),
        Command::Merge(a) => build::run_merge(a),
        Command::Check(a) => durable::run_check(a),
        Command::Retract(a) => durable::run_retract(a),
        Command::Repose(a) => durable::run_repose(a),
        Command::Export(a) => export::run(a),
        Command::Eval(a) => eval_cmd::run(a),
        Command::Bench(b) => bench::run(b),
        Command::Simulate(a) => simulate::run_simulate(a),
        #[cfg(feature = "server")]
        Command::Demo(a) => demo::run_demo(a),
        #[cfg(feature = "server")]
        Command::Serve(a) => serve::run(a),
        #[cfg(feature = "server")]
        Command::Ingest(a) => ingest::run(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
