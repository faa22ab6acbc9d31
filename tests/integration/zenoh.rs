//! zenoh acceptance tests against the real `bgkmap serve` binary on loopback: several robots
//! streaming into one map (two Rust peers and, when the test venv has `eclipse-zenoh`, one
//! Python peer), zenoh answers against gRPC answers, refusals of malformed payloads, the
//! acknowledged ingest path and the change-stream seam.
#![cfg(feature = "zenoh")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::io::pcd::read_pcd;
use bgkmap::io::scan::{PointFrame, scan_from_pcd};
use common::{ServeProcess, run_ok, start_serve};
use prost::Message;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tonic::transport::Channel;
use zenoh::Wait as _;
use zenoh::qos::CongestionControl;

type Client = MapServiceClient<Channel>;

const ZENOH_FLAGS: [&str; 2] = ["--zenoh-listen", "tcp/127.0.0.1:0"];

async fn grpc(server: &ServeProcess) -> Client {
    MapServiceClient::connect(server.grpc_url())
        .await
        .unwrap()
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20)
}

/// A zenoh peer of our own (no listener, multicast off) connected to the server.
fn peer(server: &ServeProcess) -> zenoh::Session {
    let locator = server.zenoh_locators.first().expect("the server printed its zenoh locator");
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false").unwrap();
    c.insert_json5("listen/endpoints", "[]").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"{locator}\"]")).unwrap();
    zenoh::open(c).wait().unwrap()
}

async fn create_map(client: &mut Client, map: &str) {
    let params = pb::MapParams { max_range: Some(8.0), ..Default::default() };
    client.create_map(pb::CreateMapRequest { map: map.into(), params: Some(params) }).await.unwrap();
}

async fn info(client: &mut Client, map: &str) -> pb::MapInfo {
    client.get_map(pb::GetMapRequest { map: map.into() }).await.unwrap().into_inner()
}

fn source<'a>(info: &'a pb::MapInfo, name: &str) -> Option<&'a pb::SourceStats> {
    info.sources.iter().find(|s| s.source == name)
}

/// Polls `GetMap` until `done` holds (scans over put have no reply), at most 120 s.
async fn wait_for(
    client: &mut Client,
    map: &str,
    what: &str,
    done: impl Fn(&pb::MapInfo) -> bool,
) -> pb::MapInfo {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let i = info(client, map).await;
        if done(&i) {
            return i;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}; map info: {i:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A PCD written by `bgkmap simulate` as the `Scan` message every publisher sends.
fn scan_message(path: &Path, source: &str, seq: u64) -> pb::Scan {
    let cloud = read_pcd(&std::fs::read(path).unwrap()).unwrap();
    let scan = scan_from_pcd(cloud, PointFrame::World, None).unwrap();
    pb::Scan::world(source, seq, scan.origin_world, &scan.points_world)
}

/// Publishes every scan twice (all, then all again) on `bgkmap/<map>/scans/<source>` once the
/// server's subscriber matches, with congestion control Block so nothing is dropped. The
/// session must stay open until the server has them: closing it right away may drop puts that
/// are still queued (zenoh sends its close ahead of them).
fn publish_twice(session: &zenoh::Session, map: &str, source: &str, scans: &[Vec<u8>]) {
    let key = format!("bgkmap/{map}/scans/{source}");
    let publisher =
        session.declare_publisher(key).congestion_control(CongestionControl::Block).wait().unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while !publisher.matching_status().wait().unwrap().matching() {
        assert!(Instant::now() < deadline, "the server's scan subscriber never matched");
        std::thread::sleep(Duration::from_millis(10));
    }
    for _ in 0..2 {
        for s in scans {
            publisher.put(s.clone()).wait().unwrap();
        }
    }
}

const PY_PUBLISHER: &str = r#"
import json, sys, time, zenoh
connect, key, *files = sys.argv[1:]
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", "[]")
conf.insert_json5("connect/endpoints", json.dumps([connect]))
with zenoh.open(conf) as s:
    pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 30
    while not pub.matching_status:
        if time.monotonic() > deadline:
            sys.exit("no subscriber matched " + key)
        time.sleep(0.01)
    for _ in range(2):
        for f in files:
            with open(f, "rb") as fh:
                pub.put(fh.read())
    sys.stdin.readline()  # stay connected until the test has seen every scan arrive
"#;

/// A Python with `eclipse-zenoh`: `$BGKMAP_PYTHON`, else the test venv (`$BGKMAP_VENV`, else
/// `~/.cache/bgkmap/venv`, as tests/python.sh). Missing: `None`, or a failure when
/// `BGKMAP_REQUIRE_TOOLS=1` (tests/run-all.sh sets up the venv first and sets it).
fn python_with_zenoh() -> Option<PathBuf> {
    let home = std::env::var("HOME").unwrap_or_else(|_| "/tmp".into());
    let venv = std::env::var("BGKMAP_VENV").unwrap_or_else(|_| format!("{home}/.cache/bgkmap/venv"));
    let candidates = [std::env::var("BGKMAP_PYTHON").ok(), Some(format!("{venv}/bin/python"))];
    for py in candidates.into_iter().flatten() {
        let ok = std::process::Command::new(&py).args(["-c", "import zenoh"]).output();
        if ok.is_ok_and(|o| o.status.success()) {
            return Some(PathBuf::from(py));
        }
    }
    let msg = "no Python with eclipse-zenoh (set BGKMAP_PYTHON or run tests/python.sh first)";
    assert!(std::env::var("BGKMAP_REQUIRE_TOOLS").as_deref() != Ok("1"), "{msg}");
    eprintln!("note: {msg}; the third robot publishes from Rust instead");
    None
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_robots_fill_one_map_exactly_like_an_offline_build_of_all_their_scans() {
    let dir = tempfile::tempdir().unwrap();
    let sim = common::simulate(dir.path(), 9);
    let server = start_serve(&dir.path().join("data"), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    create_map(&mut client, "team").await;
    // Disjoint scan sets: robot k takes scans k, k + 3, k + 6, numbered 1, 2, 3.
    let robots = ["r1", "r2", "r3"];
    let sets: Vec<Vec<Vec<u8>>> = (0..3)
        .map(|k| {
            (0..3)
                .map(|j| scan_message(&dir.path().join(&sim.scans[k + 3 * j]), robots[k], j as u64 + 1))
                .map(|m| m.encode_to_vec())
                .collect()
        })
        .collect();
    let python = python_with_zenoh();
    let python_child = python.as_ref().map(|py| {
        let files: Vec<PathBuf> = sets[2]
            .iter()
            .enumerate()
            .map(|(j, bytes)| {
                let f = dir.path().join(format!("r3_{j}.pb"));
                std::fs::write(&f, bytes).unwrap();
                f
            })
            .collect();
        std::process::Command::new(py)
            .arg("-c")
            .arg(PY_PUBLISHER)
            .arg(&server.zenoh_locators[0])
            .arg("bgkmap/team/scans/r3")
            .args(&files)
            .stdin(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    });
    let rust_robots = if python.is_some() { 2 } else { 3 };
    let sessions: Vec<zenoh::Session> = std::thread::scope(|scope| {
        let threads: Vec<_> = (0..rust_robots)
            .map(|k| {
                let (server, set) = (&server, &sets[k]);
                scope.spawn(move || {
                    let session = peer(server);
                    publish_twice(&session, "team", robots[k], set);
                    session
                })
            })
            .collect();
        threads.into_iter().map(|t| t.join().unwrap()).collect()
    });
    // Every put journaled (received) and every acknowledged scan integrated (none pending).
    let info = wait_for(&mut client, "team", "6 puts of each robot, integrated", |i| {
        robots.iter().all(|r| source(i, r).is_some_and(|s| s.received == 6 && s.pending == 0))
    })
    .await;
    for s in sessions {
        s.close().await.unwrap();
    }
    if let Some(mut child) = python_child {
        drop(child.stdin.take()); // end of input: the Python peer closes and exits
        assert!(child.wait().unwrap().success(), "the Python publisher failed");
    }
    assert_eq!(info.version, 9, "every scan once");
    for r in robots {
        let s = source(&info, r).unwrap();
        assert_eq!((s.applied, s.duplicates, s.rejected, s.highest_seq), (3, 3, 0, Some(3)), "{r}");
    }
    assert_eq!(server.terminate().code(), Some(0));
    let mut args =
        vec!["build".to_string(), "--out".into(), "offline.bgkmap".into(), "--max-range".into(), "8".into()];
    args.extend(sim.scans.iter().cloned());
    run_ok(dir.path(), &args);
    let live = common::export_csv(dir.path(), "data/team.bgkmap");
    let offline = common::export_csv(dir.path(), "offline.bgkmap");
    assert!(live.lines().count() > 1000, "the map has cells");
    assert!(live == offline, "the map streamed over zenoh differs from the offline build");
}

/// `get` on `key` with `payload`; the one reply, as bytes or as the error text.
async fn zget(session: &zenoh::Session, key: &str, payload: Vec<u8>) -> Result<Vec<u8>, String> {
    let replies = session.get(key).payload(payload).timeout(Duration::from_secs(60)).await.unwrap();
    let reply = replies.recv_async().await.expect("one reply");
    assert!(replies.recv_async().await.is_err(), "exactly one reply");
    match reply.result() {
        Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
        Err(e) => Err(e.payload().try_to_string().unwrap().into_owned()),
    }
}

fn points_request(points: &[[f32; 3]]) -> pb::QueryPointsRequest {
    pb::QueryPointsRequest {
        map: "room".into(),
        xyz_f32: bgkmap::api::pack_xyz(points),
        thresholds: Some(pb::Thresholds { p_occ: Some(0.6), ..Default::default() }),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zenoh_ingest_is_acknowledged_and_zenoh_answers_equal_grpc_answers() {
    let dir = tempfile::tempdir().unwrap();
    let server = start_serve(&dir.path().join("data"), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    create_map(&mut client, "room").await;
    let session = peer(&server);
    let (_, sim) = bgkmap::sim::simulate(0, 3, &bgkmap::sim::Lidar::default());
    let scans: Vec<Vec<u8>> = sim
        .iter()
        .enumerate()
        .map(|(i, s)| pb::Scan::world("lidar", i as u64 + 1, s.origin, &s.points_world).encode_to_vec())
        .collect();
    let ack = |bytes: Vec<u8>| pb::InsertScanResponse::decode(&*bytes).unwrap();
    // Read-your-writes: `?wait_applied` answers once the scan is integrated.
    for (i, scan) in scans.iter().enumerate().take(2) {
        let a = ack(zget(&session, "bgkmap/room/ingest?wait_applied", scan.clone()).await.unwrap());
        assert_eq!(a, pb::InsertScanResponse { applied: true, version: i as u64 + 1, dropped_points: 0 });
        let again = ack(zget(&session, "bgkmap/room/ingest", scan.clone()).await.unwrap());
        assert!(!again.applied, "a repeated scan is acknowledged as a duplicate");
    }
    // The plain acknowledgement means durable: a server killed right after it still has the
    // scan once it restarts (the journal is replayed).
    let a = ack(zget(&session, "bgkmap/room/ingest", scans[2].clone()).await.unwrap());
    assert!(a.applied && a.version >= 2, "{a:?}");
    session.close().await.unwrap();
    server.kill();
    let server = start_serve(&dir.path().join("data"), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    assert_eq!(info(&mut client, "room").await.version, 3, "the acknowledged scan survived SIGKILL");
    let session = peer(&server);
    let again = ack(zget(&session, "bgkmap/room/ingest", scans[2].clone()).await.unwrap());
    assert!(!again.applied, "after the restart the scan is still known: a duplicate");
    // Points over the room's lattice and beyond, a box, rays: byte-identical answers.
    let mut points = Vec::new();
    for x in 0..40 {
        for y in 0..40 {
            for z in 0..6 {
                points.push([x as f32 * 0.27 - 0.5, y as f32 * 0.31 - 0.5, z as f32 * 0.5 + 0.05]);
            }
        }
    }
    let req = points_request(&points);
    let by_grpc = client.query_points(req.clone()).await.unwrap().into_inner();
    let by_zenoh = zget(&session, "bgkmap/room/query/points", req.encode_to_vec()).await.unwrap();
    assert_eq!(by_grpc.probability.len(), points.len());
    assert_eq!(by_grpc.encode_to_vec(), by_zenoh, "query/points");
    let unnamed = pb::QueryPointsRequest { map: String::new(), ..req };
    let by_zenoh = zget(&session, "bgkmap/room/query/points", unnamed.encode_to_vec()).await.unwrap();
    assert_eq!(by_grpc.encode_to_vec(), by_zenoh, "the key names the map");
    let boxed = pb::QueryBoxRequest {
        map: "room".into(),
        min: vec![1.0, 1.0, 0.0],
        max: vec![4.0, 5.0, 2.0],
        coarsen: 1,
        ..Default::default()
    };
    let by_grpc = client.query_box(boxed.clone()).await.unwrap().into_inner();
    assert!(by_grpc.occupied > 0 && by_grpc.free > 0, "{by_grpc:?}");
    assert_eq!(
        by_grpc.encode_to_vec(),
        zget(&session, "bgkmap/room/query/box", boxed.encode_to_vec()).await.unwrap()
    );
    let rays = pb::CastRaysRequest {
        map: "room".into(),
        rays: (0..64)
            .map(|i| {
                let a = i as f64 * 0.1;
                pb::Ray {
                    origin: sim[0].origin.to_vec(),
                    direction: vec![a.cos(), a.sin(), 0.05],
                    max_range: 8.0,
                }
            })
            .collect(),
        ..Default::default()
    };
    let by_grpc = client.cast_rays(rays.clone()).await.unwrap().into_inner();
    assert!(by_grpc.results.iter().any(|r| r.blocked), "some rays hit a wall");
    assert_eq!(
        by_grpc.encode_to_vec(),
        zget(&session, "bgkmap/room/query/rays", rays.encode_to_vec()).await.unwrap()
    );
    // Errors carry gRPC's code and message.
    let bad = pb::QueryPointsRequest { xyz_f32: vec![0; 13], ..points_request(&[]) };
    let status = client.query_points(bad.clone()).await.unwrap_err();
    let text = zget(&session, "bgkmap/room/query/points", bad.encode_to_vec()).await.unwrap_err();
    assert_eq!(text, format!("INVALID_ARGUMENT: {}", status.message()));
    let text = zget(&session, "bgkmap/nope/query/box", Vec::new()).await.unwrap_err();
    assert!(text.starts_with("NOT_FOUND: "), "{text}");
    let text =
        zget(&session, "bgkmap/other/query/points", points_request(&[]).encode_to_vec()).await.unwrap_err();
    assert!(text.contains("differs from the key's map"), "{text}");
    let text = zget(&session, "bgkmap/room/ingest", vec![0x0a, 0x09, 1]).await.unwrap_err();
    assert!(text.starts_with("INVALID_ARGUMENT: malformed protobuf bgkmap.v1.Scan"), "{text}");
    assert_eq!(info(&mut client, "room").await.version, 3, "errors changed nothing");
    session.close().await.unwrap();
    assert_eq!(server.terminate().code(), Some(0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_puts_are_counted_per_source_logged_once_and_the_session_keeps_going() {
    let dir = tempfile::tempdir().unwrap();
    let server = start_serve(&dir.path().join("data"), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    create_map(&mut client, "m").await;
    let session = peer(&server);
    let (_, sim) = bgkmap::sim::simulate(0, 1, &bgkmap::sim::Lidar::default());
    let good = pb::Scan::world("", 1, sim[0].origin, &sim[0].points_world).encode_to_vec();
    let put = |source: &str, bytes: Vec<u8>| {
        let key = format!("bgkmap/m/scans/{source}");
        let p = session.declare_publisher(key).congestion_control(CongestionControl::Block).wait().unwrap();
        let deadline = Instant::now() + Duration::from_secs(30);
        while !p.matching_status().wait().unwrap().matching() {
            assert!(Instant::now() < deadline, "no subscriber");
            std::thread::sleep(Duration::from_millis(10));
        }
        p.put(bytes).wait().unwrap();
    };
    let truncated = good[..good.len() / 2].to_vec();
    put("torn", truncated.clone());
    put("torn", truncated);
    let empty = pb::Scan { xyz_f32: Vec::new(), ..pb::Scan::decode(&*good).unwrap() }.encode_to_vec();
    put("empty", empty);
    let odd = pb::Scan { xyz_f32: vec![0; 13], ..pb::Scan::decode(&*good).unwrap() }.encode_to_vec();
    put("odd", odd);
    let other =
        pb::Scan { source: "someone-else".into(), ..pb::Scan::decode(&*good).unwrap() }.encode_to_vec();
    put("liar", other);
    put("good", good);
    let info = wait_for(&mut client, "m", "the good scan", |i| i.version == 1).await;
    let rejected = |name: &str| source(&info, name).map(|s| s.rejected);
    assert_eq!(rejected("torn"), Some(2));
    assert_eq!(rejected("empty"), Some(1));
    assert_eq!(rejected("odd"), Some(1));
    assert_eq!(rejected("liar"), Some(1));
    assert_eq!(rejected("good"), Some(0));
    let stderr = server.stderr();
    assert_eq!(stderr.matches("source \"torn\": protobuf: malformed bgkmap.v1.Scan").count(), 1, "{stderr}");
    assert!(stderr.contains("source \"empty\": invalid scan: invalid points"), "{stderr}");
    assert!(stderr.contains("source \"odd\": scan: bgkmap.v1.Scan.xyz_f32: length 13"), "{stderr}");
    assert!(stderr.contains("differs from the key's source"), "{stderr}");
    session.close().await.unwrap();
    assert_eq!(server.terminate().code(), Some(0));
}

/// The next change put on a subscriber's updates key: the message and its version attachment.
async fn next_update(
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
) -> pb::MapUpdate {
    let sample = tokio::time::timeout(Duration::from_secs(60), sub.recv_async()).await.unwrap().unwrap();
    let u = pb::MapUpdate::decode(sample.payload().to_bytes().as_ref()).unwrap();
    assert_eq!(
        sample.attachment().unwrap().to_bytes().as_ref(),
        &u.version.to_le_bytes(),
        "version attached"
    );
    u
}

fn block_set(u: &pb::MapUpdate) -> BTreeSet<[i32; 3]> {
    u.block.chunks(3).map(|c| [c[0], c[1], c[2]]).collect()
}

fn sim_insert(seq: u64, s: &bgkmap::sim::SimScan) -> pb::InsertScanRequest {
    pb::InsertScanRequest {
        map: "m".into(),
        scan: Some(pb::Scan::world("robot", seq, s.origin, &s.points_world)),
        // Integrated before the next is sent: one change (one version) per scan.
        wait_applied: true,
    }
}

/// gRPC `WatchUpdates` of map `m` since `version`.
async fn grpc_watch(client: &mut Client, version: u64) -> tonic::Streaming<pb::MapUpdate> {
    let req = pb::WatchUpdatesRequest { map: "m".into(), since_version: Some(version), ..Default::default() };
    client.watch_updates(req).await.unwrap().into_inner()
}

fn since(version: u64) -> Vec<u8> {
    pb::WatchUpdatesRequest { since_version: Some(version), ..Default::default() }.encode_to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_zenoh_subscriber_since_n_ends_with_the_same_blocks_as_an_early_one() {
    use bgkmap::sim::{Lidar, simulate};
    let dir = tempfile::tempdir().unwrap();
    let server = start_serve(dir.path(), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    let early_peer = peer(&server);
    let early = early_peer.declare_subscriber("bgkmap/m/updates").await.unwrap();
    // Created after the transport started: followed from version 0.
    create_map(&mut client, "m").await;
    let mut grpc_early = grpc_watch(&mut client, 0).await;
    assert_eq!(grpc_early.message().await.unwrap().unwrap().kind, pb::UpdateKind::CatchUp as i32);

    let (_, scans) = simulate(0, 8, &Lidar::default());
    let mut early_blocks = BTreeSet::new();
    let mut known_at_3 = BTreeSet::new();
    for (i, s) in scans.iter().enumerate() {
        let seq = i as u64 + 1;
        client.insert_scan(sim_insert(seq, s)).await.unwrap();
        let u = next_update(&early).await;
        assert_eq!((u.kind, u.from_version, u.version), (pb::UpdateKind::Live as i32, seq - 1, seq));
        // The same message gRPC WatchUpdates streams.
        assert_eq!(u, grpc_early.message().await.unwrap().unwrap(), "zenoh and gRPC differ at {seq}");
        assert!(!u.block.is_empty() && u.block_edge == 8 && u.resolution == 0.1);
        assert_eq!(u.poses.iter().map(|p| p.seq).collect::<Vec<_>>(), vec![seq]);
        early_blocks.extend(block_set(&u));
        if seq == 3 {
            // A second planner knew the map up to version 3, then lost its session.
            known_at_3 = early_blocks.clone();
        }
    }

    // It comes back: subscribes first, then asks what changed since the version it holds.
    let late_peer = peer(&server);
    let late = late_peer.declare_subscriber("bgkmap/m/updates").await.unwrap();
    let catch_up =
        pb::MapUpdate::decode(zget(&late_peer, "bgkmap/m/updates/since", since(3)).await.unwrap().as_slice())
            .unwrap();
    assert_eq!(
        (catch_up.kind, catch_up.from_version, catch_up.version),
        (pb::UpdateKind::CatchUp as i32, 3, 8)
    );
    assert_eq!(catch_up.poses.iter().map(|p| p.seq).collect::<Vec<_>>(), vec![4, 5, 6, 7, 8]);
    let mut grpc_late = grpc_watch(&mut client, 3).await;
    assert_eq!(catch_up, grpc_late.message().await.unwrap().unwrap(), "the catch-up gRPC sends");
    let mut late_blocks = known_at_3;
    late_blocks.extend(block_set(&catch_up));
    assert_eq!(late_blocks, early_blocks, "the late subscriber knows every block the early one does");

    // Both go on with the next scan.
    let (_, more) = simulate(1, 1, &Lidar::default());
    client.insert_scan(sim_insert(9, &more[0])).await.unwrap();
    let (a, b) = (next_update(&early).await, next_update(&late).await);
    assert_eq!(a, b);
    assert_eq!((a.kind, a.from_version, a.version), (pb::UpdateKind::Live as i32, 8, 9));
    early_blocks.extend(block_set(&a));

    // Bad requests answer the gRPC error, and change nothing.
    let ahead = zget(&late_peer, "bgkmap/m/updates/since", since(99)).await.unwrap_err();
    assert!(ahead.starts_with("INVALID_ARGUMENT: bgkmap.v1.WatchUpdatesRequest.since_version: "), "{ahead}");
    let torn = zget(&late_peer, "bgkmap/m/updates/since", vec![0x08]).await.unwrap_err();
    assert!(torn.starts_with("INVALID_ARGUMENT: malformed protobuf bgkmap.v1.WatchUpdatesRequest"), "{torn}");
    let none = zget(&late_peer, "bgkmap/nope/updates/since", since(0)).await.unwrap_err();
    assert!(none.starts_with("NOT_FOUND: "), "{none}");
    // A box filter narrows the catch-up to the blocks inside it (2 m around the first pose).
    let o = scans[0].origin;
    let (min, max) = (o.map(|c| c - 1.0), o.map(|c| c + 1.0));
    let boxed = pb::WatchUpdatesRequest {
        since_version: Some(0),
        min: min.to_vec(),
        max: max.to_vec(),
        ..Default::default()
    };
    let decode = |b: Vec<u8>| pb::MapUpdate::decode(b.as_slice()).unwrap();
    let boxed = decode(zget(&late_peer, "bgkmap/m/updates/since", boxed.encode_to_vec()).await.unwrap());
    let all = decode(zget(&late_peer, "bgkmap/m/updates/since", since(0)).await.unwrap());
    let (inside, every) = (block_set(&boxed), block_set(&all));
    assert_eq!(every, early_blocks);
    assert!(!inside.is_empty() && inside.len() < every.len() && inside.is_subset(&every));
    let block_of = |x: f64| (x / 0.8).floor() as i32;
    assert!(inside.iter().all(|k| (0..3).all(|a| (block_of(min[a])..=block_of(max[a])).contains(&k[a]))));
    drop((early, late));
    early_peer.close().await.unwrap();
    late_peer.close().await.unwrap();
    assert_eq!(server.terminate().code(), Some(0));

    // After a restart the map is there from the start: its changes are published too.
    let server = start_serve(dir.path(), &ZENOH_FLAGS);
    let mut client = grpc(&server).await;
    let peer = peer(&server);
    let sub = peer.declare_subscriber("bgkmap/m/updates").await.unwrap();
    let (_, again) = simulate(2, 1, &Lidar::default());
    client.insert_scan(sim_insert(10, &again[0])).await.unwrap();
    let u = next_update(&sub).await;
    assert_eq!((u.kind, u.from_version, u.version), (pb::UpdateKind::Live as i32, 9, 10));
    drop(sub);
    peer.close().await.unwrap();
    assert_eq!(server.terminate().code(), Some(0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_change_stream_seam_publishes_the_version_with_the_payload() {
    let dir = tempfile::tempdir().unwrap();
    let config = bgkmap::cli::serve::ServerConfig {
        data_dir: dir.path().join("data"),
        grpc_listen: "127.0.0.1:0".parse().unwrap(),
        http_listen: "127.0.0.1:0".parse().unwrap(),
        zenoh: bgkmap::api::zenoh::ZenohConfig {
            enabled: true,
            listen: vec!["tcp/127.0.0.1:0".into()],
            ..Default::default()
        },
        ..Default::default()
    };
    let running = bgkmap::cli::serve::start(&config).await.unwrap();
    let transport = running.zenoh.as_ref().unwrap();
    let subscriber = transport.session().declare_subscriber("bgkmap/m/updates").await.unwrap();
    transport.publish_update("m", 42, vec![1, 2, 3]).await.unwrap();
    let sample =
        tokio::time::timeout(Duration::from_secs(30), subscriber.recv_async()).await.unwrap().unwrap();
    assert_eq!(sample.payload().to_bytes().as_ref(), &[1, 2, 3]);
    assert_eq!(sample.attachment().unwrap().to_bytes().as_ref(), &42u64.to_le_bytes());
    assert!(transport.publish_update("../x", 1, Vec::new()).await.is_err());
    drop(subscriber);
    running.shutdown().await.unwrap();
}

#[test]
fn zenoh_flags_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    common::run_fail(dir.path(), ["serve", "--zenoh-mode", "client"], &["client", "connect"]);
    let out = common::run(
        dir.path(),
        [
            "serve",
            "--zenoh-listen",
            "udp/127.0.0.1:0",
            "--grpc-listen",
            "127.0.0.1:0",
            "--http-listen",
            "127.0.0.1:0",
        ],
    );
    assert!(!out.status.success(), "an endpoint of a transport bgkmap was built without fails");
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("zenoh"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
