//! gRPC transport: `bgkmap.v1.MapService` over tonic, plus reflection (v1 and v1alpha) and
//! health.
//!
//! The handlers are thin: each converts its request (wire types stop at [`crate::api::proto`]),
//! calls one service function or one of the protobuf calls it shares with zenoh
//! ([`ProtoCalls`]), and converts the answer back. Malformed requests are `INVALID_ARGUMENT`
//! with a message that starts with the proto field path (`bgkmap.v1.Scan.xyz_f32: length 13 is
//! not a multiple of 12`); every service error goes through [`crate::api::status::to_grpc`], so
//! the codes are those of every other transport (unknown map `NOT_FOUND`, a full queue
//! `RESOURCE_EXHAUSTED` with `retry-after-ms`).
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
//! - `InsertScans` submits its scans in order with up to [`STREAM_WINDOW`] in flight; a failure
//!   (reported as `request i: …` with the original code) means every earlier scan is durable
//!   (later ones may be: resending is safe).
//! - Answers that depend on a corrupt block are `DATA_LOSS`; other queries are answered.
//!
//! Must not depend on the HTTP or zenoh transports.

mod edits;
mod ingest;
mod maps;
mod queries;
mod updates;

pub use ingest::STREAM_WINDOW;
pub use queries::{EXPORT_CHUNK_CELLS, ExportChunks};
pub use updates::UpdateStream;

use crate::api::proto::calls::ProtoCalls;
use crate::api::proto::codec::set_max_message_bytes;
use crate::api::proto::pb;
use crate::api::proto::pb::map_service_server::MapServiceServer;
use crate::service::MapService;
use std::sync::Arc;
use tonic::{Request, Response, Status, Streaming};

/// Settings of the gRPC port (the query limits are the service's, see
/// [`crate::service::QueryLimits`]).
#[derive(Debug, Clone)]
pub struct GrpcConfig {
    /// Largest message decoded or encoded, in bytes. Default 64 MiB.
    pub max_message_bytes: usize,
}

impl Default for GrpcConfig {
    fn default() -> Self {
        Self { max_message_bytes: 64 << 20 }
    }
}

/// The `bgkmap.v1.MapService` implementation.
#[derive(Debug, Clone)]
pub struct MapGrpc {
    calls: ProtoCalls,
}

impl MapGrpc {
    pub fn new(service: Arc<MapService>, config: GrpcConfig) -> Self {
        Self { calls: ProtoCalls::new(service, config.max_message_bytes) }
    }

    fn service(&self) -> &Arc<MapService> {
        self.calls.service()
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
    set_max_message_bytes(limit);
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

#[tonic::async_trait]
impl pb::map_service_server::MapService for MapGrpc {
    async fn create_map(
        &self,
        request: Request<pb::CreateMapRequest>,
    ) -> Result<Response<pb::MapInfo>, Status> {
        maps::create_map(self.service(), request.into_inner()).map(Response::new)
    }

    async fn list_maps(
        &self,
        _request: Request<pb::ListMapsRequest>,
    ) -> Result<Response<pb::ListMapsResponse>, Status> {
        Ok(Response::new(maps::list_maps(self.service())))
    }

    async fn get_map(&self, request: Request<pb::GetMapRequest>) -> Result<Response<pb::MapInfo>, Status> {
        maps::get_map(self.service(), request.into_inner()).map(Response::new)
    }

    async fn insert_scan(
        &self,
        request: Request<pb::InsertScanRequest>,
    ) -> Result<Response<pb::InsertScanResponse>, Status> {
        ingest::insert_scan(&self.calls, request.into_inner()).await.map(Response::new)
    }

    async fn insert_scans(
        &self,
        request: Request<Streaming<pb::InsertScanRequest>>,
    ) -> Result<Response<pb::InsertScansResponse>, Status> {
        ingest::insert_scans(&self.calls, request.into_inner()).await.map(Response::new)
    }

    async fn query_points(
        &self,
        request: Request<pb::QueryPointsRequest>,
    ) -> Result<Response<pb::QueryPointsResponse>, Status> {
        self.calls.query_points(request.into_inner()).await.map(Response::new)
    }

    async fn query_box(
        &self,
        request: Request<pb::QueryBoxRequest>,
    ) -> Result<Response<pb::QueryBoxResponse>, Status> {
        self.calls.query_box(request.into_inner()).await.map(Response::new)
    }

    async fn cast_rays(
        &self,
        request: Request<pb::CastRaysRequest>,
    ) -> Result<Response<pb::CastRaysResponse>, Status> {
        self.calls.cast_rays(request.into_inner()).await.map(Response::new)
    }

    type ExportStream = ExportChunks;

    async fn export(&self, request: Request<pb::ExportRequest>) -> Result<Response<ExportChunks>, Status> {
        queries::export(self.service(), request.into_inner()).map(Response::new)
    }

    async fn merge_map(
        &self,
        request: Request<pb::MergeMapRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        edits::merge_map(self.service(), request.into_inner()).await.map(Response::new)
    }

    async fn retract_scans(
        &self,
        request: Request<pb::RetractScansRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        edits::retract_scans(self.service(), request.into_inner()).await.map(Response::new)
    }

    async fn repose_scans(
        &self,
        request: Request<pb::ReposeScansRequest>,
    ) -> Result<Response<pb::MapChange>, Status> {
        edits::repose_scans(self.service(), request.into_inner()).await.map(Response::new)
    }

    type WatchUpdatesStream = UpdateStream;

    async fn watch_updates(
        &self,
        request: Request<pb::WatchUpdatesRequest>,
    ) -> Result<Response<UpdateStream>, Status> {
        updates::watch_updates(self.service(), request.into_inner()).map(Response::new)
    }
}
