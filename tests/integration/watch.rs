//! The change stream against the real `bgkmap serve` binary: gRPC `WatchUpdates` (a late
//! subscriber asking "since version N" ends with the same blocks as one that watched from the
//! start; a cache from before a restart is reset; box filter; bad requests) and the same stream
//! as HTTP server-sent events.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::sim::{Lidar, simulate};
use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Write};
use tonic::Code;
use tonic::transport::Channel;

type Client = MapServiceClient<Channel>;
type Block = [i32; 3];
/// A cache of cells per block: block → sorted (cell key, probability bits, variance bits).
type Cache = BTreeMap<Block, Vec<([i32; 3], u64, u64)>>;

async fn connect(url: String) -> Client {
    MapServiceClient::connect(url)
        .await
        .unwrap()
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20)
}

fn blocks_of(u: &pb::MapUpdate) -> Vec<Block> {
    u.block.chunks(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Every cell with evidence, grouped by block (Export, optionally in a box).
async fn export(client: &mut Client, bbox: Option<([f64; 3], [f64; 3])>) -> Cache {
    let (min, max) = bbox.map_or((vec![], vec![]), |(a, b)| (a.to_vec(), b.to_vec()));
    let req = pb::ExportRequest { map: "m".into(), min, max, thresholds: None };
    let mut stream = client.export(req).await.unwrap().into_inner();
    let mut cache = Cache::new();
    while let Some(chunk) = stream.message().await.unwrap() {
        for (i, c) in chunk.cell.chunks(3).enumerate() {
            let block = [c[0] >> 3, c[1] >> 3, c[2] >> 3];
            let cell = ([c[0], c[1], c[2]], chunk.probability[i].to_bits(), chunk.variance[i].to_bits());
            cache.entry(block).or_default().push(cell);
        }
    }
    cache
}

/// Re-reads the blocks an update names (one Export over their bounding box).
async fn refresh(client: &mut Client, cache: &mut Cache, blocks: &[Block], res: f64) {
    if blocks.is_empty() {
        return;
    }
    let lo = [0, 1, 2].map(|i| blocks.iter().map(|b| b[i]).min().unwrap());
    let hi = [0, 1, 2].map(|i| blocks.iter().map(|b| b[i]).max().unwrap());
    let min = lo.map(|v| (f64::from(v * 8) + 0.5) * res);
    let max = hi.map(|v| (f64::from(v * 8 + 7) + 0.5) * res);
    let fresh = export(client, Some((min, max))).await;
    for b in blocks {
        match fresh.get(b) {
            Some(cells) => cache.insert(*b, cells.clone()),
            None => cache.remove(b),
        };
    }
}

fn scan_req(seq: u64, s: &bgkmap::sim::SimScan) -> pb::InsertScanRequest {
    pb::InsertScanRequest {
        map: "m".into(),
        scan: Some(pb::Scan::world("robot", seq, s.origin, &s.points_world)),
        // Integrated before the next is sent: one live update per scan.
        wait_applied: true,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_subscriber_since_n_ends_with_the_same_blocks_as_an_early_one() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let mut client = connect(server.grpc_url()).await;
    client.create_map(pb::CreateMapRequest { map: "m".into(), params: None }).await.unwrap();
    let res = 0.1;
    let (_, scans) = simulate(0, 8, &Lidar::default());

    let watch =
        |since| pb::WatchUpdatesRequest { map: "m".into(), since_version: since, ..Default::default() };
    let mut early = client.clone().watch_updates(watch(Some(0))).await.unwrap().into_inner();
    let first = early.message().await.unwrap().unwrap();
    assert_eq!((first.kind, first.version, first.block.len()), (pb::UpdateKind::CatchUp as i32, 0, 0));
    assert_eq!((first.block_edge, first.resolution), (8, res));

    let mut early_cache = Cache::new();
    let mut late_cache = Cache::new();
    let mut named_after_3 = BTreeSet::new();
    for (i, s) in scans.iter().enumerate() {
        let seq = i as u64 + 1;
        client.insert_scan(scan_req(seq, s)).await.unwrap();
        let u = early.message().await.unwrap().unwrap();
        assert_eq!((u.kind, u.from_version, u.version), (pb::UpdateKind::Live as i32, seq - 1, seq));
        let pose = &u.poses[0];
        assert_eq!((pose.version, pose.seq, pose.source.as_str()), (seq, seq, "robot"));
        assert_eq!(pose.world_from_sensor.as_ref().unwrap().translation, s.origin.to_vec());
        let blocks = blocks_of(&u);
        refresh(&mut client, &mut early_cache, &blocks, res).await;
        if seq == 3 {
            // A second client caches the map at version 3, then goes away.
            late_cache = export(&mut client, None).await;
        } else if seq > 3 {
            named_after_3.extend(blocks);
        }
    }

    // It comes back and asks for what changed since version 3.
    let mut late = client.clone().watch_updates(watch(Some(3))).await.unwrap().into_inner();
    let catch_up = late.message().await.unwrap().unwrap();
    assert_eq!(
        (catch_up.kind, catch_up.from_version, catch_up.version),
        (pb::UpdateKind::CatchUp as i32, 3, 8)
    );
    let blocks = blocks_of(&catch_up);
    assert_eq!(
        blocks.iter().copied().collect::<BTreeSet<_>>(),
        named_after_3,
        "exactly the blocks changed after 3"
    );
    assert!(blocks.windows(2).all(|w| w[0] < w[1]), "sorted");
    assert_eq!(catch_up.poses.iter().map(|p| p.seq).collect::<Vec<_>>(), vec![4, 5, 6, 7, 8]);
    refresh(&mut client, &mut late_cache, &blocks, res).await;

    let truth = export(&mut client, None).await;
    assert_eq!(early_cache, truth, "the watcher's cache is the map");
    assert_eq!(late_cache, truth, "the late subscriber's cache is the map");

    // Both streams go on with the next scan.
    let (_, more) = simulate(1, 1, &Lidar::default());
    client.insert_scan(scan_req(9, &more[0])).await.unwrap();
    for stream in [&mut early, &mut late] {
        let u = stream.message().await.unwrap().unwrap();
        assert_eq!((u.kind, u.version), (pb::UpdateKind::Live as i32, 9));
    }
    // Shutdown ends the streams with UNAVAILABLE instead of hanging the server.
    let status = server.terminate();
    assert!(status.success(), "{status}");
    let end = early.message().await;
    assert!(matches!(&end, Err(s) if s.code() == Code::Unavailable) || matches!(end, Ok(None)), "{end:?}");
}

async fn first_update(client: &mut Client, since: u64) -> pb::MapUpdate {
    let req = pb::WatchUpdatesRequest { map: "m".into(), since_version: Some(since), ..Default::default() };
    client.watch_updates(req).await.unwrap().into_inner().message().await.unwrap().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cache_from_before_a_restart_is_reset_not_left_stale() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let mut client = connect(server.grpc_url()).await;
    client.create_map(pb::CreateMapRequest { map: "m".into(), params: None }).await.unwrap();
    let (_, scans) = simulate(0, 2, &Lidar::default());
    for (i, s) in scans.iter().enumerate() {
        client.insert_scan(scan_req(i as u64 + 1, s)).await.unwrap();
    }
    // A patch far from the room from a second source: blocks only it touches.
    let points: Vec<[f32; 3]> =
        (0..400).map(|i| [30.0 + (i % 20) as f32 * 0.05, 30.0 + (i / 20) as f32 * 0.05, 0.5]).collect();
    let scan = pb::Scan::world("robot2", 1, [30.5, 30.5, 2.5], &points);
    client
        .insert_scan(pb::InsertScanRequest { map: "m".into(), scan: Some(scan), wait_applied: true })
        .await
        .unwrap();
    let mut cache = export(&mut client, None).await;
    let patch = blocks_of(&first_update(&mut client, 2).await);
    assert!(!patch.is_empty() && patch.iter().all(|b| cache.contains_key(b)));
    let retract = pb::RetractScansRequest { map: "m".into(), source: "robot2".into(), ..Default::default() };
    assert_eq!(client.retract_scans(retract).await.unwrap().into_inner().version, 4);
    assert!(server.terminate().success());

    // Versions resume from the map file; the blocks the retraction emptied are not known any more.
    let server = common::start_serve(dir.path(), &[]);
    let mut client = connect(server.grpc_url()).await;
    let u = first_update(&mut client, 3).await;
    assert_eq!((u.kind, u.from_version, u.version, u.reset), (pb::UpdateKind::CatchUp as i32, 3, 4, true));
    let listed = blocks_of(&u);
    assert!(patch.iter().all(|b| !listed.contains(b)));
    cache.retain(|b, _| listed.contains(b));
    refresh(&mut client, &mut cache, &listed, u.resolution).await;
    assert_eq!(cache, export(&mut client, None).await, "the reset cache holds exactly the map");
    let now = first_update(&mut client, 4).await;
    assert!(now.block.is_empty() && !now.reset);
    // The viewer's binary `since` answer cannot list the forgotten blocks either: 410.
    let (code, body) = common::http_request(server.http_addr, "GET", "/v1/maps/m/cells?since=3", b"");
    assert_eq!(code, 410, "{body}");
    assert!(body.contains("load the whole map"), "{body}");
    assert_eq!(common::http_request(server.http_addr, "GET", "/v1/maps/m/cells?since=4", b"").0, 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn box_filter_and_bad_watch_requests() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let mut client = connect(server.grpc_url()).await;
    client.create_map(pb::CreateMapRequest { map: "m".into(), params: None }).await.unwrap();
    let (_, scans) = simulate(0, 1, &Lidar::default());
    client.insert_scan(scan_req(1, &scans[0])).await.unwrap();

    let all = client
        .watch_updates(pb::WatchUpdatesRequest {
            map: "m".into(),
            since_version: Some(0),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
        .message()
        .await
        .unwrap()
        .unwrap();
    let boxed = pb::WatchUpdatesRequest {
        map: "m".into(),
        min: vec![0.0, 0.0, 0.0],
        max: vec![2.0, 2.0, 1.0],
        since_version: Some(0),
    };
    let inside = client.watch_updates(boxed).await.unwrap().into_inner().message().await.unwrap().unwrap();
    // Blocks of 0.8 m overlapping [0, 2] × [0, 2] × [0, 1]: keys 0..=2, 0..=2, 0..=1.
    let want: Vec<Block> = blocks_of(&all)
        .into_iter()
        .filter(|b| (0..=2).contains(&b[0]) && (0..=2).contains(&b[1]) && (0..=1).contains(&b[2]))
        .collect();
    assert!(!want.is_empty() && want.len() < blocks_of(&all).len());
    assert_eq!(blocks_of(&inside), want);

    let err = |r: Result<tonic::Response<tonic::Streaming<pb::MapUpdate>>, tonic::Status>| r.unwrap_err();
    let e =
        err(client.watch_updates(pb::WatchUpdatesRequest { map: "nope".into(), ..Default::default() }).await);
    assert_eq!(e.code(), Code::NotFound);
    let ahead = pb::WatchUpdatesRequest { map: "m".into(), since_version: Some(5), ..Default::default() };
    let e = err(client.watch_updates(ahead).await);
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("bgkmap.v1.WatchUpdatesRequest.since_version: "), "{}", e.message());
    let half = pb::WatchUpdatesRequest { map: "m".into(), min: vec![0.0; 3], ..Default::default() };
    let e = err(client.watch_updates(half).await);
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("WatchUpdatesRequest.max"), "{}", e.message());
    let inverted = pb::WatchUpdatesRequest {
        map: "m".into(),
        min: vec![1.0; 3],
        max: vec![0.0; 3],
        ..Default::default()
    };
    assert_eq!(err(client.watch_updates(inverted).await).code(), Code::InvalidArgument);
}

/// Reads SSE `data:` JSON messages from a raw HTTP/1.1 response until one has `version`.
fn sse_until(reader: &mut impl BufRead, version: u64) -> Vec<serde_json::Value> {
    let mut out: Vec<serde_json::Value> = Vec::new();
    let mut line = String::new();
    while out.last().is_none_or(|v| v["version"] != version) {
        line.clear();
        assert!(reader.read_line(&mut line).unwrap() > 0, "the stream ended early");
        if let Some(d) = line.trim_end().strip_prefix("data: ") {
            out.push(serde_json::from_str(d).unwrap());
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_stream_as_server_sent_events() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let mut client = connect(server.grpc_url()).await;
    client.create_map(pb::CreateMapRequest { map: "m".into(), params: None }).await.unwrap();
    let (_, scans) = simulate(0, 3, &Lidar::default());
    client.insert_scan(scan_req(1, &scans[0])).await.unwrap();

    let addr = server.http_addr;
    let reader = std::thread::spawn(move || {
        let mut s = std::net::TcpStream::connect(addr).unwrap();
        write!(
            s,
            "GET /v1/maps/m/updates?since=0 HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
        )
        .unwrap();
        let mut r = BufReader::new(s);
        let mut status = String::new();
        r.read_line(&mut status).unwrap();
        assert!(status.contains(" 200 "), "{status}");
        sse_until(&mut r, 3)
    });
    client.insert_scan(scan_req(2, &scans[1])).await.unwrap();
    client.insert_scan(scan_req(3, &scans[2])).await.unwrap();
    let events = tokio::task::spawn_blocking(move || reader.join().unwrap()).await.unwrap();
    // A catch-up since 0 (up to whatever version the connect saw), then consecutive live updates.
    assert_eq!((events[0]["kind"].as_str(), events[0]["from_version"].as_u64()), (Some("catch_up"), Some(0)));
    assert!(!events[0]["blocks"].as_array().unwrap().is_empty());
    for w in events.windows(2) {
        assert_eq!(w[1]["kind"], "live");
        assert_eq!(w[1]["from_version"], w[0]["version"]);
        assert_eq!(w[1]["version"].as_u64().unwrap(), w[0]["version"].as_u64().unwrap() + 1);
    }
    let last = events.last().unwrap();
    assert_eq!(last["poses"][0]["source"], "robot");
    assert_eq!(last["poses"][0]["seq"], 3);
    assert_eq!(last["poses"][0]["rotation"], serde_json::json!([1.0, 0.0, 0.0, 0.0]));
    assert_eq!((last["block_edge"].as_u64(), last["resolution"].as_f64()), (Some(8), Some(0.1)));

    let (code, body) = get(addr, "/v1/maps/m/updates?since=x");
    assert_eq!(code, 400, "{body}");
    let (code, _) = get(addr, "/v1/maps/nope/updates");
    assert_eq!(code, 404);
    let (code, body) = get(addr, "/v1/maps/m/updates?since=99");
    assert_eq!(code, 400, "{body}");
}

/// A GET with `Connection: close`: status code and the whole response text.
fn get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    use std::io::Read;
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (code, text)
}
