//! The updates over HTTP: server-sent events at `GET /v1/maps/{map}/updates?since=N`.
//!
//! The stream starts with the catch-up (the blocks changed since the version asked for; none
//! when none was asked), then one message per change of the map; a watcher that falls behind
//! gets one `resync` message listing every block changed since the last version it was sent.
//! When the server shuts down the stream closes (browsers reconnect with `Last-Event-ID`, which
//! is the last version they saw, so they resume exactly; after a restart a version from before
//! it gets a catch-up with `reset`: every block the map holds, drop the rest).
//!
//! Messages are JSON: `{"kind": "catch_up"|"live"|"resync", "from_version", "version",
//! "blocks": [[x, y, z], …], "block_edge", "resolution", "poses": [{"version", "source",
//! "seq", "translation": [x, y, z], "rotation": [w, x, y, z]}, …], "reset"}`; the event id is
//! `version`.

use super::{ApiError, AppState, parse_box};
use crate::core::key::BLOCK_EDGE;
use crate::service::{BlockBox, MapUpdate, ScanPose, UpdateKind, Watch};
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::pin::Pin;
use std::task::{Context, Poll};

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
        let resolution = self.0.resolution_m;
        self.0.poll_update(cx).map(|u| {
            u.map(|u| {
                Ok(Event::default().id(u.version.to_string()).data(update_json(&u, resolution).to_string()))
            })
        })
    }
}

/// `GET /v1/maps/{map}/updates?since=N[&min=x,y,z&max=x,y,z]`; a `Last-Event-ID` header (an
/// SSE reconnect) takes the place of `since`.
pub(super) async fn sse_updates(
    State(st): State<AppState>,
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
    let resolution = st.service.snapshot(&map)?.map.params().resolution_m;
    let filter = match parse_box(&q)? {
        None => None,
        Some((min, max)) => Some(BlockBox::from_world(min, max, resolution)?),
    };
    let watch = Watch::new(st.service.watch(&map, since, filter)?, resolution);
    Ok(Sse::new(SseUpdates(watch)).keep_alive(KeepAlive::default()).into_response())
}
