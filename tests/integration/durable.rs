//! Durable maps through the real server: a map built over three sessions equals one built in
//! one; merges of maps sharing scans equal the single build of the union (online over gRPC and
//! HTTP, and offline with `bgkmap merge`); retracting a source and re-posing a scan equal the
//! clean builds; what cannot be done exactly is refused and changes nothing.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::sim::{Lidar, simulate};
use common::{ServeProcess, http_request, run_fail, run_ok, start_serve};
use std::path::Path;
use tonic::Code;
use tonic::transport::Channel;

type Client = MapServiceClient<Channel>;

/// A scan as a robot sends it: points in the sensor frame, the pose given.
#[derive(Clone)]
struct RobotScan {
    pose: pb::Pose,
    xyz: Vec<u8>,
}

/// `n` scans of the room of `seed`, thinned, expressed in a yawed sensor frame.
fn robot_scans(seed: u64, n: usize) -> Vec<RobotScan> {
    let (_, sims) = simulate(seed, n, &Lidar::default());
    sims.iter()
        .enumerate()
        .map(|(k, s)| {
            let yaw = 0.4 * k as f64;
            let (c, sn) = (yaw.cos(), yaw.sin());
            let t = s.origin;
            let xyz = s
                .points_world
                .iter()
                .step_by(4)
                .flat_map(|p| {
                    let d = [f64::from(p[0]) - t[0], f64::from(p[1]) - t[1], f64::from(p[2]) - t[2]];
                    // R(yaw)ᵀ · d
                    [(c * d[0] + sn * d[1]) as f32, (-sn * d[0] + c * d[1]) as f32, d[2] as f32]
                })
                .flat_map(f32::to_le_bytes)
                .collect();
            let pose = pb::Pose {
                translation: t.to_vec(),
                rotation: vec![(yaw / 2.0).cos(), 0.0, 0.0, (yaw / 2.0).sin()],
            };
            RobotScan { pose, xyz }
        })
        .collect()
}

fn msg(source: &str, seq: u64, s: &RobotScan) -> pb::Scan {
    pb::Scan {
        source: source.into(),
        seq,
        world_from_sensor: Some(s.pose.clone()),
        frame: pb::Frame::Sensor as i32,
        xyz_f32: s.xyz.clone(),
        max_range: None,
        stamp_nanos: Some(1_000_000 * seq as i64),
    }
}

async fn connect(server: &ServeProcess) -> Client {
    MapServiceClient::connect(server.grpc_url()).await.unwrap()
}

async fn create(c: &mut Client, map: &str) {
    c.create_map(pb::CreateMapRequest { map: map.into(), params: Some(pb::MapParams::default()) })
        .await
        .unwrap();
}

async fn insert(c: &mut Client, map: &str, scans: &[(&str, u64, &RobotScan)]) {
    for (source, seq, s) in scans {
        let req =
            pb::InsertScanRequest { map: map.into(), scan: Some(msg(source, *seq, s)), wait_applied: false };
        let ack = c.insert_scan(req).await.unwrap().into_inner();
        assert!(ack.applied);
    }
}

/// `bgkmap export MAP --format csv` (the map file of a stopped server).
fn csv(dir: &Path, map: &str) -> Vec<u8> {
    let out = run_ok(dir, ["export", map, "--format", "csv"]);
    assert!(out.len() > 1000, "{map} is nearly empty");
    out
}

async fn version(c: &mut Client, map: &str) -> u64 {
    c.get_map(pb::GetMapRequest { map: map.into() }).await.unwrap().into_inner().version
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_map_built_over_three_sessions_equals_one_built_in_one() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let scans = robot_scans(3, 9);
    for session in 0..3 {
        let server = start_serve(&dir.join("three"), &[]);
        let mut c = connect(&server).await;
        if session == 0 {
            create(&mut c, "m").await;
        }
        let part: Vec<_> = (3 * session..3 * session + 3).map(|k| ("r", k as u64 + 1, &scans[k])).collect();
        insert(&mut c, "m", &part).await;
        assert_eq!(server.terminate().code(), Some(0));
    }
    let server = start_serve(&dir.join("one"), &[]);
    let mut c = connect(&server).await;
    create(&mut c, "m").await;
    let all: Vec<_> = scans.iter().enumerate().map(|(k, s)| ("r", k as u64 + 1, s)).collect();
    insert(&mut c, "m", &all).await;
    assert_eq!(server.terminate().code(), Some(0));
    assert!(csv(dir, "three/m.bgkmap") == csv(dir, "one/m.bgkmap"), "three sessions differ from one");
    // The stored blocks themselves are byte-identical.
    let blocks = |p: &str| -> Vec<(i32, i32, i32, Vec<u8>)> {
        let c = rusqlite::Connection::open(dir.join(p)).unwrap();
        let mut s = c.prepare("SELECT bx, by, bz, data FROM blocks ORDER BY bx, by, bz").unwrap();
        s.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
            .unwrap()
            .map(Result::unwrap)
            .collect()
    };
    assert_eq!(blocks("three/m.bgkmap"), blocks("one/m.bgkmap"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn merging_three_sources_with_a_shared_set_equals_the_single_build_of_the_union() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let own: Vec<Vec<RobotScan>> = (0..3).map(|r| robot_scans(10 + r, 3)).collect();
    let shared = robot_scans(20, 2);
    let server = start_serve(&dir.join("data"), &[]);
    let mut c = connect(&server).await;
    for (r, map) in ["a", "b", "c"].iter().enumerate() {
        create(&mut c, map).await;
        let source = format!("robot{r}");
        let mut part: Vec<_> =
            own[r].iter().enumerate().map(|(k, s)| (source.as_str(), k as u64 + 1, s)).collect();
        part.extend(shared.iter().enumerate().map(|(k, s)| ("shared", k as u64 + 1, s)));
        insert(&mut c, map, &part).await;
    }
    create(&mut c, "union").await;
    for (r, scans) in own.iter().enumerate() {
        let source = format!("robot{r}");
        let part: Vec<_> =
            scans.iter().enumerate().map(|(k, s)| (source.as_str(), k as u64 + 1, s)).collect();
        insert(&mut c, "union", &part).await;
    }
    let part: Vec<_> = shared.iter().enumerate().map(|(k, s)| ("shared", k as u64 + 1, s)).collect();
    insert(&mut c, "union", &part).await;
    assert_eq!(server.terminate().code(), Some(0));
    // Offline: the map files as they are.
    std::fs::create_dir(dir.join("copies")).unwrap();
    for m in ["a", "b", "c"] {
        std::fs::copy(dir.join(format!("data/{m}.bgkmap")), dir.join(format!("copies/{m}.bgkmap"))).unwrap();
    }
    run_ok(
        dir,
        ["merge", "copies/a.bgkmap", "copies/b.bgkmap", "copies/c.bgkmap", "--out", "offline.bgkmap"],
    );
    // Online: gRPC from another map, HTTP from a map file.
    let server = start_serve(&dir.join("data"), &[]);
    let mut c = connect(&server).await;
    let req =
        pb::MergeMapRequest { map: "a".into(), from: Some(pb::merge_map_request::From::FromMap("b".into())) };
    let change = c.merge_map(req).await.unwrap().into_inner();
    assert_eq!((change.scans, change.shared_scans), (3, 2));
    let (code, body) =
        http_request(server.http_addr, "POST", "/v1/maps/a/merge", br#"{"from_file": "../copies/c.bgkmap"}"#);
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"shared_scans\":2"), "{body}");
    let info = c.get_map(pb::GetMapRequest { map: "a".into() }).await.unwrap().into_inner();
    assert_eq!(info.scans, 11, "3 × 3 own scans + 2 shared, each once");
    let err = c
        .merge_map(pb::MergeMapRequest {
            map: "a".into(),
            from: Some(pb::merge_map_request::From::FromMap("a".into())),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    assert_eq!(server.terminate().code(), Some(0));
    let union = csv(dir, "data/union.bgkmap");
    assert!(csv(dir, "data/a.bgkmap") == union, "online merge differs from the union");
    assert!(csv(dir, "offline.bgkmap") == union, "offline merge differs from the union");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_merge_that_cannot_be_exact_is_refused_and_changes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let scans = robot_scans(5, 3);
    let server = start_serve(&dir.join("data"), &["--journal-retention", "none"]);
    let mut c = connect(&server).await;
    for map in ["p", "q"] {
        create(&mut c, map).await;
        insert(&mut c, map, &[("own", if map == "p" { 1 } else { 2 }, &scans[0]), ("both", 1, &scans[1])])
            .await;
    }
    // Integration (and pruning) is done once a read-your-writes scan comes back.
    for (map, seq) in [("p", 3), ("q", 4)] {
        let req = pb::InsertScanRequest {
            map: map.into(),
            scan: Some(msg("own", seq, &scans[2])),
            wait_applied: true,
        };
        c.insert_scan(req).await.unwrap();
    }
    let before = version(&mut c, "p").await;
    let req =
        pb::MergeMapRequest { map: "p".into(), from: Some(pb::merge_map_request::From::FromMap("q".into())) };
    let err = c.merge_map(req).await.unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition, "{err:?}");
    assert!(err.message().contains("(both, 1)") && err.message().contains("pruned"), "{}", err.message());
    assert_eq!(version(&mut c, "p").await, before, "nothing changed");
    // Retraction needs the raw scans too.
    let req = pb::RetractScansRequest { map: "p".into(), source: "both".into(), ..Default::default() };
    let err = c.retract_scans(req).await.unwrap_err();
    assert_eq!(err.code(), Code::FailedPrecondition, "{err:?}");
    let (code, body) = http_request(
        server.http_addr,
        "POST",
        "/v1/maps/p/retract",
        br#"{"scans": [{"source": "own", "seq": 9}]}"#,
    );
    assert_eq!(code, 404, "{body}");
    assert_eq!(server.terminate().code(), Some(0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retracting_a_source_and_reposing_a_scan_equal_the_clean_builds() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let r: Vec<Vec<RobotScan>> = (0..3).map(|i| robot_scans(30 + i, 3)).collect();
    let mut corrected = r[0][1].clone();
    corrected.pose.translation =
        vec![corrected.pose.translation[0] + 0.15, corrected.pose.translation[1] - 0.1, 0.7];
    corrected.pose.rotation = vec![(0.05f64).cos(), 0.0, 0.0, (0.05f64).sin()];
    let server = start_serve(&dir.join("data"), &[]);
    let mut c = connect(&server).await;
    let named = |i: usize, scans: &[RobotScan]| -> Vec<(String, u64, RobotScan)> {
        scans.iter().enumerate().map(|(k, s)| (format!("r{i}"), k as u64 + 1, s.clone())).collect()
    };
    let mut all = named(0, &r[0]);
    all.extend(named(1, &r[1]));
    all.extend(named(2, &r[2]));
    let keep = |f: &dyn Fn(&(String, u64, RobotScan)) -> bool| -> Vec<(String, u64, RobotScan)> {
        all.iter().filter(|x| f(x)).cloned().collect()
    };
    let without_r1 = keep(&|x| x.0 != "r1");
    let mut reposed = without_r1.clone();
    reposed.iter_mut().filter(|x| x.0 == "r0" && x.1 == 2).for_each(|x| x.2 = corrected.clone());
    for (map, scans) in [("m", &all), ("clean1", &without_r1), ("clean2", &reposed)] {
        create(&mut c, map).await;
        let refs: Vec<_> = scans.iter().map(|(s, q, x)| (s.as_str(), *q, x)).collect();
        insert(&mut c, map, &refs).await;
    }
    let change = c
        .retract_scans(pb::RetractScansRequest { map: "m".into(), source: "r1".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(change.scans, 3);
    // Re-pose over HTTP.
    let [tx, ty, tz] =
        [corrected.pose.translation[0], corrected.pose.translation[1], corrected.pose.translation[2]];
    let q = &corrected.pose.rotation;
    let body = format!(
        r#"{{"poses": [{{"source": "r0", "seq": 2, "pose": {{"translation": [{tx:?}, {ty:?}, {tz:?}], "rotation": [{:?}, {:?}, {:?}, {:?}]}}}}]}}"#,
        q[0], q[1], q[2], q[3]
    );
    std::fs::write(dir.join("repose.json"), &body).unwrap();
    let snapshot_after_retract = {
        let server_stop = server.terminate();
        assert_eq!(server_stop.code(), Some(0));
        csv(dir, "data/m.bgkmap")
    };
    assert!(
        snapshot_after_retract == csv(dir, "data/clean1.bgkmap"),
        "retracting r1 differs from the build without it"
    );
    let server = start_serve(&dir.join("data"), &[]);
    let (code, text) = http_request(server.http_addr, "POST", "/v1/maps/m/repose", body.as_bytes());
    assert_eq!(code, 200, "{text}");
    let mut c = connect(&server).await;
    let bad = pb::ReposeScansRequest {
        map: "m".into(),
        poses: vec![pb::ScanPose {
            scan: Some(pb::ScanId { source: "r0".into(), seq: 1 }),
            world_from_sensor: Some(pb::Pose {
                translation: vec![0.0; 3],
                rotation: vec![2.0, 0.0, 0.0, 0.0],
            }),
        }],
    };
    assert_eq!(c.repose_scans(bad).await.unwrap_err().code(), Code::InvalidArgument);
    // While the server holds the map, offline writers are refused.
    run_fail(dir, ["retract", "data/m.bgkmap", "--source", "r2"], &["in use by another process"]);
    assert_eq!(server.terminate().code(), Some(0));
    assert!(
        csv(dir, "data/m.bgkmap") == csv(dir, "data/clean2.bgkmap"),
        "re-posing differs from the clean build"
    );
    // Offline: retract by stamp range (seq 3 of every source has stamp 3 ms) equals a clean
    // build without those scans.
    run_ok(dir, ["retract", "data/m.bgkmap", "--from-stamp", "3000000", "--to-stamp", "3000001"]);
    run_ok(dir, ["retract", "data/clean2.bgkmap", "--scan", "r0:3", "--scan", "r2:3"]);
    assert!(csv(dir, "data/m.bgkmap") == csv(dir, "data/clean2.bgkmap"));
    run_ok(dir, ["check", "data/m.bgkmap"]);
}
