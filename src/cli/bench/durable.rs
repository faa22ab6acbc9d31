//! `bgkmap bench durable`: the figures of durable maps —
//! - durable ingest: scans of `--points` points acknowledged once journaled with fsync, over
//!   gRPC to an in-process server on loopback (one unary client; one `InsertScans` stream; four
//!   concurrent streams), and the rate at which they are integrated;
//! - restart: time and resident memory to open a data directory holding one map of `--blocks`
//!   blocks (in a fresh process);
//! - merge: the exact offline merge of two such maps.
//!
//! The server's limit of journaled-but-unintegrated scans is raised to hold a whole run, so the
//! acknowledged rate is the journal's; the integrated rate is what a long run sustains.
//! The data directory is created under `--dir` (default: the current directory, so fsync hits
//! the real disk, not a tmpfs) and removed afterwards. Measured figures only; nothing asserts.

use super::common::{Cleanup, loopback_server};
use super::maps::{merge, restart_in_child, scans_of, write_maps};
use crate::api::pb;
use crate::cli::serve::{ServerConfig, runtime, start};
use crate::core::RawScan;
use anyhow::{Context, Result, ensure};
use clap::Args;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct DurableBenchArgs {
    /// Scans per ingest run.
    #[arg(long, default_value_t = 300)]
    pub scans: usize,
    /// Points per scan.
    #[arg(long, default_value_t = 3500)]
    pub points: usize,
    /// Blocks per map in the restart and merge runs (0 skips them).
    #[arg(long, default_value_t = 100_000)]
    pub blocks: usize,
    /// Raw scans journaled in each of those maps.
    #[arg(long, default_value_t = 1000)]
    pub journal_scans: usize,
    /// Where to create the (temporary) data directory.
    #[arg(long, default_value = ".")]
    pub dir: PathBuf,
    /// Integration threads of the server (`threads_per_scan`: batches one scan per thread).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

type Client = pb::map_service_client::MapServiceClient<tonic::transport::Channel>;

/// Robots of the fleet run, one `InsertScans` stream each into one map.
const FLEET_STREAMS: usize = 4;

fn request(map: &str, source: &str, seq: u64, s: &RawScan) -> pb::InsertScanRequest {
    let scan = pb::Scan::world(source, seq, s.origin_world(), &s.points);
    pb::InsertScanRequest { map: map.into(), scan: Some(scan), wait_applied: false }
}

/// Seconds until `map` has integrated `scans` scans.
async fn until_applied(c: &mut Client, map: &str, scans: u64, t0: Instant) -> Result<f64> {
    loop {
        let info = c.get_map(pb::GetMapRequest { map: map.into() }).await?.into_inner();
        if info.scans >= scans {
            return Ok(t0.elapsed().as_secs_f64());
        }
        tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    }
}

async fn new_map(c: &mut Client, map: &str) -> Result<()> {
    c.create_map(pb::CreateMapRequest { map: map.into(), params: Some(pb::MapParams::default()) }).await?;
    Ok(())
}

/// (acknowledged scans/s, integrated scans/s) of the three ingest runs.
async fn ingest(addr: SocketAddr, scans: &[RawScan]) -> Result<Value> {
    let url = format!("http://{addr}");
    let mut c = Client::connect(url.clone()).await?.max_encoding_message_size(64 << 20);
    let n = scans.len() as u64;
    // One client, one scan at a time: every acknowledgement waits for its own fsync.
    new_map(&mut c, "unary").await?;
    let t0 = Instant::now();
    for (i, s) in scans.iter().enumerate() {
        c.insert_scan(request("unary", "r", i as u64 + 1, s)).await?;
    }
    let unary =
        (n as f64 / t0.elapsed().as_secs_f64(), n as f64 / until_applied(&mut c, "unary", n, t0).await?);
    // One stream: up to 32 scans in flight share their fsyncs.
    new_map(&mut c, "stream").await?;
    let reqs: Vec<_> =
        scans.iter().enumerate().map(|(i, s)| request("stream", "r", i as u64 + 1, s)).collect();
    let t0 = Instant::now();
    let summary = c.insert_scans(tokio_stream::iter(reqs)).await?.into_inner();
    ensure!(summary.applied == n, "stream journaled {} of {n}", summary.applied);
    let stream =
        (n as f64 / t0.elapsed().as_secs_f64(), n as f64 / until_applied(&mut c, "stream", n, t0).await?);
    // Four robots, one stream each, into one map.
    new_map(&mut c, "fleet").await?;
    let t0 = Instant::now();
    let mut tasks = Vec::new();
    for r in 0..FLEET_STREAMS {
        let reqs: Vec<_> = scans
            .iter()
            .enumerate()
            .map(|(i, s)| request("fleet", &format!("r{r}"), i as u64 + 1, s))
            .collect();
        let mut c = c.clone();
        tasks.push(tokio::spawn(async move { c.insert_scans(tokio_stream::iter(reqs)).await }));
    }
    for t in tasks {
        t.await.context("ingest task")??;
    }
    let fleet_n = FLEET_STREAMS as u64 * n;
    let fleet = (
        fleet_n as f64 / t0.elapsed().as_secs_f64(),
        fleet_n as f64 / until_applied(&mut c, "fleet", fleet_n, t0).await?,
    );
    Ok(json!({"unary": {"acked_per_s": unary.0, "applied_per_s": unary.1},
              "stream": {"acked_per_s": stream.0, "applied_per_s": stream.1},
              "four_streams": {"acked_per_s": fleet.0, "applied_per_s": fleet.1}}))
}

pub fn run(a: DurableBenchArgs) -> Result<()> {
    ensure!(a.scans > 0 && a.points > 0, "--scans and --points must be > 0");
    let root = a.dir.join(format!("bgkmap-bench-durable-{}", std::process::id()));
    std::fs::create_dir_all(root.join("ingest"))
        .with_context(|| format!("{}: cannot create", root.display()))?;
    let _cleanup = Cleanup(root.clone());
    let scans = scans_of(a.points, a.scans);
    let config = ServerConfig {
        // Room for every scan of a run, so acknowledgements measure the journal, not the
        // integration backlog (reported separately as the integrated rate).
        max_unapplied_scans: 8 * a.scans,
        // And room in the journal's queue for every scan the streams keep in flight, so they
        // never wait for room behind each other (with the default of 64, four streams of 32
        // did whenever fsync fell behind).
        queue_capacity: FLEET_STREAMS * crate::api::STREAM_WINDOW,
        threads_per_scan: a.threads.max(1),
        ..loopback_server(root.join("ingest"))
    };
    let ingest = runtime()?.block_on(async {
        let running = start(&config).await?;
        let r = ingest(running.grpc_addr, &scans).await;
        running.shutdown().await?;
        r
    })?;
    let mut v = json!({"bench": "durable", "scans": a.scans, "points_per_scan": a.points, "ingest": ingest,
                       "dir": std::fs::canonicalize(&root).unwrap_or(root.clone())});
    if a.blocks > 0 {
        // Map a alone in a data directory (the restart figure), map b beside it.
        let (dir_a, path_b) = (root.join("restart"), root.join("b.bgkmap"));
        std::fs::create_dir_all(&dir_a)?;
        let path_a = dir_a.join("a.bgkmap");
        v["write_maps_s"] = json!(write_maps(&path_a, &path_b, a.blocks, a.journal_scans, a.points)?);
        v["restart"] = restart_in_child(&dir_a)?;
        let (merge_s, merged_blocks) = merge(&path_a, &path_b, &root.join("merged.bgkmap"))?;
        v["merge"] = json!({"seconds": merge_s, "blocks": merged_blocks, "map_blocks": a.blocks,
                            "journal_scans_per_map": a.journal_scans});
    }
    if a.json {
        println!("{v}");
    } else {
        print_summary(&v);
    }
    Ok(())
}

fn print_summary(v: &Value) {
    let f = |p: &str| v.pointer(p).and_then(Value::as_f64).unwrap_or(f64::NAN);
    println!(
        "durable bench ({} scans of {} points; data in {}):",
        v["scans"], v["points_per_scan"], v["dir"]
    );
    for (name, key) in [
        ("1 client, InsertScan", "unary"),
        ("1 InsertScans stream", "stream"),
        ("4 streams, 1 map", "four_streams"),
    ] {
        println!(
            "  {name}: {:.0} scans/s acknowledged (durable, fsync), {:.0} scans/s integrated",
            f(&format!("/ingest/{key}/acked_per_s")),
            f(&format!("/ingest/{key}/applied_per_s"))
        );
    }
    if v.get("restart").is_some() {
        println!(
            "  restart, a map of {} blocks ({} journaled scans): open {:.2} s, resident memory {:.0} MB (+{:.0} MB)",
            v["merge"]["map_blocks"],
            v["restart"]["scans"],
            f("/restart/open_s"),
            f("/restart/rss_after_mb"),
            f("/restart/rss_after_mb") - f("/restart/rss_before_mb")
        );
        println!(
            "  exact offline merge of the two maps: {:.2} s ({} blocks)",
            f("/merge/seconds"),
            v["merge"]["blocks"]
        );
    }
}
