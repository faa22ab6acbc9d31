//! gRPC transport: `bgkmap.v1.MapService` over tonic, plus reflection (v1 and v1alpha) and
//! health.
//!
//! The handlers are thin: each converts its request (wire types stop here), calls the
//! [`MapService`] or a read-only query of [`crate::core::query`] on the map's current snapshot,
//! and converts the answer back. Malformed requests are `INVALID_ARGUMENT` with a message that
//! starts with the proto field path (`bgkmap.v1.Scan.xyz_f32: length 13 is not a multiple of
//! 12`); every service error goes through [`to_grpc`], so the codes are those of every other
//! transport (unknown map `NOT_FOUND`, a full queue `RESOURCE_EXHAUSTED` with `retry-after-ms`).
//!
//! Conventions beyond the proto comments:
//! - Query answers carry `version`, the number of scans in the snapshot they were computed on.
//! - A clear ray (`blocked = false`) has no `cell`, `distance` = its `max_range`, and the
//!   defaults for `state` and `probability`.
//! - An answer that would exceed the message limit ([`GrpcConfig::max_message_bytes`]) is
//!   refused with `INVALID_ARGUMENT` instead of failing on the wire.
//! - `Export` streams cells with evidence sorted by key (x, then y, then z) in chunks of at most
//!   [`EXPORT_CHUNK_CELLS`] cells, always at least one chunk (so `resolution` is known).
//! - `InsertScan` answers once the scan is durable in the journal (`version` is then the map
//!   version at that moment), or with `wait_applied` once it is integrated.
//! - `InsertScans` submits its scans in order with up to 32 in flight; a failure (reported as `request i: …` with the original code) means every
//!   earlier scan is durable (later ones may be: resending is safe).
//! - Answers that depend on a corrupt block are `DATA_LOSS`; other queries are answered.

use super::pb;
use super::pb::map_service_server::MapServiceServer;
use super::status::to_grpc;
use crate::core::key::BLOCK_CELLS;
use crate::core::query::{
    BoxError, BoxQuery, RayHit, StopAt, cast_ray, count_box, for_each_point, query_box,
};
use crate::core::{CellKey, CellState, MapParams, PointFrame, Pose, RangeMode, Thresholds};
use crate::service::{Ack, MapInfo, MapService, ScanInput, ServiceError, Snapshot, SubmitOptions};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tonic::{Request, Response, Status, Streaming};

/// Settings of the gRPC port.
#[derive(Debug, Clone)]
pub struct GrpcConfig {
    /// Most lattice positions one `QueryBox` may visit (at its coarsened resolution). Default 4 M.
    pub max_box_cells: u64,
    /// Largest message decoded or encoded, in bytes. Default 64 MiB.
    pub max_message_bytes: usize,
}

impl Default for GrpcConfig {
    fn default() -> Self {
        Self { max_box_cells: 4_000_000, max_message_bytes: 64 << 20 }
    }
}

/// Cells per `ExportChunk`.
pub const EXPORT_CHUNK_CELLS: usize = 65_536;

/// Query points above which the work moves to a blocking thread.
const INLINE_POINTS: usize = 10_000;

/// The `bgkmap.v1.MapService` implementation.
#[derive(Debug, Clone)]
pub struct MapGrpc {
    service: Arc<MapService>,
    config: GrpcConfig,
}

impl MapGrpc {
    pub fn new(service: Arc<MapService>, config: GrpcConfig) -> Self {
        Self { service, config }
    }
}

/// Everything the gRPC port serves: MapService (with the message size limits set), reflection
/// v1 and v1alpha, and health (`""` and `bgkmap.v1.MapService` SERVING).
pub async fn routes(
    service: Arc<MapService>,
    config: GrpcConfig,
) -> Result<tonic::service::Routes, Box<dyn std::error::Error + Send + Sync>> {
    Ok(routes_with_health(service, config).await?.0)
}

/// As [`routes`], also returning the health reporter (to report NOT_SERVING while draining).
pub async fn routes_with_health(
    service: Arc<MapService>,
    config: GrpcConfig,
) -> Result<
    (tonic::service::Routes, tonic_health::server::HealthReporter),
    Box<dyn std::error::Error + Send + Sync>,
> {
    let limit = config.max_message_bytes;
    super::codec::set_max_message_bytes(limit);
    let map = MapServiceServer::new(MapGrpc::new(service, config))
        .max_decoding_message_size(limit.saturating_mul(4))
        .max_encoding_message_size(limit);
    let (reporter, health) = tonic_health::server::health_reporter();
    reporter.set_serving::<MapServiceServer<MapGrpc>>().await;
    reporter.set_service_status("", tonic_health::ServingStatus::Serving).await;
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let v1 = reflection().build_v1()?;
    let v1alpha = reflection().build_v1alpha()?;
    let routes = tonic::service::Routes::new(health).add_service(v1).add_service(v1alpha).add_service(map);
    Ok((routes, reporter))
}

// ---------------------------------------------------------------------------------------------
// Conversions (wire → core). Errors name the proto field path.

/// `INVALID_ARGUMENT` naming `bgkmap.v1.<field>`.
pub(super) fn bad(field: &str, reason: impl std::fmt::Display) -> Status {
    Status::invalid_argument(format!("bgkmap.v1.{field}: {reason}"))
}

pub(super) fn service_err(e: ServiceError) -> Status {
    to_grpc(&e)
}

/// Exactly three values (x, y, z).
pub(super) fn vec3(v: &[f64], field: &str) -> Result<[f64; 3], Status> {
    <[f64; 3]>::try_from(v).map_err(|_| bad(field, format!("expected 3 values (x, y, z), got {}", v.len())))
}

/// Little-endian f32 triplets.
fn xyz_f32(bytes: &[u8], field: &str) -> Result<Vec<[f32; 3]>, Status> {
    if !bytes.len().is_multiple_of(12) {
        return Err(bad(field, format!("length {} is not a multiple of 12", bytes.len())));
    }
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    Ok(bytes.chunks_exact(12).map(|c| [f(&c[0..4]), f(&c[4..8]), f(&c[8..12])]).collect())
}

fn map_params(p: Option<pb::MapParams>) -> Result<MapParams, Status> {
    let p = p.unwrap_or_default();
    let d = MapParams::default();
    let range_mode = match p.range_mode.as_deref() {
        None => d.range_mode,
        Some(s) => s.parse::<RangeMode>().map_err(|e| bad("MapParams.range_mode", e.reason))?,
    };
    let params = MapParams {
        resolution_m: p.resolution.unwrap_or(d.resolution_m),
        sf2: p.sf2.unwrap_or(d.sf2),
        ell_m: p.ell.unwrap_or(d.ell_m),
        free_resolution_m: p.free_resolution.unwrap_or(d.free_resolution_m),
        ds_resolution_m: p.ds_resolution.unwrap_or(d.ds_resolution_m),
        max_range_m: p.max_range.unwrap_or(d.max_range_m),
        range_mode,
        prior_a: p.prior_a.unwrap_or(d.prior_a),
        prior_b: p.prior_b.unwrap_or(d.prior_b),
        origin_as_free: d.origin_as_free,
        thresholds: Thresholds {
            p_free: p.p_free.unwrap_or(d.thresholds.p_free),
            p_occ: p.p_occ.unwrap_or(d.thresholds.p_occ),
            var_max: p.var_max.unwrap_or(d.thresholds.var_max),
        },
    };
    params.validate().map_err(|e| bad(&format!("MapParams.{}", e.name), e.reason))?;
    Ok(params)
}

/// Query thresholds: unset fields take the map's defaults.
fn thresholds(t: Option<pb::Thresholds>, map_default: Thresholds, field: &str) -> Result<Thresholds, Status> {
    let t = t.unwrap_or_default();
    let th = Thresholds {
        p_free: t.p_free.unwrap_or(map_default.p_free),
        p_occ: t.p_occ.unwrap_or(map_default.p_occ),
        var_max: t.var_max.unwrap_or(map_default.var_max),
    };
    th.validate().map_err(|e| bad(&format!("{field}.{}", e.name), e.reason))?;
    Ok(th)
}

pub(super) fn scan_input(scan: Option<pb::Scan>) -> Result<ScanInput, Status> {
    let scan = scan.ok_or_else(|| bad("InsertScanRequest.scan", "missing"))?;
    let pose = scan.world_from_sensor.ok_or_else(|| bad("Scan.world_from_sensor", "missing"))?;
    let translation_m = <[f64; 3]>::try_from(pose.translation.as_slice()).map_err(|_| {
        bad(
            "Scan.world_from_sensor.translation",
            format!("expected 3 values (x, y, z), got {}", pose.translation.len()),
        )
    })?;
    let rotation_wxyz = <[f64; 4]>::try_from(pose.rotation.as_slice()).map_err(|_| {
        bad(
            "Scan.world_from_sensor.rotation",
            format!("expected 4 values (w, x, y, z), got {}", pose.rotation.len()),
        )
    })?;
    let frame = match pb::Frame::try_from(scan.frame) {
        Ok(pb::Frame::World) => PointFrame::World,
        Ok(pb::Frame::Sensor) => PointFrame::Sensor,
        Err(_) => return Err(bad("Scan.frame", format!("unknown value {}", scan.frame))),
    };
    Ok(ScanInput {
        source: scan.source,
        seq: scan.seq,
        world_from_sensor: Pose { translation_m, rotation_wxyz },
        frame,
        points: xyz_f32(&scan.xyz_f32, "Scan.xyz_f32")?,
        max_range_m: scan.max_range,
        stamp_nanos: scan.stamp_nanos,
    })
}

fn stop_at(v: i32) -> Result<StopAt, Status> {
    match pb::StopAt::try_from(v) {
        Ok(pb::StopAt::Occupied) => Ok(StopAt::Occupied),
        Ok(pb::StopAt::NotFree) => Ok(StopAt::NotFree),
        Err(_) => Err(bad("CastRaysRequest.stop_at", format!("unknown value {v}"))),
    }
}

fn cell_state_from_pb(v: i32) -> Result<CellState, Status> {
    match pb::CellState::try_from(v) {
        Ok(pb::CellState::Free) => Ok(CellState::Free),
        Ok(pb::CellState::Occupied) => Ok(CellState::Occupied),
        Ok(pb::CellState::Unknown) => Ok(CellState::Unknown),
        Err(_) => Err(bad("QueryBoxRequest.state", format!("unknown value {v}"))),
    }
}

// ---------------------------------------------------------------------------------------------
// Conversions (core → wire).

fn cell_state_to_pb(s: CellState) -> i32 {
    match s {
        CellState::Free => pb::CellState::Free as i32,
        CellState::Occupied => pb::CellState::Occupied as i32,
        CellState::Unknown => pb::CellState::Unknown as i32,
    }
}

fn push_key(out: &mut Vec<i32>, k: CellKey) {
    out.extend_from_slice(&[k.x, k.y, k.z]);
}

fn map_params_to_pb(p: &MapParams) -> pb::MapParams {
    pb::MapParams {
        resolution: Some(p.resolution_m),
        sf2: Some(p.sf2),
        ell: Some(p.ell_m),
        free_resolution: Some(p.free_resolution_m),
        ds_resolution: Some(p.ds_resolution_m),
        max_range: Some(p.max_range_m),
        range_mode: Some(p.range_mode.as_str().to_string()),
        prior_a: Some(p.prior_a),
        prior_b: Some(p.prior_b),
        p_free: Some(p.thresholds.p_free),
        p_occ: Some(p.thresholds.p_occ),
        var_max: Some(p.thresholds.var_max),
    }
}

fn map_info_to_pb(info: MapInfo) -> pb::MapInfo {
    pb::MapInfo {
        params: Some(map_params_to_pb(&info.params)),
        map: info.name,
        version: info.version,
        blocks: info.blocks as u64,
        cells_with_evidence: info.cells_with_evidence as u64,
        queued: info.queued as u64,
        scans: info.scans,
        journal_bytes: info.journal_bytes,
        corrupt_blocks: info.corrupt_blocks as u64,
        read_only: info.read_only.unwrap_or_default(),
        sources: info
            .sources
            .into_iter()
            .map(|(source, s)| pb::SourceStats {
                source,
                received: s.received,
                applied: s.applied,
                duplicates: s.duplicates,
                rejected: s.rejected,
                highest_seq: s.highest_seq,
                pending: s.pending,
                gaps: s.gaps,
                pruned: s.pruned,
                retracted: s.retracted,
            })
            .collect(),
    }
}

/// Refuses an answer that would not fit in one message.
fn fits<M: prost::Message>(msg: M, limit: usize, what: &str, hint: &str) -> Result<M, Status> {
    let len = msg.encoded_len();
    if len > limit {
        return Err(bad(
            what,
            format!("the answer is {len} bytes, over the message limit of {limit}; {hint}"),
        ));
    }
    Ok(msg)
}

/// Runs `f` on a blocking thread when `heavy`, else inline.
async fn compute<T: Send + 'static>(
    heavy: bool,
    f: impl FnOnce() -> Result<T, Status> + Send + 'static,
) -> Result<T, Status> {
    if !heavy {
        return f();
    }
    tokio::task::spawn_blocking(f).await.map_err(|e| Status::internal(format!("query task failed: {e}")))?
}

// ---------------------------------------------------------------------------------------------
// Handlers.

impl MapGrpc {
    /// Submits one scan and waits until it is durable (or, with `wait_applied`, integrated).
    async fn insert(&self, map: &str, scan: ScanInput, wait_applied: bool) -> Result<Ack, Status> {
        let rx = self.submit(map, scan, wait_applied)?;
        match rx.await {
            Ok(r) => r.map_err(service_err),
            Err(_) => Err(service_err(ServiceError::ShuttingDown)),
        }
    }

    /// Submits one scan; the receiver gets its outcome.
    pub(super) fn submit(
        &self,
        map: &str,
        scan: ScanInput,
        wait_applied: bool,
    ) -> Result<tokio::sync::oneshot::Receiver<Result<Ack, ServiceError>>, Status> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let options = SubmitOptions { wait_applied };
        self.service.submit(map, scan, options, Box::new(move |r| drop(tx.send(r)))).map_err(service_err)?;
        Ok(rx)
    }

    fn snapshot(&self, map: &str) -> Result<Arc<Snapshot>, Status> {
        self.service.snapshot(map).map_err(service_err)
    }
}

fn query_points_answer(
    snap: &Snapshot,
    points: &[[f64; 3]],
    th: &Thresholds,
) -> Result<pb::QueryPointsResponse, Status> {
    let n = points.len();
    let mut out = pb::QueryPointsResponse {
        probability: Vec::with_capacity(n),
        variance: Vec::with_capacity(n),
        state: Vec::with_capacity(n),
        cell: Vec::with_capacity(3 * n),
        version: snap.version,
    };
    let mut outside = None;
    for_each_point(&snap.map, points, th, |a| match a {
        Some(a) => {
            out.probability.push(a.estimate.probability);
            out.variance.push(a.estimate.variance);
            out.state.push(cell_state_to_pb(a.estimate.state));
            push_key(&mut out.cell, a.cell);
        }
        None => {
            outside.get_or_insert(out.probability.len());
        }
    });
    if let Some(i) = outside {
        return Err(bad("QueryPointsRequest.xyz_f32", format!("point {i} is outside the map's key range")));
    }
    Ok(out)
}

fn query_box_answer(
    snap: &Snapshot,
    q: &BoxQuery,
    th: &Thresholds,
    max_cells: u64,
    counts_only: bool,
) -> Result<pb::QueryBoxResponse, Status> {
    let cells = query_box(&snap.map, q, th, max_cells).map_err(|e| match e {
        BoxError::Malformed => bad("QueryBoxRequest.min", e),
        BoxError::Coarsen(_) => bad("QueryBoxRequest.coarsen", e),
        BoxError::TooLarge { .. } => bad("QueryBoxRequest", e),
    })?;
    let [free, occupied, unknown] = count_box(&cells).map(|n| n as u64);
    let mut out =
        pb::QueryBoxResponse { free, occupied, unknown, version: snap.version, ..Default::default() };
    if !counts_only {
        let n = cells.len();
        out.min_cell.reserve(3 * n);
        out.size_cells.reserve(n);
        out.probability.reserve(n);
        out.variance.reserve(n);
        out.state.reserve(n);
        for c in &cells {
            push_key(&mut out.min_cell, c.min_cell);
            out.size_cells.push(c.size_cells.unsigned_abs());
            out.probability.push(c.estimate.probability);
            out.variance.push(c.estimate.variance);
            out.state.push(cell_state_to_pb(c.estimate.state));
        }
    }
    Ok(out)
}

struct RayInput {
    origin: [f64; 3],
    direction: [f64; 3],
    max_range: f64,
}

fn cast_rays_answer(
    snap: &Snapshot,
    rays: &[RayInput],
    stop: StopAt,
    th: &Thresholds,
) -> Result<pb::CastRaysResponse, Status> {
    let mut results = Vec::with_capacity(rays.len());
    let res = snap.map.params().resolution_m;
    for (i, r) in rays.iter().enumerate() {
        let hit = cast_ray(&snap.map, r.origin, r.direction, r.max_range, stop, th)
            .map_err(|e| bad(&format!("CastRaysRequest.rays[{i}]"), e))?;
        let reach = match hit {
            RayHit::Clear => r.max_range,
            RayHit::Blocked { distance_m, .. } => distance_m + res * 3f64.sqrt(),
        };
        snap.check_ray(r.origin, r.direction, reach, &format!("ray {i}")).map_err(service_err)?;
        results.push(match hit {
            RayHit::Clear => pb::RayResult { blocked: false, distance: r.max_range, ..Default::default() },
            RayHit::Blocked { cell, distance_m, estimate } => pb::RayResult {
                blocked: true,
                cell: vec![cell.x, cell.y, cell.z],
                distance: distance_m,
                state: cell_state_to_pb(estimate.state),
                probability: estimate.probability,
            },
        });
    }
    Ok(pb::CastRaysResponse { results, version: snap.version })
}

/// Sends every cell with evidence (inside `[lo, hi]` keys, if given) sorted by key, in chunks.
/// Blocks come sorted by block key, so all cells of one block-x slab precede the next slab's:
/// sorting one slab at a time gives the global key order with one slab in memory.
fn export_cells(
    snap: &Snapshot,
    bounds: Option<(CellKey, CellKey)>,
    th: &Thresholds,
    tx: &tokio::sync::mpsc::Sender<Result<pb::ExportChunk, Status>>,
) {
    let map = &snap.map;
    let resolution = map.params().resolution_m;
    let inside = |c: CellKey| {
        bounds.is_none_or(|(lo, hi)| {
            (lo.x..=hi.x).contains(&c.x) && (lo.y..=hi.y).contains(&c.y) && (lo.z..=hi.z).contains(&c.z)
        })
    };
    let block_overlaps = |b: crate::core::BlockKey| {
        bounds.is_none_or(|(lo, hi)| {
            let (bl, bh) = (lo.block(), hi.block());
            (bl.x..=bh.x).contains(&b.x) && (bl.y..=bh.y).contains(&b.y) && (bl.z..=bh.z).contains(&b.z)
        })
    };
    let mut chunk = pb::ExportChunk { resolution, ..Default::default() };
    let mut sent_any = false;
    let flush = |chunk: &mut pb::ExportChunk| -> bool {
        let full = std::mem::replace(chunk, pb::ExportChunk { resolution, ..Default::default() });
        tx.blocking_send(Ok(full)).is_ok()
    };
    let keys: Vec<_> = map.block_keys_sorted().into_iter().filter(|k| block_overlaps(*k)).collect();
    let mut slab: Vec<CellKey> = Vec::new();
    for (i, key) in keys.iter().enumerate() {
        if let Some(block) = map.block(*key) {
            for j in 0..BLOCK_CELLS {
                if block.a[j] != 0 || block.b[j] != 0 {
                    let cell = key.cell(j);
                    if inside(cell) {
                        slab.push(cell);
                    }
                }
            }
        }
        let slab_ends = keys.get(i + 1).is_none_or(|next| next.x != key.x);
        if !slab_ends {
            continue;
        }
        slab.sort_unstable();
        for cell in slab.drain(..) {
            let e = map.estimate(cell, th);
            push_key(&mut chunk.cell, cell);
            chunk.probability.push(e.probability);
            chunk.variance.push(e.variance);
            if chunk.probability.len() == EXPORT_CHUNK_CELLS {
                if !flush(&mut chunk) {
                    return; // the client went away
                }
                sent_any = true;
            }
        }
    }
    if !chunk.probability.is_empty() || !sent_any {
        flush(&mut chunk);
    }
}

/// The `Export` response stream.
#[derive(Debug)]
pub struct ExportChunks(tokio::sync::mpsc::Receiver<Result<pb::ExportChunk, Status>>);

impl tokio_stream::Stream for ExportChunks {
    type Item = Result<pb::ExportChunk, Status>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.0.poll_recv(cx)
    }
}

#[tonic::async_trait]
impl pb::map_service_server::MapService for MapGrpc {
    async fn create_map(
        &self,
        request: Request<pb::CreateMapRequest>,
    ) -> Result<Response<pb::MapInfo>, Status> {
        let req = request.into_inner();
        let params = map_params(req.params)?;
        let info = self.service.create_map(&req.map, params).map_err(service_err)?;
        Ok(Response::new(map_info_to_pb(info)))
    }

    async fn list_maps(
        &self,
        _request: Request<pb::ListMapsRequest>,
    ) -> Result<Response<pb::ListMapsResponse>, Status> {
        let maps = self.service.list_maps().into_iter().map(map_info_to_pb).collect();
        Ok(Response::new(pb::ListMapsResponse { maps }))
    }

    async fn get_map(&self, request: Request<pb::GetMapRequest>) -> Result<Response<pb::MapInfo>, Status> {
        let info = self.service.map_info(&request.into_inner().map).map_err(service_err)?;
        Ok(Response::new(map_info_to_pb(info)))
    }

    async fn insert_scan(
        &self,
        request: Request<pb::InsertScanRequest>,
    ) -> Result<Response<pb::InsertScanResponse>, Status> {
        let req = request.into_inner();
        let scan = scan_input(req.scan)?;
        let ack = self.insert(&req.map, scan, req.wait_applied).await?;
        Ok(Response::new(pb::InsertScanResponse {
            applied: ack.applied,
            version: ack.version,
            dropped_points: ack.dropped_points as u64,
        }))
    }

    async fn insert_scans(
        &self,
        request: Request<Streaming<pb::InsertScanRequest>>,
    ) -> Result<Response<pb::InsertScansResponse>, Status> {
        super::grpc_ops::insert_scans(self, request.into_inner()).await.map(Response::new)
    }

    async fn query_points(
        &self,
        request: Request<pb::QueryPointsRequest>,
    ) -> Result<Response<pb::QueryPointsResponse>, Status> {
        let req = request.into_inner();
        let snap = self.snapshot(&req.map)?;
        let th = thresholds(req.thresholds, snap.map.params().thresholds, "QueryPointsRequest.thresholds")?;
        let raw = xyz_f32(&req.xyz_f32, "QueryPointsRequest.xyz_f32")?;
        let mut points = Vec::with_capacity(raw.len());
        for (i, p) in raw.iter().enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                return Err(bad("QueryPointsRequest.xyz_f32", format!("point {i} is not finite: {p:?}")));
            }
            points.push(p.map(f64::from));
        }
        snap.check_points(&points).map_err(service_err)?;
        let limit = self.config.max_message_bytes;
        let answer = compute(points.len() > INLINE_POINTS, move || {
            let out = query_points_answer(&snap, &points, &th)?;
            fits(out, limit, "QueryPointsRequest.xyz_f32", "query fewer points per request")
        })
        .await?;
        Ok(Response::new(answer))
    }

    async fn query_box(
        &self,
        request: Request<pb::QueryBoxRequest>,
    ) -> Result<Response<pb::QueryBoxResponse>, Status> {
        let req = request.into_inner();
        let snap = self.snapshot(&req.map)?;
        let th = thresholds(req.thresholds, snap.map.params().thresholds, "QueryBoxRequest.thresholds")?;
        let min_world = vec3(&req.min, "QueryBoxRequest.min")?;
        let max_world = vec3(&req.max, "QueryBoxRequest.max")?;
        let state = req.state.map(cell_state_from_pb).transpose()?;
        let coarsen = u8::try_from(req.coarsen).ok().filter(|c| *c <= 10).ok_or_else(|| {
            bad("QueryBoxRequest.coarsen", format!("must be at most 10, got {}", req.coarsen))
        })?;
        let q = BoxQuery { min_world, max_world, state, coarsen };
        snap.check_box(min_world, max_world).map_err(service_err)?;
        let (max_cells, limit, counts_only) =
            (self.config.max_box_cells, self.config.max_message_bytes, req.counts_only);
        let answer = compute(true, move || {
            let out = query_box_answer(&snap, &q, &th, max_cells, counts_only)?;
            fits(out, limit, "QueryBoxRequest", "use counts_only, coarsen, a smaller box or Export")
        })
        .await?;
        Ok(Response::new(answer))
    }

    async fn cast_rays(
        &self,
        request: Request<pb::CastRaysRequest>,
    ) -> Result<Response<pb::CastRaysResponse>, Status> {
        let req = request.into_inner();
        let snap = self.snapshot(&req.map)?;
        let th = thresholds(req.thresholds, snap.map.params().thresholds, "CastRaysRequest.thresholds")?;
        let stop = stop_at(req.stop_at)?;
        let rays = req
            .rays
            .iter()
            .enumerate()
            .map(|(i, r)| {
                Ok(RayInput {
                    origin: vec3(&r.origin, &format!("CastRaysRequest.rays[{i}].origin"))?,
                    direction: vec3(&r.direction, &format!("CastRaysRequest.rays[{i}].direction"))?,
                    max_range: r.max_range,
                })
            })
            .collect::<Result<Vec<_>, Status>>()?;
        let limit = self.config.max_message_bytes;
        let answer = compute(true, move || {
            let out = cast_rays_answer(&snap, &rays, stop, &th)?;
            fits(out, limit, "CastRaysRequest.rays", "cast fewer rays per request")
        })
        .await?;
        Ok(Response::new(answer))
    }

    type ExportStream = ExportChunks;

    async fn export(&self, request: Request<pb::ExportRequest>) -> Result<Response<ExportChunks>, Status> {
        let req = request.into_inner();
        let snap = self.snapshot(&req.map)?;
        let th = thresholds(req.thresholds, snap.map.params().thresholds, "ExportRequest.thresholds")?;
        let bounds = if req.min.is_empty() && req.max.is_empty() {
            None
        } else {
            let res = snap.map.params().resolution_m;
            let min = vec3(&req.min, "ExportRequest.min")?;
            let max = vec3(&req.max, "ExportRequest.max")?;
            match (CellKey::from_point(min, res), CellKey::from_point(max, res)) {
                (Some(lo), Some(hi)) if lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z => {
                    snap.check_cells(lo, hi).map_err(service_err)?;
                    Some((lo, hi))
                }
                _ => {
                    return Err(bad(
                        "ExportRequest.min",
                        "min and max must be finite, inside the key range, with min ≤ max on every axis",
                    ));
                }
            }
        };
        if bounds.is_none() {
            snap.check_whole().map_err(service_err)?;
        }
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::task::spawn_blocking(move || export_cells(&snap, bounds, &th, &tx));
        Ok(Response::new(ExportChunks(rx)))
    }

    async fn merge_map(
        &self,
        request: Request<pb::MergeMapRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        super::grpc_ops::merge_map(&self.service, request.into_inner()).await.map(Response::new)
    }

    async fn retract_scans(
        &self,
        request: Request<pb::RetractScansRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        super::grpc_ops::retract_scans(&self.service, request.into_inner()).await.map(Response::new)
    }

    async fn repose_scans(
        &self,
        request: Request<pb::ReposeScansRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        super::grpc_ops::repose_scans(&self.service, request.into_inner()).await.map(Response::new)
    }

    type WatchUpdatesStream = super::watch::UpdateStream;

    async fn watch_updates(
        &self,
        request: Request<pb::WatchUpdatesRequest>,
    ) -> Result<Response<super::watch::UpdateStream>, Status> {
        Ok(Response::new(super::watch::watch_updates(&self.service, request.into_inner())?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xyz_bytes_decode_little_endian_and_reject_partial_triplets() {
        let mut b = Vec::new();
        for v in [1.5f32, -2.0, 3.25, 0.0, f32::NAN, 7.0] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        let p = xyz_f32(&b, "Scan.xyz_f32").unwrap();
        assert_eq!(p.len(), 2);
        assert_eq!(p[0], [1.5, -2.0, 3.25]);
        assert!(p[1][1].is_nan());
        b.push(0);
        let e = xyz_f32(&b, "Scan.xyz_f32").unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert_eq!(e.message(), "bgkmap.v1.Scan.xyz_f32: length 25 is not a multiple of 12");
    }

    #[test]
    fn params_default_when_unset_and_round_trip() {
        assert_eq!(map_params(None).unwrap(), MapParams::default());
        let p = MapParams { max_range_m: 5.0, range_mode: RangeMode::Drop, ..MapParams::default() };
        assert_eq!(map_params(Some(map_params_to_pb(&p))).unwrap(), p);
        let e = map_params(Some(pb::MapParams { ell: Some(-1.0), ..Default::default() })).unwrap_err();
        assert!(e.message().starts_with("bgkmap.v1.MapParams.ell: "), "{}", e.message());
        let e = map_params(Some(pb::MapParams { range_mode: Some("x".into()), ..Default::default() }))
            .unwrap_err();
        assert!(e.message().starts_with("bgkmap.v1.MapParams.range_mode: "), "{}", e.message());
    }

    #[test]
    fn pose_lengths_are_checked() {
        let scan = |t: Vec<f64>, r: Vec<f64>| pb::Scan {
            source: "a".into(),
            world_from_sensor: Some(pb::Pose { translation: t, rotation: r }),
            xyz_f32: vec![0; 12],
            ..Default::default()
        };
        let e = scan_input(Some(scan(vec![0.0; 3], vec![1.0, 0.0, 0.0]))).unwrap_err();
        assert_eq!(
            e.message(),
            "bgkmap.v1.Scan.world_from_sensor.rotation: expected 4 values (w, x, y, z), got 3"
        );
        let e = scan_input(Some(scan(vec![0.0; 2], vec![1.0, 0.0, 0.0, 0.0]))).unwrap_err();
        assert!(e.message().starts_with("bgkmap.v1.Scan.world_from_sensor.translation: "));
        let s = scan_input(Some(scan(vec![1.0, 2.0, 3.0], vec![1.0, 0.0, 0.0, 0.0]))).unwrap();
        assert_eq!(s.world_from_sensor, Pose::at([1.0, 2.0, 3.0]));
        let e = scan_input(Some(pb::Scan { world_from_sensor: None, ..scan(vec![], vec![]) })).unwrap_err();
        assert_eq!(e.message(), "bgkmap.v1.Scan.world_from_sensor: missing");
    }
}
