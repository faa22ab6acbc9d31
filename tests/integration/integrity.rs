//! Damage and failure through the real server: a block with flipped bytes is found by
//! `bgkmap check` and answered DATA_LOSS by the server while other blocks keep serving; a full
//! disk (a file size limit, `RLIMIT_FSIZE`, on the server process) makes the map read-only with
//! a clear error, loses nothing acknowledged, keeps queries working, and ingest resumes once
//! space returns.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::io::pcd::write_pcd_binary;
use bgkmap::sim::{Lidar, simulate};
use common::{http_request, run_fail, run_ok, start_serve, start_serve_wrapped};
use std::path::Path;
use std::time::Duration;
use tonic::Code;

/// Thinned simulated scans (origin rounded to f32, as PCD readers take it), also written as PCD
/// files for offline builds.
fn scans(dir: &Path, n: usize) -> (Vec<pb::Scan>, Vec<String>) {
    std::fs::create_dir_all(dir.join("pcd")).unwrap();
    let (_, sims) = simulate(7, n, &Lidar::default());
    let mut files = Vec::new();
    let msgs = sims
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let points: Vec<[f32; 3]> = s.points_world.iter().step_by(4).copied().collect();
            let origin = s.origin.map(|v| f64::from(v as f32));
            let name = format!("pcd/{k:03}.pcd");
            let vp = [origin[0], origin[1], origin[2], 1.0, 0.0, 0.0, 0.0];
            std::fs::write(dir.join(&name), write_pcd_binary(&points, vp)).unwrap();
            files.push(name);
            pb::Scan::world("robot", k as u64 + 1, origin, &points)
        })
        .collect();
    (msgs, files)
}

fn xyz(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

/// Flips one byte inside a small block's data in the file itself; returns the block key.
fn flip_block_byte(path: &Path) -> [i32; 3] {
    let c = rusqlite::Connection::open(path).unwrap();
    let (x, y, z, data): (i32, i32, i32, Vec<u8>) = c
        .query_row(
            "SELECT bx, by, bz, data FROM blocks WHERE length(data) < 900 ORDER BY length(data) DESC LIMIT 1",
            [],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
        )
        .unwrap();
    c.execute_batch("PRAGMA wal_checkpoint(TRUNCATE)").unwrap();
    drop(c);
    let mut bytes = std::fs::read(path).unwrap();
    // Every copy of the block's bytes: SQLite leaves old copies of rows in pages it has freed
    // (a B-tree page split moves them), and which copy comes first in the file is chance.
    let copies: Vec<usize> = bytes
        .windows(data.len())
        .enumerate()
        .filter(|(_, w)| *w == data.as_slice())
        .map(|(at, _)| at)
        .collect();
    assert!(!copies.is_empty(), "block bytes in the file");
    for at in copies {
        bytes[at + data.len() / 2] ^= 0x40;
    }
    std::fs::write(path, bytes).unwrap();
    [x, y, z]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_block_is_found_by_check_and_answered_data_loss_by_the_server() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (msgs, _) = scans(dir, 3);
    let server = start_serve(&dir.join("data"), &[]);
    let mut c = MapServiceClient::connect(server.grpc_url()).await.unwrap();
    c.create_map(pb::CreateMapRequest { map: "m".into(), params: Some(pb::MapParams::default()) })
        .await
        .unwrap();
    for m in &msgs {
        c.insert_scan(pb::InsertScanRequest { map: "m".into(), scan: Some(m.clone()), wait_applied: true })
            .await
            .unwrap();
    }
    assert_eq!(server.terminate().code(), Some(0));
    run_ok(dir, ["check", "data/m.bgkmap"]);
    let [bx, by, bz] = flip_block_byte(&dir.join("data/m.bgkmap"));
    let err = run_fail(dir, ["check", "data/m.bgkmap"], &["damaged", "1 corrupt blocks"]);
    let out = String::from_utf8(common::run(dir, ["check", "data/m.bgkmap"]).stdout).unwrap();
    assert!(out.contains(&format!("corrupt block ({bx}, {by}, {bz}): checksum mismatch")), "{out}\n{err}");

    let server = start_serve(&dir.join("data"), &[]);
    let mut c = MapServiceClient::connect(server.grpc_url()).await.unwrap();
    let info = c.get_map(pb::GetMapRequest { map: "m".into() }).await.unwrap().into_inner();
    assert_eq!(info.corrupt_blocks, 1);
    assert!(info.read_only.contains("corrupt"), "{}", info.read_only);
    // Block (bx, by, bz) spans [8·b·0.1, 8·(b+1)·0.1) m per axis.
    let inside = [bx, by, bz].map(|b| (f64::from(b) * 0.8 + 0.4) as f32);
    let q = |p: [f32; 3]| pb::QueryPointsRequest { map: "m".into(), xyz_f32: xyz(&[p]), thresholds: None };
    let err = c.query_points(q(inside)).await.unwrap_err();
    assert_eq!(err.code(), Code::DataLoss, "{err:?}");
    assert!(err.message().contains(&format!("({bx}, {by}, {bz})")), "{}", err.message());
    let elsewhere = [inside[0] + 3.2, inside[1], inside[2]];
    let ok = c.query_points(q(elsewhere)).await.unwrap().into_inner();
    assert_eq!(ok.probability.len(), 1, "other blocks keep serving");
    let lo = inside.map(|v| f64::from(v) - 0.1);
    let hi = inside.map(|v| f64::from(v) + 0.1);
    let boxq =
        pb::QueryBoxRequest { map: "m".into(), min: lo.to_vec(), max: hi.to_vec(), ..Default::default() };
    assert_eq!(c.query_box(boxq).await.unwrap_err().code(), Code::DataLoss);
    // A ray from inside the damaged block; and one that stays clear of it is answered.
    let ray = |o: [f32; 3]| pb::Ray {
        origin: o.map(f64::from).to_vec(),
        direction: vec![0.0, 0.0, 1.0],
        max_range: 0.3,
    };
    let rays = |o| pb::CastRaysRequest {
        map: "m".into(),
        rays: vec![ray(o)],
        stop_at: pb::StopAt::Occupied as i32,
        thresholds: None,
    };
    assert_eq!(c.cast_rays(rays(inside)).await.unwrap_err().code(), Code::DataLoss);
    c.cast_rays(rays(elsewhere)).await.unwrap();
    let mut export = c.export(pb::ExportRequest { map: "m".into(), ..Default::default() }).await;
    if let Ok(stream) = &mut export {
        let first = stream.get_mut().message().await;
        assert!(first.is_err(), "export must not succeed");
    }
    let scan = pb::Scan::world("late", 1, [0.0; 3], &[[1.0, 0.0, 0.0]]);
    let err = c
        .insert_scan(pb::InsertScanRequest { map: "m".into(), scan: Some(scan), wait_applied: false })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::Unavailable, "{err:?}");
    assert!(err.message().contains("read-only"), "{}", err.message());
    let body = format!("{{\"points\": [[{}, {}, {}]]}}", inside[0], inside[1], inside[2]);
    let (code, text) = http_request(server.http_addr, "POST", "/v1/maps/m/query/points", body.as_bytes());
    assert!(code == 500 && text.contains("corrupt"), "{text}");
    let (code, text) = http_request(server.http_addr, "GET", "/readyz", b"");
    assert!(code == 503 && text.contains("degraded") && text.contains("map m"), "{text}");
    assert_eq!(http_request(server.http_addr, "GET", "/healthz", b"").0, 200);
    assert_eq!(server.terminate().code(), Some(0));
}

fn prlimit_available() -> bool {
    std::process::Command::new("prlimit").arg("--version").output().is_ok_and(|o| o.status.success())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_makes_the_map_read_only_and_ingest_resumes_when_space_returns() {
    assert!(prlimit_available(), "this test needs prlimit (util-linux)");
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let (msgs, files) = scans(dir, 40);
    // Files of the server may grow to 3 MB ("disk full" beyond); SIGXFSZ is ignored so the
    // write fails with EFBIG instead of killing the process.
    let wrapper =
        ["sh", "-c", "trap '' XFSZ; exec \"$@\"", "sh", "prlimit", "--fsize=3000000:unlimited", "--"];
    let server = start_serve_wrapped(&dir.join("data"), &["--write-retry-ms", "200"], &wrapper);
    let mut c = MapServiceClient::connect(server.grpc_url()).await.unwrap();
    c.create_map(pb::CreateMapRequest { map: "m".into(), params: Some(pb::MapParams::default()) })
        .await
        .unwrap();
    // Read-your-writes: every scan's blocks are written on its own, so the files grow steadily.
    let insert = |c: &mut MapServiceClient<_>, m: &pb::Scan| {
        let req = pb::InsertScanRequest { map: "m".into(), scan: Some(m.clone()), wait_applied: true };
        let mut c = c.clone();
        async move { c.insert_scan(req).await }
    };
    let mut next = 0;
    let failure = loop {
        assert!(next < msgs.len(), "the file size limit was never reached");
        match insert(&mut c, &msgs[next]).await {
            Ok(_) => next += 1,
            Err(e) => break e,
        }
    };
    eprintln!("after {next} scans: {}", failure.message());
    assert_eq!(failure.code(), Code::Unavailable, "{failure:?}");
    assert!(failure.message().contains("read-only"), "{}", failure.message());
    assert!(next >= 2, "only {next} scans fitted");
    let (code, text) = http_request(server.http_addr, "GET", "/readyz", b"");
    assert!(code == 503 && text.contains("degraded"), "{text}");
    // Queries keep working; ingest keeps being refused while the disk is full.
    let probe =
        pb::QueryPointsRequest { map: "m".into(), xyz_f32: xyz(&[[1.0, 1.0, 0.7]]), thresholds: None };
    c.query_points(probe.clone()).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(insert(&mut c, &msgs[next]).await.unwrap_err().code(), Code::Unavailable);
    // Space returns.
    let pid = server.pid().to_string();
    let st = std::process::Command::new("prlimit")
        .args(["--pid", &pid, "--fsize=unlimited:unlimited"])
        .status()
        .unwrap();
    assert!(st.success());
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while next < msgs.len() {
        match insert(&mut c, &msgs[next]).await {
            Ok(_) => next += 1,
            Err(e) if e.code() == Code::Unavailable && std::time::Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("ingest did not resume: {e:?}"),
        }
    }
    let last = pb::InsertScanRequest { map: "m".into(), scan: Some(msgs[0].clone()), wait_applied: true };
    assert!(!c.insert_scan(last).await.unwrap().into_inner().applied, "a duplicate");
    assert_eq!(http_request(server.http_addr, "GET", "/readyz", b"").0, 200);
    assert_eq!(server.terminate().code(), Some(0));
    let mut args: Vec<String> = vec!["build".into(), "--out".into(), "offline.bgkmap".into()];
    args.extend(files);
    run_ok(dir, &args);
    let offline = run_ok(dir, ["export", "offline.bgkmap", "--format", "csv"]);
    assert!(
        run_ok(dir, ["export", "data/m.bgkmap", "--format", "csv"]) == offline,
        "the map differs from the offline build"
    );
    run_ok(dir, ["check", "data/m.bgkmap"]);
}
