//! Crash test: the real server is killed with SIGKILL at random moments (seeded) while several
//! sources stream scans into one map; after every restart the clients resend what was not
//! acknowledged. Every acknowledged scan must survive each crash, every scan must end up applied
//! exactly once, and the final map must export byte for byte like an offline `bgkmap build` of
//! the same scans.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::io::pcd::write_pcd_binary;
use bgkmap::sim::{Lidar, simulate};
use common::{ServeProcess, run_ok, start_serve};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

const SOURCES: usize = 3;
/// Enough that every kill still finds scans to interrupt: the random delay before each kill lets
/// a fast server acknowledge many scans (60 ran out once scans went straight into the map).
const SCANS_PER_SOURCE: usize = 120;
const KILLS: usize = 22;
/// Every n-th point of a simulated scan (small scans keep the debug build quick).
const THIN: usize = 8;

struct Scan {
    origin: [f64; 3],
    points: Vec<[f32; 3]>,
}

/// Source `s` sees the room of seed `s + 1`; scans are written as PCD files for the offline build.
fn scans(dir: &std::path::Path) -> (Vec<Vec<Scan>>, Vec<String>) {
    std::fs::create_dir_all(dir.join("pcd")).unwrap();
    let mut files = Vec::new();
    let all = (0..SOURCES)
        .map(|s| {
            let (_, sim) = simulate(s as u64 + 1, SCANS_PER_SOURCE, &Lidar::default());
            sim.into_iter()
                .enumerate()
                .map(|(k, sc)| {
                    let points: Vec<[f32; 3]> = sc.points_world.iter().step_by(THIN).copied().collect();
                    let name = format!("pcd/s{s}_{k:02}.pcd");
                    let vp = [sc.origin[0], sc.origin[1], sc.origin[2], 1.0, 0.0, 0.0, 0.0];
                    std::fs::write(dir.join(&name), write_pcd_binary(&points, vp)).unwrap();
                    files.push(name);
                    // PCD readers take VIEWPOINT as f32 (as PCL does): send the same origin.
                    Scan { origin: sc.origin.map(|v| f64::from(v as f32)), points }
                })
                .collect()
        })
        .collect();
    (all, files)
}

async fn client(server: &ServeProcess) -> Option<MapServiceClient<tonic::transport::Channel>> {
    let ep = tonic::transport::Endpoint::from_shared(server.grpc_url())
        .unwrap()
        .connect_timeout(Duration::from_secs(5));
    ep.connect().await.ok().map(MapServiceClient::new)
}

/// Sends the source's unacknowledged scans in order until all are acknowledged or the server
/// goes away. Returns how many were acknowledged.
async fn stream_source(
    server_url: String,
    source: usize,
    data: Arc<Vec<Vec<Scan>>>,
    unacked: Arc<Mutex<Vec<VecDeque<usize>>>>,
    wait_applied: bool,
) -> usize {
    let ep =
        tonic::transport::Endpoint::from_shared(server_url).unwrap().connect_timeout(Duration::from_secs(5));
    let Ok(channel) = ep.connect().await else { return 0 };
    let mut c = MapServiceClient::new(channel);
    let mut acked = 0;
    loop {
        let Some(k) = unacked.lock().unwrap()[source].front().copied() else { return acked };
        let s = &data[source][k];
        let scan = pb::Scan::world(&format!("robot{source}"), k as u64 + 1, s.origin, &s.points);
        let req = pb::InsertScanRequest { map: "m".into(), scan: Some(scan), wait_applied };
        match c.insert_scan(req).await {
            Ok(_) => {
                unacked.lock().unwrap()[source].pop_front();
                acked += 1;
            }
            Err(_) => return acked,
        }
    }
}

/// Scans of each source that the map holds (applied + journaled).
async fn held(server: &ServeProcess) -> Vec<u64> {
    let mut c = client(server).await.unwrap();
    let info = c.get_map(pb::GetMapRequest { map: "m".into() }).await.unwrap().into_inner();
    (0..SOURCES)
        .map(|s| {
            let name = format!("robot{s}");
            info.sources.iter().find(|x| x.source == name).map_or(0, |x| x.applied + x.pending)
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_at_random_moments_loses_nothing_acknowledged_and_counts_each_scan_once() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let data_dir = dir.join("data");
    let (data, files) = scans(dir);
    let data = Arc::new(data);
    let unacked = Arc::new(Mutex::new(vec![(0..SCANS_PER_SOURCE).collect::<VecDeque<_>>(); SOURCES]));
    let mut rng = ChaCha8Rng::seed_from_u64(0x0005_eed4);
    let mut kills_with_progress = 0;
    for cycle in 0..=KILLS {
        let server = start_serve(&data_dir, &[]);
        let mut c = client(&server).await.unwrap();
        if cycle == 0 {
            let create = pb::CreateMapRequest { map: "m".into(), params: Some(pb::MapParams::default()) };
            c.create_map(create).await.unwrap();
        }
        // Nothing acknowledged before this (re)start is missing.
        let acked: Vec<u64> = {
            let u = unacked.lock().unwrap();
            u.iter().map(|q| (SCANS_PER_SOURCE - q.len()) as u64).collect()
        };
        let now = held(&server).await;
        for s in 0..SOURCES {
            assert!(
                now[s] >= acked[s],
                "cycle {cycle}: source {s} holds {} scans, {} were acknowledged",
                now[s],
                acked[s]
            );
        }
        let tasks: Vec<_> = (0..SOURCES)
            .map(|s| {
                let wait = rng.random_bool(0.5);
                tokio::spawn(stream_source(server.grpc_url(), s, data.clone(), unacked.clone(), wait))
            })
            .collect();
        if cycle < KILLS {
            // Kill at a random moment: after this session has acknowledged a random few scans
            // (so a fast machine does not run out of scans before the last kill), plus jitter.
            let left = |u: &Vec<VecDeque<usize>>| u.iter().map(VecDeque::len).sum::<usize>();
            let before = left(&unacked.lock().unwrap());
            let target = before.saturating_sub(rng.random_range(1..=6));
            for _ in 0..4000 {
                if left(&unacked.lock().unwrap()) <= target {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            let delay = rng.random_range(0..25);
            tokio::time::sleep(Duration::from_millis(delay)).await;
            tokio::task::spawn_blocking(move || server.kill()).await.unwrap();
            let mut progress = 0;
            for t in tasks {
                progress += t.await.unwrap();
            }
            kills_with_progress += usize::from(progress > 0);
        } else {
            for t in tasks {
                t.await.unwrap();
            }
            assert!(
                unacked.lock().unwrap().iter().all(VecDeque::is_empty),
                "the last session acknowledges the rest"
            );
            let mut c = client(&server).await.unwrap();
            let info = c.get_map(pb::GetMapRequest { map: "m".into() }).await.unwrap().into_inner();
            for s in &info.sources {
                assert_eq!(
                    s.applied + s.pending,
                    SCANS_PER_SOURCE as u64,
                    "every acknowledged scan, once: {s:?}"
                );
            }
            // Once integrated, the sequence is complete.
            let info = loop {
                let info = c.get_map(pb::GetMapRequest { map: "m".into() }).await.unwrap().into_inner();
                if info.sources.iter().all(|s| s.pending == 0) {
                    break info;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            };
            for s in &info.sources {
                assert_eq!(
                    (s.applied + s.pending, s.gaps, s.highest_seq),
                    (SCANS_PER_SOURCE as u64, 0, Some(SCANS_PER_SOURCE as u64)),
                    "{s:?}"
                );
            }
            assert_eq!(server.terminate().code(), Some(0));
        }
    }
    eprintln!("{kills_with_progress} of {KILLS} kills interrupted ingest");
    assert!(
        kills_with_progress >= KILLS * 2 / 3,
        "only {kills_with_progress} of {KILLS} kills interrupted ingest"
    );
    // Exactly once: the map equals the offline build of every scan, byte for byte.
    let mut args: Vec<String> = vec!["build".into(), "--out".into(), "offline.bgkmap".into()];
    args.extend(files);
    run_ok(dir, &args);
    let offline = run_ok(dir, ["export", "offline.bgkmap", "--format", "csv"]);
    let served = run_ok(dir, ["export", "data/m.bgkmap", "--format", "csv"]);
    assert!(offline.len() > 1000);
    assert!(served == offline, "the crash-tested map differs from the offline build");
    run_ok(dir, ["check", "data/m.bgkmap"]);
}
