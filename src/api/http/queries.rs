//! HTTP queries: `POST /v1/maps/{map}/query/points`, `…/query/box`, `…/query/rays` with JSON
//! bodies, answered through the service's front door ([`crate::service::query`]) as gRPC's are,
//! each counted in `/metrics`.

use super::{ApiError, ApiResult, AppState, parse};
use crate::api::offload;
use crate::core::CellState;
use crate::core::query::{RayHit, StopAt};
use crate::service::query::{BoxRequest, RayRequest, ThresholdsIn};
use crate::service::{QueryError, Snapshot};
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::response::IntoResponse;
use serde::Deserialize;
use serde_json::{Value, json};

/// The one mapping of a refused query to an HTTP answer, naming the JSON field.
impl From<QueryError> for ApiError {
    fn from(e: QueryError) -> Self {
        match e {
            QueryError::Threshold { name, reason } => Self::bad(format!("thresholds.{name}: {reason}")),
            QueryError::NotFinite { index } => {
                Self::bad(format!("points[{index}]: coordinates must be finite"))
            }
            QueryError::Outside { index } => {
                Self::bad(format!("points[{index}]: outside the map's key range"))
            }
            QueryError::Coarsen(c) => Self::bad(format!("box: coarsen must be at most 10, got {c}")),
            // A box over the limit is a bad request (400, as gRPC's INVALID_ARGUMENT); the
            // message gives the limit.
            QueryError::Box(e) => Self::bad(e.to_string()),
            QueryError::Ray { index, error } => Self::bad(format!("rays[{index}]: {error}")),
            QueryError::RayCorrupt { index, block } => {
                Snapshot::loss(&block, format!("rays[{index}]")).into()
            }
            QueryError::Service(e) => e.into(),
        }
    }
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ThresholdsJson {
    p_free: Option<f64>,
    p_occ: Option<f64>,
    var_max: Option<f64>,
}

fn thresholds(t: Option<ThresholdsJson>) -> ThresholdsIn {
    let t = t.unwrap_or_default();
    ThresholdsIn { p_free: t.p_free, p_occ: t.p_occ, var_max: t.var_max }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PointsJson {
    points: Vec<[f64; 3]>,
    thresholds: Option<ThresholdsJson>,
}

pub(super) async fn points_query(
    State(st): State<AppState>,
    Path(map): Path<String>,
    body: Bytes,
) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: PointsJson = parse(&body)?;
    let queries = st.service.queries(&map)?;
    let th = queries.thresholds(thresholds(q.thresholds))?;
    let query = queries.points(q.points, th)?;
    let out = offload::run(query.runs_inline(), move || {
        let mut results = Vec::with_capacity(query.len());
        query.run(|a| {
            let e = a.estimate;
            results.push(json!({"probability": e.probability, "variance": e.variance,
                "state": e.state.as_str(), "cell": [a.cell.x, a.cell.y, a.cell.z]}));
        })?;
        Ok::<_, QueryError>(json!({"results": results, "version": query.version()}))
    })
    .await??;
    st.counters.count(0, t0);
    Ok(axum::Json(out).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxJson {
    min: [f64; 3],
    max: [f64; 3],
    state: Option<String>,
    #[serde(default)]
    coarsen: u8,
    #[serde(default)]
    counts_only: bool,
    thresholds: Option<ThresholdsJson>,
}

fn parse_state(s: &str) -> Result<CellState, ApiError> {
    match s {
        "free" => Ok(CellState::Free),
        "occupied" => Ok(CellState::Occupied),
        "unknown" => Ok(CellState::Unknown),
        other => Err(ApiError::bad(format!("state: {other:?} is not free|occupied|unknown"))),
    }
}

pub(super) async fn box_query(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: BoxJson = parse(&body)?;
    let queries = st.service.queries(&map)?;
    let th = queries.thresholds(thresholds(q.thresholds))?;
    let state = q.state.as_deref().map(parse_state).transpose()?;
    let request = BoxRequest { min_world: q.min, max_world: q.max, state, coarsen: u32::from(q.coarsen) };
    let query = queries.cuboid(request, th)?;
    let counts_only = q.counts_only;
    let out = offload::run(query.runs_inline(), move || {
        let answer = query.run()?;
        let [free, occupied, unknown] = answer.counts;
        let mut out = json!({"counts": {"free": free, "occupied": occupied, "unknown": unknown},
                             "version": answer.version});
        if !counts_only {
            let list: Vec<Value> = answer
                .cells
                .iter()
                .map(|c| {
                    json!({"min_cell": [c.min_cell.x, c.min_cell.y, c.min_cell.z], "size_cells": c.size_cells,
                           "probability": c.estimate.probability, "variance": c.estimate.variance,
                           "state": c.estimate.state.as_str()})
                })
                .collect();
            out["cells"] = Value::Array(list);
        }
        Ok::<_, QueryError>(out)
    })
    .await??;
    st.counters.count(1, t0);
    Ok(axum::Json(out).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RayJson {
    origin: [f64; 3],
    direction: [f64; 3],
    max_range: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RaysJson {
    rays: Vec<RayJson>,
    stop_at: Option<String>,
    thresholds: Option<ThresholdsJson>,
}

pub(super) async fn rays_query(
    State(st): State<AppState>,
    Path(map): Path<String>,
    body: Bytes,
) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: RaysJson = parse(&body)?;
    let queries = st.service.queries(&map)?;
    let th = queries.thresholds(thresholds(q.thresholds))?;
    let stop = match q.stop_at.as_deref().unwrap_or("occupied") {
        "occupied" => StopAt::Occupied,
        "not_free" | "unknown" => StopAt::NotFree,
        other => return Err(ApiError::bad(format!("stop_at: {other:?} is not occupied|not_free"))),
    };
    let rays = q
        .rays
        .iter()
        .map(|r| RayRequest {
            origin_world: r.origin,
            direction_world: r.direction,
            max_range_m: r.max_range,
        })
        .collect();
    let query = queries.rays(rays, stop, th);
    let out = offload::run(query.runs_inline(), move || {
        let mut results = Vec::with_capacity(query.len());
        query.run(|_, hit| {
            results.push(match hit {
                RayHit::Clear => json!({"blocked": false, "verdict": "clear"}),
                RayHit::Blocked { cell, distance_m, estimate } => {
                    json!({"blocked": true, "verdict": "blocked",
                    "cell": [cell.x, cell.y, cell.z], "distance": distance_m,
                    "state": estimate.state.as_str(), "probability": estimate.probability})
                }
            })
        })?;
        Ok::<_, QueryError>(json!({"results": results, "version": query.version()}))
    })
    .await??;
    st.counters.count(2, t0);
    Ok(axum::Json(out).into_response())
}
