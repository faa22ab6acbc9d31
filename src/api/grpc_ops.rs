//! gRPC handlers of streamed ingest and of the exact map operations (merge, retract,
//! re-pose): convert, call one service method (on a blocking thread: they wait for the map's
//! writer), convert back.

use super::grpc::{MapGrpc, bad, scan_input, service_err};
use super::pb;
use crate::core::Pose;
use crate::service::{Ack, Change, MapService, MergeSource, ServiceError};
use crate::store::ScanSelector;
use std::collections::VecDeque;
use std::sync::Arc;
use tonic::{Status, Streaming};

/// Scans of one `InsertScans` stream in flight at once (their journal writes share fsyncs).
pub const STREAM_WINDOW: usize = 32;

/// Longest wait of a stream with no scan in flight before it offers its next scan again.
const MAX_BUSY_WAIT: std::time::Duration = std::time::Duration::from_millis(50);

type InFlight = VecDeque<(u64, tokio::sync::oneshot::Receiver<Result<Ack, ServiceError>>)>;

fn at(index: u64, s: Status) -> Status {
    Status::with_metadata(s.code(), format!("request {index}: {}", s.message()), s.metadata().clone())
}

/// Waits for the oldest scan in flight and counts it.
async fn settle(inflight: &mut InFlight, summary: &mut pb::InsertScansResponse) -> Result<(), Status> {
    let Some((index, rx)) = inflight.pop_front() else { return Ok(()) };
    let ack = rx.await.unwrap_or(Err(ServiceError::ShuttingDown)).map_err(|e| at(index, service_err(e)))?;
    summary.scans += 1;
    if ack.applied {
        summary.applied += 1;
    } else {
        summary.duplicates += 1;
    }
    summary.version = summary.version.max(ack.version);
    Ok(())
}

async fn drain(inflight: &mut InFlight, summary: &mut pb::InsertScansResponse) -> Result<(), Status> {
    while !inflight.is_empty() {
        settle(inflight, summary).await?;
    }
    Ok(())
}

/// `InsertScans`: scans are submitted in stream order with up to [`STREAM_WINDOW`] awaiting
/// their acknowledgement; a full queue waits for the oldest instead of failing (with none in
/// flight, for the time the busy refusal names, at most [`MAX_BUSY_WAIT`] at a time). The first
/// failure ends the stream as `request i: …`: every earlier scan is durable; later ones may be
/// too (resending them is safe: duplicates are acknowledged, not applied twice).
pub(super) async fn insert_scans(
    g: &MapGrpc,
    mut stream: Streaming<pb::InsertScanRequest>,
) -> Result<pb::InsertScansResponse, Status> {
    let mut summary = pb::InsertScansResponse::default();
    let mut inflight = InFlight::new();
    let mut index = 0u64;
    loop {
        let req = match stream.message().await {
            Ok(Some(r)) => r,
            Ok(None) => break,
            Err(e) => {
                drain(&mut inflight, &mut summary).await?;
                return Err(e);
            }
        };
        let scan = match scan_input(req.scan) {
            Ok(s) => s,
            Err(e) => {
                drain(&mut inflight, &mut summary).await?;
                return Err(at(index, e));
            }
        };
        loop {
            match g.submit(&req.map, scan.clone(), req.wait_applied) {
                Ok(rx) => {
                    inflight.push_back((index, rx));
                    break;
                }
                Err(e) if e.code() == tonic::Code::ResourceExhausted && !inflight.is_empty() => {
                    settle(&mut inflight, &mut summary).await?;
                }
                // The queue is full of other clients' scans: wait for room as above, by the
                // refusal's own hint (a stream that failed here broke the "waits" promise
                // whenever several robots streamed into one map and the journal fell behind).
                Err(e) if let Some(wait) = super::status::retry_after(&e) => {
                    tokio::time::sleep(wait.min(MAX_BUSY_WAIT)).await;
                }
                Err(e) => {
                    drain(&mut inflight, &mut summary).await?;
                    return Err(at(index, e));
                }
            }
        }
        index += 1;
        while inflight.len() >= STREAM_WINDOW {
            settle(&mut inflight, &mut summary).await?;
        }
    }
    drain(&mut inflight, &mut summary).await?;
    Ok(summary)
}

fn change_to_pb(c: Change) -> pb::MapChange {
    pb::MapChange {
        scans: c.scans,
        shared_scans: c.shared,
        blocks_changed: c.blocks_changed,
        version: c.version,
    }
}

/// Runs a blocking service operation off the async workers.
async fn blocking(
    f: impl FnOnce() -> Result<Change, ServiceError> + Send + 'static,
) -> Result<pb::MapChange, Status> {
    let r = tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| Status::internal(format!("operation task failed: {e}")))?;
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

fn pose(p: Option<pb::Pose>, field: &str) -> Result<Pose, Status> {
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
