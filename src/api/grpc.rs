//! gRPC transport: `bgkmap.v1.MapService` over tonic, plus reflection (v1 and v1alpha) and
//! health.
//!
//! The handlers are thin: each converts its request (wire types stop here), calls the
//! [`MapService`] or a read-only query of [`crate::core::query`] on the map's current snapshot,
//! and converts the answer back. Malformed requests are `INVALID_ARGUMENT` with a message that
//! starts with the proto field path (`bgkmap.v1.Scan.xyz_f32: length 13 is not a multiple of
//! 12`); every service error goes through [`super::status::to_grpc`], so the codes are those of every other
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
use crate::core::key::BLOCK_CELLS;
use crate::core::{CellKey, MapParams, RangeMode, Thresholds};
use crate::service::{MapInfo, MapService, ScanInput, Snapshot};
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
// Conversions (wire → core) shared with zenoh live in `super::calls`; these are gRPC's own.

use super::calls::{ProtoCalls, push_key, thresholds};
pub(super) use super::calls::{bad, scan_input, service_err, vec3};

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
        sub_cells: p.sub_cells.unwrap_or(d.sub_cells),
        thresholds: Thresholds {
            p_free: p.p_free.unwrap_or(d.thresholds.p_free),
            p_occ: p.p_occ.unwrap_or(d.thresholds.p_occ),
            var_max: p.var_max.unwrap_or(d.thresholds.var_max),
        },
    };
    params.validate().map_err(|e| bad(&format!("MapParams.{}", e.name), e.reason))?;
    Ok(params)
}

// ---------------------------------------------------------------------------------------------
// Conversions (core → wire).

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
        sub_cells: Some(p.sub_cells),
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
                dropped_points: s.dropped_points,
            })
            .collect(),
    }
}

// ---------------------------------------------------------------------------------------------
// Handlers.

impl MapGrpc {
    /// The calls shared with zenoh, over this port's service and limits.
    fn calls(&self) -> ProtoCalls {
        ProtoCalls::new(self.service.clone(), self.config.clone())
    }

    /// Submits one scan; the receiver gets its outcome.
    pub(super) fn submit(
        &self,
        map: &str,
        scan: ScanInput,
        wait_applied: bool,
    ) -> Result<super::calls::AckReceiver, Status> {
        self.calls().submit(map, scan, wait_applied)
    }

    fn snapshot(&self, map: &str) -> Result<Arc<Snapshot>, Status> {
        self.service.snapshot(map).map_err(service_err)
    }
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
                if !block.get(j).is_empty() {
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
        let ack = self.calls().insert(&req.map, scan, req.wait_applied).await?;
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
        self.calls().query_points(request.into_inner()).await.map(Response::new)
    }

    async fn query_box(
        &self,
        request: Request<pb::QueryBoxRequest>,
    ) -> Result<Response<pb::QueryBoxResponse>, Status> {
        self.calls().query_box(request.into_inner()).await.map(Response::new)
    }

    async fn cast_rays(
        &self,
        request: Request<pb::CastRaysRequest>,
    ) -> Result<Response<pb::CastRaysResponse>, Status> {
        self.calls().cast_rays(request.into_inner()).await.map(Response::new)
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
}
