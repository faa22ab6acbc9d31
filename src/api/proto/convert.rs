//! Conversions between protobuf messages and service types, shared by gRPC and zenoh.
//!
//! Wire → service conversions name the proto field path in their `INVALID_ARGUMENT` errors
//! (`bgkmap.v1.Scan.xyz_f32: length 13 is not a multiple of 12`); service errors go through
//! [`crate::api::status::to_grpc`], and query errors through [`query_status`], the one mapping
//! of [`QueryError`] for the protobuf transports.

use super::pb;
use crate::api::status::to_grpc;
use crate::core::query::{BoxError, StopAt};
use crate::core::{CellKey, CellState, PointFrame, Pose};
use crate::service::query::ThresholdsIn;
use crate::service::{QueryError, ScanInput, ServiceError, Snapshot};
use crate::store::Change;
use tonic::Status;

/// `INVALID_ARGUMENT` naming `bgkmap.v1.<field>`.
pub fn bad(field: &str, reason: impl std::fmt::Display) -> Status {
    Status::invalid_argument(format!("bgkmap.v1.{field}: {reason}"))
}

pub fn service_err(e: ServiceError) -> Status {
    to_grpc(&e)
}

/// A query refused by the service, as gRPC says it; `request` names the request message
/// (`QueryBoxRequest`) whose `thresholds` field an invalid threshold came in. Each other
/// variant comes from one kind of request only, so it names that request's field.
pub fn query_status(e: QueryError, request: &str) -> Status {
    match e {
        QueryError::Threshold { name, reason } => bad(&format!("{request}.thresholds.{name}"), reason),
        QueryError::NotFinite { index } => {
            bad("QueryPointsRequest.xyz_f32", format!("point {index} is not finite"))
        }
        QueryError::Outside { index } => {
            bad("QueryPointsRequest.xyz_f32", format!("point {index} is outside the map's key range"))
        }
        QueryError::Coarsen(c) => bad("QueryBoxRequest.coarsen", format!("must be at most 10, got {c}")),
        QueryError::Box(e @ BoxError::Malformed) => bad("QueryBoxRequest.min", e),
        QueryError::Box(e @ BoxError::Coarsen(_)) => bad("QueryBoxRequest.coarsen", e),
        QueryError::Box(e @ BoxError::TooLarge { .. }) => bad("QueryBoxRequest", e),
        QueryError::Ray { index, error } => bad(&format!("CastRaysRequest.rays[{index}]"), error),
        QueryError::RayCorrupt { index, block } => {
            service_err(Snapshot::loss(&block, format!("ray {index}")))
        }
        QueryError::Service(e) => service_err(e),
    }
}

/// Exactly three values (x, y, z). `field` is formatted only for the error.
pub fn vec3(v: &[f64], field: impl std::fmt::Display) -> Result<[f64; 3], Status> {
    <[f64; 3]>::try_from(v)
        .map_err(|_| bad(&field.to_string(), format!("expected 3 values (x, y, z), got {}", v.len())))
}

/// Little-endian f32 triplets.
pub fn xyz_f32(bytes: &[u8], field: &str) -> Result<Vec<[f32; 3]>, Status> {
    if !bytes.len().is_multiple_of(12) {
        return Err(bad(field, format!("length {} is not a multiple of 12", bytes.len())));
    }
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    Ok(bytes.chunks_exact(12).map(|c| [f(&c[0..4]), f(&c[4..8]), f(&c[8..12])]).collect())
}

/// Threshold overrides; unset fields take the map's defaults (in the service).
pub fn thresholds(t: Option<pb::Thresholds>) -> ThresholdsIn {
    let t = t.unwrap_or_default();
    ThresholdsIn { p_free: t.p_free, p_occ: t.p_occ, var_max: t.var_max }
}

pub fn scan_input(scan: Option<pb::Scan>) -> Result<ScanInput, Status> {
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

/// A pose at `field` (`…world_from_sensor`), naming its translation or rotation when wrong.
pub fn pose(p: Option<pb::Pose>, field: &str) -> Result<Pose, Status> {
    let p = p.ok_or_else(|| bad(field, "missing"))?;
    let translation_m = <[f64; 3]>::try_from(p.translation.as_slice()).map_err(|_| {
        bad(
            &format!("{field}.translation"),
            format!("expected 3 values (x, y, z), got {}", p.translation.len()),
        )
    })?;
    let rotation_wxyz = <[f64; 4]>::try_from(p.rotation.as_slice()).map_err(|_| {
        bad(&format!("{field}.rotation"), format!("expected 4 values (w, x, y, z), got {}", p.rotation.len()))
    })?;
    Ok(Pose { translation_m, rotation_wxyz })
}

pub fn stop_at(v: i32) -> Result<StopAt, Status> {
    match pb::StopAt::try_from(v) {
        Ok(pb::StopAt::Occupied) => Ok(StopAt::Occupied),
        Ok(pb::StopAt::NotFree) => Ok(StopAt::NotFree),
        Err(_) => Err(bad("CastRaysRequest.stop_at", format!("unknown value {v}"))),
    }
}

pub fn cell_state_from_pb(v: i32) -> Result<CellState, Status> {
    match pb::CellState::try_from(v) {
        Ok(pb::CellState::Free) => Ok(CellState::Free),
        Ok(pb::CellState::Occupied) => Ok(CellState::Occupied),
        Ok(pb::CellState::Unknown) => Ok(CellState::Unknown),
        Err(_) => Err(bad("QueryBoxRequest.state", format!("unknown value {v}"))),
    }
}

pub fn cell_state_to_pb(s: CellState) -> i32 {
    match s {
        CellState::Free => pb::CellState::Free as i32,
        CellState::Occupied => pb::CellState::Occupied as i32,
        CellState::Unknown => pb::CellState::Unknown as i32,
    }
}

pub fn push_key(out: &mut Vec<i32>, k: CellKey) {
    out.extend_from_slice(&[k.x, k.y, k.z]);
}

pub fn change_to_pb(c: Change) -> pb::MapChange {
    pb::MapChange {
        scans: c.scans,
        shared_scans: c.shared,
        blocks_changed: c.blocks_changed,
        version: c.version,
    }
}

/// Refuses an answer that would not fit in one message.
pub fn fits<M: prost::Message + 'static>(msg: M, limit: usize, what: &str, hint: &str) -> Result<M, Status> {
    let len = super::codec::encoded_len(&msg);
    if len > limit {
        return Err(bad(
            what,
            format!("the answer is {len} bytes, over the message limit of {limit}; {hint}"),
        ));
    }
    Ok(msg)
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
