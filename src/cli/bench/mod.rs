//! `bgkmap bench`: measured figures (never timed tests). This module only names the
//! subcommands and hands each to its bench; what several benches share lives in [`common`],
//! so no bench imports this module or another bench's runner.

mod common;
#[cfg(feature = "server")]
mod durable;
mod ingest;
mod maps;
#[cfg(feature = "server")]
mod query;
#[cfg(feature = "server")]
mod query_net;
mod report;
mod scale;
#[cfg(feature = "server")]
mod server;
mod world;
#[cfg(feature = "zenoh")]
mod zenoh;

use anyhow::Result;
use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Scan integration (training data + evidence + map update); files are loaded before timing.
    Ingest(ingest::IngestArgs),
    /// The map server in-process on loopback: ingest, gRPC / HTTP query throughput and latency.
    #[cfg(feature = "server")]
    Server(server::ServerBenchArgs),
    /// The map server's zenoh session in-process on loopback: scans/s from several publishers,
    /// point-query throughput over zenoh next to gRPC.
    #[cfg(feature = "zenoh")]
    Zenoh(zenoh::ZenohBenchArgs),
    /// Durable maps: ingest acknowledged after fsync, restart time and memory of a large map,
    /// exact merge of two.
    #[cfg(feature = "server")]
    Durable(durable::DurableBenchArgs),
    /// Queries on a map of over a million cells (a simulated 64-beam drive): in-process, gRPC,
    /// HTTP and zenoh — batched points, single-point latency (gRPC also while ingesting), boxes, rays.
    #[cfg(feature = "server")]
    Query(query::QueryBenchArgs),
    /// Ingest and query time as the map grows from 10³ to 10⁶ blocks; memory per cell in RAM
    /// and on disk.
    Scale(scale::ScaleArgs),
    /// Exact offline merge of two large maps (half their blocks overlap).
    Merge(maps::MergeArgs),
    /// Opens a data directory as a restarting server does (a large generated map unless
    /// `--data-dir` is given): time and memory, in a fresh process.
    Restart(maps::RestartArgs),
    /// Every figure with a target (issue 6), each bench run in turn for some rounds, as the
    /// README's Markdown table: per figure the median, range and a verdict.
    Report(report::ReportArgs),
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Ingest(a) => ingest::run(a),
        #[cfg(feature = "server")]
        BenchCommand::Server(a) => server::run(a),
        #[cfg(feature = "zenoh")]
        BenchCommand::Zenoh(a) => zenoh::run(a),
        #[cfg(feature = "server")]
        BenchCommand::Durable(a) => durable::run(a),
        #[cfg(feature = "server")]
        BenchCommand::Query(a) => query::run(a),
        BenchCommand::Scale(a) => scale::run(a),
        BenchCommand::Merge(a) => maps::run_merge(a),
        BenchCommand::Restart(a) => maps::run_restart(a),
        BenchCommand::Report(a) => report::run(a),
    }
}
