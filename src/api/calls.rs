//! The protobuf calls shared by the two protobuf transports, gRPC ([`super::grpc`]) and zenoh
//! ([`super::zenoh_transport`]): request message in, answer message out, so both answer
//! identically by construction (same validation, same exactly-once ingest, same query answers).
//!
//! Conversions (wire → core) name the proto field path in their `INVALID_ARGUMENT` errors
//! (`bgkmap.v1.QueryPointsRequest.xyz_f32: length 13 is not a multiple of 12`); service errors go
//! through [`to_grpc`], the one mapping of every transport. Queries read the map's current
//! snapshot (answers that depend on a corrupt block are `DATA_LOSS`); heavy ones run on a
//! blocking thread.

use super::grpc::GrpcConfig;
use super::pb;
use super::status::to_grpc;
use crate::core::query::{
    BoxError, BoxQuery, RayHit, StopAt, cast_ray, count_box, for_each_point, query_box,
};
use crate::core::{CellKey, CellState, PointFrame, Pose, Thresholds};
use crate::service::{Ack, MapService, ScanInput, ServiceError, Snapshot, SubmitOptions};
use std::sync::Arc;
use tonic::Status;

/// Query points above which the work moves to a blocking thread.
const INLINE_POINTS: usize = 10_000;

/// The service and the limits of the protobuf transports (those of the gRPC port).
#[derive(Debug, Clone)]
pub struct ProtoCalls {
    service: Arc<MapService>,
    config: GrpcConfig,
}

/// The outcome of a submitted scan, once known.
pub type AckReceiver = tokio::sync::oneshot::Receiver<Result<Ack, ServiceError>>;

impl ProtoCalls {
    pub fn new(service: Arc<MapService>, config: GrpcConfig) -> Self {
        Self { service, config }
    }

    pub fn service(&self) -> &Arc<MapService> {
        &self.service
    }

    pub fn config(&self) -> &GrpcConfig {
        &self.config
    }

    /// Submits one scan (validated, then journaled by the service); the receiver gets its
    /// outcome once it is durable or, with `wait_applied`, integrated.
    pub fn submit(&self, map: &str, scan: ScanInput, wait_applied: bool) -> Result<AckReceiver, Status> {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let options = SubmitOptions { wait_applied };
        self.service.submit(map, scan, options, Box::new(move |r| drop(tx.send(r)))).map_err(service_err)?;
        Ok(rx)
    }

    /// Submits one scan and waits until it is durable (or, with `wait_applied`, integrated).
    pub async fn insert(&self, map: &str, scan: ScanInput, wait_applied: bool) -> Result<Ack, Status> {
        let rx = self.submit(map, scan, wait_applied)?;
        match rx.await {
            Ok(r) => r.map_err(service_err),
            Err(_) => Err(service_err(ServiceError::ShuttingDown)),
        }
    }

    pub fn snapshot(&self, map: &str) -> Result<Arc<Snapshot>, Status> {
        self.service.snapshot(map).map_err(service_err)
    }

    pub async fn query_points(&self, req: pb::QueryPointsRequest) -> Result<pb::QueryPointsResponse, Status> {
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
        Ok(answer)
    }

    pub async fn query_box(&self, req: pb::QueryBoxRequest) -> Result<pb::QueryBoxResponse, Status> {
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
        Ok(answer)
    }

    pub async fn cast_rays(&self, req: pb::CastRaysRequest) -> Result<pb::CastRaysResponse, Status> {
        let snap = self.snapshot(&req.map)?;
        let th = thresholds(req.thresholds, snap.map.params().thresholds, "CastRaysRequest.thresholds")?;
        let stop = stop_at(req.stop_at)?;
        let rays = req
            .rays
            .iter()
            .enumerate()
            .map(|(i, r)| {
                Ok(RayInput {
                    origin: vec3(&r.origin, format_args!("CastRaysRequest.rays[{i}].origin"))?,
                    direction: vec3(&r.direction, format_args!("CastRaysRequest.rays[{i}].direction"))?,
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
        Ok(answer)
    }
}

/// `INVALID_ARGUMENT` naming `bgkmap.v1.<field>`.
pub(super) fn bad(field: &str, reason: impl std::fmt::Display) -> Status {
    Status::invalid_argument(format!("bgkmap.v1.{field}: {reason}"))
}

pub(super) fn service_err(e: ServiceError) -> Status {
    to_grpc(&e)
}

/// Exactly three values (x, y, z). `field` is formatted only for the error.
pub(super) fn vec3(v: &[f64], field: impl std::fmt::Display) -> Result<[f64; 3], Status> {
    <[f64; 3]>::try_from(v)
        .map_err(|_| bad(&field.to_string(), format!("expected 3 values (x, y, z), got {}", v.len())))
}

/// Little-endian f32 triplets.
pub(super) fn xyz_f32(bytes: &[u8], field: &str) -> Result<Vec<[f32; 3]>, Status> {
    if !bytes.len().is_multiple_of(12) {
        return Err(bad(field, format!("length {} is not a multiple of 12", bytes.len())));
    }
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    Ok(bytes.chunks_exact(12).map(|c| [f(&c[0..4]), f(&c[4..8]), f(&c[8..12])]).collect())
}

/// Query thresholds: unset fields take the map's defaults.
pub(super) fn thresholds(
    t: Option<pb::Thresholds>,
    map_default: Thresholds,
    field: &str,
) -> Result<Thresholds, Status> {
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

pub(super) fn stop_at(v: i32) -> Result<StopAt, Status> {
    match pb::StopAt::try_from(v) {
        Ok(pb::StopAt::Occupied) => Ok(StopAt::Occupied),
        Ok(pb::StopAt::NotFree) => Ok(StopAt::NotFree),
        Err(_) => Err(bad("CastRaysRequest.stop_at", format!("unknown value {v}"))),
    }
}

pub(super) fn cell_state_from_pb(v: i32) -> Result<CellState, Status> {
    match pb::CellState::try_from(v) {
        Ok(pb::CellState::Free) => Ok(CellState::Free),
        Ok(pb::CellState::Occupied) => Ok(CellState::Occupied),
        Ok(pb::CellState::Unknown) => Ok(CellState::Unknown),
        Err(_) => Err(bad("QueryBoxRequest.state", format!("unknown value {v}"))),
    }
}

pub(super) fn cell_state_to_pb(s: CellState) -> i32 {
    match s {
        CellState::Free => pb::CellState::Free as i32,
        CellState::Occupied => pb::CellState::Occupied as i32,
        CellState::Unknown => pb::CellState::Unknown as i32,
    }
}

pub(super) fn push_key(out: &mut Vec<i32>, k: CellKey) {
    out.extend_from_slice(&[k.x, k.y, k.z]);
}

/// Refuses an answer that would not fit in one message.
pub(super) fn fits<M: prost::Message + 'static>(
    msg: M,
    limit: usize,
    what: &str,
    hint: &str,
) -> Result<M, Status> {
    let len = super::codec::encoded_len(&msg);
    if len > limit {
        return Err(bad(
            what,
            format!("the answer is {len} bytes, over the message limit of {limit}; {hint}"),
        ));
    }
    Ok(msg)
}

/// Runs `f` on a blocking thread when `heavy`, else inline.
pub(super) async fn compute<T: Send + 'static>(
    heavy: bool,
    f: impl FnOnce() -> Result<T, Status> + Send + 'static,
) -> Result<T, Status> {
    if !heavy {
        return f();
    }
    tokio::task::spawn_blocking(f).await.map_err(|e| Status::internal(format!("query task failed: {e}")))?
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
    // Columns written as the batched lookups answer; the first point outside the key range
    // (all before it answered) is the one named.
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
        snap.check_ray(r.origin, r.direction, reach, format_args!("ray {i}")).map_err(service_err)?;
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
