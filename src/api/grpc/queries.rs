//! gRPC `Export`: every cell with evidence (optionally inside a box) sorted by key, streamed in
//! chunks from a blocking thread. The point, box and ray queries are the protobuf calls gRPC
//! shares with zenoh ([`crate::api::proto::calls`]).

use crate::api::offload;
use crate::api::proto::convert::{bad, push_key, query_status, service_err, thresholds, vec3};
use crate::api::proto::pb;
use crate::core::query::BoxError;
use crate::service::query::cells::ExportQuery;
use crate::service::{MapService, QueryError};
use std::ops::ControlFlow;
use std::pin::Pin;
use std::task::{Context, Poll};
use tonic::Status;

/// Cells per `ExportChunk`.
pub const EXPORT_CHUNK_CELLS: usize = 65_536;

type ChunkSender = tokio::sync::mpsc::Sender<Result<pb::ExportChunk, Status>>;

/// The `Export` response stream.
#[derive(Debug)]
pub struct ExportChunks(tokio::sync::mpsc::Receiver<Result<pb::ExportChunk, Status>>);

impl tokio_stream::Stream for ExportChunks {
    type Item = Result<pb::ExportChunk, Status>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.0.poll_recv(cx)
    }
}

/// Validates the request at the service's front door and starts the stream.
pub(super) fn export(service: &MapService, req: pb::ExportRequest) -> Result<ExportChunks, Status> {
    const REQ: &str = "ExportRequest";
    let queries = service.queries(&req.map).map_err(service_err)?;
    let th = queries.thresholds(thresholds(req.thresholds)).map_err(|e| query_status(e, REQ))?;
    let bounds = if req.min.is_empty() && req.max.is_empty() {
        None
    } else {
        Some((vec3(&req.min, "ExportRequest.min")?, vec3(&req.max, "ExportRequest.max")?))
    };
    let q = queries.export(bounds, th).map_err(|e| match e {
        QueryError::Box(BoxError::Malformed) => bad(
            "ExportRequest.min",
            "min and max must be finite, inside the key range, with min ≤ max on every axis",
        ),
        other => query_status(other, REQ),
    })?;
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    offload::detach(move || send_chunks(&q, &tx));
    Ok(ExportChunks(rx))
}

/// Sends the export's cells in chunks; always at least one (so `resolution` is known).
fn send_chunks(q: &ExportQuery, tx: &ChunkSender) {
    let resolution = q.resolution_m();
    let empty = || pb::ExportChunk { resolution, ..Default::default() };
    let mut chunk = empty();
    let mut sent_any = false;
    let flush = |chunk: &mut pb::ExportChunk| tx.blocking_send(Ok(std::mem::replace(chunk, empty()))).is_ok();
    let mut gone = false;
    q.for_each_sorted(|cell, e| {
        push_key(&mut chunk.cell, cell);
        chunk.probability.push(e.probability);
        chunk.variance.push(e.variance);
        if chunk.probability.len() == EXPORT_CHUNK_CELLS {
            if !flush(&mut chunk) {
                gone = true; // the client went away
                return ControlFlow::Break(());
            }
            sent_any = true;
        }
        ControlFlow::Continue(())
    });
    if !gone && (!chunk.probability.is_empty() || !sent_any) {
        flush(&mut chunk);
    }
}
