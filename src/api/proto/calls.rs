//! The protobuf calls shared by the two protobuf transports, gRPC and zenoh: request message
//! in, answer message out, so both answer identically by construction (same validation, same
//! exactly-once ingest, same query answers).
//!
//! A query converts its request ([`super::convert`]), builds the validated query at the
//! service's front door ([`crate::service::query`]), runs it where the query says
//! (`api::offload`) writing the answer straight into its message, and refuses an
//! answer over the message limit. Answers that depend on a corrupt block are `DATA_LOSS`.

use super::convert::{bad, cell_state_from_pb, cell_state_to_pb, fits, push_key, query_status};
use super::convert::{service_err, stop_at, thresholds, vec3, xyz_f32};
use super::pb;
use crate::api::offload;
use crate::core::query::RayHit;
use crate::service::query::{BoxRequest, RayRequest};
use crate::service::{Ack, MapService, QueryError, ScanInput, ServiceError, SubmitOptions};
use std::sync::Arc;
use tonic::Status;

/// The service and the message limit of the protobuf transports (the gRPC port's).
#[derive(Debug, Clone)]
pub struct ProtoCalls {
    service: Arc<MapService>,
    max_message_bytes: usize,
}

/// The outcome of a submitted scan, once known.
pub type AckReceiver = tokio::sync::oneshot::Receiver<Result<Ack, ServiceError>>;

/// A blocking task that died is INTERNAL.
fn task_failed(e: offload::TaskFailed) -> Status {
    Status::internal(format!("query task failed: {}", e.0))
}

impl ProtoCalls {
    /// `max_message_bytes`: the largest message decoded or answered.
    pub fn new(service: Arc<MapService>, max_message_bytes: usize) -> Self {
        Self { service, max_message_bytes }
    }

    pub fn service(&self) -> &Arc<MapService> {
        &self.service
    }

    pub fn max_message_bytes(&self) -> usize {
        self.max_message_bytes
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

    pub async fn query_points(&self, req: pb::QueryPointsRequest) -> Result<pb::QueryPointsResponse, Status> {
        const REQ: &str = "QueryPointsRequest";
        let queries = self.service.queries(&req.map).map_err(service_err)?;
        let th = queries.thresholds(thresholds(req.thresholds)).map_err(|e| query_status(e, REQ))?;
        let raw = xyz_f32(&req.xyz_f32, "QueryPointsRequest.xyz_f32")?;
        let points = raw.iter().map(|p| p.map(f64::from)).collect();
        let q = queries.points(points, th).map_err(|e| match e {
            QueryError::NotFinite { index: i } => {
                bad("QueryPointsRequest.xyz_f32", format!("point {i} is not finite: {:?}", raw[i]))
            }
            other => query_status(other, REQ),
        })?;
        let limit = self.max_message_bytes;
        offload::run(q.runs_inline(), move || {
            let n = q.len();
            let mut out = pb::QueryPointsResponse {
                probability: Vec::with_capacity(n),
                variance: Vec::with_capacity(n),
                state: Vec::with_capacity(n),
                cell: Vec::with_capacity(3 * n),
                version: q.version(),
            };
            // Columns written as the batched lookups answer, with no answer vector between.
            q.run(|a| {
                out.probability.push(a.estimate.probability);
                out.variance.push(a.estimate.variance);
                out.state.push(cell_state_to_pb(a.estimate.state));
                push_key(&mut out.cell, a.cell);
            })
            .map_err(|e| query_status(e, REQ))?;
            fits(out, limit, "QueryPointsRequest.xyz_f32", "query fewer points per request")
        })
        .await
        .map_err(task_failed)?
    }

    pub async fn query_box(&self, req: pb::QueryBoxRequest) -> Result<pb::QueryBoxResponse, Status> {
        const REQ: &str = "QueryBoxRequest";
        let queries = self.service.queries(&req.map).map_err(service_err)?;
        let th = queries.thresholds(thresholds(req.thresholds)).map_err(|e| query_status(e, REQ))?;
        let min_world = vec3(&req.min, "QueryBoxRequest.min")?;
        let max_world = vec3(&req.max, "QueryBoxRequest.max")?;
        let state = req.state.map(cell_state_from_pb).transpose()?;
        let request = BoxRequest { min_world, max_world, state, coarsen: req.coarsen };
        let q = queries.cuboid(request, th).map_err(|e| query_status(e, REQ))?;
        let (limit, counts_only) = (self.max_message_bytes, req.counts_only);
        offload::run(q.runs_inline(), move || {
            let answer = q.run().map_err(|e| query_status(e, REQ))?;
            let [free, occupied, unknown] = answer.counts.map(|n| n as u64);
            let mut out = pb::QueryBoxResponse {
                free,
                occupied,
                unknown,
                version: answer.version,
                ..Default::default()
            };
            if !counts_only {
                let n = answer.cells.len();
                out.min_cell.reserve(3 * n);
                out.size_cells.reserve(n);
                out.probability.reserve(n);
                out.variance.reserve(n);
                out.state.reserve(n);
                for c in &answer.cells {
                    push_key(&mut out.min_cell, c.min_cell);
                    out.size_cells.push(c.size_cells.unsigned_abs());
                    out.probability.push(c.estimate.probability);
                    out.variance.push(c.estimate.variance);
                    out.state.push(cell_state_to_pb(c.estimate.state));
                }
            }
            fits(out, limit, "QueryBoxRequest", "use counts_only, coarsen, a smaller box or Export")
        })
        .await
        .map_err(task_failed)?
    }

    pub async fn cast_rays(&self, req: pb::CastRaysRequest) -> Result<pb::CastRaysResponse, Status> {
        const REQ: &str = "CastRaysRequest";
        let queries = self.service.queries(&req.map).map_err(service_err)?;
        let th = queries.thresholds(thresholds(req.thresholds)).map_err(|e| query_status(e, REQ))?;
        let stop = stop_at(req.stop_at)?;
        let rays = req
            .rays
            .iter()
            .enumerate()
            .map(|(i, r)| {
                Ok(RayRequest {
                    origin_world: vec3(&r.origin, format_args!("CastRaysRequest.rays[{i}].origin"))?,
                    direction_world: vec3(&r.direction, format_args!("CastRaysRequest.rays[{i}].direction"))?,
                    max_range_m: r.max_range,
                })
            })
            .collect::<Result<Vec<_>, Status>>()?;
        let q = queries.rays(rays, stop, th);
        let limit = self.max_message_bytes;
        offload::run(q.runs_inline(), move || {
            let mut results = Vec::with_capacity(q.len());
            q.run(|r, hit| {
                results.push(match hit {
                    RayHit::Clear => {
                        pb::RayResult { blocked: false, distance: r.max_range_m, ..Default::default() }
                    }
                    RayHit::Blocked { cell, distance_m, estimate } => pb::RayResult {
                        blocked: true,
                        cell: vec![cell.x, cell.y, cell.z],
                        distance: distance_m,
                        state: cell_state_to_pb(estimate.state),
                        probability: estimate.probability,
                    },
                })
            })
            .map_err(|e| query_status(e, REQ))?;
            let out = pb::CastRaysResponse { results, version: q.version() };
            fits(out, limit, "CastRaysRequest.rays", "cast fewer rays per request")
        })
        .await
        .map_err(task_failed)?
    }
}
