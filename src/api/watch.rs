//! The change stream on the wire: gRPC `WatchUpdates` (server streaming) and HTTP
//! server-sent events (`GET /v1/maps/{map}/updates?since=N`), both over
//! [`MapService::watch`].
//!
//! Each stream starts with the catch-up (the blocks changed since the version asked for; none
//! when none was asked), then one message per change of the map (a batch of integrated scans,
//! a merge, a retraction, a re-pose). A watcher that falls behind the service's bounded feed
//! gets one `resync` message listing every block changed since the last version it was sent.
//! When the server shuts down the gRPC stream ends with `UNAVAILABLE` and the SSE stream closes
//! (browsers reconnect with `Last-Event-ID`, which is the last version they saw, so they resume
//! exactly; after a restart a version from before it gets a catch-up with `reset`: every block
//! the map holds, drop the rest).
//!
//! SSE messages are JSON: `{"kind": "catch_up"|"live"|"resync", "from_version", "version",
//! "blocks": [[x, y, z], …], "block_edge", "resolution", "poses": [{"version", "source",
//! "seq", "translation": [x, y, z], "rotation": [w, x, y, z]}, …], "reset"}`; the event id is
//! `version`.

use super::grpc::{bad, vec3};
use super::http::ApiError;
use super::pb;
use super::status::to_grpc;
use crate::core::key::BLOCK_EDGE;
use crate::service::{BlockBox, MapService, MapUpdate, Next, ScanPose, Subscription, UpdateKind};
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tonic::Status;

/// One watch: the catch-up still to send, then the live subscription.
#[derive(Debug)]
struct Watch {
    first: Option<MapUpdate>,
    sub: Subscription,
    resolution: f64,
    closed: bool,
}

impl Watch {
    /// The next update to send; `None` once the service has closed the feed.
    fn poll_update(&mut self, cx: &mut Context<'_>) -> Poll<Option<Arc<MapUpdate>>> {
        if let Some(first) = self.first.take() {
            return Poll::Ready(Some(Arc::new(first)));
        }
        if self.closed {
            return Poll::Ready(None);
        }
        match self.sub.poll_next(cx) {
            Poll::Ready(Next::Update(u)) => Poll::Ready(Some(u)),
            Poll::Ready(Next::Closed) => {
                self.closed = true;
                Poll::Ready(None)
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// gRPC

/// The `WatchUpdates` response stream.
#[derive(Debug)]
pub struct UpdateStream {
    watch: Watch,
    ended: bool,
}

impl tokio_stream::Stream for UpdateStream {
    type Item = Result<pb::MapUpdate, Status>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.ended {
            return Poll::Ready(None);
        }
        let resolution = self.watch.resolution;
        match self.watch.poll_update(cx) {
            Poll::Ready(Some(u)) => Poll::Ready(Some(Ok(update_to_pb(&u, resolution)))),
            Poll::Ready(None) => {
                self.ended = true;
                Poll::Ready(Some(Err(Status::unavailable("the server is shutting down; watch again"))))
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

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

/// A feed update as the wire message (gRPC `WatchUpdates`, zenoh `bgkmap/<map>/updates`).
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
    let snap = service.snapshot(&req.map).map_err(|e| to_grpc(&e))?;
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
fn since_error(e: crate::service::ServiceError) -> Status {
    match e {
        crate::service::ServiceError::InvalidArgument { reason, .. } => {
            bad("WatchUpdatesRequest.since_version", reason)
        }
        other => to_grpc(&other),
    }
}

/// `WatchUpdates`: validates the request and starts the watch.
pub fn watch_updates(service: &MapService, req: pb::WatchUpdatesRequest) -> Result<UpdateStream, Status> {
    let (resolution, filter) = watch_filter(service, &req)?;
    let (first, sub) = service.watch(&req.map, req.since_version, filter).map_err(since_error)?;
    Ok(UpdateStream { watch: Watch { first: Some(first), sub, resolution, closed: false }, ended: false })
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

// ---------------------------------------------------------------------------------------------
// HTTP server-sent events

fn update_json(u: &MapUpdate, resolution: f64) -> Value {
    let kind = match u.kind {
        UpdateKind::CatchUp => "catch_up",
        UpdateKind::Live => "live",
        UpdateKind::Resync => "resync",
    };
    let poses: Vec<Value> = u.poses.iter().map(pose_json).collect();
    let blocks: Vec<[i32; 3]> = u.blocks.iter().map(|k| [k.x, k.y, k.z]).collect();
    json!({"kind": kind, "from_version": u.from_version, "version": u.version, "blocks": blocks,
           "block_edge": BLOCK_EDGE, "resolution": resolution, "poses": poses, "reset": u.reset})
}

/// A pose as JSON (shared with the viewer's `poses` endpoint).
pub fn pose_json(p: &ScanPose) -> Value {
    json!({"version": p.version, "source": p.source, "seq": p.seq,
           "translation": p.world_from_sensor.translation_m, "rotation": p.world_from_sensor.rotation_wxyz})
}

/// The SSE body stream.
#[derive(Debug)]
struct SseUpdates(Watch);

impl tokio_stream::Stream for SseUpdates {
    type Item = Result<Event, std::convert::Infallible>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let resolution = self.0.resolution;
        self.0.poll_update(cx).map(|u| {
            u.map(|u| {
                Ok(Event::default().id(u.version.to_string()).data(update_json(&u, resolution).to_string()))
            })
        })
    }
}

/// Parses `x,y,z`.
pub fn parse_xyz(s: &str, name: &str) -> Result<[f64; 3], ApiError> {
    let v: Vec<f64> = s.split(',').filter_map(|t| t.trim().parse().ok()).collect();
    <[f64; 3]>::try_from(v.as_slice())
        .ok()
        .filter(|v| v.iter().all(|c| c.is_finite()))
        .ok_or_else(|| ApiError::bad(format!("{name}: expected three finite numbers x,y,z, got {s:?}")))
}

/// A world box `(min, max)`, metres.
pub type WorldBox = ([f64; 3], [f64; 3]);

/// `min=x,y,z&max=x,y,z` (both or neither).
pub fn parse_box(q: &HashMap<String, String>) -> Result<Option<WorldBox>, ApiError> {
    match (q.get("min"), q.get("max")) {
        (None, None) => Ok(None),
        (Some(a), Some(b)) => Ok(Some((parse_xyz(a, "min")?, parse_xyz(b, "max")?))),
        _ => Err(ApiError::bad("min and max go together")),
    }
}

/// `GET /v1/maps/{map}/updates?since=N[&min=x,y,z&max=x,y,z]`; a `Last-Event-ID` header (an
/// SSE reconnect) takes the place of `since`.
pub async fn sse_updates(
    State(service): State<Arc<MapService>>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let last_id = headers.get("last-event-id").and_then(|v| v.to_str().ok());
    let since = match last_id.or(q.get("since").map(String::as_str)) {
        None => None,
        Some(s) => Some(
            s.trim()
                .parse::<u64>()
                .map_err(|_| ApiError::bad(format!("since: {s:?} is not an unsigned integer")))?,
        ),
    };
    let snap = service.snapshot(&map)?;
    let resolution = snap.map.params().resolution_m;
    let filter = match parse_box(&q)? {
        None => None,
        Some((min, max)) => Some(BlockBox::from_world(min, max, resolution)?),
    };
    let (first, sub) = service.watch(&map, since, filter)?;
    let watch = Watch { first: Some(first), sub, resolution, closed: false };
    Ok(Sse::new(SseUpdates(watch)).keep_alive(KeepAlive::default()).into_response())
}
