#![allow(clippy::unwrap_used)]
//! Many query clients while scans stream in over gRPC: every answer must be the answer of some
//! whole number of applied scans — never of a partly applied scan.
#![cfg(feature = "server")]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::core::query::query_points;
use bgkmap::core::{EvidenceMap, Integrator, MapParams};
use bgkmap::sim::{Lidar, simulate};

use bgkmap::api::pack_xyz as packed;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_queries_see_whole_scans_only() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let (_, scans) = simulate(0, 8, &Lidar::default());
    // Query points along the robot's route and at the walls, where scans change the answers.
    let probe: Vec<[f32; 3]> =
        (0..400).map(|i| [0.05 + (i % 20) as f32 * 0.5, 0.05 + (i / 20) as f32 * 0.6, 0.7]).collect();
    let probe64: Vec<[f64; 3]> = probe.iter().map(|p| p.map(f64::from)).collect();
    // The expected answers after each whole number of scans, from an offline build.
    let params = MapParams::default();
    let mut map = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    let th = params.thresholds;
    let answers = |m: &EvidenceMap| -> Vec<f64> {
        query_points(m, &probe64, &th).iter().map(|a| a.unwrap().estimate.probability).collect()
    };
    let mut expected = vec![answers(&map)];
    for s in &scans {
        integ.integrate(&mut map, &s.points_world, s.origin, 1);
        expected.push(answers(&map));
    }

    let mut client = MapServiceClient::connect(server.grpc_url()).await.unwrap();
    client
        .create_map(pb::CreateMapRequest { map: "m".into(), params: Some(pb::MapParams::default()) })
        .await
        .unwrap();
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    let stop = Arc::new(AtomicBool::new(false));
    // The newest version any reader has been answered at, plus one (0: no answer yet).
    let seen_upto = Arc::new(AtomicU64::new(0));
    let mut readers = Vec::new();
    for _ in 0..4 {
        let (url, xyz, stop, seen_upto) =
            (server.grpc_url(), packed(&probe), stop.clone(), seen_upto.clone());
        readers.push(tokio::spawn(async move {
            let mut c = MapServiceClient::connect(url).await.unwrap();
            let mut seen = Vec::new();
            while !stop.load(Ordering::Relaxed) {
                let req = pb::QueryPointsRequest { map: "m".into(), xyz_f32: xyz.clone(), thresholds: None };
                let r = c.query_points(req).await.unwrap().into_inner();
                seen_upto.fetch_max(r.version + 1, Ordering::Relaxed);
                seen.push((r.version, r.probability));
            }
            seen
        }));
    }
    // One stream of scans, each sent only once a reader has been answered at the version before
    // it: the readers then query while every scan is applied, however fast the server is (a
    // stream sent all at once was applied before a slow machine's readers asked twice).
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let requests: Vec<pb::InsertScanRequest> = scans
        .iter()
        .enumerate()
        .map(|(i, s)| pb::InsertScanRequest {
            map: "m".into(),
            scan: Some(pb::Scan::world("robot", i as u64 + 1, s.origin, &s.points_world)),
            wait_applied: true,
        })
        .collect();
    let feeder = {
        let seen_upto = seen_upto.clone();
        tokio::spawn(async move {
            for (version, request) in requests.into_iter().enumerate() {
                let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
                while seen_upto.load(Ordering::Relaxed) <= version as u64 {
                    assert!(
                        std::time::Instant::now() < deadline,
                        "no reader was answered at version {version}"
                    );
                    tokio::time::sleep(std::time::Duration::from_millis(1)).await;
                }
                tx.send(request).await.unwrap();
            }
        })
    };
    let summary =
        client.insert_scans(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap().into_inner();
    feeder.await.unwrap();
    assert_eq!(summary.applied, scans.len() as u64);
    stop.store(true, Ordering::Relaxed);
    let mut versions = std::collections::BTreeSet::new();
    let mut total = 0;
    for r in readers {
        for (version, probs) in r.await.unwrap() {
            assert_eq!(
                probs, expected[version as usize],
                "answer at version {version} is not a whole-scan state"
            );
            versions.insert(version);
            total += 1;
        }
    }
    assert!(total >= 4, "readers answered {total} times");
    // The feeder waited for each of these, so this holds unless an answer went missing.
    assert!(
        (0..scans.len() as u64).all(|v| versions.contains(&v)),
        "readers saw versions {versions:?}: queries did not overlap ingest"
    );
    assert_eq!(server.terminate().code(), Some(0));
}
