//! The updates (the change stream) as protobuf: the `bgkmap.v1.MapUpdate` that gRPC
//! `WatchUpdates` streams and zenoh puts on `bgkmap/<map>/updates`, and the validation of a
//! `WatchUpdatesRequest`, shared by gRPC and zenoh (`bgkmap/<map>/updates/since`).

use super::convert::{bad, service_err, vec3};
use super::pb;
use crate::core::key::BLOCK_EDGE;
use crate::service::{BlockBox, MapService, MapUpdate, ScanPose, ServiceError, UpdateKind, Watch};
use tonic::Status;

fn pose_to_pb(p: &ScanPose) -> pb::SensorPose {
    pb::SensorPose {
        version: p.version,
        source: p.source.clone(),
        seq: p.seq,
        world_from_sensor: Some(pb::Pose {
            translation: p.world_from_sensor.translation_m.to_vec(),
            rotation: p.world_from_sensor.rotation_wxyz.to_vec(),
        }),
    }
}

/// An update as the wire message (gRPC `WatchUpdates`, zenoh `bgkmap/<map>/updates`).
pub fn update_to_pb(u: &MapUpdate, resolution: f64) -> pb::MapUpdate {
    let kind = match u.kind {
        UpdateKind::CatchUp => pb::UpdateKind::CatchUp,
        UpdateKind::Live => pb::UpdateKind::Live,
        UpdateKind::Resync => pb::UpdateKind::Resync,
    };
    pb::MapUpdate {
        kind: kind as i32,
        from_version: u.from_version,
        version: u.version,
        block: u.blocks.iter().flat_map(|k| [k.x, k.y, k.z]).collect(),
        block_edge: BLOCK_EDGE.unsigned_abs(),
        resolution,
        poses: u.poses.iter().map(pose_to_pb).collect(),
        reset: u.reset,
    }
}

/// The map's resolution and the request's box filter, validated.
fn watch_filter(
    service: &MapService,
    req: &pb::WatchUpdatesRequest,
) -> Result<(f64, Option<BlockBox>), Status> {
    let snap = service.snapshot(&req.map).map_err(service_err)?;
    let resolution = snap.map.params().resolution_m;
    let filter = match (req.min.is_empty(), req.max.is_empty()) {
        (true, true) => None,
        _ => {
            let min = vec3(&req.min, "WatchUpdatesRequest.min")?;
            let max = vec3(&req.max, "WatchUpdatesRequest.max")?;
            Some(BlockBox::from_world(min, max, resolution).map_err(|e| bad("WatchUpdatesRequest.min", e))?)
        }
    };
    Ok((resolution, filter))
}

/// A `since_version` ahead of the map is the request's fault.
fn since_error(e: ServiceError) -> Status {
    match e {
        ServiceError::InvalidArgument { reason, .. } => bad("WatchUpdatesRequest.since_version", reason),
        other => service_err(other),
    }
}

/// Validates a `WatchUpdatesRequest` and starts the watch it asks for.
pub fn watch(service: &MapService, req: &pb::WatchUpdatesRequest) -> Result<Watch, Status> {
    let (resolution, filter) = watch_filter(service, req)?;
    let started = service.watch(&req.map, req.since_version, filter).map_err(since_error)?;
    Ok(Watch::new(started, resolution))
}

/// The catch-up alone: every block changed after `since_version` (0 when unset) inside the
/// request's box, as the first message of a `WatchUpdates` stream with the same request would
/// carry it (zenoh `bgkmap/<map>/updates/since`).
pub fn changes_since(service: &MapService, req: &pb::WatchUpdatesRequest) -> Result<pb::MapUpdate, Status> {
    let (resolution, filter) = watch_filter(service, req)?;
    let u = service
        .changes_since(&req.map, req.since_version.unwrap_or(0), filter.as_ref())
        .map_err(since_error)?;
    Ok(update_to_pb(&u, resolution))
}
