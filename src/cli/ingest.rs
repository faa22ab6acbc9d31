//! `bgkmap ingest`: stream PCD files to a running server over gRPC.

use super::args::{ScanArgs, load_scan, progress};
use crate::api::pb;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct IngestArgs {
    /// gRPC address of the server (`http://127.0.0.1:50051` or `127.0.0.1:50051`).
    #[arg(long, default_value = "127.0.0.1:50051", env = "BGKMAP_SERVER")]
    pub server: String,
    /// Target map (created with default parameters if it does not exist).
    #[arg(long, default_value = "demo")]
    pub map: String,
    /// Source name of the scans; with the sequence number, their identity in the map.
    #[arg(long, default_value = "ingest")]
    pub source: String,
    /// Sequence number of the first file; the others follow in order.
    #[arg(long, default_value_t = 1)]
    pub first_seq: u64,
    #[command(flatten)]
    pub scan: ScanArgs,
    /// PCD files, sent in the order given.
    #[arg(required = true)]
    pub scans: Vec<PathBuf>,
}

pub fn run(a: IngestArgs) -> Result<()> {
    let url = if a.server.contains("://") { a.server.clone() } else { format!("http://{}", a.server) };
    super::serve::runtime()?.block_on(async {
        let mut client = pb::map_service_client::MapServiceClient::connect(url.clone())
            .await
            .with_context(|| format!("connecting to {url}"))?
            .max_encoding_message_size(256 << 20);
        let create = pb::CreateMapRequest { map: a.map.clone(), params: Some(pb::MapParams::default()) };
        match client.create_map(create).await {
            Ok(_) => eprintln!("created map {}", a.map),
            Err(s) if s.code() == tonic::Code::AlreadyExists => {}
            Err(s) => return Err(anyhow::anyhow!("creating map {}: {}", a.map, s.message())),
        }
        let bar = progress(a.scans.len() as u64, "ingest");
        let (mut applied, mut duplicates) = (0, 0);
        for (i, path) in a.scans.iter().enumerate() {
            let scan = load_scan(path, &a.scan)?;
            let seq = a.first_seq + i as u64;
            let scan = pb::Scan::world(&a.source, seq, scan.origin_world, &scan.points_world);
            let request = pb::InsertScanRequest { map: a.map.clone(), scan: Some(scan), wait_applied: false };
            let ack = client
                .insert_scan(request)
                .await
                .map_err(|s| anyhow::anyhow!("{}: {:?}: {}", path.display(), s.code(), s.message()))?
                .into_inner();
            if ack.applied {
                applied += 1
            } else {
                duplicates += 1
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        eprintln!("{}: {applied} scans acknowledged (durable), {duplicates} already in the map", a.map);
        Ok(())
    })
}
