//! gRPC ingest: `InsertScan` (one scan, answered once durable or integrated) and the
//! `InsertScans` stream (many scans in flight, sharing their journal fsyncs).

use crate::api::proto::calls::{AckReceiver, ProtoCalls};
use crate::api::proto::convert::{scan_input, service_err};
use crate::api::proto::pb;
use crate::api::status::retry_after;
use crate::service::ServiceError;
use std::collections::VecDeque;
use tonic::{Status, Streaming};

/// Scans of one `InsertScans` stream in flight at once (their journal writes share fsyncs).
pub const STREAM_WINDOW: usize = 32;

/// Longest wait of a stream with no scan in flight before it offers its next scan again.
const MAX_BUSY_WAIT: std::time::Duration = std::time::Duration::from_millis(50);

type InFlight = VecDeque<(u64, AckReceiver)>;

pub(super) async fn insert_scan(
    calls: &ProtoCalls,
    req: pb::InsertScanRequest,
) -> Result<pb::InsertScanResponse, Status> {
    let scan = scan_input(req.scan)?;
    let ack = calls.insert(&req.map, scan, req.wait_applied).await?;
    Ok(pb::InsertScanResponse {
        applied: ack.applied,
        version: ack.version,
        dropped_points: ack.dropped_points as u64,
    })
}

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
    calls: &ProtoCalls,
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
            match calls.submit(&req.map, scan.clone(), req.wait_applied) {
                Ok(rx) => {
                    inflight.push_back((index, rx));
                    break;
                }
                Err(e) if e.code() == tonic::Code::ResourceExhausted && !inflight.is_empty() => {
                    settle(&mut inflight, &mut summary).await?;
                }
                // The queue is full of other clients' scans: wait for room as above, by the
                // refusal's own hint, so the stream keeps its promise to wait rather than fail
                // when several robots stream into one map and the journal falls behind.
                Err(e) if let Some(wait) = retry_after(&e) => {
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
