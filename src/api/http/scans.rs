//! HTTP ingest: `POST /v1/maps/{map}/scans` with a JSON scan or a raw PCD body
//! (`Content-Type: application/x-pcd`, the pose from its VIEWPOINT), answered once the scan is
//! durable (`?wait_applied=true`: once it is integrated).

use super::{ApiError, ApiResult, AppState, parse};
use crate::core::{PointFrame, Pose};
use crate::io::pcd::read_pcd;
use crate::service::{ScanInput, ServiceError, SubmitOptions};
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, header};
use axum::response::IntoResponse;
use serde::Deserialize;
use serde_json::json;
use std::collections::HashMap;

/// A sensor pose in JSON (`rotation` as w, x, y, z), for scans and re-poses.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PoseJson {
    translation: [f64; 3],
    rotation: [f64; 4],
}

impl From<PoseJson> for Pose {
    fn from(p: PoseJson) -> Self {
        Pose { translation_m: p.translation, rotation_wxyz: p.rotation }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanJson {
    source: String,
    seq: u64,
    pose: PoseJson,
    #[serde(default)]
    frame: Option<String>,
    points: Vec<[f32; 3]>,
    #[serde(default)]
    max_range: Option<f64>,
    #[serde(default)]
    stamp_nanos: Option<i64>,
}

fn parse_frame(s: Option<&str>) -> Result<PointFrame, ApiError> {
    match s.unwrap_or("world") {
        "world" => Ok(PointFrame::World),
        "sensor" => Ok(PointFrame::Sensor),
        other => Err(ApiError::bad(format!("invalid frame: {other:?} (world|sensor)"))),
    }
}

pub(super) async fn insert_scan(
    State(st): State<AppState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult {
    let is_pcd = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/x-pcd"));
    let scan = if is_pcd { scan_from_pcd_body(&q, &body)? } else { scan_from_json(&body)? };
    let wait_applied = match q.get("wait_applied").map(String::as_str) {
        None | Some("false" | "0") => false,
        Some("true" | "1" | "") => true,
        Some(other) => {
            return Err(ApiError::bad(format!("query parameter wait_applied: {other:?} is not true|false")));
        }
    };
    let (tx, rx) = tokio::sync::oneshot::channel();
    let options = SubmitOptions { wait_applied };
    st.service.submit(&map, scan, options, Box::new(move |r| drop(tx.send(r))))?;
    let ack = rx.await.map_err(|_| ServiceError::ShuttingDown)??;
    Ok(axum::Json(
        json!({"applied": ack.applied, "version": ack.version, "dropped_points": ack.dropped_points}),
    )
    .into_response())
}

fn scan_from_json(body: &Bytes) -> Result<ScanInput, ApiError> {
    let s: ScanJson = parse(body)?;
    Ok(ScanInput {
        frame: parse_frame(s.frame.as_deref())?,
        source: s.source,
        seq: s.seq,
        world_from_sensor: s.pose.into(),
        points: s.points,
        max_range_m: s.max_range,
        stamp_nanos: s.stamp_nanos,
    })
}

/// A raw PCD body: `?source=…&seq=…[&max_range=…][&frame=world|sensor]`; the pose is the
/// file's VIEWPOINT.
fn scan_from_pcd_body(q: &HashMap<String, String>, body: &Bytes) -> Result<ScanInput, ApiError> {
    let source =
        q.get("source").cloned().ok_or_else(|| ApiError::bad("query parameter source is required"))?;
    let seq = q
        .get("seq")
        .ok_or_else(|| ApiError::bad("query parameter seq is required"))?
        .parse::<u64>()
        .map_err(|_| ApiError::bad("query parameter seq must be an unsigned integer"))?;
    let max_range = match q.get("max_range") {
        None => None,
        Some(v) => {
            Some(v.parse::<f64>().map_err(|_| ApiError::bad("query parameter max_range must be a number"))?)
        }
    };
    let stamp_nanos = match q.get("stamp_nanos") {
        None => None,
        Some(v) => Some(
            v.parse::<i64>().map_err(|_| ApiError::bad("query parameter stamp_nanos must be an integer"))?,
        ),
    };
    let cloud = read_pcd(body).map_err(|e| ApiError::bad(e.to_string()))?;
    let vp =
        cloud.viewpoint.ok_or_else(|| ApiError::bad("the PCD has no VIEWPOINT line (the sensor pose)"))?;
    Ok(ScanInput {
        source,
        seq,
        world_from_sensor: Pose {
            translation_m: [vp[0], vp[1], vp[2]],
            rotation_wxyz: [vp[3], vp[4], vp[5], vp[6]],
        },
        frame: parse_frame(q.get("frame").map(String::as_str))?,
        points: cloud.points,
        max_range_m: max_range,
        stamp_nanos,
    })
}
