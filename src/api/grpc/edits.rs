//! gRPC `MergeMap`, `RetractScans` and `ReposeScans`: convert, run one service edit on a
//! blocking thread (it waits for the map's writer), convert the change back.

use crate::api::offload;
use crate::api::proto::convert::{bad, change_to_pb, pose, service_err};
use crate::api::proto::pb;
use crate::service::{Change, MapService, MergeSource, ServiceError};
use crate::store::ScanSelector;
use std::sync::Arc;
use tonic::Status;

/// Runs a service edit off the async workers.
async fn blocking(
    f: impl FnOnce() -> Result<Change, ServiceError> + Send + 'static,
) -> Result<pb::MapChange, Status> {
    let r = offload::blocking(f)
        .await
        .map_err(|e| Status::internal(format!("operation task failed: {}", e.0)))?;
    r.map(change_to_pb).map_err(service_err)
}

pub(super) async fn merge_map(
    service: &Arc<MapService>,
    req: pb::MergeMapRequest,
) -> Result<pb::MapChange, Status> {
    let from = match req.from {
        Some(pb::merge_map_request::From::FromMap(m)) => MergeSource::Map(m),
        Some(pb::merge_map_request::From::FromFile(f)) => MergeSource::File(f.into()),
        None => return Err(bad("MergeMapRequest.from", "set from_map or from_file")),
    };
    let service = service.clone();
    blocking(move || service.merge(&req.map, from)).await
}

fn scan_id(id: Option<pb::ScanId>, field: &str) -> Result<(String, u64), Status> {
    let id = id.ok_or_else(|| bad(field, "missing"))?;
    Ok((id.source, id.seq))
}

pub(super) async fn retract_scans(
    service: &Arc<MapService>,
    req: pb::RetractScansRequest,
) -> Result<pb::MapChange, Status> {
    let selector = ScanSelector {
        scans: req.scans.into_iter().map(|id| (id.source, id.seq)).collect(),
        source: Some(req.source).filter(|s| !s.is_empty()),
        from_stamp_nanos: req.from_stamp_nanos,
        to_stamp_nanos: req.to_stamp_nanos,
    };
    let service = service.clone();
    blocking(move || service.retract(&req.map, selector)).await
}

pub(super) async fn repose_scans(
    service: &Arc<MapService>,
    req: pb::ReposeScansRequest,
) -> Result<pb::MapChange, Status> {
    let mut poses = Vec::with_capacity(req.poses.len());
    for (i, p) in req.poses.into_iter().enumerate() {
        let field = format!("ReposeScansRequest.poses[{i}]");
        poses.push((
            scan_id(p.scan, &format!("{field}.scan"))?,
            pose(p.world_from_sensor, &format!("{field}.world_from_sensor"))?,
        ));
    }
    let service = service.clone();
    blocking(move || service.repose(&req.map, poses)).await
}
