//! The viewer's HTTP side against the real `bgkmap serve`: the page and its assets, the binary
//! cells answer (decoded here and compared bit for bit with the core on an offline build),
//! `since` answers, one cell's details, recent poses, and bad requests.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::core::query::{BoxQuery, query_box};
use bgkmap::core::{EvidenceMap, Integrator, MapParams};
use bgkmap::sim::{Lidar, simulate};
use std::io::{Read, Write};

/// A GET with `Connection: close`: status, headers (lower-case text) and body.
fn get(addr: std::net::SocketAddr, path: &str) -> (u16, String, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&raw[..split]).to_lowercase();
    assert!(!head.contains("transfer-encoding: chunked"), "{head}");
    let code = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (code, head, raw[split + 4..].to_vec())
}

/// The binary cells answer, decoded as the module docs of `src/api/http/viewer.rs` lay it out.
#[derive(Debug)]
struct Cells {
    version: u64,
    resolution: f64,
    coarsen: u32,
    lo: [f32; 3],
    hi: [f32; 3],
    centres: Vec<[f32; 3]>,
    sizes: Vec<f32>,
    probability: Vec<f64>,
    variance: Vec<f64>,
    blocks: Vec<[i32; 3]>,
}

fn decode(b: &[u8]) -> Cells {
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let f32_at = |o: usize| f32::from_le_bytes(b[o..o + 4].try_into().unwrap());
    let f64_at = |o: usize| f64::from_le_bytes(b[o..o + 8].try_into().unwrap());
    assert_eq!(&b[..4], b"BGKC");
    assert_eq!(u32_at(4), 1);
    let (n, m) = (u32_at(8) as usize, u32_at(12) as usize);
    assert_eq!(b.len(), 64 + 32 * n + 12 * m);
    assert_eq!(u32_at(36), 8);
    let (c0, s0, p0, v0, k0) = (64, 64 + 12 * n, 64 + 16 * n, 64 + 24 * n, 64 + 32 * n);
    Cells {
        version: u64::from_le_bytes(b[16..24].try_into().unwrap()),
        resolution: f64_at(24),
        coarsen: u32_at(32),
        lo: [f32_at(40), f32_at(44), f32_at(48)],
        hi: [f32_at(52), f32_at(56), f32_at(60)],
        centres: (0..n).map(|i| [0, 1, 2].map(|k| f32_at(c0 + 12 * i + 4 * k))).collect(),
        sizes: (0..n).map(|i| f32_at(s0 + 4 * i)).collect(),
        probability: (0..n).map(|i| f64_at(p0 + 8 * i)).collect(),
        variance: (0..n).map(|i| f64_at(v0 + 8 * i)).collect(),
        blocks: (0..m).map(|i| [0, 1, 2].map(|k| u32_at(k0 + 12 * i + 4 * k) as i32)).collect(),
    }
}

/// The core's box answer in the same form: (centre, size, p bits, var bits), sorted by key.
fn core_cells(
    map: &EvidenceMap,
    min: [f64; 3],
    max: [f64; 3],
    coarsen: u8,
) -> Vec<([f32; 3], f32, u64, u64)> {
    let res = map.params().resolution_m;
    let q = BoxQuery { min_world: min, max_world: max, state: None, coarsen };
    query_box(map, &q, &map.params().thresholds, u64::MAX)
        .unwrap()
        .iter()
        .map(|c| {
            let half = f64::from(c.size_cells) / 2.0;
            let k = c.min_cell;
            let centre = [k.x, k.y, k.z].map(|v| ((f64::from(v) + half) * res) as f32);
            let size = (f64::from(c.size_cells) * res) as f32;
            (centre, size, c.estimate.probability.to_bits(), c.estimate.variance.to_bits())
        })
        .collect()
}

fn rows(c: &Cells) -> Vec<([f32; 3], f32, u64, u64)> {
    (0..c.sizes.len())
        .map(|i| (c.centres[i], c.sizes[i], c.probability[i].to_bits(), c.variance[i].to_bits()))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_cells_cell_and_poses() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &[]);
    let addr = server.http_addr;
    let mut client = MapServiceClient::connect(server.grpc_url()).await.unwrap();
    client.create_map(pb::CreateMapRequest { map: "m".into(), params: None }).await.unwrap();
    let (_, scans) = simulate(0, 3, &Lidar::default());
    let mut offline = vec![EvidenceMap::new(MapParams::default())];
    let mut integ = Integrator::new(MapParams::default());
    for (i, s) in scans.iter().enumerate() {
        let scan = pb::Scan::world("r", i as u64 + 1, s.origin, &s.points_world);
        client
            .insert_scan(pb::InsertScanRequest { map: "m".into(), scan: Some(scan), wait_applied: true })
            .await
            .unwrap();
        let mut next = offline.last().unwrap().clone();
        integ.integrate(&mut next, &s.points_world, s.origin, 1);
        offline.push(next);
    }
    let map = offline.last().unwrap();

    let (code, head, page) = get(addr, "/");
    assert_eq!(code, 200);
    assert!(head.contains("content-type: text/html"));
    assert!(
        String::from_utf8(page).unwrap().contains(r#"<script type="module" src="/static/viewer.bundle.js">"#)
    );
    let (code, head, js) = get(addr, "/static/viewer.bundle.js");
    assert_eq!(code, 200);
    assert!(head.contains("content-type: text/javascript"), "{head}");
    assert!(js.len() > 100_000, "three.js is in the bundle");

    // The whole map: every cell with evidence, equal to the core's answer over the map's blocks.
    let (code, head, body) = get(addr, "/v1/maps/m/cells");
    assert_eq!(code, 200);
    assert!(head.contains("content-type: application/octet-stream"));
    let all = decode(&body);
    assert_eq!((all.version, all.resolution, all.coarsen), (3, 0.1, 0));
    assert_eq!(all.sizes.len(), map.cells_with_evidence());
    assert!(all.blocks.is_empty());
    let (lo, hi) = (all.lo.map(f64::from), all.hi.map(f64::from));
    let inner = |v: [f64; 3], d: f64| v.map(|x| x + d);
    assert_eq!(rows(&all), core_cells(map, inner(lo, 0.05), inner(hi, -0.05), 0));

    // A box, coarsened.
    let (_, _, body) = get(addr, "/v1/maps/m/cells?min=1,1,0&max=4,3.5,1.5&coarsen=1");
    let coarse = decode(&body);
    assert_eq!(coarse.coarsen, 1);
    assert!(coarse.sizes.iter().all(|s| *s == 0.2f32));
    assert_eq!(rows(&coarse), core_cells(map, [1.0, 1.0, 0.0], [4.0, 3.5, 1.5], 1));

    // Since version 1: the blocks scans 2 and 3 changed, and all their cells now.
    let (_, _, body) = get(addr, "/v1/maps/m/cells?since=1");
    let since = decode(&body);
    let mut watch = client
        .watch_updates(pb::WatchUpdatesRequest {
            map: "m".into(),
            since_version: Some(1),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let catch_up = watch.message().await.unwrap().unwrap();
    let want: Vec<[i32; 3]> = catch_up.block.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    assert_eq!(since.blocks, want);
    let mut expect = Vec::new();
    for b in &want {
        let lo = b.map(|v| (f64::from(v * 8) + 0.5) * 0.1);
        let hi = b.map(|v| (f64::from(v * 8 + 7) + 0.5) * 0.1);
        expect.extend(core_cells(map, lo, hi, 0));
    }
    assert_eq!(rows(&since), expect);
    assert!(since.sizes.len() < all.sizes.len());
    let (_, _, body) = get(addr, "/v1/maps/m/cells?since=3");
    assert!(decode(&body).sizes.is_empty());

    // One cell, with its Beta posterior.
    let (code, _, body) = get(addr, "/v1/maps/m/cell?at=2.05,1.05,0.55&p_occ=0.6");
    assert_eq!(code, 200);
    let cell: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let th = bgkmap::core::Thresholds { p_occ: 0.6, ..Default::default() };
    let e = map.estimate(bgkmap::core::CellKey::new(20, 10, 5), &th);
    assert_eq!(cell["cell"], serde_json::json!([20, 10, 5]));
    assert_eq!(cell["probability"].as_f64().unwrap().to_bits(), e.probability.to_bits());
    assert_eq!(cell["variance"].as_f64().unwrap().to_bits(), e.variance.to_bits());
    assert_eq!(cell["state"], e.state.as_str());
    let (alpha, beta) = e.alpha_beta(map.params());
    assert_eq!((cell["alpha"].as_f64().unwrap(), cell["beta"].as_f64().unwrap()), (alpha, beta));

    let (_, _, body) = get(addr, "/v1/maps/m/poses");
    let poses: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let seqs: Vec<u64> =
        poses["poses"].as_array().unwrap().iter().map(|p| p["seq"].as_u64().unwrap()).collect();
    assert_eq!(seqs, vec![1, 2, 3]);

    for (path, needle) in [
        ("/v1/maps/m/cells?coarsen=11", "coarsen"),
        ("/v1/maps/m/cells?since=4", "ahead"),
        ("/v1/maps/m/cells?since=1&coarsen=4", "coarsen"),
        ("/v1/maps/m/cells?state=solid", "state"),
        ("/v1/maps/m/cells?min=0,0,0", "min and max"),
        ("/v1/maps/m/cells?min=0,0,0&max=1,1", "max"),
        ("/v1/maps/m/cells?p_occ=2", "p_occ"),
        ("/v1/maps/m/cell?at=1,2", "at"),
    ] {
        let (code, _, body) = get(addr, path);
        let text = String::from_utf8_lossy(&body);
        assert_eq!(code, 400, "{path}: {text}");
        assert!(text.contains(needle), "{path}: {text}");
    }
    assert_eq!(get(addr, "/v1/maps/nope/cells").0, 404);
    assert_eq!(get(addr, "/v1/maps/nope/poses").0, 404);
}

#[test]
fn a_box_over_the_limit_is_coarsened_until_it_fits() {
    let dir = tempfile::tempdir().unwrap();
    let server = common::start_serve(dir.path(), &["--max-box-cells", "1000"]);
    let addr = server.http_addr;
    let body = br#"{"source": "r", "seq": 1, "pose": {"translation": [0, 0, 1], "rotation": [1, 0, 0, 0]},
                    "points": [[2, 0, 1], [2, 0.5, 1], [2, 1, 1], [2, -0.5, 1]]}"#;
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "PUT /v1/maps/m HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
        .unwrap();
    s.read_to_end(&mut Vec::new()).unwrap();
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(
        s,
        "POST /v1/maps/m/scans?wait_applied=true HTTP/1.1\r\nHost: x\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    )
    .unwrap();
    s.write_all(body).unwrap();
    let mut ack = String::new();
    s.read_to_string(&mut ack).unwrap();
    assert!(ack.contains(r#""applied":true"#), "{ack}");
    // The answer is at the finest level whose lattice over the map's blocks fits the limit.
    let (code, _, body) = get(addr, "/v1/maps/m/cells");
    assert_eq!(code, 200);
    let cells = decode(&body);
    let lo = cells.lo.map(|v| ((f64::from(v) + 0.05) / 0.1).floor() as i64);
    let hi = cells.hi.map(|v| ((f64::from(v) - 0.05) / 0.1).floor() as i64);
    let positions = |s: u32| (0..3).map(|k| (hi[k] >> s) - (lo[k] >> s) + 1).product::<i64>();
    assert!(positions(0) > 1000, "the map's box is over the limit at full resolution");
    assert!(cells.coarsen >= 1 && positions(cells.coarsen) <= 1000 && positions(cells.coarsen - 1) > 1000);
    let edge = (0.1 * f64::from(1u32 << cells.coarsen)) as f32;
    assert!(!cells.sizes.is_empty() && cells.sizes.iter().all(|s| *s == edge));
    // Asking for a coarser level than needed gets that level.
    let (_, _, body) = get(addr, "/v1/maps/m/cells?coarsen=5");
    assert_eq!(decode(&body).coarsen, 5);
}
