//! gRPC acceptance tests: the real `bgkmap serve` binary (and, for the busy answer, the gRPC
//! routes served in-process) driven by the generated client. Every query answer must equal, bit
//! for bit, the in-process core answer on a map built offline from the same scans.
#![cfg(feature = "server")]
#![allow(clippy::unwrap_used)]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use bgkmap::core::query::{BoxQuery, RayHit, StopAt, cast_ray, query_box, query_points};
use bgkmap::core::{CellKey, CellState, EvidenceMap, Integrator, MapParams};
use bgkmap::sim::{Lidar, SimScan, simulate};
use common::{ServeProcess, start_serve};
use tonic::Code;
use tonic::transport::Channel;

type Client = MapServiceClient<Channel>;

const MIB64: usize = 64 << 20;

async fn connect(server: &ServeProcess) -> Client {
    connect_url(server.grpc_url()).await
}

async fn connect_url(url: String) -> Client {
    MapServiceClient::connect(url)
        .await
        .unwrap()
        .max_decoding_message_size(MIB64)
        .max_encoding_message_size(MIB64)
}

fn xyz_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flatten().flat_map(|v| v.to_le_bytes()).collect()
}

/// A world-frame scan message: pose translation = the scan origin, identity rotation.
fn scan_msg(source: &str, seq: u64, s: &SimScan) -> pb::Scan {
    pb::Scan {
        source: source.into(),
        seq,
        world_from_sensor: Some(pb::Pose {
            translation: s.origin.to_vec(),
            rotation: vec![1.0, 0.0, 0.0, 0.0],
        }),
        frame: pb::Frame::World as i32,
        xyz_f32: xyz_bytes(&s.points_world),
        max_range: None,
        stamp_nanos: None,
    }
}

fn insert_req(map: &str, scan: pb::Scan) -> pb::InsertScanRequest {
    // The tests compare with offline builds right after: answer once integrated.
    pb::InsertScanRequest { map: map.into(), scan: Some(scan), wait_applied: true }
}

/// The map parameters every test uses: the defaults with `max_range: 8` set explicitly.
fn params() -> MapParams {
    MapParams { max_range_m: 8.0, ..MapParams::default() }
}

fn pb_params() -> pb::MapParams {
    pb::MapParams { max_range: Some(8.0), ..Default::default() }
}

fn offline(scans: &[SimScan]) -> EvidenceMap {
    let mut map = EvidenceMap::new(params());
    let mut integ = Integrator::new(params());
    for s in scans {
        integ.integrate(&mut map, &s.points_world, s.origin, 1);
    }
    map
}

fn pb_state(s: CellState) -> i32 {
    match s {
        CellState::Free => pb::CellState::Free as i32,
        CellState::Occupied => pb::CellState::Occupied as i32,
        CellState::Unknown => pb::CellState::Unknown as i32,
    }
}

fn key(v: &[i32]) -> CellKey {
    CellKey::new(v[0], v[1], v[2])
}

/// Query points on a lattice over (and a little beyond) the room interior.
fn query_lattice(lo: [f64; 3], hi: [f64; 3]) -> Vec<[f32; 3]> {
    let mut pts = Vec::new();
    let mut z = lo[2] - 0.3;
    while z <= hi[2] + 0.3 {
        let mut y = lo[1] - 0.5;
        while y <= hi[1] + 0.5 {
            let mut x = lo[0] - 0.5;
            while x <= hi[0] + 0.5 {
                pts.push([x as f32, y as f32, z as f32]);
                x += 0.37;
            }
            y += 0.29;
        }
        z += 0.23;
    }
    pts
}

async fn map_info(client: &mut Client, map: &str) -> pb::MapInfo {
    client.get_map(pb::GetMapRequest { map: map.into() }).await.unwrap().into_inner()
}

/// (version, blocks, cells with evidence) of a map.
async fn state_of(client: &mut Client, map: &str) -> (u64, u64, u64) {
    let i = map_info(client, map).await;
    (i.version, i.blocks, i.cells_with_evidence)
}

/// QueryPoints over the lattice equals `query_points` on the offline map, bit for bit.
async fn assert_points_equal(
    client: &mut Client,
    map: &str,
    reference: &EvidenceMap,
    pts: &[[f32; 3]],
) -> usize {
    let resp = client
        .query_points(pb::QueryPointsRequest { map: map.into(), xyz_f32: xyz_bytes(pts), thresholds: None })
        .await
        .unwrap()
        .into_inner();
    let p64: Vec<[f64; 3]> = pts.iter().map(|p| p.map(f64::from)).collect();
    let want = query_points(reference, &p64, &reference.params().thresholds);
    assert_eq!(resp.probability.len(), pts.len());
    assert_eq!(resp.variance.len(), pts.len());
    assert_eq!(resp.state.len(), pts.len());
    assert_eq!(resp.cell.len(), 3 * pts.len());
    let mut occupied = 0;
    for (i, w) in want.iter().enumerate() {
        let w = w.unwrap();
        assert_eq!(key(&resp.cell[3 * i..3 * i + 3]), w.cell, "point {i}");
        assert_eq!(resp.probability[i].to_bits(), w.estimate.probability.to_bits(), "point {i}");
        assert_eq!(resp.variance[i].to_bits(), w.estimate.variance.to_bits(), "point {i}");
        assert_eq!(resp.state[i], pb_state(w.estimate.state), "point {i}");
        occupied += usize::from(w.estimate.state == CellState::Occupied);
    }
    occupied
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_answers_equal_the_core_and_survive_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (scene, scans) = simulate(0, 3, &Lidar::default());
    let reference = offline(&scans);
    let server = start_serve(dir.path(), &[]);
    let mut client = connect(&server).await;

    // Create, list, get: every parameter is filled in.
    let info = client
        .create_map(pb::CreateMapRequest { map: "room".into(), params: Some(pb_params()) })
        .await
        .unwrap()
        .into_inner();
    let p = params();
    let want_params = pb::MapParams {
        resolution: Some(p.resolution_m),
        sf2: Some(p.sf2),
        ell: Some(p.ell_m),
        free_resolution: Some(p.free_resolution_m),
        ds_resolution: Some(p.ds_resolution_m),
        max_range: Some(8.0),
        range_mode: Some("truncate".into()),
        prior_a: Some(p.prior_a),
        prior_b: Some(p.prior_b),
        p_free: Some(p.thresholds.p_free),
        p_occ: Some(p.thresholds.p_occ),
        var_max: Some(p.thresholds.var_max),
        sub_cells: Some(p.sub_cells),
    };
    assert_eq!(info.map, "room");
    assert_eq!(info.params.as_ref(), Some(&want_params));
    assert_eq!((info.version, info.blocks, info.cells_with_evidence), (0, 0, 0));
    let listed = client.list_maps(pb::ListMapsRequest {}).await.unwrap().into_inner().maps;
    assert_eq!(listed.iter().map(|m| m.map.as_str()).collect::<Vec<_>>(), ["room"]);
    assert_eq!(map_info(&mut client, "room").await, info);

    // One scan with InsertScan, the other two over one InsertScans stream.
    let ack = client.insert_scan(insert_req("room", scan_msg("robot1", 1, &scans[0]))).await.unwrap();
    assert_eq!(ack.into_inner(), pb::InsertScanResponse { applied: true, version: 1, dropped_points: 0 });
    let stream = tokio_stream::iter(vec![
        insert_req("room", scan_msg("robot1", 2, &scans[1])),
        insert_req("room", scan_msg("robot1", 3, &scans[2])),
    ]);
    let summary = client.insert_scans(stream).await.unwrap().into_inner();
    assert_eq!(summary, pb::InsertScansResponse { scans: 2, applied: 2, duplicates: 0, version: 3 });

    let info = map_info(&mut client, "room").await;
    assert_eq!(info.version, 3);
    assert_eq!(info.blocks, reference.block_count() as u64);
    assert_eq!(info.cells_with_evidence, reference.cells_with_evidence() as u64);
    assert_eq!(info.sources.len(), 1);
    let src = &info.sources[0];
    assert_eq!((src.source.as_str(), src.received, src.applied, src.highest_seq), ("robot1", 3, 3, Some(3)));

    // QueryPoints.
    let lattice = query_lattice(scene.interior_min, scene.interior_max);
    assert!(lattice.len() > 10_000, "exercise the blocking path too ({} points)", lattice.len());
    let occupied = assert_points_equal(&mut client, "room", &reference, &lattice).await;
    assert!(occupied > 0, "the lattice should touch some occupied cells");
    assert_points_equal(&mut client, "room", &reference, &lattice[..500]).await;

    // QueryBox at two resolutions, with and without a state filter, and counts only.
    let th = reference.params().thresholds;
    for (coarsen, state) in
        [(0u8, None), (2, None), (0, Some(CellState::Occupied)), (1, Some(CellState::Free))]
    {
        let (min, max) = ([4.0, 1.0, 0.0], [6.5, 3.0, 1.5]);
        let q = BoxQuery { min_world: min, max_world: max, state, coarsen };
        let want = query_box(&reference, &q, &th, 4_000_000).unwrap();
        assert!(!want.is_empty());
        let req = pb::QueryBoxRequest {
            map: "room".into(),
            min: min.to_vec(),
            max: max.to_vec(),
            state: state.map(pb_state),
            coarsen: u32::from(coarsen),
            thresholds: None,
            counts_only: false,
        };
        let got = client.query_box(req.clone()).await.unwrap().into_inner();
        assert_eq!(got.version, 3);
        assert_eq!(got.size_cells.len(), want.len());
        for (i, w) in want.iter().enumerate() {
            assert_eq!(key(&got.min_cell[3 * i..3 * i + 3]), w.min_cell);
            assert_eq!(got.size_cells[i], 1u32 << coarsen);
            assert_eq!(got.probability[i].to_bits(), w.estimate.probability.to_bits());
            assert_eq!(got.variance[i].to_bits(), w.estimate.variance.to_bits());
            assert_eq!(got.state[i], pb_state(w.estimate.state));
        }
        let n = |s| want.iter().filter(|c| c.estimate.state == s).count() as u64;
        let counts = (n(CellState::Free), n(CellState::Occupied), n(CellState::Unknown));
        assert_eq!((got.free, got.occupied, got.unknown), counts);
        let only =
            client.query_box(pb::QueryBoxRequest { counts_only: true, ..req }).await.unwrap().into_inner();
        assert!(only.min_cell.is_empty() && only.probability.is_empty() && only.state.is_empty());
        assert_eq!((only.free, only.occupied, only.unknown), counts);
    }

    // CastRays from every scan origin in 26 directions, both stop rules.
    let mut rays = Vec::new();
    for s in &scans {
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if (dx, dy, dz) != (0, 0, 0) {
                        let d = [f64::from(dx), f64::from(dy) * 0.7, f64::from(dz) * 0.3];
                        rays.push(pb::Ray {
                            origin: s.origin.to_vec(),
                            direction: d.to_vec(),
                            max_range: 8.0,
                        });
                    }
                }
            }
        }
        rays.push(pb::Ray { origin: s.origin.to_vec(), direction: vec![0.0, 0.0, 1.0], max_range: 0.05 });
    }
    for (stop, pb_stop) in [(StopAt::Occupied, pb::StopAt::Occupied), (StopAt::NotFree, pb::StopAt::NotFree)]
    {
        let resp = client
            .cast_rays(pb::CastRaysRequest {
                map: "room".into(),
                rays: rays.clone(),
                stop_at: pb_stop as i32,
                thresholds: None,
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(resp.version, 3);
        assert_eq!(resp.results.len(), rays.len());
        let mut blocked = 0;
        for (r, got) in rays.iter().zip(&resp.results) {
            let o = [r.origin[0], r.origin[1], r.origin[2]];
            let d = [r.direction[0], r.direction[1], r.direction[2]];
            match cast_ray(&reference, o, d, r.max_range, stop, &th).unwrap() {
                RayHit::Clear => {
                    assert!(!got.blocked);
                    assert!(got.cell.is_empty());
                    assert_eq!(got.distance, r.max_range);
                }
                RayHit::Blocked { cell, distance_m, estimate } => {
                    blocked += 1;
                    assert!(got.blocked);
                    assert_eq!(key(&got.cell), cell);
                    assert_eq!(got.distance.to_bits(), distance_m.to_bits());
                    assert_eq!(got.state, pb_state(estimate.state));
                    assert_eq!(got.probability.to_bits(), estimate.probability.to_bits());
                }
            }
        }
        assert!(blocked > rays.len() / 2, "most rays should hit the room's walls");
    }

    // Export: every cell with evidence, sorted by key, in chunks.
    let mut chunks = client
        .export(pb::ExportRequest { map: "room".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    let mut cells: Vec<CellKey> = Vec::new();
    while let Some(chunk) = chunks.message().await.unwrap() {
        let n = chunk.probability.len();
        assert!(n <= 65_536);
        assert_eq!((chunk.cell.len(), chunk.variance.len()), (3 * n, n));
        assert_eq!(chunk.resolution, 0.1);
        for i in 0..n {
            let c = key(&chunk.cell[3 * i..3 * i + 3]);
            let e = reference.estimate(c, &th);
            assert_eq!(chunk.probability[i].to_bits(), e.probability.to_bits());
            assert_eq!(chunk.variance[i].to_bits(), e.variance.to_bits());
            cells.push(c);
        }
    }
    assert_eq!(cells.len(), reference.cells_with_evidence());
    assert!(cells.len() > 65_536, "the export should take several chunks ({} cells)", cells.len());
    assert!(cells.windows(2).all(|w| w[0] < w[1]), "export must be sorted by key");
    // With a box: the same cells as the box query.
    let (min, max) = ([4.0, 1.0, 0.0], [6.5, 3.0, 1.5]);
    let q = BoxQuery { min_world: min, max_world: max, state: None, coarsen: 0 };
    let mut want: Vec<CellKey> =
        query_box(&reference, &q, &th, 4_000_000).unwrap().iter().map(|c| c.min_cell).collect();
    want.sort_unstable(); // the box query walks z-major; the export is in key order
    let req =
        pb::ExportRequest { map: "room".into(), min: min.to_vec(), max: max.to_vec(), thresholds: None };
    let mut chunks = client.export(req).await.unwrap().into_inner();
    let mut boxed = Vec::new();
    while let Some(chunk) = chunks.message().await.unwrap() {
        boxed.extend(chunk.cell.chunks(3).map(key));
    }
    assert_eq!(boxed.len(), want.len());
    assert!(boxed == want, "the boxed export differs from the box query's cells");

    // A duplicate (source, seq) is acknowledged, not applied.
    let before = state_of(&mut client, "room").await;
    let ack = client.insert_scan(insert_req("room", scan_msg("robot1", 2, &scans[0]))).await.unwrap();
    assert_eq!(ack.into_inner(), pb::InsertScanResponse { applied: false, version: 3, dropped_points: 0 });
    let stream = tokio_stream::iter(vec![insert_req("room", scan_msg("robot1", 3, &scans[2]))]);
    let summary = client.insert_scans(stream).await.unwrap().into_inner();
    assert_eq!(summary, pb::InsertScansResponse { scans: 1, applied: 0, duplicates: 1, version: 3 });
    assert_eq!(state_of(&mut client, "room").await, before);
    assert_eq!(map_info(&mut client, "room").await.sources[0].duplicates, 2);

    // SIGTERM: a clean exit; the restarted server has the same map.
    drop(client);
    let status = server.terminate();
    assert!(status.success(), "serve exited with {status}");
    let server = start_serve(dir.path(), &[]);
    let mut client = connect(&server).await;
    assert_eq!(state_of(&mut client, "room").await, before);
    assert_eq!(map_info(&mut client, "room").await.params, Some(want_params));
    assert_eq!(assert_points_equal(&mut client, "room", &reference, &lattice).await, occupied);
    // Dedup survives the restart.
    let ack = client.insert_scan(insert_req("room", scan_msg("robot1", 1, &scans[0]))).await.unwrap();
    assert!(!ack.into_inner().applied);
    drop(client);
    let status = server.terminate();
    assert!(status.success(), "serve exited with {status}");
}

/// Asserts a call failed with `code` and a message containing every needle.
fn expect_err<T: std::fmt::Debug>(
    r: Result<tonic::Response<T>, tonic::Status>,
    code: Code,
    needles: &[&str],
) {
    let s = r.expect_err("expected an error");
    assert_eq!(s.code(), code, "{s:?}");
    for n in needles {
        assert!(s.message().contains(n), "{:?} lacks {n:?}", s.message());
    }
}

/// Raw bytes in and out, to send a malformed protobuf message.
#[derive(Debug, Clone, Copy, Default)]
struct RawCodec;

impl tonic::codec::Codec for RawCodec {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawCodec;
    type Decoder = RawCodec;
    fn encoder(&mut self) -> Self::Encoder {
        RawCodec
    }
    fn decoder(&mut self) -> Self::Decoder {
        RawCodec
    }
}

impl tonic::codec::Encoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn encode(&mut self, item: Vec<u8>, dst: &mut tonic::codec::EncodeBuf<'_>) -> Result<(), tonic::Status> {
        prost::bytes::BufMut::put_slice(dst, &item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawCodec {
    type Item = Vec<u8>;
    type Error = tonic::Status;
    fn decode(&mut self, src: &mut tonic::codec::DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
        let n = prost::bytes::Buf::remaining(src);
        Ok(Some(prost::bytes::Buf::copy_to_bytes(src, n).to_vec()))
    }
}

async fn raw_unary(
    url: String,
    method: &'static str,
    body: Vec<u8>,
) -> Result<tonic::Response<Vec<u8>>, tonic::Status> {
    let channel = Channel::from_shared(url).unwrap().connect().await.unwrap();
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let path = tonic::codegen::http::uri::PathAndQuery::from_static(method);
    grpc.unary(tonic::Request::new(body), path, RawCodec).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_are_refused_with_the_field_named_and_leave_the_map_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let (_, scans) = simulate(0, 3, &Lidar::default());
    let server = start_serve(dir.path(), &["--max-box-cells", "1000000"]);
    let mut client = connect(&server).await;
    let create = |map: &str, params| pb::CreateMapRequest { map: map.into(), params: Some(params) };
    client.create_map(create("room", pb_params())).await.unwrap();
    client.insert_scan(insert_req("room", scan_msg("robot1", 1, &scans[0]))).await.unwrap();
    let before = state_of(&mut client, "room").await;
    assert_eq!(before.0, 1);

    // Map creation.
    expect_err(client.create_map(create("room", pb_params())).await, Code::AlreadyExists, &["room"]);
    let bad_ell = pb::MapParams { ell: Some(-0.2), ..pb_params() };
    expect_err(client.create_map(create("other", bad_ell)).await, Code::InvalidArgument, &["MapParams.ell"]);
    let bad_sub = pb::MapParams { sub_cells: Some(6), ..pb_params() };
    expect_err(
        client.create_map(create("other", bad_sub)).await,
        Code::InvalidArgument,
        &["MapParams.sub_cells"],
    );
    let bad_mode = pb::MapParams { range_mode: Some("clip".into()), ..pb_params() };
    expect_err(client.create_map(create("other", bad_mode)).await, Code::InvalidArgument, &["range_mode"]);
    expect_err(client.create_map(create("no/slash", pb_params())).await, Code::InvalidArgument, &["map"]);

    // Scans.
    let good = || scan_msg("robot1", 100, &scans[1]);
    let pose = |t: Vec<f64>, r: Vec<f64>| Some(pb::Pose { translation: t, rotation: r });
    let origin = scans[1].origin.to_vec();
    let cases: Vec<(pb::Scan, Vec<&str>)> = vec![
        (
            pb::Scan {
                world_from_sensor: pose(vec![f64::NAN, 2.0, 0.7], vec![1.0, 0.0, 0.0, 0.0]),
                ..good()
            },
            vec!["world_from_sensor", "translation"],
        ),
        (
            pb::Scan { world_from_sensor: pose(origin.clone(), vec![2.0, 0.0, 0.0, 0.0]), ..good() },
            vec!["world_from_sensor", "rotation"],
        ),
        (
            pb::Scan { world_from_sensor: pose(origin.clone(), vec![1.0, 0.0, 0.0]), ..good() },
            vec!["bgkmap.v1.Scan.world_from_sensor.rotation: expected 4 values (w, x, y, z), got 3"],
        ),
        (
            pb::Scan { world_from_sensor: pose(vec![1.0, 2.0], vec![1.0, 0.0, 0.0, 0.0]), ..good() },
            vec!["bgkmap.v1.Scan.world_from_sensor.translation: expected 3 values"],
        ),
        (pb::Scan { world_from_sensor: None, ..good() }, vec!["bgkmap.v1.Scan.world_from_sensor: missing"]),
        (pb::Scan { xyz_f32: Vec::new(), ..good() }, vec!["points", "no points"]),
        (
            pb::Scan { xyz_f32: vec![0; 13], ..good() },
            vec!["bgkmap.v1.Scan.xyz_f32: length 13 is not a multiple of 12"],
        ),
        (pb::Scan { xyz_f32: xyz_bytes(&[[f32::NAN; 3]]), ..good() }, vec!["no finite points"]),
        (pb::Scan { source: String::new(), ..good() }, vec!["source"]),
        (pb::Scan { frame: 7, ..good() }, vec!["bgkmap.v1.Scan.frame"]),
        (pb::Scan { max_range: Some(-1.0), ..good() }, vec!["max_range"]),
    ];
    for (scan, needles) in cases {
        expect_err(client.insert_scan(insert_req("room", scan)).await, Code::InvalidArgument, &needles);
        assert_eq!(state_of(&mut client, "room").await, before);
    }
    let no_scan = pb::InsertScanRequest { map: "room".into(), scan: None, wait_applied: false };
    expect_err(client.insert_scan(no_scan).await, Code::InvalidArgument, &["InsertScanRequest.scan"]);

    // Unknown map.
    expect_err(client.insert_scan(insert_req("nope", good())).await, Code::NotFound, &["nope"]);
    expect_err(client.get_map(pb::GetMapRequest { map: "nope".into() }).await, Code::NotFound, &["nope"]);
    let qp = |map: &str, pts: &[[f32; 3]]| pb::QueryPointsRequest {
        map: map.into(),
        xyz_f32: xyz_bytes(pts),
        thresholds: None,
    };
    expect_err(client.query_points(qp("nope", &[[1.0; 3]])).await, Code::NotFound, &["nope"]);
    let export = pb::ExportRequest { map: "nope".into(), ..Default::default() };
    expect_err(client.export(export).await, Code::NotFound, &["nope"]);

    // Queries.
    let pts = [[1.0, 1.0, 1.0], [f32::NAN, 0.0, 0.0]];
    expect_err(client.query_points(qp("room", &pts)).await, Code::InvalidArgument, &["xyz_f32", "point 1"]);
    let bad_th = pb::QueryPointsRequest {
        thresholds: Some(pb::Thresholds { p_free: Some(0.9), ..Default::default() }),
        ..qp("room", &[[1.0; 3]])
    };
    expect_err(client.query_points(bad_th).await, Code::InvalidArgument, &["thresholds.p_free"]);
    let qbox = |min: Vec<f64>, max: Vec<f64>| pb::QueryBoxRequest {
        map: "room".into(),
        min,
        max,
        ..Default::default()
    };
    expect_err(
        client.query_box(qbox(vec![-100.0; 3], vec![100.0; 3])).await,
        Code::InvalidArgument,
        &["limit of 1000000"],
    );
    // Coarsened, a box of 15.6 M cells fits (250³ cells, 32³ positions).
    let coarse = pb::QueryBoxRequest { coarsen: 3, counts_only: true, ..qbox(vec![-10.0; 3], vec![15.0; 3]) };
    client.query_box(coarse).await.unwrap();
    expect_err(client.query_box(qbox(vec![0.0; 2], vec![1.0; 3])).await, Code::InvalidArgument, &["min"]);
    expect_err(client.query_box(qbox(vec![1.0; 3], vec![0.0; 3])).await, Code::InvalidArgument, &["min"]);
    let coarsen = pb::QueryBoxRequest { coarsen: 11, ..qbox(vec![0.0; 3], vec![1.0; 3]) };
    expect_err(client.query_box(coarsen).await, Code::InvalidArgument, &["coarsen"]);
    let ray = |d: Vec<f64>, r: f64| pb::Ray { origin: vec![5.0, 2.0, 0.7], direction: d, max_range: r };
    let rays = |rays: Vec<pb::Ray>| pb::CastRaysRequest { map: "room".into(), rays, ..Default::default() };
    let req = rays(vec![ray(vec![1.0, 0.0, 0.0], 1.0), ray(vec![0.0; 3], 1.0)]);
    expect_err(client.cast_rays(req).await, Code::InvalidArgument, &["rays[1]", "direction"]);
    let req = rays(vec![ray(vec![1.0, 0.0, 0.0], f64::INFINITY)]);
    expect_err(client.cast_rays(req).await, Code::InvalidArgument, &["rays[0]", "max_range"]);
    let req = rays(vec![ray(vec![1.0, 0.0], 1.0)]);
    expect_err(client.cast_rays(req).await, Code::InvalidArgument, &["rays[0].direction"]);
    let export = pb::ExportRequest { map: "room".into(), min: vec![1.0; 3], ..Default::default() };
    expect_err(client.export(export).await, Code::InvalidArgument, &["ExportRequest.max"]);

    // A malformed protobuf message (a truncated varint).
    for method in ["/bgkmap.v1.MapService/InsertScan", "/bgkmap.v1.MapService/QueryPoints"] {
        let garbage = vec![0x0a, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01];
        let r = raw_unary(server.grpc_url(), method, garbage).await;
        expect_err(r, Code::InvalidArgument, &["malformed protobuf"]);
    }
    // The server is still there, and the map did not move.
    assert_eq!(state_of(&mut client, "room").await, before);

    // A stream fails at its first bad request; the earlier scans stay applied.
    client.create_map(create("stream", pb_params())).await.unwrap();
    let bad = pb::Scan { xyz_f32: vec![0; 5], ..scan_msg("r", 2, &scans[1]) };
    let stream = tokio_stream::iter(vec![
        insert_req("stream", scan_msg("r", 1, &scans[0])),
        insert_req("stream", bad),
        insert_req("stream", scan_msg("r", 3, &scans[2])),
    ]);
    expect_err(client.insert_scans(stream).await, Code::InvalidArgument, &["request 1", "xyz_f32"]);
    assert_eq!(state_of(&mut client, "stream").await.0, 1);
    let stream = tokio_stream::iter(vec![
        insert_req("stream", scan_msg("r", 2, &scans[1])),
        insert_req("nope", good()),
    ]);
    expect_err(client.insert_scans(stream).await, Code::NotFound, &["request 1", "nope"]);
    assert_eq!(state_of(&mut client, "stream").await.0, 2);
    assert_eq!(state_of(&mut client, "room").await, before);

    drop(client);
    let status = server.terminate();
    assert!(status.success(), "serve exited with {status}");
}

/// A supervisor may send SIGTERM the instant the server prints its addresses: that is a graceful
/// shutdown (exit 0), never death by the signal's default action. While the ready lines came
/// before the handlers were installed, about one start in six died here (one did in CI).
#[test]
fn sigterm_right_after_the_ready_lines_is_a_clean_exit() {
    for start in 0..20 {
        let dir = tempfile::tempdir().unwrap();
        let status = start_serve(dir.path(), &[]).terminate();
        assert!(status.success(), "start {start}: serve exited with {status}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection_v1_and_v1alpha() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let dir = tempfile::tempdir().unwrap();
    let server = start_serve(dir.path(), &[]);
    let channel = Channel::from_shared(server.grpc_url()).unwrap().connect().await.unwrap();
    let mut health = HealthClient::new(channel.clone());
    for service in ["", "bgkmap.v1.MapService"] {
        let r = health.check(HealthCheckRequest { service: service.into() }).await.unwrap().into_inner();
        assert_eq!(r.status, ServingStatus::Serving as i32, "{service:?}");
    }

    let want = ["bgkmap.v1.MapService", "grpc.health.v1.Health"];
    {
        use tonic_reflection::pb::v1alpha::ServerReflectionRequest;
        use tonic_reflection::pb::v1alpha::server_reflection_client::ServerReflectionClient;
        use tonic_reflection::pb::v1alpha::server_reflection_request::MessageRequest;
        use tonic_reflection::pb::v1alpha::server_reflection_response::MessageResponse;
        let mut refl = ServerReflectionClient::new(channel.clone());
        let req = ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::ListServices(String::new())),
        };
        let mut resp = refl.server_reflection_info(tokio_stream::iter(vec![req])).await.unwrap().into_inner();
        let msg = resp.message().await.unwrap().unwrap();
        let Some(MessageResponse::ListServicesResponse(list)) = msg.message_response else {
            panic!("{msg:?}")
        };
        let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
        for w in want {
            assert!(names.iter().any(|n| n == w), "v1alpha lacks {w}: {names:?}");
        }
    }
    {
        use tonic_reflection::pb::v1::ServerReflectionRequest;
        use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
        use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
        use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
        let mut refl = ServerReflectionClient::new(channel);
        let req = ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::FileContainingSymbol("bgkmap.v1.MapService".into())),
        };
        let mut resp = refl.server_reflection_info(tokio_stream::iter(vec![req])).await.unwrap().into_inner();
        let msg = resp.message().await.unwrap().unwrap();
        let Some(MessageResponse::FileDescriptorResponse(files)) = msg.message_response else {
            panic!("{msg:?}")
        };
        assert!(!files.file_descriptor_proto.is_empty());
    }
    let status = server.terminate();
    assert!(status.success(), "serve exited with {status}");
}

/// Serves `routes` in-process on a loopback port; returns its URL.
async fn serve_in_process(service: std::sync::Arc<bgkmap::service::MapService>) -> String {
    let config = bgkmap::api::grpc::GrpcConfig::default();
    let routes = bgkmap::api::grpc::routes(service, config).await.unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_routes(routes)
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    format!("http://{addr}")
}

/// A server in this process whose journal queue holds one scan, with map `room`; the data
/// directory lives as long as the returned guard.
async fn room_behind_a_queue_of_one() -> (tempfile::TempDir, Client) {
    use bgkmap::service::{MapService, ServiceConfig};
    let dir = tempfile::tempdir().unwrap();
    let config = ServiceConfig { queue_capacity: 1, ..ServiceConfig::default() };
    let service = std::sync::Arc::new(MapService::open(dir.path(), config).unwrap());
    let url = serve_in_process(service).await;
    let mut client = connect_url(url).await;
    client.create_map(pb::CreateMapRequest { map: "room".into(), params: Some(pb_params()) }).await.unwrap();
    (dir, client)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_full_queue_answers_resource_exhausted_with_retry_after() {
    let (_dir, mut client) = room_behind_a_queue_of_one().await;
    let (_, scans) = simulate(0, 4, &Lidar::default());

    // Many concurrent scans into a queue of one: some are refused as busy, none is lost.
    let calls = (0..32u64).map(|i| {
        let mut c = client.clone();
        let scan = scan_msg("robot1", i + 1, &scans[i as usize % scans.len()]);
        tokio::spawn(async move { c.insert_scan(insert_req("room", scan)).await })
    });
    let mut applied = 0;
    let mut busy = 0;
    for call in calls.collect::<Vec<_>>() {
        match call.await.unwrap() {
            Ok(r) => {
                assert!(r.into_inner().applied);
                applied += 1;
            }
            Err(s) => {
                assert_eq!(s.code(), Code::ResourceExhausted, "{s:?}");
                assert!(s.metadata().get("retry-after-ms").is_some(), "{s:?}");
                busy += 1;
            }
        }
    }
    assert!(busy > 0, "32 concurrent scans should overflow a queue of one");
    assert_eq!(applied + busy, 32);
    let info = map_info(&mut client, "room").await;
    assert_eq!(info.version, applied);
    assert_eq!(info.sources[0].applied, applied);
}

/// Several robots streaming into one map whose queue is full of the others' scans: a stream
/// with none of its own scans in flight waits for room, as one with scans in flight waits for
/// its oldest; every scan of every stream is applied once.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn streams_wait_for_room_in_a_queue_the_others_fill() {
    let (_dir, mut client) = room_behind_a_queue_of_one().await;
    let (_, scans) = simulate(0, 12, &Lidar::default());
    let streams = (0..4).map(|r| {
        let mut c = client.clone();
        let reqs: Vec<_> = (0..12u64)
            .map(|i| insert_req("room", scan_msg(&format!("robot{r}"), i + 1, &scans[i as usize])))
            .collect();
        tokio::spawn(async move { c.insert_scans(tokio_stream::iter(reqs)).await })
    });
    for s in streams.collect::<Vec<_>>() {
        let summary = s.await.unwrap().expect("a stream refused as busy").into_inner();
        assert_eq!((summary.scans, summary.applied, summary.duplicates), (12, 12, 0));
    }
    let info = map_info(&mut client, "room").await;
    assert_eq!(info.sources.iter().map(|s| s.applied).sum::<u64>(), 48);
}
