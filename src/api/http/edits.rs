//! HTTP handlers of the exact edits, mirroring the gRPC calls:
//!
//! - `POST /v1/maps/{map}/merge` `{"from_map": "other"}` or `{"from_file": "path.bgkmap"}`
//! - `POST /v1/maps/{map}/retract` `{"scans": [{"source": "r1", "seq": 3}]}` or
//!   `{"source": "r1", "from_stamp_nanos": …, "to_stamp_nanos": …}` (filters optional, at least one)
//! - `POST /v1/maps/{map}/repose` `{"poses": [{"source": "r1", "seq": 3, "pose": {"translation":
//!   [x, y, z], "rotation": [w, x, y, z]}}]}`
//!
//! Each answers `{"scans", "shared_scans", "blocks_changed", "version"}`.

use super::scans::PoseJson;
use super::{ApiError, ApiResult, AppState, parse};
use crate::api::offload;
use crate::core::Pose;
use crate::service::{Change, MergeSource, ServiceError};
use crate::store::ScanSelector;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::response::IntoResponse;
use serde::Deserialize;
use serde_json::json;

/// Runs a service edit off the async workers (it waits for the map's writer).
async fn blocking(f: impl FnOnce() -> Result<Change, ServiceError> + Send + 'static) -> ApiResult {
    let c = offload::blocking(f)
        .await
        .map_err(|e| ApiError::internal(format!("operation task failed: {}", e.0)))??;
    Ok(axum::Json(json!({"scans": c.scans, "shared_scans": c.shared, "blocks_changed": c.blocks_changed,
                         "version": c.version}))
    .into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MergeJson {
    from_map: Option<String>,
    from_file: Option<String>,
}

pub(super) async fn merge(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let m: MergeJson = parse(&body)?;
    let from = match (m.from_map, m.from_file) {
        (Some(name), None) => MergeSource::Map(name),
        (None, Some(file)) => MergeSource::File(file.into()),
        _ => return Err(ApiError::bad("give exactly one of from_map and from_file")),
    };
    let service = st.service.clone();
    blocking(move || service.merge(&map, from)).await
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanIdJson {
    source: String,
    seq: u64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RetractJson {
    #[serde(default)]
    scans: Vec<ScanIdJson>,
    source: Option<String>,
    from_stamp_nanos: Option<i64>,
    to_stamp_nanos: Option<i64>,
}

pub(super) async fn retract(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let r: RetractJson = parse(&body)?;
    let selector = ScanSelector {
        scans: r.scans.into_iter().map(|s| (s.source, s.seq)).collect(),
        source: r.source,
        from_stamp_nanos: r.from_stamp_nanos,
        to_stamp_nanos: r.to_stamp_nanos,
    };
    let service = st.service.clone();
    blocking(move || service.retract(&map, selector)).await
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanPoseJson {
    source: String,
    seq: u64,
    pose: PoseJson,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ReposeJson {
    poses: Vec<ScanPoseJson>,
}

pub(super) async fn repose(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let r: ReposeJson = parse(&body)?;
    let poses = r.poses.into_iter().map(|p| ((p.source, p.seq), Pose::from(p.pose))).collect();
    let service = st.service.clone();
    blocking(move || service.repose(&map, poses)).await
}
